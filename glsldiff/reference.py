"""CPU oracle: the identical discrete system assembled with scipy.sparse.

:func:`assemble` builds, for all three channels at once, the block-diagonal system
``A x = b`` whose rows are exactly the relaxation formulas the GLSL shaders apply
(see :mod:`glsldiff.problem`): Jacobi is ``x <- x + D^-1 (b - A x)`` with
``D = diag(A)``. :class:`DirectSolver` factorises it (SuperLU) and :func:`jacobi`
runs the same Jacobi iteration in numpy. Both return ``(phi, report)`` with the
fluence ``phi`` as a ``(nz, ny, nx, 3)`` volume (0 at inactive edge/corner nodes).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Callable, Mapping

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import ArrayLike, NDArray

from glsldiff.problem import DiffusionProblem
from glsldiff.errors import InputError, SolverError
from glsldiff.report import ConvergenceMonitor, SolveReport, channel_ratio, contraction_error_estimate

logger = logging.getLogger(__name__)


@dataclass
class LinearSystem:
    """``A x = b`` over the active nodes, channel-major (``x[c * n + i]``).

    Attributes
    ----------
    A
        ``(3n, 3n)`` CSR matrix, block diagonal over channels.
    b
        ``(3n,)`` right-hand side.
    diag
        ``(3n,)`` diagonal of ``A`` (the Jacobi divisor).
    active
        ``(n,)`` flat indices (into the ``(nz, ny, nx)`` volume) of the unknowns.
    norm_ref
        ``(3n,)`` vector whose per-channel norm divides the residual (default ``D^-1 b``);
        a system with rows pinned to fixed values keeps the unpinned system's here, so
        that its residual means the same as the full system's.
    """

    A: sp.csr_matrix
    b: NDArray[np.float64]
    diag: NDArray[np.float64]
    active: NDArray[np.int64]
    norm_ref: NDArray[np.float64] | None = None

    @property
    def n(self) -> int:
        return self.active.size

    def to_volume(self, x: NDArray, shape: tuple[int, int, int]) -> NDArray[np.float64]:
        """Channel-major unknown vector -> ``shape + (3,)`` volume, 0 at inactive nodes."""
        out = np.zeros((int(np.prod(shape)), 3))
        out[self.active] = x.reshape(3, self.n).T
        return out.reshape(shape + (3,))

    def from_volume(self, vol: NDArray) -> NDArray[np.float64]:
        """``(nz, ny, nx, 3)`` volume -> channel-major unknown vector."""
        return np.asarray(vol, dtype=np.float64).reshape(-1, 3)[self.active].T.reshape(-1)

    def block(self, c: int) -> tuple[sp.csr_matrix, NDArray[np.float64]]:
        """Matrix and right-hand side of channel ``c`` alone."""
        sl = slice(c * self.n, (c + 1) * self.n)
        return self.A[sl, sl], self.b[sl]

    def jacobi_step(self, x: NDArray) -> NDArray[np.float64]:
        """The Jacobi increment ``D^-1 (b - A x)``."""
        return (self.b - self.A @ x) / self.diag

    def residual(self, x: NDArray, step: NDArray | None = None) -> float:
        """Jacobi-scaled relative residual ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||``
        (``step`` = :meth:`jacobi_step` of ``x`` when already computed)."""
        r = self.jacobi_step(x) if step is None else step
        ref = self.b / self.diag if self.norm_ref is None else self.norm_ref
        return channel_ratio(r.reshape(3, self.n), ref.reshape(3, self.n))

    def pinned(self, rows: NDArray[np.bool_], x: NDArray) -> "LinearSystem":
        """The same system with the unknowns where ``rows`` (``(n,)``, all channels) is true
        held at their values in ``x`` (rows ``diag_i x_i = diag_i x_fixed_i``): what a
        relaxation that never updates those nodes converges to."""
        fixed = np.tile(np.asarray(rows, dtype=bool), 3)
        keep = sp.diags((~fixed).astype(np.float64))
        A = (keep @ self.A + sp.diags(np.where(fixed, self.diag, 0.0))).tocsr()
        b = np.where(fixed, self.diag * x, self.b)
        return LinearSystem(A, b, self.diag, self.active, self.b / self.diag)


def jacobi_radius_bound(system: LinearSystem) -> float:
    """Lower bound on the spectral radius of the Jacobi matrix ``J = I - D^-1 A``.

    ``J`` is non-negative, so ``rho(J) >= sqrt(J_ij J_ji)`` for every linked pair.
    A value >= 1 means Jacobi cannot converge and ``A`` is not an M-matrix (its
    solution may be negative): this happens with the paper's stencil where a
    boundary node's kappa exceeds its interior partner's by a large factor.
    """
    off = (system.A - sp.diags(system.diag)).tocsr()
    J = sp.diags(1.0 / system.diag) @ abs(off)
    pair = J.multiply(J.T)
    return float(np.sqrt(pair.max())) if pair.nnz else 0.0


def diverged_message(problem: DiffusionProblem, method: str, sweeps: int) -> str:
    """Explanation for a diverging iteration, with the spectral-radius bound."""
    bound = jacobi_radius_bound(assemble(problem))
    hint = (" The paper's stencil loses diagonal dominance where kappa jumps at the boundary; "
            "use stencil='conservative' or a smoother kappa." if problem.stencil == "paper" else "")
    return (f"{method} diverged after {sweeps} sweeps: the Jacobi matrix has spectral radius "
            f">= {bound:.3f} (bound from linked node pairs).{hint}")


def _matrix(problem: DiffusionProblem, c: int) -> tuple[sp.csr_matrix, NDArray]:
    """Matrix and its diagonal for channel ``c`` (rows of :mod:`glsldiff.graph`).

    Interior row ``i`` (times the row scale ``s_i``; ``w_j`` the scaled weights):
    paper ``(sum_j w_j + s_i mu_i/kappa_i) u_i - sum_j w_j u_j``, conservative
    ``(sum_j w_j k_ij + s_i mu_i) phi_i - sum_j w_j k_ij phi_j``. Boundary row ``b``
    (times ``d_b``, and ``kappa_b`` for the paper's unknown): ``phi_b + 2 C kappa_b
    (phi_b - phi_j) / d_b = q_b``.
    """
    g = problem.graph
    k = problem.kappa.reshape(-1, 3)[:, c]
    m = problem.mu.reshape(-1, 3)[:, c]
    C = float(problem.C)
    active = g.active
    pos = np.full(g.size, -1, dtype=np.int64)
    pos[active] = np.arange(active.size)

    interior, nb = g.interior, g.neighbours
    if problem.stencil == "paper":
        w = g.weights
    else:
        ki, kj = k[interior, None], k[nb]
        face = 0.5 * (ki + kj) if problem.face_mean == "arithmetic" else 2.0 * ki * kj / (ki + kj)
        w = g.weights * face
    diag = np.zeros(g.size)
    diag[interior] = w.sum(axis=1) + g.scale * (m[interior] / k[interior] if problem.stencil == "paper"
                                                else m[interior])
    boundary, j = g.boundary, g.link
    kb = k[boundary]
    diag[boundary] = g.d + 2.0 * C * kb
    off_b = 2.0 * C * kb * kb / k[j] if problem.stencil == "paper" else 2.0 * C * kb

    r = np.concatenate([np.repeat(interior, 6), boundary, active])
    cc = np.concatenate([nb.ravel(), j, active])
    v = np.concatenate([-w.ravel(), -off_b, diag[active]])
    A = sp.csr_matrix((v, (pos[r], pos[cc])), shape=(active.size, active.size))
    return A, diag[active]


def assemble(problem: DiffusionProblem) -> LinearSystem:
    """The discrete system of ``problem`` for all three channels (block diagonal)."""
    blocks = [_matrix(problem, c) for c in range(3)]
    active = problem.graph.active
    return LinearSystem(sp.block_diag([A for A, _ in blocks], format="csr"), assemble_rhs(problem),
                        np.concatenate([d for _, d in blocks]), active)


class DirectSolver:
    """Sparse LU factorisation of the problem's matrix, reusable for many sources ``q``.

    Examples
    --------
    >>> from glsldiff.grid import RegularGrid
    >>> p = DiffusionProblem(RegularGrid(5, 5, 5), kappa=0.5, mu=0.1, q={"z-": 1.0})
    >>> phi, rep = DirectSolver(p).solve()
    >>> bool(phi.min() >= 0 and rep.residual < 1e-12)
    True
    """

    def __init__(self, problem: DiffusionProblem) -> None:
        t0 = time.perf_counter()
        self.problem = problem
        self.system = assemble(problem)
        self._lu = [spla.splu(self.system.block(c)[0].tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.1)
                    for c in range(3)]
        self.factor_seconds = time.perf_counter() - t0

    def solve(self, q: ArrayLike | Mapping[str, ArrayLike] | None = None) -> tuple[NDArray, SolveReport]:
        """Fluence for source ``q`` (default: the problem's own)."""
        t0 = time.perf_counter()
        p, s = self.problem, self.system
        prob = p if q is None else p.with_q(q)
        sysq = s if q is None else replace(s, b=assemble_rhs(prob))
        x = np.concatenate([self._lu[c].solve(sysq.b.reshape(3, s.n)[c]) for c in range(3)])
        seconds = time.perf_counter() - t0
        phi = prob.to_phi(s.to_volume(x, p.node_shape))
        rep = SolveReport("scipy-direct", nodes=s.n, residual=sysq.residual(x), seconds=seconds,
                          converged=True, error_estimate=0.0,
                          radiance=prob.exitant_radiance(phi))
        return phi, rep


def assemble_rhs(problem: DiffusionProblem) -> NDArray[np.float64]:
    """Right-hand side ``b`` (channel-major over the active nodes): ``d_b kappa_b q_b``
    (paper) or ``d_b q_b`` (conservative) at boundary nodes, 0 at interior nodes."""
    g = problem.graph
    q = problem.q.reshape(-1, 3)
    b = np.zeros((g.size, 3))
    kb = problem.kappa.reshape(-1, 3)[g.boundary] if problem.stencil == "paper" else 1.0
    b[g.boundary] = g.d[:, None] * kb * q[g.boundary]
    return b[g.active].T.reshape(-1)


def solve_direct(problem: DiffusionProblem) -> tuple[NDArray, SolveReport]:
    """Factorise and solve once; the report's time includes the factorisation."""
    solver = DirectSolver(problem)
    phi, rep = solver.solve()
    rep.seconds += solver.factor_seconds
    return phi, rep


def solve_amg(problem: DiffusionProblem, tol: float = 1e-12, maxiter: int = 200) -> tuple[NDArray, SolveReport]:
    """Algebraic multigrid (pyamg smoothed aggregation, GMRES-accelerated) per channel.

    The matrix is non-symmetric (boundary rows), so aggregation runs with
    ``symmetry="nonsymmetric"``. Used as the converged reference where a sparse LU
    factorisation does not fit (about 1e6 nodes). ``tol`` is the relative residual
    ``||b - A x|| / ||b||`` of each channel.
    """
    try:
        import pyamg
    except ImportError as exc:
        raise SolverError("solve_amg needs pyamg: pip install 'glsldiff[validation]'") from exc
    t0 = time.perf_counter()
    s = assemble(problem)
    n = s.n
    xs, cycles = [], 0
    for c in range(3):
        A, b = s.block(c)
        if not b.any():
            xs.append(np.zeros(n))
            continue
        ml = pyamg.smoothed_aggregation_solver(A, symmetry="nonsymmetric", max_coarse=500)
        res: list[float] = []
        xs.append(ml.solve(b, tol=tol, accel="gmres", maxiter=maxiter, residuals=res))
        cycles = max(cycles, len(res) - 1)
    x = np.concatenate(xs)
    phi = problem.to_phi(s.to_volume(x, problem.node_shape))
    res_final = s.residual(x)
    rep = SolveReport("pyamg-sa-gmres", nodes=n, sweeps=cycles, residual=res_final,
                      seconds=time.perf_counter() - t0, converged=bool(np.isfinite(res_final)),
                      error_estimate=float("nan"), radiance=problem.exitant_radiance(phi))
    return phi, rep


def relax(system: LinearSystem, advance: Callable[[int], NDArray], x: NDArray, tol: float,
          max_sweeps: int, check_every: int,
          callback: Callable[[NDArray], None] | None = None,
          floor_max: float = 1e-2) -> tuple[NDArray, str, list[tuple[int, float]], float]:
    """Drive an iterative solver of ``system`` with periodic float64 residual checks.

    ``advance(n)`` runs ``n`` more sweeps and returns the new iterate (channel-major
    unknown vector). The residual of each returned iterate is evaluated here, in
    float64, as ``max_c ||D^-1 (b - A x)|| / ||D^-1 b||`` (so an iterate frozen by
    rounding still shows its true residual), and fed to a :class:`ConvergenceMonitor`
    (``floor_max``: the largest residual taken for a rounding floor).

    Returns
    -------
    x, status, history, step
        Final iterate, monitor status, ``(sweeps, residual)`` pairs (the initial
        guess at 0 sweeps first) and ``||D^-1 (b - A x)||`` of the final iterate.
    """
    if check_every < 1 or max_sweeps < 0:
        raise InputError(f"check_every must be >= 1 and max_sweeps >= 0 (got check_every={check_every}, "
                         f"max_sweeps={max_sweeps})")
    zero_source = not np.any(system.b)
    monitor = ConvergenceMonitor(tol, max_sweeps, floor_max=floor_max)

    def check(sweeps: int, x: NDArray) -> tuple[str | None, float]:
        with np.errstate(over="ignore", invalid="ignore"):
            r = system.jacobi_step(x)
            res = float(np.linalg.norm(r)) if zero_source else system.residual(x, r)
            return monitor.update(sweeps, res), float(np.linalg.norm(r))

    status, step = check(0, x)
    sweeps = 0
    while status is None:
        n_run = min(check_every, max_sweeps - sweeps)
        x = advance(n_run)
        sweeps += n_run
        status, step = check(sweeps, x)
        if callback is not None:
            callback(x)
    return x, status, monitor.history, step


def jacobi(problem: DiffusionProblem, x0: NDArray | None = None, tol: float = 1e-6,
           maxiter: int = 10000, check_every: int = 10,
           residuals: list[float] | None = None,
           callback: Callable[[NDArray], None] | None = None) -> tuple[NDArray, SolveReport]:
    """Jacobi relaxation ``x <- x + D^-1 (b - A x)`` of the same system in numpy (float64).

    Parameters
    ----------
    x0
        Initial fluence volume ``(nz, ny, nx, 3)``; zero by default.
    tol
        Stop when the Jacobi-scaled residual (:meth:`LinearSystem.residual`) is <= tol.
    maxiter
        Sweep budget.
    check_every
        Sweeps between residual checks.
    residuals
        If a list is given, the residual at each check (initial guess first) is
        appended (pyamg convention).
    callback
        Called as ``callback(x)`` with the unknown vector after each check.

    Raises
    ------
    SolverError
        The iteration diverged (spectral radius >= 1).
    """
    t0 = time.perf_counter()
    s = assemble(problem)
    state = {"x": np.zeros_like(s.b) if x0 is None else s.from_volume(problem.from_phi(np.asarray(x0)))}

    def advance(n: int) -> NDArray:
        x = state["x"]
        with np.errstate(over="ignore", invalid="ignore"):
            for _ in range(n):
                x = x + s.jacobi_step(x)
        state["x"] = x
        return x

    x, status, history, step = relax(s, advance, state["x"], tol, maxiter, check_every, callback)
    if residuals is not None:
        residuals.extend(r for _, r in history)
    sweeps = history[-1][0]
    if status == "diverged":
        raise SolverError(diverged_message(problem, "numpy Jacobi", sweeps))
    converged = status == "converged"
    if not converged:
        logger.warning("numpy Jacobi did not converge (%s): residual %.3e after %d sweeps",
                       status, history[-1][1], sweeps)
    phi = problem.to_phi(s.to_volume(x, problem.node_shape))
    rep = SolveReport("numpy-jacobi", nodes=s.n, sweeps=sweeps, residual=history[-1][1],
                      seconds=time.perf_counter() - t0, converged=converged, residuals=history,
                      status=status,
                      error_estimate=contraction_error_estimate(history, step, float(np.linalg.norm(x))),
                      radiance=problem.exitant_radiance(phi))
    return phi, rep
