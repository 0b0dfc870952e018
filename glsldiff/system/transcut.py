"""TransCut's diffusion matrix on a tetrahedral mesh (Li et al. 2012, eqs. 10-14;
``../shared/notes/transcut.md`` section 2).

Per tetrahedron ``t = {i, j, k, l}`` with ``kappa_t`` (mm) and ``mu_t`` (mm^-1) constant, the
cotangent weight of edge ``{i, j}`` is ``w_ijt = -(1/6) kappa_t |kl| cot(theta_kl)``, ``|kl|``
the length of the opposite edge and ``theta_kl`` the dihedral angle there (eq. 10). With
``V_i`` the summed volume of the tetrahedra around node ``i`` and ``S_i`` the summed area of
the boundary triangles around it:

    M_ij = 4 w_ij (eq. 14),   M_ii = -4 sum_j w_ij + sum_t mu_t V_t + [2 S_i / (3A)]_boundary (eq. 13),
    b_i = 8 S_i q_i / (3 A (1 - F_dr)) on the boundary (eq. 12),

``A = (1 + F_dr) / (1 - F_dr)`` the boundary constant, ``q`` the transmitted irradiance (the
"diffused incoming light" of eq. 2). The absorption term takes the paper's ``V_i mu(x_i)`` as
the volume-weighted ``sum_t mu_t V_t`` (the notes' reading). ``M / 4`` is then the linear
finite-element matrix with lumped absorption and boundary mass, which
:func:`glsldiff.oracle.fem.assemble_p1` builds independently (tests compare them). Lengths in
mm; ``M`` in mm, ``b`` in mm^2 times the units of ``q``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.pillow import TET_EDGES, signed_volumes
from glsldiff.grids.tetrahedral.tetwild import dihedral_cos_sin
from glsldiff.mesh import vertex_areas
from glsldiff.physics.material import coefficients
from glsldiff.physics.optics import boundary_constant, fdr
from scipy.spatial import cKDTree

__all__ = ["cotangent_weights", "de_matrix", "de_rhs", "paint_weights", "paint_blend", "TransCutSystem"]

def _check(positions: ArrayLike, tets: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    X = np.asarray(positions, dtype=np.float64)
    T = np.asarray(tets, dtype=np.int64)
    if X.ndim != 2 or X.shape[1] != 3 or T.ndim != 2 or T.shape[1] != 4 or len(T) == 0:
        raise InputError(f"positions {X.shape} and tets {T.shape} must be (n, 3) and (T, 4), T > 0")
    if T.min() < 0 or T.max() >= len(X):
        raise InputError("tets index nodes outside positions")
    return X, T


def cotangent_weights(positions: ArrayLike, tets: ArrayLike, kappa_t: ArrayLike) -> NDArray[np.float64]:
    """``(T, 6)`` ``w_ijt = -(1/6) kappa_t |kl| cot(theta_kl)`` for the edges ``{i, j}`` of
    :data:`glsldiff.grids.tetrahedral.pillow.TET_EDGES` (eq. 10), ``{k, l}`` the opposite edge (``5 - e``) and
    ``theta_kl`` the dihedral angle there; positive where it is obtuse."""
    X, T = _check(positions, tets)
    P = X[T]
    k = np.broadcast_to(np.asarray(kappa_t, dtype=np.float64), (len(T),))
    c, s = dihedral_cos_sin(P)
    length = np.stack([np.linalg.norm(P[:, j] - P[:, i], axis=1) for i, j in TET_EDGES], axis=1)
    cot_len = length * c / np.maximum(s, 1e-300)                 # |kl| cot(theta_kl) at each edge
    return -k[:, None] * cot_len[:, ::-1] / 6.0                  # the opposite edge's, for each edge


def _S(X: NDArray[np.float64], surface: NDArray[np.int64]) -> NDArray[np.float64]:
    """``(n,)`` ``S_i``: the summed area of the boundary triangles around each node, mm^2."""
    return 3.0 * vertex_areas(X, surface)


def de_matrix(positions: ArrayLike, tets: ArrayLike, surface: ArrayLike, kappa_t: ArrayLike, mu_t: ArrayLike,
              eta: float, A: float | None = None, inert: ArrayLike | None = None) -> sp.csr_matrix:
    """``(n, n)`` TransCut's ``M`` (eqs. 13-14) for per-tetrahedron ``kappa_t``, ``mu_t``
    (scalars: homogeneous), boundary triangles ``surface`` ``(F, 3)``; ``A`` defaults to
    ``boundary_constant(eta)``; ``inert`` ``(T,)`` marks tetrahedra that carry no stiffness
    (:attr:`glsldiff.grids.tetrahedral.tetwild.TetMesh.inert`: slivers; their absorption stays)."""
    X, T = _check(positions, tets)
    S = np.asarray(surface, dtype=np.int64)
    A = float(boundary_constant(eta)) if A is None else float(A)
    live = np.ones(len(T)) if inert is None else ~np.asarray(inert, dtype=bool)
    w = cotangent_weights(X, T, kappa_t) * live[:, None]
    n = len(X)
    i, j = T[:, TET_EDGES[:, 0]].ravel(), T[:, TET_EDGES[:, 1]].ravel()
    off = 4.0 * w.ravel()
    diag = -np.bincount(i, off, minlength=n) - np.bincount(j, off, minlength=n)
    vol = np.abs(signed_volumes(X, T))
    mu = np.broadcast_to(np.asarray(mu_t, dtype=np.float64), (len(T),))
    diag += np.bincount(T.ravel(), np.repeat(mu * vol, 4), minlength=n)          # sum_t mu_t V_t
    diag += 2.0 * _S(X, S) / (3.0 * A)                                           # 2 S_i / (3A)
    M = sp.coo_matrix((np.concatenate([off, off, diag]), (np.concatenate([i, j, np.arange(n)]),
                                                          np.concatenate([j, i, np.arange(n)]))), shape=(n, n))
    return M.tocsr()


def de_rhs(positions: ArrayLike, surface: ArrayLike, q: ArrayLike, eta: float, A: float | None = None
           ) -> NDArray[np.float64]:
    """``(n,)`` TransCut's ``b`` (eq. 12) for transmitted irradiance ``q`` per node (only
    boundary nodes' values matter)."""
    X = np.asarray(positions, dtype=np.float64)
    S = np.asarray(surface, dtype=np.int64)
    A = float(boundary_constant(eta)) if A is None else float(A)
    qn = np.broadcast_to(np.asarray(q, dtype=np.float64), (len(X),))
    return 8.0 * _S(X, S) * qn / (3.0 * A * (1.0 - float(fdr(eta))))


