"""CPU oracle: the identical discrete system assembled with scipy.sparse.

:func:`assemble` builds, for all three channels at once, the block-diagonal system
``A x = b`` whose rows are exactly the relaxation formulas the GLSL shaders apply
(see :mod:`glsldiff.system.problem`): Jacobi is ``x <- x + D^-1 (b - A x)`` with
``D = diag(A)``. The solvers of :mod:`glsldiff.oracle.solvers` work on it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from glsldiff.system.problem import DiffusionProblem
from glsldiff.system.report import channel_ratio


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


class ChannelSystem(LinearSystem):
    """A :class:`LinearSystem` kept as its channel matrices (:attr:`blocks`, ``(n, n)`` CSR each,
    channel-major as ``A``): the Jacobi step multiplies channel by channel (the same bits as the
    block-diagonal product), and the block-diagonal :attr:`A` is assembled
    (:func:`block_diagonal`) only when asked for, then kept until :meth:`set_blocks`. A solver's
    system so holds no second copy of its matrix (25-80 MB on the bunny's 147k-node grid)."""

    def __init__(self, blocks: Sequence[sp.csr_matrix], b: NDArray[np.float64], diag: NDArray[np.float64],
                 active: NDArray[np.int64], norm_ref: NDArray[np.float64] | None = None) -> None:
        self.blocks = list(blocks)
        super().__init__(None, b, diag, active, norm_ref)     # type: ignore[arg-type]

    @property  # type: ignore[override]
    def A(self) -> sp.csr_matrix:
        """The block-diagonal ``(3n, 3n)`` matrix (assembled at the first use)."""
        if self._A is None:
            self._A = block_diagonal(self.blocks)
        return self._A

    @A.setter
    def A(self, value: sp.csr_matrix | None) -> None:
        self._A = value

    def set_blocks(self, blocks: Sequence[sp.csr_matrix]) -> None:
        """New channel matrices (the block-diagonal ``A`` is assembled again when asked for)."""
        self.blocks, self._A = list(blocks), None

    def block(self, c: int) -> tuple[sp.csr_matrix, NDArray[np.float64]]:
        """Matrix and right-hand side of channel ``c`` alone."""
        return self.blocks[c], self.b[c * self.n:(c + 1) * self.n]

    def jacobi_step(self, x: NDArray) -> NDArray[np.float64]:
        """The Jacobi increment ``D^-1 (b - A x)``, ``A x`` channel by channel."""
        xs = np.asarray(x).reshape(len(self.blocks), -1)
        return (self.b - np.concatenate([M @ xc for M, xc in zip(self.blocks, xs)])) / self.diag


def _same_array(a: NDArray, b: NDArray) -> bool:
    """Whether ``a`` and ``b`` are views of the same memory with the same layout."""
    return (a.dtype == b.dtype and a.shape == b.shape and a.strides == b.strides
            and a.__array_interface__["data"][0] == b.__array_interface__["data"][0])


def channel_values(mats: Sequence[object]) -> NDArray[np.float64] | None:
    """The ``(3, nnz)`` array whose rows are the data of the three channel matrices ``mats``
    when they are in the compact form (float64 CSR, one ``indptr`` and ``indices`` array for
    the three, their data the rows of one C-contiguous ``(3, nnz)`` array: what
    :func:`glsldiff.solve.gather.channel_matrices` returns, and
    :meth:`glsldiff.oracle.fem_update.P1System.matrices`); else ``None``."""
    if len(mats) != 3 or not all(sp.issparse(M) and M.format == "csr" for M in mats):
        return None
    M0 = mats[0]
    base = M0.data.base
    if (not isinstance(base, np.ndarray) or base.dtype != np.float64 or base.shape != (3, M0.nnz)
            or not base.flags.c_contiguous):
        return None
    for c, M in enumerate(mats):
        if (M.shape != M0.shape or not _same_array(M.data, base[c]) or not _same_array(M.indices, M0.indices)
                or not _same_array(M.indptr, M0.indptr)):
            return None
    return base


def block_diagonal(mats: Sequence[sp.csr_matrix]) -> sp.csr_matrix:
    """The block-diagonal CSR matrix of the square CSR ``mats`` (channel-major, the
    :class:`LinearSystem` layout), assembled from their arrays (``scipy.sparse.block_diag`` goes
    through COO: 1.5 s for three 125k-row P1 matrices), with int32 indices where they fit. Of
    matrices in the compact form (:func:`channel_values`) its data is a view of their values
    (it follows their changes; only the indices are new: 4 bytes per entry)."""
    offs = np.cumsum([0] + [M.shape[0] for M in mats])
    nnz = np.cumsum([0] + [M.nnz for M in mats])
    dt = np.int32 if max(int(offs[-1]), int(nnz[-1])) < np.iinfo(np.int32).max else np.int64
    indptr = np.empty(int(offs[-1]) + 1, dtype=dt)
    indices = np.empty(int(nnz[-1]), dtype=dt)
    for c, M in enumerate(mats):
        np.add(M.indptr[:-1], nnz[c], out=indptr[offs[c]:offs[c + 1]], casting="unsafe")
        np.add(M.indices, offs[c], out=indices[nnz[c]:nnz[c + 1]], casting="unsafe")
    indptr[-1] = nnz[-1]
    values = channel_values(mats)
    data = values.reshape(-1) if values is not None else np.concatenate([M.data for M in mats])
    out = sp.csr_matrix((data, indices, indptr), shape=(int(offs[-1]), int(offs[-1])))
    out.data, out.indices, out.indptr = data, indices, indptr      # no copies by scipy
    return out


def row_entries(indptr: NDArray[np.integer], rows: NDArray[np.integer]) -> NDArray[np.int64]:
    """Positions of the stored entries of ``rows`` in a CSR structure with ``indptr`` (row by
    row, each row's entries in order): the concatenated ranges ``indptr[r] .. indptr[r + 1]``."""
    start = np.asarray(indptr)[rows].astype(np.int64)
    counts = np.asarray(indptr)[np.asarray(rows) + 1].astype(np.int64) - start
    return np.repeat(start - np.cumsum(counts) + counts, counts) + np.arange(int(counts.sum()))


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


def stencil_terms(problem: DiffusionProblem, c: int) -> tuple[NDArray, NDArray, NDArray]:
    """The stencil variants, the one place they live on the CPU (GLSL twin: the section "the
    stencil" of ``shaders/diffusion.glsl``), for channel ``c``:

    ``a``, ``(n_interior, 6)``
        coupling of each interior node to its neighbours: the scaled weight ``w_j`` (paper,
        Laplacian of ``kappa phi``) or ``w_j k_ij`` with the face mean ``k_ij`` of ``kappa_i``
        and ``kappa_j`` (conservative, ``div(kappa grad phi)``);
    ``sigma``, ``(n_interior,)``
        absorption times the row scale: ``s mu / kappa`` (paper) or ``s mu``;
    ``t``, ``(N,)``
        the unknown per unit fluence, ``x = t phi`` (:func:`unknown_factor`).
    """
    g = problem.graph
    k = problem.kappa.reshape(-1, 3)[:, c]
    m = problem.mu.reshape(-1, 3)[:, c]
    interior = g.interior
    t = unknown_factor(problem)[:, c]
    if problem.stencil == "paper":
        return g.weights, g.scale * (m[interior] / k[interior]), t
    ki, kj = k[interior, None], k[g.neighbours]
    face = 0.5 * (ki + kj) if problem.face_mean == "arithmetic" else 2.0 * ki * kj / (ki + kj)
    return g.weights * face, g.scale * m[interior], t


def unknown_factor(problem: DiffusionProblem) -> NDArray[np.float64]:
    """``(N, 3)`` unknown per unit fluence, ``x = t phi``: kappa (paper) or 1, as defined by
    :meth:`DiffusionProblem.from_phi`."""
    return problem.from_phi(np.ones(problem.kappa.shape)).reshape(-1, 3)


def channel_matrix(problem: DiffusionProblem, c: int) -> tuple[sp.csr_matrix, NDArray]:
    """Matrix and its diagonal for channel ``c`` (rows of :mod:`glsldiff.grids.graph`, in the
    unknown ``x = t phi`` of :func:`stencil_terms`).

    Interior row ``i`` (times the row scale ``s_i``): ``(sum_j a_ij + sigma_i) x_i - sum_j a_ij
    x_j``. Boundary row ``b`` (times ``d_b t_b``): ``phi_b + 2 C kappa_b (phi_b - phi_j) / d_b
    = q_b``, i.e. ``(d_b + 2 C kappa_b) x_b - 2 C kappa_b (t_b / t_j) x_j = d_b t_b q_b``.
    """
    g = problem.graph
    a, sigma, t = stencil_terms(problem, c)
    kappa = problem.kappa.reshape(-1, 3)[:, c]
    C = float(problem.C)
    active = g.active
    pos = np.full(g.size, -1, dtype=np.int64)
    pos[active] = np.arange(active.size)

    interior, nb = g.interior, g.neighbours
    diag = np.zeros(g.size)
    diag[interior] = a.sum(axis=1) + sigma
    boundary, j = g.boundary, g.link
    kb = kappa[boundary]
    diag[boundary] = g.d + 2.0 * C * kb
    off_b = 2.0 * C * kb * t[boundary] / t[j]

    r = np.concatenate([np.repeat(interior, 6), boundary, active])
    cc = np.concatenate([nb.ravel(), j, active])
    v = np.concatenate([-a.ravel(), -off_b, diag[active]])
    A = sp.csr_matrix((v, (pos[r], pos[cc])), shape=(active.size, active.size))
    return A, diag[active]


def assemble(problem: DiffusionProblem) -> LinearSystem:
    """The discrete system of ``problem`` for all three channels (block diagonal)."""
    blocks = [channel_matrix(problem, c) for c in range(3)]
    active = problem.graph.active
    return LinearSystem(sp.block_diag([A for A, _ in blocks], format="csr"), assemble_rhs(problem),
                        np.concatenate([d for _, d in blocks]), active)


def assemble_rhs(problem: DiffusionProblem) -> NDArray[np.float64]:
    """Right-hand side ``b`` (channel-major over the active nodes): ``d_b t_b q_b`` at boundary
    nodes (:func:`channel_matrix`), 0 at interior nodes."""
    g = problem.graph
    q = problem.q.reshape(-1, 3)
    b = np.zeros((g.size, 3))
    b[g.boundary] = g.d[:, None] * unknown_factor(problem)[g.boundary] * q[g.boundary]
    return b[g.active].T.reshape(-1)
