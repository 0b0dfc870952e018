"""Map a polycube lattice into the object (Wang et al. 2008, section 5.1, figure 4 (d)-(f)).

1. **Project** each boundary node from the polycube surface (its cell centre moved half a
   step outward) to the closest point of the mesh.
2. **Relax** the boundary nodes towards an even distribution on the surface: a few rounds
   of Laplacian smoothing over the polycube-surface adjacency, each followed by
   re-projection onto the mesh (after Turk 1992). Smoothing also unfolds the places where
   closest-point projection put neighbours in the wrong order. Nodes it leaves on top of
   one another (a cluster funnelled onto a sharp feature) are moved to the surface hit of
   the line along their polycube face axis (:func:`separate_collapsed`).
3. **Partners**: each boundary node's interior partner goes to ``p_b - d n_b``, ``n_b`` the
   mesh normal, ``d = 1/10`` of the mean distance between surface-adjacent boundary nodes
   (a partner shared by two or three boundary nodes at a polycube edge takes the mean).
4. **Remaining interior nodes**: first the harmonic (Tutte-like) embedding with boundary
   nodes and partners fixed (sparse CG solve), then the paper's objective
   ``sum_i Var({|v_i - v_j|})``, minimised with L-BFGS over these free nodes (the sum runs
   over them too: a partner's short link ``d`` is there by design, and its variance
   would pull the next layer towards the surface). The objective does not see orientation
   and, left alone, folds cells; so only the largest fraction of the move away from the
   harmonic placement is kept that inverts no cell and keeps every free node inside.

Every stage records what it achieved in :class:`MappingStats`.
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import scipy.optimize as so
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff.core.errors import InputError
from glsldiff.grids.lattice import Lattice
from glsldiff.grids.graph import edge_adjacency, mean_operator
from glsldiff.mesh import Mesh, axis_hits, closest_points, contains

logger = logging.getLogger(__name__)


@dataclass
class MappingStats:
    """Quality and cost of the mapping (lengths in mm, times in s)."""

    boundary_spacing: float = float("nan")     # mean distance of surface-adjacent boundary nodes
    spacing_cv_projected: float = float("nan")  # coefficient of variation after projection
    spacing_cv_relaxed: float = float("nan")    # ... after relaxation
    flipped_projected: int = 0                  # boundary nodes whose mesh normal opposes the polycube face
    flipped_relaxed: int = 0
    separated: int = 0                          # collapsed boundary nodes moved to their axis ray hit
    d: float = float("nan")                     # boundary-to-partner distance
    shared_partners: int = 0
    variance_harmonic: float = float("nan")     # mean link-length variance / h^2, harmonic placement
    variance_final: float = float("nan")        # ... after the variance minimisation
    variance_iterations: int = 0
    variance_step: float = float("nan")         # fraction of the L-BFGS move kept (fold/containment guard)
    inverted: int = 0                           # interior nodes whose local frame is left-handed
    outside_checked: int = 0                    # interior nodes tested for containment
    outside: int = 0                            # of those, outside the mesh
    seconds: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


def _pair_lengths(x: NDArray, pairs_local: NDArray) -> NDArray:
    return np.linalg.norm(x[pairs_local[:, 0]] - x[pairs_local[:, 1]], axis=1)


def _inverted(pos: NDArray, nbrs: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Interior nodes whose lattice axes (x+ - x-, y+ - y-, z+ - z-) are not right-handed."""
    ex = pos[nbrs[:, 1]] - pos[nbrs[:, 0]]
    ey = pos[nbrs[:, 3]] - pos[nbrs[:, 2]]
    ez = pos[nbrs[:, 5]] - pos[nbrs[:, 4]]
    return np.einsum("ij,ij->i", np.cross(ex, ey), ez) <= 0


def _collapsed(xb: NDArray, tol: float) -> NDArray[np.int64]:
    """Indices of the boundary nodes closer than ``tol`` (mm) to another one."""
    pairs = cKDTree(xb).query_pairs(tol, output_type="ndarray")
    return np.unique(pairs)


