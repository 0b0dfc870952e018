"""A pillowed polycube complex mapped into a mesh: the tetrahedral grid of the consistent
(P1 finite-element) discretisation.

:func:`build_fem_grid` runs::

    mesh --polycube_from_mesh--> Polycube --Lattice--> PillowComplex --map_pillow--> FemGrid

Mapping (:func:`map_pillow`):

1. **Surface nodes** go to the closest mesh point of their reference position on the
   polycube surface, then a few rounds of Laplacian smoothing over the surface triangles,
   each followed by re-projection (as the paper's boundary relaxation, Turk 1992).
2. **Outer lattice layer**: each outer lattice node sits under its surface node along the
   inward mesh normal, at depth ``depth * h``; where the object is thinner than that (the
   point would be closer to another part of the surface), the depth is halved until it is
   not (thin parts keep a thin, valid layer).
3. **Remaining lattice nodes**: harmonic placement (graph Laplacian of the lattice, the
   outer layer fixed).

:class:`MappingQuality` reports inverted and the worst tetrahedra and the surface nodes'
spacing.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.lattice import Lattice
from glsldiff.grids.pillow import PillowComplex, signed_volumes
from glsldiff.grids.polycube import Polycube, polycube_from_mesh
from glsldiff.mesh import Mesh, closest_points

__all__ = ["FemGrid", "MappingQuality", "build_fem_grid", "map_pillow"]


@dataclass
class MappingQuality:
    """What the mapping achieved (lengths mm, times s)."""

    tets: int = 0
    inverted: int = 0                       # tetrahedra with volume <= 0
    worst_quality: float = float("nan")     # smallest volume / (mean edge)^3 * 6 sqrt(2) (1: regular)
    quality_p1: float = float("nan")        # its 1st percentile
    surface_spacing: float = float("nan")   # mean surface edge length
    surface_spacing_cv: float = float("nan")
    thinned: int = 0                        # outer nodes placed shallower than depth * h (thin parts)
    seconds: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


@dataclass(eq=False)
class FemGrid:
    """A tetrahedral grid of a mesh's interior (see the module docstring).

    Attributes
    ----------
    complex
        The topology (:class:`glsldiff.grids.pillow.PillowComplex`); node ``i < N`` is
        lattice node ``i``, node ``N + k`` the surface copy of lattice node ``complex.outer[k]``.
    positions
        ``(N + S, 3)`` node positions, mm (lattice nodes of no cell: lattice position).
    normals
        ``(S, 3)`` outward unit mesh normals at the surface nodes.
    """

    complex: PillowComplex
    positions: NDArray[np.float64]
    normals: NDArray[np.float64]
    quality: MappingQuality
    mesh: Mesh | None = None
    polycube: Polycube | None = None

    @property
    def tets(self) -> NDArray[np.int64]:
        return self.complex.tets

    @property
    def surface(self) -> NDArray[np.int64]:
        return self.complex.surface

    @property
    def surface_nodes(self) -> NDArray[np.int64]:
        """``(S,)`` node indices of the surface nodes (``N .. N+S-1``)."""
        return self.complex.n_lattice + np.arange(len(self.complex.outer))

    @property
    def active(self) -> NDArray[np.bool_]:
        """``(N + S,)`` nodes that belong to a tetrahedron."""
        a = np.zeros(self.complex.n_nodes, dtype=bool)
        a[self.complex.used] = True
        a[self.complex.n_lattice:] = True
        return a

    @property
    def h(self) -> float:
        return self.complex.lattice.h


def _surface_smoother(surface: NDArray[np.int64], offset: int, n: int) -> sp.csr_matrix:
    """Row-normalised adjacency (mean of edge neighbours) of the surface nodes."""
    e = np.concatenate([surface[:, [0, 1]], surface[:, [1, 2]], surface[:, [2, 0]]]) - offset
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    A.data[:] = 1.0
    return sp.diags(1.0 / np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1)) @ A


def _quality(X: NDArray[np.float64], tets: NDArray[np.int64]) -> NDArray[np.float64]:
    """Volume over the regular tetrahedron's of the same mean edge length (1 regular, <= 0 inverted)."""
    P = X[tets]
    edges = [P[:, j] - P[:, i] for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))]
    mean = np.mean([np.linalg.norm(e, axis=1) for e in edges], axis=0)
    return signed_volumes(X, tets) * 6.0 * np.sqrt(2.0) / np.maximum(mean, 1e-300) ** 3


