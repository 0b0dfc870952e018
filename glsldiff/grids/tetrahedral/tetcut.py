"""Cutting a tetrahedral mesh (TransCut, Li et al. 2012, section 5.1; ``../shared/notes/transcut.md``
section 4.1): remove the tetrahedra on one side of a cut surface, relax the remaining vertices
on that side towards the cut, rebuild the boundary.

The cut surface is a signed function ``side(X)`` (mm for a plane; positive on the side that goes):

* :func:`plane_side`: the plane ``n . x = d``, removing ``n . x > d``;
* :func:`stroke_side`: a screen stroke (pixel polyline) extruded along the view rays of a
  camera (the paper's stroke; it does not say how the 2-D stroke becomes a surface: here each
  segment spans a plane through the eye, and a point's side is that of the segment its image
  is nearest to, the end segments extended), removing the stroke's left (``u`` right, ``v`` down
  in the image, left = the side a walker along the stroke has on the left).

Steps (the paper's): delete every tetrahedron whose four vertices are all on the removed side
(a vertex goes with its last tetrahedron); then, ``iterations`` times, move each remaining vertex
on the removed side by ``rho = 0.1`` of the way to the mean of its one-ring neighbours, unless
the move would leave a tetrahedron around it inverted or with a dihedral angle below
``min_dihedral_deg = 0.5``. A move that would cross the cut stops on it (the paper skips such
a move; stopping on the cut lets the cross-section become the cut surface) and the vertex stays
there. The boundary is rebuilt: the new faces are ordinary boundary faces (normals from them),
every tetrahedron keeps the index of its original (:attr:`TetMesh.origin`, used by painting) and
the cut's triangles are flagged (:attr:`TetMesh.cut_faces`: the renderer keeps a crease there).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.graph import edge_adjacency
from glsldiff.grids.tetrahedral.pillow import node_tets, signed_volumes, tet_edges
from glsldiff.grids.tetrahedral.tetwild import INERT_DIHEDRAL_DEG, TetMesh, boundary_faces, tet_quality
from glsldiff.grids.tetrahedral.tetwild import min_dihedral_deg as smallest_dihedral
from glsldiff.mesh import Mesh

__all__ = ["CutReport", "cut", "plane_side", "stroke_side", "RHO", "MIN_DIHEDRAL_DEG"]

#: TransCut's relaxation step (section 5.1).
RHO = 0.1
#: No move may leave a tetrahedron with a dihedral angle below this, degrees (TransCut section 7).
MIN_DIHEDRAL_DEG = INERT_DIHEDRAL_DEG

Side = Callable[[NDArray[np.float64]], NDArray[np.float64]]


def plane_side(normal: Sequence[float], offset: float) -> Side:
    """The side function of the plane ``n . x = offset`` (``n`` normalised; mm): positive where
    ``n . x > offset``, the part that is removed."""
    n = np.asarray(normal, dtype=np.float64)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.linalg.norm(n) > 0 or not np.isfinite(offset):
        raise InputError(f"cut plane normal {normal!r} must be three finite numbers, not all zero, and the offset "
                         f"{offset!r} mm finite")
    n = n / np.linalg.norm(n)
    return lambda X: np.asarray(X, dtype=np.float64) @ n - float(offset)


def stroke_side(project: Callable[[NDArray[np.float64]], NDArray[np.float64]], stroke: ArrayLike) -> Side:
    """The side function of a screen stroke ``(k, 2)`` pixels (``k >= 2``) extruded along the view:
    ``project`` maps ``(n, 3)`` points to ``(n, 2)`` pixels. The value is the signed pixel
    distance of a point's image to the polyline, positive on its left (module docstring)."""
    S = np.asarray(stroke, dtype=np.float64)
    if S.ndim != 2 or S.shape[1] != 2 or len(S) < 2 or not np.all(np.isfinite(S)):
        raise InputError(f"a cut stroke needs at least two finite (u, v) pixel points, got shape {S.shape}")
    seg = np.diff(S, axis=0)
    length = np.linalg.norm(seg, axis=1)
    if np.any(length == 0):
        raise InputError("a cut stroke has two equal consecutive points; remove the repeat")

    def side(X: NDArray[np.float64]) -> NDArray[np.float64]:
        p = project(np.atleast_2d(np.asarray(X, dtype=np.float64)))
        d = p[:, None, :] - S[None, :-1, :]                                 # (n, k-1, 2)
        t = np.einsum("nkc,kc->nk", d, seg) / length ** 2
        t[:, 0] = np.minimum(t[:, 0], 1.0)                                  # the end segments extend
        t[:, -1] = np.maximum(t[:, -1], 0.0)
        inner = np.ones(len(seg), dtype=bool)
        inner[0] = inner[-1] = False
        t[:, inner] = np.clip(t[:, inner], 0.0, 1.0)
        r = d - t[..., None] * seg[None]
        dist = np.linalg.norm(r, axis=2)
        k = np.argmin(dist, axis=1)
        rows = np.arange(len(p))
        cross = seg[k, 0] * d[rows, k, 1] - seg[k, 1] * d[rows, k, 0]     # v down: left is cross < 0
        return -np.sign(cross) * dist[rows, k]
    return side


