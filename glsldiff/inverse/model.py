"""Single-channel forward model of a block sample and its exact discrete adjoint.

For one RGB channel, material vectors ``kappa`` (mm) and ``mu`` (mm^-1) over the active
nodes of a :class:`~glsldiff.grids.regular.RegularGrid` (order of ``grid.graph.active``) define the
system ``A(kappa, mu) x_m = b_m(kappa)`` of :mod:`glsldiff.oracle.solvers` (either stencil), one
right-hand side per illumination ``m``. An illumination ``Q`` is the transmitted irradiance at
the boundary nodes; the predicted radiance at boundary node ``b`` is ``L = F_t B`` with the
exitant bracket of the model's convention (:mod:`glsldiff.physics.exitance`): by default
``"p1"``, the Marshak source ``q = s Q``, ``s = 4 / (1 - Fdr)``, and ``B = a phi - b q``, the
form that matches Monte Carlo (so a fit recovers physical kappa and mu); ``"paper"``:
``q = Q`` and ``B = (phi - q) / (2 pi)``, the paper's net flux. The fluence is linear in the
source, so the model solves with ``Q`` itself and folds ``s`` into the bracket's coefficients.

All M forward and all M adjoint systems share one matrix, so :class:`Factorized` factorises
it once (SuperLU) and solves every right-hand side with that factor; the adjoint uses the
transposed factor. Above :data:`~glsldiff.inverse.amg.AUTO_MAX_DIRECT` nodes (``solver="auto"``)
or with ``solver="pyamg"``, :class:`AmgFactorized` does the same with one multigrid hierarchy
per material (classical Ruge-Stueben) and conjugate gradients, warm-started from the previous evaluation
(:mod:`glsldiff.inverse.amg`). :meth:`Factorized.contract` gives ``sum_m lambda_m^T d r_m / dp`` for the
residual ``r_m = A x_m - b_m``: with the explicit part of the objective's derivative this
is the gradient of the *discrete* objective (checked against finite differences in tests).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from glsldiff.core.interrupt import interruptible
from glsldiff.core.checks import choice, integer, real
from glsldiff.core.errors import InputError, SolverError
from glsldiff.grids.regular import RegularGrid
from glsldiff.physics.exitance import EXITANT, exitance_coefficients, source_from_irradiance
from glsldiff.physics.optics import boundary_constant, fresnel_transmittance
from glsldiff.system.problem import FACE_MEANS, STENCILS, DiffusionProblem
from glsldiff.oracle.assembly import channel_matrix
from glsldiff.inverse.amg import (AMG_KINDS, AMG_MAXITER, AMG_RTOL, AUTO_MAX_DIRECT, SYMMETRY_TOL, AmgState, Hierarchy,
                                  KrylovReport, asymmetry, boundary_scaling, nonsymmetric_hierarchy, solve_columns,
                                  solve_nonsymmetric)

Array = NDArray[np.float64]

#: ``ForwardModel.solver``: "auto" picks "superlu" up to AUTO_MAX_DIRECT active nodes, "pyamg" above.
SOLVERS = ("auto", "superlu", "pyamg")


def resolve_solver(solver: str, n: int) -> str:
    """``solver`` with "auto" resolved for a system of ``n`` active nodes."""
    choice(solver, "solver", SOLVERS)
    if solver != "auto":
        return solver
    return "superlu" if n <= AUTO_MAX_DIRECT else "pyamg"


@dataclass
class SolveStats:
    """Work counters of a model: materials prepared (``factorizations``: SuperLU factors or
    multigrid hierarchies; ``setups`` of them full pyamg set-ups, ``galerkin`` reused
    prolongators), right-hand sides solved, Krylov iterations summed over the columns, columns
    accepted above the tolerance (``strict=False``), the largest relative residual of an
    iterative solve, seconds."""

    factorizations: int = 0
    solves: int = 0
    factor_seconds: float = 0.0
    solve_seconds: float = 0.0
    setups: int = 0
    galerkin: int = 0
    iterations: int = 0
    unconverged: int = 0
    worst_residual: float = 0.0

    @property
    def seconds(self) -> float:
        return self.factor_seconds + self.solve_seconds


@dataclass
class ForwardModel:
    """Grid and discretisation shared by every material the fit tries.

    Parameters
    ----------
    grid
        The sample's regular grid (spacing ``grid.h`` in mm).
    stencil, face_mean
        Interior discretisation (:mod:`glsldiff.system.problem`).
    eta
        Relative refractive index: ``F_t(eta, 1)`` scales the radiance and, when ``C`` is
        not given, ``C = boundary_constant(eta)``.
    C
        Boundary constant; ``glsldiff.physics.optics.PAPER_C`` reproduces the paper's 2.1489.
    exitant
        Source and exitance convention (module docstring): ``"p1"`` (default), ``"arbree"``
        or ``"paper"``.
    solver
        ``"superlu"`` (one sparse LU factor per material), ``"pyamg"`` (multigrid-preconditioned
        CG, :mod:`glsldiff.inverse.amg`) or ``"auto"``: SuperLU up to
        :data:`~glsldiff.inverse.amg.AUTO_MAX_DIRECT` active nodes, pyamg above.
    amg_rtol, amg_maxiter, strict
        pyamg: relative residual and iterations per column; ``strict`` (default) makes a
        column that misses ``amg_rtol`` a :class:`~glsldiff.core.errors.SolverError`, else it is
        only counted (``stats.unconverged``).
    reuse, warm, amg
        pyamg: redo only the Galerkin products of the last hierarchy while the matrix diagonal
        has changed by less than ``reuse`` (relative; 0: a full set-up per material); start each
        column from the previous evaluation's solution (``warm``); the set-up, "rs" (classical
        Ruge-Stueben) or "sa" (smoothed aggregation).
    """

    grid: RegularGrid
    stencil: str = "conservative"
    face_mean: str = "arithmetic"
    eta: float = 1.3
    C: float | None = None
    exitant: str = "p1"
    stats: SolveStats = field(default_factory=SolveStats)
    solver: str = "auto"
    amg_rtol: float = AMG_RTOL
    amg_maxiter: int = AMG_MAXITER
    strict: bool = True
    reuse: float = 0.5
    warm: bool = True
    amg: str = "rs"
    _amg: AmgState = field(default_factory=AmgState, repr=False)

    def __post_init__(self) -> None:
        choice(self.stencil, "stencil", STENCILS)
        choice(self.solver, "solver", SOLVERS)
        real(self.amg_rtol, "amg_rtol", 0.0, lo_open=True)
        integer(self.amg_maxiter, "amg_maxiter", 1, 2**31)
        real(self.reuse, "reuse", 0.0)
        choice(self.amg, "amg", AMG_KINDS)
        choice(self.face_mean, "face_mean", FACE_MEANS)
        if self.C is None:
            self.C = float(boundary_constant(self.eta))
        g = self.grid.graph
        self.n = g.active.size
        pos = np.full(g.size, -1, dtype=np.int64)
        pos[g.active] = np.arange(self.n)
        self.interior = pos[g.interior]                       # (n_i,) positions in active order
        self.neighbours = pos[g.neighbours]                   # (n_i, 6)
        self.boundary = pos[g.boundary]                       # (n_b,)
        self.partner = pos[g.link]                            # (n_b,)
        self.weights, self.scale, self.d = g.weights, g.scale, g.d
        self.ft = float(fresnel_transmittance(self.eta, 1.0))
        # L = F_t (a phi(q) - b q) with q = s Q: F_t s (a phi(Q) - b Q) (module docstring)
        choice(self.exitant, "exitant", EXITANT)
        a, b = exitance_coefficients(self.eta, self.exitant, self.C)
        s = float(source_from_irradiance(np.ones(1), self.eta, self.exitant)[0])
        self.exit_a, self.exit_b = s * a, s * b

    @property
    def n_boundary(self) -> int:
        return self.boundary.size

    @property
    def method(self) -> str:
        """The solver the model uses: ``solver`` with "auto" resolved by the node count."""
        return resolve_solver(self.solver, self.n)

    def volume(self, values: Array, fill: float) -> Array:
        """Active-node vector -> ``(nz, ny, nx)`` volume, ``fill`` at inactive nodes."""
        out = np.full(self.grid.size, fill)
        out[self.grid.graph.active] = values
        return out.reshape(self.grid.shape)

    def active_values(self, volume: Array) -> Array:
        """``(nz, ny, nx)`` volume -> active-node vector."""
        return np.asarray(volume, dtype=np.float64).reshape(-1)[self.grid.graph.active]

    def matrix(self, kappa: Array, mu: Array) -> sp.csr_matrix:
        """``A(kappa, mu)`` of one channel (vectors over the active nodes), validated."""
        kappa, mu = np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64)
        if kappa.shape != (self.n,) or mu.shape != (self.n,):
            raise InputError(f"kappa and mu must be vectors over the {self.n} active nodes, "
                             f"got {kappa.shape} and {mu.shape}")
        if not (np.all(np.isfinite(kappa)) and np.all(np.isfinite(mu))):
            raise SolverError("the material became non-finite during the fit")
        prob = DiffusionProblem(self.grid, self.volume(kappa, 1.0), self.volume(mu, 0.0), C=self.C,
                                eta=self.eta, stencil=self.stencil, face_mean=self.face_mean)
        return channel_matrix(prob, 0)[0].tocsr()

    def factorize(self, kappa: Array, mu: Array) -> "Factorized":
        """Assemble and factorise ``A(kappa, mu)`` (vectors over the active nodes); with the
        pyamg solver, build (or update) its multigrid hierarchy instead."""
        t0 = time.perf_counter()
        kappa, mu = np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64)
        A = self.matrix(kappa, mu)
        if self.method == "pyamg":
            fac: Factorized = AmgFactorized.prepare(self, kappa, mu, A)
        else:
            lu = interruptible(spla.splu, A.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1)
            fac = Factorized(self, kappa, mu, A, lu)
        self.stats.factorizations += 1
        self.stats.factor_seconds += time.perf_counter() - t0
        return fac


@dataclass
class Factorized:
    """``A(kappa, mu)`` with its LU factor: forward, adjoint and derivative contractions."""

    model: ForwardModel
    kappa: Array
    mu: Array
    A: sp.csr_matrix
    lu: spla.SuperLU | None

    def rhs(self, Q: Array) -> Array:
        """``(n, M)`` right-hand sides for boundary sources ``Q`` ``(n_b, M)``."""
        m = self.model
        B = np.zeros((m.n, Q.shape[1]))
        kb = self.kappa[m.boundary][:, None] if m.stencil == "paper" else 1.0
        B[m.boundary] = m.d[:, None] * kb * Q
        return B

    def _solve(self, B: Array, trans: str, key: str | None = None) -> Array:
        """``A X = B`` (``trans="N"``) or ``A^T X = B`` (``"T"``); ``key`` names the kind of
        right-hand side for an iterative solver's warm start (unused by the factor)."""
        t0 = time.perf_counter()
        X = self.lu.solve(np.ascontiguousarray(B), trans=trans)
        st = self.model.stats
        st.solves += B.shape[1]
        st.solve_seconds += time.perf_counter() - t0
        if not np.all(np.isfinite(X)):
            raise SolverError("the diffusion solve returned non-finite values (singular matrix)")
        return X

    def solve(self, Q: Array) -> Array:
        """Unknowns ``X`` ``(n, M)`` (``kappa phi`` or ``phi``) for sources ``Q`` ``(n_b, M)``."""
        return self._solve(self.rhs(Q), "N")

    def adjoint(self, G: Array) -> Array:
        """``Lambda`` with ``A^T Lambda = G`` (``G``: ``(n, M)``)."""
        return self._solve(G, "T")

    def boundary_phi(self, X: Array) -> Array:
        """Fluence at the boundary nodes, ``(n_b, M)``."""
        m = self.model
        xb = X[m.boundary]
        return xb / self.kappa[m.boundary][:, None] if m.stencil == "paper" else xb

    def radiance(self, X: Array, Q: Array) -> Array:
        """Predicted radiance ``F_t B`` (module docstring) at the boundary nodes, ``(n_b, M)``,
        for ``X = solve(Q)``."""
        m = self.model
        return m.ft * (m.exit_a * self.boundary_phi(X) - m.exit_b * Q)

    def radiance_sensitivity(self, dL: Array, X: Array) -> tuple[Array, Array]:
        """Chain rule through :meth:`radiance`: given ``dL = df/dL`` ``(n_b, M)``, return
        ``df/dX`` as ``(n, M)`` and the explicit ``df/dkappa`` ``(n,)`` (paper stencil only)."""
        m = self.model
        c = m.ft * m.exit_a
        G = np.zeros((m.n, dL.shape[1]))
        dk = np.zeros(m.n)
        if m.stencil == "paper":
            kb = self.kappa[m.boundary]
            G[m.boundary] = c * dL / kb[:, None]
            dk[m.boundary] = -c * np.sum(dL * X[m.boundary], axis=1) / kb**2
        else:
            G[m.boundary] = c * dL
        return G, dk

    def contract(self, X: Array, Lam: Array, Q: Array) -> tuple[Array, Array]:
        """``sum_m Lambda_m^T d(A x_m - b_m)/d(kappa, mu)`` as two ``(n,)`` vectors."""
        m = self.model
        k, mu = self.kappa, self.mu
        I, J = m.interior, m.neighbours
        dk, dmu = np.zeros(m.n), np.zeros(m.n)
        lam_i = Lam[I]                                           # (n_i, M)
        # interior rows
        if m.stencil == "paper":
            lx = np.sum(lam_i * X[I], axis=1)
            dmu[I] += m.scale * lx / k[I]
            dk[I] += -m.scale * mu[I] * lx / k[I] ** 2
        else:
            dmu[I] += m.scale * np.sum(lam_i * X[I], axis=1)
            ki, kj = k[I][:, None], k[J]
            if m.face_mean == "arithmetic":
                dfi = dfj = np.full(kj.shape, 0.5)
            else:
                s2 = (ki + kj) ** 2
                dfi, dfj = 2.0 * kj**2 / s2, 2.0 * ki**2 / s2
            # P_is = sum_m lambda_im (x_im - x_jm), one direction s at a time (an (n_i, 6, M)
            # temporary is 1 GB at 1.3 M nodes and 16 conditions)
            xi = X[I]
            P = np.empty(J.shape)
            for d in range(J.shape[1]):
                P[:, d] = np.einsum("im,im->i", lam_i, xi - X[J[:, d]])
            wp = m.weights * P
            dk += np.bincount(np.repeat(I, 6), (wp * dfi).ravel(), minlength=m.n)
            dk += np.bincount(J.ravel(), (wp * dfj).ravel(), minlength=m.n)
        # boundary rows: (d + 2 C k_b) x_b - c_bj x_j - d (k_b) q_b
        B, P_ = m.boundary, m.partner
        C = float(m.C)
        lam_b, xb, xj = Lam[B], X[B], X[P_]
        if m.stencil == "paper":
            kb, kj = k[B], k[P_]
            dk_b = np.sum(lam_b * (2 * C * xb - (4 * C * kb / kj)[:, None] * xj - m.d[:, None] * Q), axis=1)
            dk_j = np.sum(lam_b * xj, axis=1) * 2 * C * kb**2 / kj**2
            np.add.at(dk, P_, dk_j)
        else:
            dk_b = 2 * C * np.sum(lam_b * (xb - xj), axis=1)
        dk[B] += dk_b
        return dk, dmu

    def tangent(self, X: Array, Q: Array, dkappa: Array, dmu: Array, eps: float = 1e-4,
                key: str | None = None) -> Array:
        """Forward sensitivity ``dX`` of the unknowns along the material direction
        ``(dkappa, dmu)``: ``A dX = -(dA X - db)``, with the residual derivative taken by a
        central difference of the (cheap) assembly -- exact where ``A`` is linear in the
        material (conservative stencil, arithmetic face mean), O(eps^2) otherwise. ``key``:
        warm start of an iterative solver (the same direction in successive calls)."""
        m = self.model

        def residual(sign: float) -> Array:
            k, mu = self.kappa + sign * eps * dkappa, self.mu + sign * eps * dmu
            A = m.matrix(k, mu)
            fac = Factorized(m, k, mu, A, self.lu)
            return A @ X - fac.rhs(Q)

        dR = (residual(1.0) - residual(-1.0)) / (2.0 * eps)
        return -self._solve(dR, "N", key)

    def radiance_tangent(self, X: Array, dX: Array, dkappa: Array) -> Array:
        """Derivative of :meth:`radiance` for unknown change ``dX`` and kappa change ``dkappa``."""
        m = self.model
        c = m.ft * m.exit_a
        if m.stencil != "paper":
            return c * dX[m.boundary]
        kb, dkb = self.kappa[m.boundary][:, None], dkappa[m.boundary][:, None]
        return c * (dX[m.boundary] / kb - X[m.boundary] * dkb / kb**2)