def separate_collapsed(lattice: Lattice, mesh: Mesh, xb: NDArray, nrm: NDArray, tol: float,
                       rounds: int = 3) -> int:
    """Move boundary nodes that closest-point projection collapsed onto one point.

    Closest points funnel every query point in the normal cone of a convex feature (or
    of a concave one, from inside) onto that feature, and re-projection during
    relaxation can keep a cluster together; its partners then coincide and the links
    have zero length. A node within ``tol`` (mm) of another is moved to the nearest
    surface hit of the line through its lattice position along its polycube face axis:
    distinct parallel lines cannot share a hit (a node whose line misses the mesh stays).
    ``xb``, ``nrm`` are updated in place; returns the number of nodes moved. Raises
    InputError if two nodes still coincide (closer than ``1e-4 tol``).
    """
    moved = np.zeros(len(xb), dtype=bool)
    for _ in range(rounds):
        bad = _collapsed(xb, tol)
        bad = bad[~moved[bad]]
        if bad.size == 0:
            break
        nodes = lattice.boundary[bad]
        hit = axis_hits(mesh, lattice.lattice_positions[nodes], np.abs(lattice.outward[bad]).argmax(axis=1))
        ok = np.isfinite(hit[:, 0])
        if ok.any():
            xb[bad[ok]], _, _, nrm[bad[ok]] = closest_points(mesh, hit[ok])
        moved[bad] = True
    left = _collapsed(xb, 1e-4 * tol)
    if left.size:
        raise InputError(f"mapping: {left.size} boundary nodes still coincide with another after "
                         "re-projection along their polycube axes (the mesh has features thinner than the "
                         "node spacing here); use smaller cubes or a smoother mesh")
    return int(moved.sum())


def link_variance(pos: NDArray, centers: NDArray[np.int64], nbrs: NDArray[np.int64]) -> NDArray[np.float64]:
    """Variance of the six link lengths of each node ``centers[i]`` (mm^2)."""
    L = np.linalg.norm(pos[nbrs] - pos[centers, None, :], axis=2)
    return L.var(axis=1)


def _variance_objective(x: NDArray, pos: NDArray, free: NDArray, centers: NDArray, nbrs: NDArray,
                        h2: float) -> tuple[float, NDArray]:
    """``sum_i Var_j |v_i - v_j| / h^2`` and its gradient w.r.t. the free node positions."""
    p = pos.copy()
    p[free] = x.reshape(-1, 3)
    diff = p[centers, None, :] - p[nbrs]                       # (m, 6, 3)
    L = np.sqrt(np.einsum("mkc,mkc->mk", diff, diff))
    dev = L - L.mean(axis=1, keepdims=True)
    f = float((dev ** 2).mean(axis=1).sum() / h2)
    g_l = (2.0 / 6.0) * dev / h2                                # d f / d L (mean term cancels)
    g_vec = (g_l / np.maximum(L, 1e-300))[..., None] * diff     # d f / d v_center per link
    grad = np.zeros_like(p)
    np.add.at(grad, centers, g_vec.sum(axis=1))
    np.add.at(grad, nbrs.ravel(), -g_vec.reshape(-1, 3))
    return f, grad[free].ravel()


