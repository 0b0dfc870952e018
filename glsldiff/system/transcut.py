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

import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.pillow import TET_EDGES, signed_volumes
from glsldiff.grids.tetwild import dihedral_cos_sin
from glsldiff.mesh import vertex_areas
from glsldiff.physics.optics import boundary_constant, fdr

__all__ = ["cotangent_weights", "de_matrix", "de_rhs"]

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
    :data:`glsldiff.grids.pillow.TET_EDGES` (eq. 10), ``{k, l}`` the opposite edge (``5 - e``) and
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
              eta: float, A: float | None = None) -> sp.csr_matrix:
    """``(n, n)`` TransCut's ``M`` (eqs. 13-14) for per-tetrahedron ``kappa_t``, ``mu_t``
    (scalars: homogeneous), boundary triangles ``surface`` ``(F, 3)``; ``A`` defaults to
    ``boundary_constant(eta)``."""
    X, T = _check(positions, tets)
    S = np.asarray(surface, dtype=np.int64)
    A = float(boundary_constant(eta)) if A is None else float(A)
    w = cotangent_weights(X, T, kappa_t)
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
