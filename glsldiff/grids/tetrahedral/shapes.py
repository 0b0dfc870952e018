"""Shape quality of tetrahedra and its improvement by moving nodes one at a time.

:func:`shape_quality` is ``6 sqrt(2) V / l^3`` with ``l`` the mean edge length: 1 for the
regular tetrahedron, 0 for a flat one, negative for an inverted one.

:func:`improve_shapes` raises the worst shapes of a mapped grid (Freitag and Ollivier-Gooch,
"Tetrahedral mesh improvement using swapping and smoothing", 1997: smart Laplacian smoothing,
then optimisation-based smoothing where it stalls). Every node of a tetrahedron below
``target`` is visited in turn and moved only if the worst shape among its own tetrahedra
gets better and no more of them are inverted, so no tetrahedron gets worse than the worst it
touched and none inverts that was not:

1. towards the mean of its neighbours (steps 1, 1/2, 1/4 of the way);
2. where no such step helps, a Nelder-Mead search over its position (surface nodes: in their
   tangent plane, projected onto the surface at the end) maximising that worst shape.

Surface nodes move along the surface: ``project`` maps their new positions back onto the
mesh (crease nodes onto the creases); nodes that must stay (mesh corners, tips) are in
neither ``free`` nor ``sliding``. Why it matters: a flat tetrahedron couples its nodes with
large positive stiffness entries, and the discrete fluence then dips below zero next to lit
nodes (dark specks on the back-lit bunny's ear rim, see :mod:`glsldiff.grids.tetrahedral.fem_grid`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from glsldiff.core.jit import kernel
from glsldiff.grids.graph import edge_adjacency
from glsldiff.grids.tetrahedral.pillow import TET_EDGES, node_tets, triangle_edges, unique_tet_edges

__all__ = ["SHAPE_TARGET", "ShapeReport", "improve_shapes", "shape_quality"]

#: Tetrahedra below this shape quality get their nodes moved (:func:`improve_shapes`).
SHAPE_TARGET = 0.1
#: Sweeps of each stage over the nodes of tetrahedra still below the target.
SHAPE_SWEEPS = 6
#: Nelder-Mead evaluations per node, and its first simplex as a share of the node's mean edge.
SEARCH_EVALUATIONS = 80
SEARCH_SIMPLEX = 0.2

#: TET_EDGES' ends as tuples (a kernel reading a global array cannot be cached)
_EDGE_FROM, _EDGE_TO = tuple(int(i) for i in TET_EDGES[:, 0]), tuple(int(j) for j in TET_EDGES[:, 1])
Project = Callable[[NDArray[np.float64], NDArray[np.int64]], NDArray[np.float64]]


def shape_quality(X: NDArray[np.float64], tets: NDArray[np.int64]) -> NDArray[np.float64]:
    """``(T,)`` volume over the regular tetrahedron's of the same mean edge length (1 regular,
    <= 0 inverted)."""
    det, mean = np.empty(len(tets)), np.empty(len(tets))
    _volume_and_edge(np.asarray(X, dtype=np.float64), np.asarray(tets, dtype=np.int64), det, mean)
    return det * np.sqrt(2.0) / np.maximum(mean, 1e-300) ** 3   # numpy's power: its bits


@kernel
def _volume_and_edge(X: NDArray[np.float64], tets: NDArray[np.int64], det: NDArray[np.float64],
                     mean: NDArray[np.float64]) -> None:
    """``6 V`` (mm^3) and the mean edge length (mm) of each tetrahedron, with the floating-point
    operations of the numpy expressions they replace (edge vectors along ``TET_EDGES``, their
    squares summed as ``np.einsum`` does: first and third first)."""
    for t in range(len(tets)):
        s = 0.0
        for e in range(6):
            i, j = tets[t, _EDGE_FROM[e]], tets[t, _EDGE_TO[e]]
            d0, d1, d2 = X[j, 0] - X[i, 0], X[j, 1] - X[i, 1], X[j, 2] - X[i, 2]
            s += np.sqrt((d0 * d0 + d2 * d2) + d1 * d1)
        mean[t] = s / 6.0
        p0, p1, p2, p3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        a0, a1, a2 = X[p1, 0] - X[p0, 0], X[p1, 1] - X[p0, 1], X[p1, 2] - X[p0, 2]
        b0, b1, b2 = X[p2, 0] - X[p0, 0], X[p2, 1] - X[p0, 1], X[p2, 2] - X[p0, 2]
        c0, c1, c2 = X[p3, 0] - X[p0, 0], X[p3, 1] - X[p0, 1], X[p3, 2] - X[p0, 2]
        det[t] = (a1 * b2 - a2 * b1) * c0 + (a2 * b0 - a0 * b2) * c1 + (a0 * b1 - a1 * b0) * c2


@kernel
def _worst_at(X: NDArray[np.float64], own: NDArray[np.int64], v: int, old: NDArray[np.float64],
              basis: NDArray[np.float64], u: NDArray[np.float64], sliding: bool, start: NDArray[np.float64],
              max_slide: float) -> float:
    """The worst shape of the tetrahedra ``own`` with node ``v`` at ``old + u @ basis`` (moved
    there in ``X``); ``-inf`` for a sliding node more than ``max_slide`` (mm) from ``start``."""
    p = np.zeros(3)
    for k in range(3):
        for i in range(len(u)):
            p[k] += u[i] * basis[i, k]
        p[k] += old[k]
    if sliding:
        d0, d1, d2 = p[0] - start[0], p[1] - start[1], p[2] - start[2]
        if math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) > max_slide:
            return -np.inf
    X[v, 0], X[v, 1], X[v, 2] = p[0], p[1], p[2]
    det, mean = np.empty(len(own)), np.empty(len(own))
    _volume_and_edge(X, own, det, mean)
    worst = np.inf
    for t in range(len(own)):
        worst = min(worst, det[t] * math.sqrt(2.0) / math.pow(max(mean[t], 1e-300), 3.0))
    return worst


@kernel
def _spread(d: NDArray[np.float64]) -> float:
    """``max |d|`` over all entries, nan if any is nan (as ``np.max``)."""
    out = 0.0
    for x in d.ravel():
        a = abs(x)
        if math.isnan(a):
            return math.nan
        out = max(out, a)
    return out


@kernel
def _sort_simplex(sim: NDArray[np.float64], fsim: NDArray[np.float64]) -> None:
    """Order the simplex by value, ties kept in place (the insertion sort numpy's ``argsort``
    runs on so few points)."""
    for i in range(1, len(fsim)):
        j = i
        while j > 0 and fsim[j] < fsim[j - 1]:
            fsim[j], fsim[j - 1] = fsim[j - 1], fsim[j]
            for k in range(sim.shape[1]):
                sim[j, k], sim[j - 1, k] = sim[j - 1, k], sim[j, k]
            j -= 1


@kernel
def _nelder_mead(X: NDArray[np.float64], own: NDArray[np.int64], v: int, old: NDArray[np.float64],
                 basis: NDArray[np.float64], simplex: NDArray[np.float64], maxfev: int, xatol: float,
                 fatol: float, sliding: bool, start: NDArray[np.float64], max_slide: float
                 ) -> NDArray[np.float64]:
    """The ``u`` (``(d,)``, mm along ``basis``' rows) that maximises the worst shape of
    :func:`_worst_at`: SciPy's Nelder-Mead (``scipy.optimize.minimize``, non-adaptive, no
    bounds; the same steps, stops and evaluation budget) from ``simplex`` ``(d + 1, d)``,
    compiled (the Python loop cost 1-2 s of the bunny's grid build in objective calls)."""
    n = simplex.shape[1]
    sim = simplex.copy()
    fsim = np.full(n + 1, np.inf)
    calls = 0
    for k in range(n + 1):
        if calls >= maxfev:
            break
        calls += 1
        fsim[k] = -_worst_at(X, own, v, old, basis, sim[k], sliding, start, max_slide)
    _sort_simplex(sim, fsim)
    while calls < maxfev:
        if _spread(sim - sim[0]) <= xatol and _spread(fsim - fsim[0]) <= fatol:   # np.max's nan fails both
            break
        xbar = np.zeros(n)
        for j in range(n):
            xbar += sim[j]
        xbar /= n
        xr = 2 * xbar - sim[-1]
        calls += 1
        fxr = -_worst_at(X, own, v, old, basis, xr, sliding, start, max_slide)
        if fxr < fsim[0]:
            if calls >= maxfev:
                _sort_simplex(sim, fsim)
                break
            xe = 3 * xbar - 2 * sim[-1]
            calls += 1
            fxe = -_worst_at(X, own, v, old, basis, xe, sliding, start, max_slide)
            if fxe < fxr:
                sim[-1], fsim[-1] = xe, fxe
            else:
                sim[-1], fsim[-1] = xr, fxr
        elif fxr < fsim[-2]:
            sim[-1], fsim[-1] = xr, fxr
        else:
            shrink = False
            if calls >= maxfev:
                _sort_simplex(sim, fsim)
                break
            if fxr < fsim[-1]:
                xc = 1.5 * xbar - 0.5 * sim[-1]
                calls += 1
                fxc = -_worst_at(X, own, v, old, basis, xc, sliding, start, max_slide)
                if fxc <= fxr:
                    sim[-1], fsim[-1] = xc, fxc
                else:
                    shrink = True
            else:
                xcc = 0.5 * xbar + 0.5 * sim[-1]
                calls += 1
                fxcc = -_worst_at(X, own, v, old, basis, xcc, sliding, start, max_slide)
                if fxcc < fsim[-1]:
                    sim[-1], fsim[-1] = xcc, fxcc
                else:
                    shrink = True
            if shrink:
                for j in range(1, n + 1):
                    sim[j] = sim[0] + 0.5 * (sim[j] - sim[0])
                    if calls >= maxfev:
                        break
                    calls += 1
                    fsim[j] = -_worst_at(X, own, v, old, basis, sim[j], sliding, start, max_slide)
        _sort_simplex(sim, fsim)
    return sim[0].copy()


@dataclass
class ShapeReport:
    """What :func:`improve_shapes` did: tetrahedra below the target and the worst shape,
    before and after; nodes moved by each stage; seconds."""

    below_before: int = 0
    below_after: int = 0
    worst_before: float = float("nan")
    worst_after: float = float("nan")
    smoothed: int = 0
    searched: int = 0
    seconds: float = 0.0


def improve_shapes(X: NDArray[np.float64], tets: NDArray[np.int64], free: NDArray[np.bool_],
                   sliding: NDArray[np.bool_], surface: NDArray[np.int64], project: Project,
                   max_slide: float = np.inf, target: float = SHAPE_TARGET, sweeps: int = SHAPE_SWEEPS,
                   edges: NDArray[np.int64] | None = None) -> ShapeReport:
    """Move nodes (in place) to raise the tetrahedra below ``target`` (module docstring).

    ``free``: nodes that move in space; ``sliding``: surface nodes that move along the
    surface, ``project(points, nodes)`` putting them back on it, at most ``max_slide`` (mm)
    from where they started (so they keep covering what they covered); ``surface`` ``(F, 3)``
    the surface triangles (their edges are a sliding node's neighbours and give its tangent
    plane). ``edges``: the unique edges of ``tets``
    (:func:`~glsldiff.grids.tetrahedral.pillow.unique_tet_edges`), if known.
    """
    t0 = time.perf_counter()
    n = len(X)
    q = shape_quality(X, tets)
    rep = ShapeReport(below_before=int((q < target).sum()), worst_before=float(q.min()) if len(q) else 1.0)
    movable = free | sliding
    start = X.copy()
    incident = node_tets(tets, n)
    # the unique edges: faster than every copy of each edge
    volume_nb = edge_adjacency(unique_tet_edges(tets, n)[0] if edges is None else edges, n)
    surface_nb = edge_adjacency(triangle_edges(surface), n)
    on_surface = sp.csr_matrix((np.ones(surface.size), (surface.ravel(), np.repeat(np.arange(len(surface)), 3))),
                               shape=(n, len(surface)))   # node -> its surface triangles

    def place(v: int, p: NDArray[np.float64]) -> NDArray[np.float64]:
        return project(p[None], np.array([v]))[0] if sliding[v] else p

    def worst(v: int, tt: NDArray[np.int64], p: NDArray[np.float64], own: NDArray[np.int64] | None = None
              ) -> tuple[float, NDArray[np.float64]]:
        """The worst shape of ``v``'s tetrahedra ``tt`` (``own``: ``tets[tt]``) with ``v`` at ``p``."""
        if sliding[v]:
            d = p - start[v]
            if math.sqrt(d.dot(d)) > max_slide:   # np.linalg.norm's operations
                return -np.inf, np.empty(0)
        X[v] = p
        qn = shape_quality(X, tets[tt] if own is None else own)
        return float(qn.min()), qn

    def targets(nodes: NDArray[np.int64]) -> NDArray[np.float64]:
        """``(3, k, 3)`` the nodes' positions 1, 1/2 and 1/4 of the way to their neighbours'
        mean (sliding nodes: projected, all in one call)."""
        mean = np.empty((len(nodes), 3))
        for A, sel in ((surface_nb, sliding[nodes]), (volume_nb, ~sliding[nodes])):
            deg = np.maximum(np.diff(A.indptr)[nodes[sel]], 1)[:, None]
            mean[sel] = (A[nodes[sel]] @ X) / deg
        out = np.stack([X[nodes] + step * (mean - X[nodes]) for step in (1.0, 0.5, 0.25)])
        s = sliding[nodes]
        if s.any():
            out[:, s] = project(out[:, s].reshape(-1, 3), np.tile(nodes[s], 3)).reshape(3, -1, 3)
        return out

    def better(m: float, qn: NDArray[np.float64], before: NDArray[np.float64]) -> bool:
        """A higher worst shape, and no more inverted tetrahedra (raising an inverted one may
        not invert another)."""
        return m > float(before.min()) + 1e-6 and int((qn <= 0).sum()) <= int((before <= 0).sum())

    def smooth(v: int, tt: NDArray[np.int64], before: NDArray[np.float64], cand: NDArray[np.float64]
               ) -> NDArray[np.float64] | None:
        old = X[v].copy()
        for p in cand:
            m, qn = worst(v, tt, p)
            if better(m, qn, before):
                return qn
        X[v] = old
        return None

    def search(v: int, tt: NDArray[np.int64], before: NDArray[np.float64], _: NDArray[np.float64]
               ) -> NDArray[np.float64] | None:
        old = X[v].copy()
        if sliding[v]:
            P = X[surface[on_surface.indices[on_surface.indptr[v]:on_surface.indptr[v + 1]]]]   # in index order
            nrm = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]).sum(axis=0)   # area-weighted, outward
            nrm /= max(float(np.linalg.norm(nrm)), 1e-300)
            a = np.cross(nrm, np.eye(3)[int(np.argmin(np.abs(nrm)))])
            a /= np.linalg.norm(a)
            basis = np.stack([a, np.cross(nrm, a)])
        else:
            basis = np.eye(3)
        edge = float(np.linalg.norm(X[volume_nb.indices[volume_nb.indptr[v]:volume_nb.indptr[v + 1]]] - old,
                                    axis=1).mean())
        d = len(basis)
        simplex = np.vstack([np.zeros(d), SEARCH_SIMPLEX * edge * np.eye(d)])
        # in the tangent plane (projection onto the mesh costs ~1 ms a point): projected once at the end
        u = _nelder_mead(X, tets[tt], v, old, np.ascontiguousarray(basis), simplex, SEARCH_EVALUATIONS,
                         1e-3 * edge, 1e-6, bool(sliding[v]), start[v], float(max_slide))
        m, qn = worst(v, tt, place(v, old + u @ basis))
        if better(m, qn, before):
            return qn
        X[v] = old
        return None

    for stage in (smooth, search):
        for _ in range(sweeps):
            moved = 0
            nodes = np.unique(tets[q < target])
            nodes = nodes[movable[nodes]]
            cand = targets(nodes) if stage is smooth else np.empty((0, len(nodes), 3))
            for k, v in enumerate(nodes):
                tt = incident.indices[incident.indptr[v]:incident.indptr[v + 1]]
                qn = stage(int(v), tt, q[tt], cand[:, k])
                if qn is not None:
                    q[tt] = qn
                    moved += 1
            if stage is smooth:
                rep.smoothed += moved
            else:
                rep.searched += moved
            if moved == 0:
                break
    rep.below_after = int((q < target).sum())
    rep.worst_after = float(q.min()) if len(q) else 1.0
    rep.seconds = time.perf_counter() - t0
    return rep