def paint_weights(centres: ArrayLike, points: ArrayLike, radius_mm: float) -> NDArray[np.float64]:
    """TransCut's paint influence (section 5.2): ``exp(-d^2 / (2 r^2))`` with ``d`` the distance
    (mm) from each of ``centres`` ``(n, 3)`` to the closest stroke point of ``points`` ``(k, 3)``,
    ``r = radius_mm`` the user's Gaussian (how far the paint reaches into the volume)."""
    P = np.atleast_2d(np.asarray(points, dtype=np.float64))
    if P.ndim != 2 or P.shape[1] != 3 or len(P) == 0 or not np.all(np.isfinite(P)):
        raise InputError(f"paint points must be (k, 3) finite mm coordinates, k >= 1; got shape {P.shape}")
    if not (np.isfinite(radius_mm) and radius_mm > 0):
        raise InputError(f"paint radius {radius_mm!r} mm must be positive")
    d, _ = cKDTree(P).query(np.asarray(centres, dtype=np.float64))
    return np.exp(-0.5 * (d / float(radius_mm)) ** 2)


def paint_blend(old: ArrayLike, target: ArrayLike, weight: ArrayLike, strength: float = 1.0) -> NDArray[np.float64]:
    """``old + strength w (target - old)``: the paint's new value (the paper does not say how the
    weight blends; this is a linear blend, full ``target`` where ``strength w = 1``)."""
    if not 0.0 <= strength <= 1.0:
        raise InputError(f"paint strength {strength!r} must be in [0, 1]")
    o, t = np.asarray(old, dtype=np.float64), np.asarray(target, dtype=np.float64)
    w = np.asarray(weight, dtype=np.float64)
    w = w.reshape(w.shape + (1,) * (o.ndim - w.ndim))
    return o + strength * w * (t - o)