def map_pillow(cx: PillowComplex, mesh: Mesh, relax_iterations: int = 10, relax_step: float = 0.5,
               depth: float = 0.5) -> tuple[NDArray[np.float64], NDArray[np.float64], MappingQuality]:
    """Positions of every node of ``cx`` in ``mesh`` and the surface normals (module docstring).

    ``depth``: the outer lattice layer's distance under the surface, in lattice spacings."""
    q = MappingQuality()
    t0 = time.perf_counter()
    lat = cx.lattice
    N, h = cx.n_lattice, lat.h
    X = cx.reference_positions()
    S = len(cx.outer)
    xs, _, _, nrm = closest_points(mesh, X[N:])
    M = _surface_smoother(cx.surface, N, S)
    for _ in range(relax_iterations):
        xs = xs + relax_step * (M @ xs - xs)
        xs, _, _, nrm = closest_points(mesh, xs)
    X[N:] = xs
    e = np.concatenate([cx.surface[:, [0, 1]], cx.surface[:, [1, 2]], cx.surface[:, [2, 0]]])
    L = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    q.surface_spacing, q.surface_spacing_cv = float(L.mean()), float(L.std() / L.mean())
    q.seconds["surface"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    s = np.full(S, depth * h)
    inner = xs - s[:, None] * nrm
    for _ in range(6):   # thin parts: halve the depth where another surface part is closer
        _, dist, _, _ = closest_points(mesh, inner)
        thin = dist < 0.75 * s
        if not thin.any():
            break
        s[thin] *= 0.5
        inner[thin] = xs[thin] - s[thin, None] * nrm[thin]
    q.thinned = int((s < depth * h).sum())
    X[cx.outer] = inner
    q.seconds["layer"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    used = cx.used
    fixed = np.zeros(N, dtype=bool)
    fixed[cx.outer] = True
    free = used[~fixed[used]]
    if free.size:
        nb = lat.lattice_neighbours
        rows = np.repeat(np.arange(N), 6)
        cols = nb.ravel()
        ok = cols >= 0
        A = sp.csr_matrix((np.ones(ok.sum()), (rows[ok], cols[ok])), shape=(N, N))
        Lap = sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A
        Lff = Lap[free][:, free].tocsc()
        rhs = -(Lap[free][:, cx.outer] @ X[cx.outer])
        X[free] = spla.splu(Lff).solve(rhs)
    q.seconds["interior"] = time.perf_counter() - t2

    qual = _quality(X, cx.tets)
    q.tets = len(qual)
    q.inverted = int((qual <= 0).sum())
    q.worst_quality = float(qual.min())
    q.quality_p1 = float(np.percentile(qual, 1))
    q.seconds["total"] = time.perf_counter() - t0
    return X, nrm, q


def build_fem_grid(mesh: Mesh, n: int = 4, cube_size: float | None = None, n_cubes: int | None = None,
                   threshold: float = 0.5, polycube: Polycube | None = None,
                   mapping: dict[str, Any] | None = None) -> FemGrid:
    """Polycube, pillowed lattice and mapping for a closed mesh (mm)."""
    if polycube is None:
        polycube = polycube_from_mesh(mesh, cube_size=cube_size, n_cubes=n_cubes, threshold=threshold)
    if not isinstance(n, (int, np.integer)) or n < 2:
        raise InputError(f"n={n!r} nodes per cube edge must be an integer >= 2")
    lattice = Lattice(polycube.cubes, int(n), polycube.size, np.asarray(polycube.origin, dtype=np.float64))
    cx = PillowComplex.build(lattice)
    X, nrm, q = map_pillow(cx, mesh, **(mapping or {}))
    return FemGrid(cx, X, nrm, q, mesh, polycube)
