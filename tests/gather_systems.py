"""Test systems shared by the gather-solver tests (test_gather.py, test_gather_multigrid.py)."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
from glsldiff.mesh import sphere_mesh
from glsldiff.oracle.fem import assemble_tet
from glsldiff.system.tet_problem import TetProblem

KAPPA_MU = ((0.3, 0.05), (0.2, 0.1), (0.45, 0.02))


def laplacian7(m: int, kappa: float, mu: float, robin: float, h: float = 0.5) -> sp.csr_matrix:
    """``m^3`` 7-point ``-div(kappa grad)`` + ``mu`` (finite volumes, mm) with ``robin h^2`` added
    on the diagonal per boundary face of a node."""
    e = np.ones(m)
    T = sp.diags([-e[:-1], 2 * e, -e[:-1]], [-1, 0, 1])
    I = sp.identity(m)
    L = (sp.kron(sp.kron(T, I), I) + sp.kron(sp.kron(I, T), I) + sp.kron(sp.kron(I, I), T)) * kappa * h
    idx = np.indices((m, m, m)).reshape(3, -1)
    faces = ((idx == 0) | (idx == m - 1)).sum(axis=0)
    return (L + sp.diags(mu * h**3 + robin * h**2 * faces)).tocsr()


def lit_laplacians(m: int, kappas=((0.3, 0.3), (0.2, 0.5), (0.5, 0.2))) -> tuple[list[sp.csr_matrix], np.ndarray]:
    """:func:`laplacian7` of ``m^3`` nodes per channel (kappa, mu pairs), Robin 0.25, the
    z = 0 face lit by a random source: the three matrices and ``b`` ``(m^3, 3)``."""
    mats = [laplacian7(m, kappa, mu, 0.25) for kappa, mu in kappas]
    b = np.zeros((m**3, 3))
    b[: m * m] = np.random.default_rng(3).uniform(0.5, 1.0, (m * m, 3))   # the z = 0 face lit
    return mats, b


def p1_system(subdivisions: int, n: int) -> tuple[list[sp.csr_matrix], np.ndarray]:
    """The P1 system (oracle.fem.assemble_tet) of a 10 mm sphere (5 mm cubes, ``n`` nodes per
    cube edge) on the active nodes, kappa and mu per channel (:data:`KAPPA_MU`), C = 2, a random
    boundary source: the three channel matrices and ``b`` ``(n_active, 3)``."""
    g = build_fem_grid(sphere_mesh(10.0, subdivisions=subdivisions), n=n, cube_size=5.0)
    q = np.random.default_rng(5).uniform(0.5, 1.5, len(g.positions))[g.surface_nodes]
    kappa, mu = (np.array([km[i] for km in KAPPA_MU]) for i in (0, 1))
    s = assemble_tet(TetProblem(g, kappa, mu, np.repeat(q[:, None], 3, axis=1), C=2.0))
    return [s.block(c)[0].tocsr() for c in range(3)], s.b.reshape(3, -1).T.copy()


def spsolve3(mats: list[sp.csr_matrix], b: np.ndarray) -> np.ndarray:
    """Direct solve of each channel: ``(n, 3)``."""
    return np.stack([spla.spsolve(M.tocsc(), b[:, c]) for c, M in enumerate(mats)], axis=1)


def rel(x: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(x - ref) / np.linalg.norm(ref))