@dataclass(eq=False)
class TransCutSystem:
    """``M`` of eqs. 13-14 for per-tetrahedron absorption ``sigma_a`` and reduced scattering
    ``sigma_s`` (mm^-1, one channel), kept so that a paint stroke updates only the entries of
    the tetrahedra it changes (:meth:`paint`; TransCut section 5.2) instead of re-assembling."""

    positions: NDArray[np.float64]
    tets: NDArray[np.int64]
    surface: NDArray[np.int64]
    sigma_a: NDArray[np.float64]
    sigma_s: NDArray[np.float64]
    eta: float
    M: sp.csr_matrix = field(init=False)
    _slots: NDArray[np.int64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        T = len(self.tets)
        self.sigma_a = np.array(np.broadcast_to(np.asarray(self.sigma_a, dtype=np.float64), (T,)))
        self.sigma_s = np.array(np.broadcast_to(np.asarray(self.sigma_s, dtype=np.float64), (T,)))
        if np.any(self.sigma_a < 0) or np.any(self.sigma_s < 0) or np.any(self.sigma_a + self.sigma_s <= 0):
            raise InputError("sigma_a and sigma_s' must be >= 0 with a positive sum in every tetrahedron")
        self.M = de_matrix(self.positions, self.tets, self.surface, self.kappa, self.sigma_a, self.eta)
        self.M.sort_indices()
        n = self.M.shape[0]
        rows = np.repeat(np.arange(n), np.diff(self.M.indptr))
        keys = rows * n + self.M.indices                            # increasing: rows, then sorted columns
        T4 = self.tets
        r = np.concatenate([T4[:, TET_EDGES[:, 0]], T4[:, TET_EDGES[:, 1]], T4], axis=1)   # (T, 16)
        c = np.concatenate([T4[:, TET_EDGES[:, 1]], T4[:, TET_EDGES[:, 0]], T4], axis=1)
        self._slots = np.searchsorted(keys, r * n + c)

    @property
    def kappa(self) -> NDArray[np.float64]:
        """``(T,)`` diffusion coefficient ``1 / (3 (sigma_a + sigma_s'))``, mm."""
        return coefficients(self.sigma_a, self.sigma_s)[0]

    def _entries(self, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        """``(len(idx), 16)`` the tetrahedra's contributions at :attr:`_slots`: off-diagonal
        ``4 w`` twice, then the diagonal ``-4 sum w + mu V`` of each vertex."""
        X, T = self.positions, self.tets[idx]
        w = 4.0 * cotangent_weights(X, T, self.kappa[idx])                    # (k, 6)
        diag = np.zeros((len(idx), 4))
        for e, (a, b) in enumerate(TET_EDGES):
            diag[:, a] -= w[:, e]
            diag[:, b] -= w[:, e]
        diag += (self.sigma_a[idx] * np.abs(signed_volumes(X, T)))[:, None]
        return np.concatenate([w, w, diag], axis=1)

    def paint(self, points: ArrayLike, radius_mm: float, sigma_a: float | None = None,
              sigma_s: float | None = None, strength: float = 1.0, cutoff: float = 1e-4) -> dict[str, Any]:
        """Blend the tetrahedra's ``sigma_a`` / ``sigma_s'`` towards the given values with the
        Gaussian weight of their centres' distance to the stroke ``points`` (:func:`paint_weights`,
        :func:`paint_blend`); tetrahedra whose weight is below ``cutoff`` keep theirs. Only
        the rows of the changed tetrahedra's vertices change. Returns counts and seconds."""
        if sigma_a is None and sigma_s is None:
            raise InputError("paint needs a target sigma_a or sigma_s' (mm^-1)")
        for name, v in (("sigma_a", sigma_a), ("sigma_s'", sigma_s)):
            if v is not None and not (np.isfinite(v) and v >= 0):
                raise InputError(f"paint target {name} {v!r} mm^-1 must be finite and >= 0")
        t0 = time.perf_counter()
        centres = self.positions[self.tets].mean(axis=1)
        w = paint_weights(centres, points, radius_mm)
        idx = np.flatnonzero(w * strength >= cutoff)
        before = self._entries(idx)
        if sigma_a is not None:
            self.sigma_a[idx] = paint_blend(self.sigma_a[idx], sigma_a, w[idx], strength)
        if sigma_s is not None:
            self.sigma_s[idx] = paint_blend(self.sigma_s[idx], sigma_s, w[idx], strength)
        if np.any(self.sigma_a[idx] + self.sigma_s[idx] <= 0):
            raise InputError("the paint leaves sigma_a + sigma_s' = 0 in some tetrahedra; paint a positive value")
        np.add.at(self.M.data, self._slots[idx].ravel(), (self._entries(idx) - before).ravel())
        return {"tets": int(len(idx)), "rows": int(len(np.unique(self.tets[idx]))),
                "seconds": time.perf_counter() - t0}