@dataclass
class AmgFactorized(Factorized):
    """``A(kappa, mu)`` with a multigrid hierarchy (``ForwardModel.amg``) instead of an LU factor: the
    forward and adjoint solves by preconditioned CG on the symmetrised ``K = S A``
    (:mod:`glsldiff.inverse.amg`), or, where ``S A`` is not symmetric, BiCGSTAB with one
    nonsymmetric hierarchy for ``A`` and one for ``A^T``."""

    scale: Array | None = None
    K: sp.csr_matrix | None = None
    hierarchy: Hierarchy | None = None
    symmetric: bool = True
    _nonsym: dict = field(default_factory=dict, repr=False)

    @classmethod
    def prepare(cls, model: ForwardModel, kappa: Array, mu: Array, A: sp.csr_matrix,
                symmetric: bool | None = None) -> "AmgFactorized":
        """The hierarchy of ``A`` (``symmetric=False`` forces the nonsymmetric path)."""
        s = boundary_scaling(A, model.boundary, model.partner)
        K = (sp.diags(s) @ A).tocsr()
        if symmetric is None:
            symmetric = bool(np.all(s > 0)) and asymmetry(K) <= SYMMETRY_TOL
        fac = cls(model, kappa, mu, A, None, scale=s, K=K, symmetric=symmetric)
        if not symmetric:
            return fac
        K = (0.5 * (K + K.T)).tocsr()   # exactly symmetric: CG and the V-cycle assume it
        fac.K = K
        st, stats = model._amg, model.stats
        H = st.hierarchy
        d = K.diagonal()
        if (H is not None and model.reuse > 0 and not st.rebuild and H.A[0].shape == K.shape
                and float(np.max(np.abs(d - H.diag) / H.diag)) <= model.reuse):
            H.galerkin(K)
            stats.galerkin += 1
        else:
            H = Hierarchy(K, model.amg)
            st.hierarchy, st.rebuild, st.fresh_iterations = H, False, 0.0
            stats.setups += 1
        fac.hierarchy = H
        return fac

    def solve(self, Q: Array) -> Array:
        return self._solve(self.rhs(Q), "N", "forward")

    def adjoint(self, G: Array) -> Array:
        return self._solve(G, "T", "adjoint")

    def _solve(self, B: Array, trans: str, key: str | None = None) -> Array:
        m = self.model
        t0 = time.perf_counter()
        st = m._amg
        warm = st.warm.get(key) if (key is not None and m.warm) else None
        if warm is not None and warm.shape != B.shape:
            warm = None
        s = self.scale[:, None]
        if self.symmetric:
            # forward: K x = S b; adjoint: K nu = g, lambda = S nu (module docstring of glsldiff.inverse.amg)
            rhs = s * B if trans == "N" else B
            Y, rep = solve_columns(self.K, rhs, self.hierarchy, warm, m.amg_rtol, m.amg_maxiter)
            X = Y if trans == "N" else s * Y
        else:
            if trans not in self._nonsym:
                self._nonsym[trans] = nonsymmetric_hierarchy(self.A if trans == "N" else self.A.T.tocsr())
                m.stats.setups += 1
            Y, rep = solve_nonsymmetric(self.A if trans == "N" else self.A.T.tocsr(), B, self._nonsym[trans], warm,
                                        m.amg_rtol, m.amg_maxiter)
            X = Y
        self._account(rep, B, trans, key)
        if key is not None and m.warm:
            st.warm[key] = Y
        st_ = m.stats
        st_.solves += B.shape[1]
        st_.solve_seconds += time.perf_counter() - t0
        if not np.all(np.isfinite(X)):
            raise SolverError("the iterative diffusion solve returned non-finite values")
        return X

    def _account(self, rep: KrylovReport, B: Array, trans: str, key: str | None) -> None:
        """Counters, the hierarchy's rebuild flag, and the strict convergence check."""
        m, st = self.model, self.model._amg
        used = np.any(B != 0.0, axis=0)
        m.stats.iterations += int(rep.iterations.sum())
        if used.any():
            m.stats.worst_residual = max(m.stats.worst_residual, float(rep.residuals[used].max()))
            mean_its = float(rep.iterations[used].mean())
            if key == "forward" and self.symmetric:
                if st.fresh_iterations == 0.0:
                    st.fresh_iterations = max(mean_its, 1.0)
                elif mean_its > 1.5 * st.fresh_iterations + 1:
                    st.rebuild = True     # the reused prolongators have gone stale
        bad = used & ~(rep.residuals <= m.amg_rtol)
        if bad.any():
            m.stats.unconverged += int(bad.sum())
            if m.strict:
                what = {"N": "forward", "T": "adjoint"}[trans] + ("" if key else " (tangent)")
                raise SolverError(
                    f"pyamg {'CG' if self.symmetric else 'BiCGSTAB'}: the {what} solve did not converge: "
                    f"{int(bad.sum())} of {int(used.sum())} columns above the relative residual {m.amg_rtol:g} after "
                    f"{m.amg_maxiter} iterations (worst {float(np.max(rep.residuals[bad])):.3g}); raise amg_maxiter or "
                    "amg_rtol, or use the superlu solver")