def map_to_mesh(lattice: Lattice, mesh: Mesh, relax_iterations: int = 10, relax_step: float = 0.5,
                variance_iterations: int = 100, d_fraction: float = 0.1,
                containment_samples: int = 20000, seed: int = 0,
                collapse_tol: float = 0.01) -> tuple[NDArray, NDArray, MappingStats]:
    """Node positions in the object for every lattice node.

    Parameters
    ----------
    lattice
        The polycube lattice (its polycube approximates ``mesh``; same units, mm).
    mesh
        A closed :class:`glsldiff.mesh.Mesh`.
    relax_iterations, relax_step
        Smoothing rounds (each followed by re-projection) and the step towards the
        neighbour mean.
    variance_iterations
        L-BFGS iterations of the link-length variance minimisation (0 keeps the
        harmonic placement).
    d_fraction
        Partner distance as a fraction of the mean boundary spacing (paper: 1/10).
    collapse_tol
        Boundary nodes closer than this fraction of the mean spacing count as collapsed
        and are separated (:func:`separate_collapsed`).
    containment_samples
        Interior nodes (random sample) tested for lying inside the mesh.

    Returns
    -------
    positions, normals, stats
        ``(N, 3)`` positions (removed nodes keep their lattice position), ``(n_boundary, 3)``
        outward unit normals at the boundary nodes, and :class:`MappingStats`.
    """
    st = MappingStats(shared_partners=lattice.shared_partners)
    t0 = time.perf_counter()
    pos = lattice.lattice_positions.copy()
    b, link = lattice.boundary, lattice.link
    local = np.full(lattice.size_nodes, -1, dtype=np.int64)
    local[b] = np.arange(b.size)
    pairs = local[lattice.surface_pairs]
    M = mean_operator(edge_adjacency(local[lattice.surface_pairs], b.size))
    axis = lattice.outward

    # 1. projection
    xb, _, _, nrm = closest_points(mesh, pos[b] + 0.5 * lattice.h * axis)
    lengths = _pair_lengths(xb, pairs)
    st.spacing_cv_projected = float(lengths.std() / lengths.mean())
    st.flipped_projected = int((np.einsum("ij,ij->i", nrm, axis) < 0).sum())
    st.seconds["project"] = time.perf_counter() - t0

    # 2. relaxation with re-projection
    t1 = time.perf_counter()
    for _ in range(relax_iterations):
        xb = xb + relax_step * (M @ xb - xb)
        xb, _, _, nrm = closest_points(mesh, xb)
    lengths = _pair_lengths(xb, pairs)
    st.boundary_spacing = float(lengths.mean())
    st.spacing_cv_relaxed = float(lengths.std() / lengths.mean())
    st.flipped_relaxed = int((np.einsum("ij,ij->i", nrm, axis) < 0).sum())
    st.separated = separate_collapsed(lattice, mesh, xb, nrm, collapse_tol * st.boundary_spacing)
    st.seconds["relax"] = time.perf_counter() - t1
    pos[b] = xb

    # 3. partners at d along the inward normal (mean over boundary nodes sharing a partner)
    d = d_fraction * st.boundary_spacing
    st.d = d
    target = xb - d * nrm
    cnt = lattice.partner_count
    acc = np.zeros_like(pos)
    np.add.at(acc, link, target)
    partners = np.flatnonzero(cnt > 0)
    pos[partners] = acc[partners] / cnt[partners, None]

    # 4. remaining interior nodes: harmonic placement, then variance minimisation
    t2 = time.perf_counter()
    interior = lattice.interior
    nbrs = lattice.neighbours
    fixed = np.zeros(lattice.size_nodes, dtype=bool)
    fixed[b] = True
    fixed[partners] = True
    free = interior[~fixed[interior]]
    if free.size:
        fi = np.full(lattice.size_nodes, -1, dtype=np.int64)
        fi[free] = np.arange(free.size)
        rows = nbrs[fi[interior] >= 0]                       # neighbours of free nodes
        r = np.repeat(np.arange(free.size), 6)
        c = rows.ravel()
        is_free = fi[c] >= 0
        L = sp.coo_matrix((np.full(is_free.sum(), -1.0), (r[is_free], fi[c[is_free]])),
                          shape=(free.size, free.size)).tocsr() + 6.0 * sp.identity(free.size, format="csr")
        rhs = np.zeros((free.size, 3))
        np.add.at(rhs, r[~is_free], pos[c[~is_free]])
        Dinv = sp.diags(1.0 / L.diagonal())
        for k in range(3):
            pos[free, k], info = spla.cg(L, rhs[:, k], x0=pos[free, k], rtol=1e-8, maxiter=2000, M=Dinv)
            if info > 0:
                logger.warning("harmonic placement: CG did not reach 1e-8 in 2000 iterations (axis %d)", k)
    h2 = lattice.h ** 2
    # the objective runs over the free nodes: a partner's links include its short link d
    # by design, and counting it would pull the next layer towards the surface
    free_nbrs = lattice.lattice_neighbours[free]
    st.variance_harmonic = float(link_variance(pos, free, free_nbrs).mean() / h2) if free.size else 0.0
    st.seconds["harmonic"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    if free.size and variance_iterations > 0:
        harmonic = pos[free].copy()
        res = so.minimize(_variance_objective, harmonic.ravel(), jac=True, method="L-BFGS-B",
                          args=(pos, free, free, free_nbrs, h2),
                          options={"maxiter": variance_iterations, "maxcor": 10})
        st.variance_iterations = int(res.nit)
        # The variance objective is blind to orientation: unconstrained it folds cells.
        # Keep the largest step from the harmonic placement that inverts no cell and
        # moves no sampled node out of the mesh that was inside.
        base_inv = _inverted(pos, nbrs)
        optimum = res.x.reshape(-1, 3)
        for alpha in (1.0, 0.5, 0.25, 0.125, 0.0625, 0.0):
            pos[free] = harmonic + alpha * (optimum - harmonic)
            if alpha == 0.0 or (np.sum(_inverted(pos, nbrs) & ~base_inv) == 0
                                and contains(mesh, pos[free]).all()):
                break
        st.variance_step = alpha
    st.variance_final = float(link_variance(pos, free, free_nbrs).mean() / h2) if free.size else 0.0
    st.seconds["variance"] = time.perf_counter() - t3

    # checks: left-handed local frames, interior nodes outside the mesh
    p = pos
    st.inverted = int(_inverted(p, nbrs).sum())
    rng = np.random.default_rng(seed)
    sample = interior if interior.size <= containment_samples else rng.choice(interior, containment_samples,
                                                                               replace=False)
    st.outside_checked = int(sample.size)
    st.outside = int((~contains(mesh, p[sample])).sum())
    st.seconds["total"] = time.perf_counter() - t0
    return pos, nrm, st
