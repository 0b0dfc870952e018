"""GLSL path of the inverse fit: forward and adjoint solves by Jacobi relaxation on the GPU.

The single-channel model runs three illumination conditions at once, one per RGB channel
of the ping-pong buffers (the material is the same in all three). The adjoint system
``A^T lambda = g`` is solved with the *forward* shaders: on a regular grid ``A`` becomes
symmetric after scaling each boundary row by ``s_b = A[j, b] / A[b, j]`` (its only
off-diagonal pair), so ``A^T = A' S^-1`` with ``A' = S A`` and the adjoint is the forward
problem ``A nu = S^-1 g`` with a signed virtual boundary source, ``lambda = S nu`` -- the
paper's adjoint equation (section 4.3) in discrete form. Every solve starts from the
previous solution of the same condition (the material changes little between steps).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import SolverError
from glsldiff.inverse.model import Factorized, ForwardModel
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import RELAX_TOL

Array = NDArray[np.float64]


@dataclass
class GlslForwardModel(ForwardModel):
    """:class:`ForwardModel` whose solves run in GLSL (``tol``: Jacobi residual, ``maxiter``: sweeps
    per solve)."""

    tol: float = RELAX_TOL
    maxiter: int = 50000
    sweeps: int = 0
    _solver: GlslDiffusion | None = field(default=None, repr=False)
    _warm: dict = field(default_factory=dict, repr=False)

    def factorize(self, kappa: Array, mu: Array) -> "GlslFactorized":
        kappa, mu = np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64)
        t0 = time.perf_counter()
        kv, mv = self.volume(kappa, 1.0), self.volume(mu, 0.0)
        if self._solver is None:
            prob = DiffusionProblem(self.grid, kv, mv, C=self.C, eta=self.eta, stencil=self.stencil,
                                    face_mean=self.face_mean)
            self._solver = GlslDiffusion(prob)
        else:
            self._solver.set_material(kv, mv)
        A = self.matrix(kappa, mu)
        self.stats.factor_seconds += time.perf_counter() - t0
        return GlslFactorized(self, kappa, mu, A, None)

    def release(self) -> None:
        if self._solver is not None:
            self._solver.release()
            self._solver = None


@dataclass
class GlslFactorized(Factorized):
    """Solves of one material on the GPU (see the module docstring)."""

    def _solve(self, B: Array, trans: str, key: str | None = None) -> Array:
        m: GlslForwardModel = self.model  # type: ignore[assignment]
        t0 = time.perf_counter()
        bnd, prt = m.boundary, m.partner
        if np.any(np.delete(B, bnd, axis=0)):
            raise SolverError("the GLSL path takes right-hand sides on boundary nodes only")
        s = np.ones(bnd.size)
        if trans == "T":
            s = np.asarray(self.A[prt, bnd]).ravel() / np.asarray(self.A[bnd, prt]).ravel()
        kb = self.kappa[bnd] if m.stencil == "paper" else 1.0
        Qv = B[bnd] / s[:, None] / (m.d * kb)[:, None]
        g = m.grid
        solver = m._solver
        X = np.zeros((m.n, B.shape[1]))
        for start in range(0, B.shape[1], 3):
            cols = list(range(start, min(start + 3, B.shape[1])))
            q = np.zeros((g.size, 3))
            q[g.graph.boundary, :len(cols)] = Qv[:, cols]
            solver.set_q(q.reshape(g.shape + (3,)))
            key = (trans, start)
            phi, rep = solver.solve(tol=m.tol, maxiter=m.maxiter, x0=m._warm.get(key))
            m._warm[key] = phi
            m.sweeps += rep.sweeps
            x = solver.problem.from_phi(phi).reshape(-1, 3)[g.graph.active]
            X[:, cols] = x[:, :len(cols)]
        if trans == "T":
            X[bnd] *= s[:, None]
        st = m.stats
        st.solves += B.shape[1]
        st.solve_seconds += time.perf_counter() - t0
        return X