def edge_difference_matrix(model: ForwardModel, keep: NDArray[np.bool_] | None = None,
                           weights: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> sp.csr_matrix:
    """Forward differences ``w_a (v_j - v_i)`` of a vector over the active nodes, one row per
    lattice edge between two active nodes (``keep``: a grid-shaped mask further limiting the
    nodes an edge may join), rows of axis ``a`` (0 is z: arrays are ``(nz, ny, nx)``) scaled by
    ``weights[a]``; rows axis by axis."""
    g = model.grid
    pos = np.full(g.shape, -1, dtype=np.int64)
    pos[g.active] = np.arange(model.n)
    if keep is not None:
        pos[~keep] = -1
    rows, cols, vals = [], [], []
    e = 0
    for axis in range(3):
        a = np.moveaxis(pos, axis, 0)
        i, j = a[:-1].ravel(), a[1:].ravel()
        both = (i >= 0) & (j >= 0)
        i, j = i[both], j[both]
        r = np.arange(e, e + i.size)
        rows += [r, r]
        cols += [i, j]
        vals += [np.full(i.size, -weights[axis]), np.full(i.size, weights[axis])]
        e += i.size
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(e, model.n))


def regularizer_matrix(model: ForwardModel) -> sp.csr_matrix:
    """Forward-difference operator ``D`` over lattice edges between active nodes, scaled so
    that ``||D kappa||^2 = sum_x |grad kappa(x)|^2`` (paper section 4.2; dimensionless):
    ``sum_edges ((kappa_i - kappa_j) / h)^2``."""
    s = 1.0 / model.grid.h
    return edge_difference_matrix(model, weights=(s, s, s))