@dataclass(frozen=True)
class CutReport:
    """What a cut did: counts, the worst dihedral angle after it (degrees), how far the
    remaining vertices stand past the cut (the side function's units: mm for a plane), and the
    time of each step (s)."""

    tets_before: int
    tets_removed: int
    nodes_removed: int
    nodes_to_relax: int
    nodes_on_cut: int
    moves_refused: int
    iterations: int
    min_dihedral_deg: float
    max_past_cut: float
    seconds: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d.update({f"{k}_s": v for k, v in d.pop("seconds").items()})
        return d


def _to_cut(side: Side, x: NDArray[np.float64], y: NDArray[np.float64], steps: int = 30) -> NDArray[np.float64]:
    """Points on the segments ``x -> y`` (``side(x) > 0 >= side(y)``) where ``side`` crosses 0."""
    lo, hi = np.zeros(len(x)), np.ones(len(x))
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        past = side(x + mid[:, None] * (y - x)) <= 0.0
        hi = np.where(past, mid, hi)
        lo = np.where(past, lo, mid)
    return x + hi[:, None] * (y - x)


def _rows_in(rows: NDArray[np.int64], table: NDArray[np.int64]) -> NDArray[np.bool_]:
    """``(k,)`` which triangles ``rows`` ``(k, 3)`` appear in ``table`` ``(m, 3)``, in any vertex order."""
    both = np.sort(np.concatenate([table, rows]), axis=1)
    _, inverse = np.unique(both, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    return np.isin(inverse[len(table):], inverse[:len(table)])


def _kept(faces: NDArray[np.int64], remap: NDArray[np.int64]) -> NDArray[np.int64]:
    """The triangles ``faces`` of the uncut mesh whose three nodes remain, renumbered."""
    f = remap[faces]
    return f[np.all(f >= 0, axis=1)]


def cut(tm: TetMesh, side: Side, iterations: int = 20, rho: float = RHO,
        min_dihedral_deg: float = MIN_DIHEDRAL_DEG) -> tuple[TetMesh, CutReport]:
    """The mesh ``tm`` cut by ``side`` (module docstring) and its :class:`CutReport`."""
    if not (isinstance(iterations, int) and iterations >= 0) or not 0.0 < rho <= 1.0:
        raise InputError(f"cut: iterations {iterations!r} must be an integer >= 0 and rho {rho!r} in (0, 1]")
    t0 = time.perf_counter()
    X = np.array(tm.positions, dtype=np.float64)
    T = tm.tets
    f = side(X)
    keep_tet = ~np.all(f[T] > 0.0, axis=1)
    if not keep_tet.any():
        raise InputError("the cut removes the whole object; move the cut plane or stroke, or flip its side")
    if keep_tet.all() and not np.any(f > 0.0):
        raise InputError("the cut misses the object (no vertex lies on the removed side); move the cut plane or "
                         "stroke onto the object")
    origin = (np.arange(len(T)) if tm.origin is None else tm.origin)[keep_tet]
    T = T[keep_tet]
    used = np.unique(T)
    remap = np.full(len(X), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    was_surface = np.zeros(len(X), dtype=bool)
    was_surface[tm.surface_nodes] = True
    old_normal = np.zeros((len(X), 3))
    old_normal[tm.surface_nodes] = tm.normals
    X, T, f = X[used], remap[T], f[used]
    was_surface, old_normal = was_surface[used], old_normal[used]
    t_remove = time.perf_counter() - t0

    t0 = time.perf_counter()
    A = edge_adjacency(tet_edges(T), len(X))
    deg = np.asarray(A.sum(axis=1)).ravel()
    movable = f > 0.0
    to_relax = int(movable.sum())
    tets_of = node_tets(T, len(X))
    mind = smallest_dihedral(X, T)
    refused, done, on_cut = 0, 0, 0
    for done in range(1, iterations + 1):
        idx = np.flatnonzero(movable)
        if len(idx) == 0:
            done -= 1
            break
        target = (A[idx] @ X) / deg[idx, None]
        new = X[idx] + rho * (target - X[idx])
        crossing = side(new) <= 0.0
        if crossing.any():
            new[crossing] = _to_cut(side, X[idx[crossing]], new[crossing])
        old = X[idx].copy()
        X[idx] = new
        moved = np.ones(len(idx), dtype=bool)
        while True:                                         # refuse moves that spoil a tetrahedron
            touched = np.flatnonzero(tets_of[idx[moved]].sum(axis=0).A1 > 0)
            vol = signed_volumes(X, T[touched])
            md = smallest_dihedral(X, T[touched])
            bad = (vol <= 0.0) | ((md < min_dihedral_deg) & (md < mind[touched]))
            if not bad.any():
                mind[touched] = md
                break
            culprits = np.isin(idx, T[touched[bad]].ravel()) & moved
            X[idx[culprits]] = old[culprits]
            moved &= ~culprits
            refused += int(culprits.sum())
            if not moved.any():
                break
        landed = np.zeros(len(idx), dtype=bool)
        landed[moved] = crossing[moved]
        movable[idx[landed]] = False
        on_cut += int(landed.sum())
        if not moved.any():
            break
    t_relax = time.perf_counter() - t0

    t0 = time.perf_counter()
    surface = boundary_faces(T)
    nodes = np.unique(surface)
    normals = Mesh(X[nodes], np.searchsorted(nodes, surface)).vertex_normals.copy()   # area-weighted
    new_face = ~_rows_in(surface, _kept(tm.surface, remap))
    on_new = np.zeros(len(X), dtype=bool)
    on_new[surface[new_face].ravel()] = True
    keep_old = was_surface[nodes] & ~on_new[nodes]                 # untouched surface: the input's normals
    normals[keep_old] = old_normal[nodes[keep_old]]
    q = tm.quality
    quality = tet_quality(X, T, surface, q.mesh_volume_mm3, q.surface_distance_max, dict(q.seconds))
    t_rebuild = time.perf_counter() - t0
    f_after = side(X)
    report = CutReport(len(tm.tets), int((~keep_tet).sum()), len(tm.positions) - len(X), to_relax, on_cut,
                       refused, done, quality.min_dihedral_deg, float(max(f_after.max(), 0.0)),
                       {"remove": t_remove, "relax": t_relax, "rebuild": t_rebuild})
    made = new_face if tm.cut_faces is None else new_face | _rows_in(surface, _kept(tm.surface[tm.cut_faces], remap))
    return TetMesh(X, T, surface, normals, quality, tm.edge_mm, origin, made), report
