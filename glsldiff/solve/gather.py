"""Damped Jacobi in GLSL for a general sparse system with RGB channels ("gather": ELLPACK in
textures), e.g. the P1 finite-element systems of :func:`glsldiff.oracle.fem.assemble_p1`.

The system is one ``n x n`` matrix per colour channel, all three with the same sparsity
pattern, and ``b`` as ``(n, 3)``. Node ``i`` lives at texel ``(i % W, i // W)`` of ``W x H``
RGBA32F textures (``W`` the smallest power of two >= ``sqrt(n)``, so that the shader finds a
neighbour's texel with a mask and a shift: llvmpipe has no vector integer division, and
``j % W, j / W`` halved its sweep rate):

``u_src`` / ``u_self``
    the iterate ``x`` (a :class:`glsldiff.gl.PingPong` pair), rgb = channels;
``u_diag``, ``u_b``
    ``a_ii`` and ``b_i`` per channel (padding texels ``i >= n``: ``a_ii = 1``, ``b = 0``);
``u_coef``
    a 2-D texture array of ``K`` layers, ``K`` the most off-diagonal entries of a row
    (ELLPACK): layer ``k`` at node ``i``'s texel holds the ``k``-th off-diagonal entry of row
    ``i``, rgb = ``a_ij`` of the three channels, alpha = ``j`` as a float (exact for ``n <=
    2^24``), and ``-1`` for an empty slot. Empty slots come last; the shader stops at the
    first. Off-diagonal entries that are zero in all three channels (stored zeros, e.g. the
    face diagonals of Kuhn tetrahedra on an undistorted cube) get no slot.

A sweep is one full-screen quad (``shaders/quad.vert`` + ``shaders/gather.frag`` in its
``JACOBI`` mode)::

    x_i <- x_i + omega (b_i - a_ii x_i - sum_j a_ij x_j) / a_ii

with texel fetches per node and sweep: ``x_i``, ``a_ii``, ``b_i`` and two per used slot
(coefficient texel, ``x_j``), plus one for the first empty slot of a row shorter than ``K``:
``3 + 2 k_i (+1)``, ``k_i`` the row's off-diagonal count.

The packing (:func:`pack_nodes`, :func:`pack_ell`), the upload (:func:`upload_ell`; both at once,
a band of texel rows at a time, :func:`upload_packed`) and the pass
(:class:`GatherProgram`: one program, the operation chosen by the uniform ``u_mode``) are shared
with the multigrid V-cycle of :mod:`glsldiff.solve.gather_multigrid`, whose restriction ``P^T``,
prolongation ``P`` and dense coarsest-level inverse are rectangular "matrices" in the same
format (every entry in a slot, ``APPLY`` and ``ADD`` modes) and whose residual is the
``RESIDUAL`` mode. The source vector of a pass may have its own power-of-two width
(``u_src_shift``): a level's texture gathers from a coarser or finer level's.

Damping. For a symmetric positive definite ``A`` the eigenvalues ``lambda`` of ``D^-1 A``
are real and positive, and damped Jacobi multiplies the error's component along each
eigenvector by ``1 - omega lambda``. It converges iff ``omega lambda_max < 2``. On a
7-point Laplacian ``lambda_max < 2`` (plain Jacobi, ``omega = 1``, converges), but the P1
matrices of distorted tetrahedra have positive off-diagonal entries and reach
``lambda_max(D^-1 A) > 2``, where plain Jacobi diverges (measured on the 10 mm sphere grids,
5 mm cubes: 2.02 at n = 3, 2.43 at n = 8; 2.22 and 3.07 with an earlier mapping).
``omega="auto"`` takes

    omega = min(1, 1.9 / lambda_max)

with ``lambda_max`` estimated on the CPU (Lanczos, :func:`glsldiff.oracle.amg.jacobi_lambda_max`, the largest over
the channels). Reasons: the slow (smooth) error modes contract by ``1 - omega lambda_min`` per
sweep, so ``omega`` should be as large as the fast modes allow; ``1.9 / lambda_max`` keeps the
fast modes' factor ``|1 - omega lambda|`` <= 0.9 (damped 200x per 50-sweep residual check, so
they never dominate it) and leaves a 5 % margin for the estimate (a Lanczos Ritz value is a
lower bound of ``lambda_max``; ARPACK's is converged to 1e-3). The optimum ``2 / (lambda_max +
lambda_min)`` is ``2 / 1.9 (1 - lambda_min / lambda_max)`` times it, i.e. at most 5 % larger
where Jacobi is slow (``lambda_min << lambda_max``), and would need ``lambda_min``, an expensive
estimate (measured on the n = 8 sphere: 1070 sweeps to a 1e-4 residual with omega = 0.78
(auto), 1280 with 0.651, 1660 with 0.5; omega = 1 diverges). The cap at 1 makes ``"auto"``
plain Jacobi, the project's relaxation, wherever that converges with the same margin
(``lambda_max <= 1.9``); on 7-point Laplacians (``lambda_max`` 1.95-1.99) auto's omega
0.95-0.97 costs about 4 % more sweeps than plain Jacobi. The omega used is
:attr:`GlslSparse.omega` and is part of the report's method string
(``"glsl-gather-fp32(omega=0.7806)"``).

Convergence is checked as for every relaxation, by :func:`glsldiff.oracle.solvers.relax`: the
iterate is read back every ``check_every`` sweeps and its Jacobi-scaled residual ``max_c
||D^-1 (b - A x)|| / ||D^-1 b||`` evaluated in float64 on the CPU system.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Sequence, TypeVar

import moderngl
import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray

from glsldiff import gl
from glsldiff.core.errors import InputError, SolverError
from glsldiff.core.jit import kernel
from glsldiff.oracle.amg import jacobi_lambda_max
from glsldiff.oracle.assembly import ChannelSystem, LinearSystem, block_diagonal, channel_values
from glsldiff.oracle.solvers import Callback, Relaxation, relax
from glsldiff.system.report import CURRENT, MAXITER, RELAX_TOL, SolveReport

__all__ = ["GlslSparse", "GatherSolver", "auto_omega", "sweep_rate", "MAX_NODES", "channel_matrices",
           "channel_values", "compact_channels", "node_rhs", "check_symmetric", "block_diagonal", "distinct",
           "texture_width", "pack_nodes", "EllPack", "pack_ell", "GatherMatrix", "upload_ell", "upload_packed",
           "write_band", "spill_layers", "GatherProgram", "parse_start", "JACOBI", "RESIDUAL", "APPLY", "ADD", "MATVEC"]

PRECISIONS = ("fp32",)
MAX_NODES = 1 << 24       # neighbour indices are stored as floats (exact integers below 2^24)
OMEGA_TARGET = 1.9        # omega = min(1, OMEGA_TARGET / lambda_max) for omega="auto"
_S = TypeVar("_S", bound="GatherSolver")
Matrices = sp.spmatrix | sp.sparray | NDArray | Sequence[sp.spmatrix | sp.sparray | NDArray]
Start = ArrayLike | str | None  # x0: (n, 3) array, CURRENT, or None (zero)
JACOBI, RESIDUAL, APPLY, ADD, MATVEC = 0, 1, 2, 3, 4   # gather.frag u_mode
BAND_BYTES = 1 << 23      # upload_packed: slots packed and written about this many bytes at a time
#: upload_packed(spill=True): at most this share of a gather's rows spill (an 8-fragment SIMD group
#: of llvmpipe with one spilled row runs the spill loop: the bunny's finest matrix, 31 slots, with
#: 14 main layers (13 % of the rows spilled) cycled 15 % slower than padded; with 19 (1 %) as fast)
SPILL_SHARE = 0.01


# ---- the damping ----------------------------------------------------------------------------
def auto_omega(lambda_max: float) -> float:
    """``min(1, 1.9 / lambda_max)``: the damping of ``omega="auto"`` (module docstring)."""
    return min(1.0, OMEGA_TARGET / lambda_max)


def parse_omega(omega: float | str) -> float | None:
    """A Jacobi damping argument checked: ``None`` for ``"auto"``, else the float in (0, 2)."""
    if isinstance(omega, str):
        if omega != "auto":
            raise InputError(f"omega={omega!r}: give a float in (0, 2) or 'auto'")
        return None
    try:
        w = float(omega)
    except (TypeError, ValueError) as exc:
        raise InputError(f"omega={omega!r}: give a float in (0, 2) or 'auto'") from exc
    if not 0.0 < w < 2.0:
        raise InputError(f"omega={omega!r} must be in (0, 2) (damped Jacobi diverges outside)")
    return w


# ---- input checks ---------------------------------------------------------------------------
def _channel_items(matrices: Matrices) -> list:
    """The three per-channel items of ``matrices`` (one matrix for all channels, or three)."""
    if sp.issparse(matrices) or (isinstance(matrices, np.ndarray) and matrices.ndim == 2):
        return [matrices] * 3
    if isinstance(matrices, (list, tuple)) and len(matrices) == 3:
        return list(matrices)
    raise InputError("matrices: give one n x n sparse matrix (used for all three channels) or a "
                     f"list of three (R, G, B), not {type(matrices).__name__}"
                     + (f" of length {len(matrices)}" if isinstance(matrices, (list, tuple)) else ""))


def compact_channels(values: NDArray[np.float64], indices: NDArray[np.integer], indptr: NDArray[np.integer],
                     shape: tuple[int, int]) -> list[sp.csr_matrix]:
    """Three CSR matrices of ``shape`` on one pattern (``indices``, ``indptr``, shared), their
    data the rows of ``values`` ``(3, nnz)`` (views: they follow changes of ``values``)."""
    out = []
    for c in range(3):
        M = sp.csr_matrix((values[c], indices, indptr), shape=shape)
        M.data, M.indices, M.indptr = values[c], indices, indptr     # scipy may have made new views or copies
        out.append(M)
    return out


def _canonical(m: object, c: int) -> sp.csr_matrix:
    """Channel ``c``'s matrix as a float64 CSR copy with summed duplicates and sorted indices."""
    try:
        M = sp.csr_matrix(m if sp.issparse(m) else np.asarray(m), copy=True)
    except (TypeError, ValueError) as exc:
        raise InputError(f"matrix of channel {c} is not a 2-D matrix ({exc})") from exc
    if M.ndim != 2 or M.shape[0] != M.shape[1]:
        raise InputError(f"matrix of channel {c} has shape {M.shape}; it must be square (n x n)")
    if np.iscomplexobj(M.data) or M.data.dtype.kind not in "biuf":
        raise InputError(f"matrix of channel {c} has dtype {M.data.dtype}; it must be real")
    M = M.astype(np.float64)
    M.sum_duplicates()
    M.sort_indices()
    _check_finite(M, c)
    return M


def _check_finite(M: sp.csr_matrix, c: int) -> None:
    """InputError naming the first non-finite entry of channel ``c``'s matrix ``M``."""
    bad = ~np.isfinite(M.data)
    if bad.any():
        k = int(np.argmax(bad))
        row = int(np.searchsorted(M.indptr, k, side="right") - 1)
        raise InputError(f"matrix of channel {c} has {int(bad.sum())} non-finite (NaN/inf) entries, "
                         f"the first at row {row}, column {int(M.indices[k])}")


def _check_pattern(out: list[sp.csr_matrix]) -> None:
    """InputError unless the three matrices are ``n x n`` with one stored pattern."""
    for c, M in enumerate(out[1:], start=1):
        if M.shape != out[0].shape:
            raise InputError(f"matrix of channel {c} is {M.shape}, channel 0's {out[0].shape}; all three "
                             "must be n x n with the same n")
        if not (np.array_equal(M.indptr, out[0].indptr) and np.array_equal(M.indices, out[0].indices)):
            rows = np.flatnonzero(np.diff(M.indptr) != np.diff(out[0].indptr))
            if rows.size == 0:
                starts = out[0].indptr[:-1]
                diff = np.flatnonzero(M.indices != out[0].indices)
                rows = np.searchsorted(starts, diff, side="right") - 1
            i = int(rows[0])
            cols = [M.indices[M.indptr[i]:M.indptr[i + 1]], out[0].indices[out[0].indptr[i]:out[0].indptr[i + 1]]]
            raise InputError(f"the channel matrices must share one sparsity pattern (stored entries): "
                             f"channel {c} differs from channel 0 first in row {i} (columns "
                             f"{cols[0].tolist()} vs {cols[1].tolist()}); store explicit zeros to align them")


def _check_size_diagonal(out: list[sp.csr_matrix], who: str) -> None:
    """InputError for a size outside ``1 .. MAX_NODES`` or a diagonal entry that is not positive."""
    n = out[0].shape[0]
    if n < 1 or n > MAX_NODES:
        raise InputError(f"the system has n = {n} unknowns; {who} takes 1 .. {MAX_NODES} "
                         "(neighbour indices are stored as exact float integers)")
    for c, M in enumerate(out):
        d = M.diagonal()
        bad = ~(d > 0)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"matrix of channel {c} has {int(bad.sum())} zero or negative diagonal entries "
                             f"(first: row {i}, a_ii = {d[i]:g}); Jacobi divides by the diagonal, and a "
                             "symmetric positive definite matrix has a positive one")


def channel_matrices(matrices: Matrices, who: str = "GlslSparse") -> list[sp.csr_matrix]:
    """The three channel matrices of ``matrices`` (one for all channels, or three), checked
    (square, real, finite, one stored pattern, positive diagonal, ``1 <= n <= MAX_NODES``), in
    the compact form of :func:`channel_values` (float64 CSR with sorted indices, one pattern
    array for the three, their values one ``(3, nnz)`` array); ``who`` names the solver in
    messages. Matrices already in that form with sorted indices (a P1 system's
    :meth:`~glsldiff.oracle.fem_update.P1System.matrices`) are used as they are, not copied
    (0.15 s and 80 MB on the bunny's 147k-node grid): a solver of them follows their later
    changes only through its ``update_fine``. Others are copied."""
    items = _channel_items(matrices)
    if channel_values(items) is not None and items[0].shape[0] == items[0].shape[1] and items[0].has_canonical_format:
        for c, M in enumerate(items):
            _check_finite(M, c)
        _check_size_diagonal(items, who)
        return items
    out = [_canonical(m, c) for c, m in enumerate(items)]
    _check_pattern(out)
    _check_size_diagonal(out, who)
    values = np.stack([M.data for M in out])
    return compact_channels(values, out[0].indices, out[0].indptr, out[0].shape)


def node_rhs(b: ArrayLike, n: int) -> NDArray[np.float64]:
    """``b`` as a checked ``(n, 3)`` float64 array (``(n,)``: the same for all channels)."""
    arr = np.asarray(b, dtype=np.float64)
    if arr.shape == (n,):
        arr = np.repeat(arr[:, None], 3, axis=1)
    if arr.shape != (n, 3):
        raise InputError(f"b has shape {arr.shape}, expected ({n}, 3) (or ({n},) for all channels)")
    if not np.isfinite(arr).all():
        raise InputError(f"b has {int((~np.isfinite(arr)).sum())} non-finite (NaN/inf) values")
    return arr


def texture_width(n: int, max_size: int) -> tuple[int, int]:
    """``(W, H)`` of the textures of ``n`` nodes: ``W`` the smallest power of two >= ``sqrt(n)``."""
    w = 1 << max(0, math.ceil(math.log2(math.sqrt(n))))   # a power of two >= sqrt(n): shifts, no division
    h = math.ceil(n / w)
    if w > max_size or h > max_size:
        raise InputError(f"n = {n} unknowns need a {w} x {h} texture; this context allows {max_size}")
    return w, h


def check_symmetric(mats: list[sp.csr_matrix], need: str, hint: str) -> None:
    """InputError ``"{need}; channel c has |A - A^T| up to ...; {hint}"`` unless every matrix is
    symmetric to 1e-10 of its largest entry."""
    for c, M in enumerate(mats):
        asym = abs(M - M.T).max() if M.nnz else 0.0
        if asym > 1e-10 * abs(M).max():
            raise InputError(f"{need}; channel {c} has |A - A^T| up to {asym:.3g}; {hint}")


# ---- packing: node textures and ELLPACK slot layers (every gather operator) ----------------
def pack_nodes(values: NDArray, size: tuple[int, int], pad: float = 0.0) -> NDArray[np.float32]:
    """``(n, 3)`` node values -> ``(H, W, 4)`` texels (node ``i`` at ``(i % W, i // W)``;
    alpha 0; padding texels ``i >= n`` get ``pad``)."""
    W, H = size
    vals = np.asarray(values)
    out = np.zeros((H * W, 4), dtype=np.float32)
    out[:, :3] = pad
    out[:len(vals), :3] = vals
    return out.reshape(H, W, 4)


@dataclass
class EllPack:
    """The slot layers of a (possibly rectangular) matrix with RGB channels.

    ``coef`` ``(max(K, 1), H, W, 4)``: layer ``k`` at row ``i``'s texel holds rgb = the ``k``-th
    stored entry of row ``i`` (columns ascending) in the three channels, alpha = its column as a
    float, ``-1`` for an empty slot; ``slots`` = ``K``, the longest row; ``row_slots`` the used
    slots per row."""

    coef: NDArray[np.float32]
    slots: int
    row_slots: NDArray[np.int64]


def _aligned(mats: Sequence[sp.csr_matrix]) -> tuple[NDArray, NDArray, list[NDArray]]:
    """``(indptr, cols, [vals_c])`` (int64, int64, float64 per channel) of three CSR matrices on
    one pattern: channel 0's when all share it (the checked systems), else the union of the
    stored entries, zero where a channel has none (Galerkin products, whose pattern scipy trims
    of exact cancellations per channel)."""
    M0 = mats[0]
    if all(np.array_equal(M.indptr, M0.indptr) and np.array_equal(M.indices, M0.indices) for M in mats[1:]):
        return (M0.indptr.astype(np.int64, copy=False), M0.indices.astype(np.int64, copy=False),
                [np.ascontiguousarray(M.data) for M in mats])
    n_rows, n_cols = M0.shape
    keys = [np.repeat(np.arange(M.shape[0], dtype=np.int64), np.diff(M.indptr)) * n_cols + M.indices
            for M in mats]       # row-major entry keys, ascending (sorted indices)
    union = np.unique(np.concatenate(keys))
    vals = [np.zeros(union.size) for _ in mats]
    for v, k, M in zip(vals, keys, mats):
        v[np.searchsorted(union, k)] = M.data
    indptr = np.concatenate([[0], np.cumsum(np.bincount(union // n_cols, minlength=n_rows))])
    return indptr, union % n_cols, vals


@kernel
def _ell_counts(indptr: NDArray[np.int64], cols: NDArray[np.int64], v0: NDArray[np.float64],
                v1: NDArray[np.float64], v2: NDArray[np.float64], keep_zeros: bool, drop_diagonal: bool,
                row_offset: int, counts: NDArray[np.int64]) -> None:
    """``counts[i]``: the slots row ``i`` needs (its entries, less the diagonal when
    ``drop_diagonal``, less those zero in all channels unless ``keep_zeros``)."""
    for i in range(indptr.size - 1):
        c = 0
        for jj in range(indptr[i], indptr[i + 1]):
            if drop_diagonal and cols[jj] == i + row_offset:
                continue
            if keep_zeros or v0[jj] != 0.0 or v1[jj] != 0.0 or v2[jj] != 0.0:
                c += 1
        counts[i] = c


@kernel
def _ell_fill(indptr: NDArray[np.int64], cols: NDArray[np.int64], v0: NDArray[np.float64],
              v1: NDArray[np.float64], v2: NDArray[np.float64], keep_zeros: bool, drop_diagonal: bool,
              row_offset: int, ranks: NDArray[np.int64], rank0: int, coef: NDArray[np.float32],
              spill: NDArray[np.float32]) -> None:
    """Every texel of ``coef`` ``(K, texels, 4)``: row ``i``'s kept entries (as
    :func:`_ell_counts` counts them) in its first slots, ``(a0, a1, a2, j)``, then empty slots
    ``(0, 0, 0, -1)``; texels past the last row all empty. A spilled row (``ranks[i] >= 0``)
    keeps its first ``K - 1`` entries here, a link ``(0, 0, 0, -2 - rank)`` in slot ``K - 1``
    and the rest in ``spill`` ``(K1, m, 4)`` at texel ``ranks[i] - rank0`` (then empty slots)."""
    K, n = coef.shape[0], indptr.size - 1
    for i in range(coef.shape[1]):
        s = 0
        if i < n:
            r = ranks[i] - rank0 if ranks[i] >= 0 else -1
            cap = K - 1 if r >= 0 else K
            for jj in range(indptr[i], indptr[i + 1]):
                if drop_diagonal and cols[jj] == i + row_offset:
                    continue
                if keep_zeros or v0[jj] != 0.0 or v1[jj] != 0.0 or v2[jj] != 0.0:
                    if s < cap:
                        coef[s, i, 0] = v0[jj]
                        coef[s, i, 1] = v1[jj]
                        coef[s, i, 2] = v2[jj]
                        coef[s, i, 3] = cols[jj]
                    else:
                        spill[s - cap, r, 0] = v0[jj]
                        spill[s - cap, r, 1] = v1[jj]
                        spill[s - cap, r, 2] = v2[jj]
                        spill[s - cap, r, 3] = cols[jj]
                    s += 1
            if r >= 0:
                for k in range(s - cap, spill.shape[0]):
                    spill[k, r, 0] = 0.0
                    spill[k, r, 1] = 0.0
                    spill[k, r, 2] = 0.0
                    spill[k, r, 3] = -1.0
                coef[cap, i, 0] = 0.0
                coef[cap, i, 1] = 0.0
                coef[cap, i, 2] = 0.0
                coef[cap, i, 3] = -2.0 - ranks[i]
                s = K
        for k in range(s, K):
            coef[k, i, 0] = 0.0
            coef[k, i, 1] = 0.0
            coef[k, i, 2] = 0.0
            coef[k, i, 3] = -1.0


@dataclass
class _EllLayout:
    """Three matrices' entries on one pattern (:func:`_aligned`) and the slots of their rows:
    what :func:`_ell_fill` packs, all at once or a band of rows at a time. ``main`` layers hold
    every row but the spilled ones (``ranks >= 0``, in row order), whose rest goes to
    ``spill_slots`` layers of a texture of their own (:func:`spill_layers`)."""

    indptr: NDArray[np.int64]
    cols: NDArray[np.int64]
    vals: list[NDArray[np.float64]]
    keep_zeros: bool
    drop_diagonal: bool
    row_offset: int
    counts: NDArray[np.int64]
    slots: int
    main: int
    ranks: NDArray[np.int64]

    @property
    def layers(self) -> int:
        """Texture-array layers: ``max(main, 1)``."""
        return max(self.main, 1)

    @property
    def spill_slots(self) -> int:
        """Layers of the spill texture (0: no row spills)."""
        return self.slots - self.main + 1 if self.main < self.slots else 0

    def fill(self, first: int, texels: int) -> tuple[NDArray[np.float32], NDArray[np.float32], int]:
        """``(layers, texels, 4)``: the slots of the rows from ``first`` on in ``texels`` texels
        (texels past the last row empty); ``(spill_slots, m, 4)``: the rest of their ``m`` spilled
        rows, from spill texel ``rank0`` on (the third value)."""
        n = self.indptr.size - 1
        r0, r1 = min(first, n), min(first + texels, n)
        ranks = self.ranks[r0:r1]
        spilled = ranks[ranks >= 0]
        rank0 = int(spilled[0]) if spilled.size else 0
        coef = np.empty((self.layers, texels, 4), dtype=np.float32)
        spill = np.empty((self.spill_slots, spilled.size, 4), dtype=np.float32)
        _ell_fill(self.indptr[r0:r1 + 1], self.cols, *self.vals, self.keep_zeros, self.drop_diagonal,
                  self.row_offset + r0, ranks, rank0, coef, spill)
        return coef, spill, rank0


def spill_layers(counts: NDArray[np.int64], texels: int, max_size: int, share: float = SPILL_SHARE) -> int:
    """The main layers ``K0`` of a gather whose rows have ``counts`` slots in ``texels`` texels:
    the fewest texels in all (``K0`` layers of ``texels``, plus ``K - K0 + 1`` layers of a
    power-of-two-wide texture of the rows longer than ``K0``, which keep a link in their last
    main slot) with at most ``share`` of the rows spilled; ``K`` (no spill) unless that saves an
    eighth. The bunny's finest matrix: 31 slots, 13.3 per row on average, 19 layers (73 -> 45 MB)."""
    K = int(counts.max()) if counts.size else 0
    if K < 2:
        return K
    longer = np.cumsum(np.bincount(counts, minlength=K + 1)[::-1])[::-1]     # longer[k]: rows of >= k slots
    best, best_texels = K, K * texels
    for k0 in range(1, K):
        m = int(longer[k0 + 1])
        if m > share * counts.size:
            continue
        W, H = texture_width(m, max_size)
        total = k0 * texels + (K - k0 + 1) * W * H
        if total < best_texels:
            best, best_texels = k0, total
    return best if 8 * best_texels <= 7 * K * texels else K


def _ell_layout(mats: Sequence[sp.spmatrix | sp.sparray], size: tuple[int, int], *, diagonal: bool,
                keep_zeros: bool = False, row_offset: int = 0, slots: int | None = None,
                main: int | None = None, ranks: NDArray[np.integer] | None = None) -> _EllLayout:
    """The :class:`_EllLayout` of ``mats`` in ``size`` texels (the arguments as :func:`pack_ell`'s;
    ``main`` layers with the rows longer than it spilled, ranked in row order, or ``ranks``
    given: a band of an uploaded gather's rows, :attr:`GatherMatrix.ranks`)."""
    W, H = size
    mats = [sp.csr_matrix(M, dtype=np.float64) for M in mats]
    for M in mats:
        M.sum_duplicates()
        M.sort_indices()
    n_rows, n_cols = mats[0].shape
    if n_rows > W * H or n_cols > MAX_NODES:
        raise InputError(f"a {n_rows} x {n_cols} matrix does not fit {W} x {H} texels / float indices")
    indptr, cols, vals = _aligned(mats)
    counts = np.zeros(n_rows, dtype=np.int64)
    _ell_counts(indptr, cols, *vals, bool(keep_zeros), not diagonal, int(row_offset), counts)
    K = int(counts.max()) if counts.size else 0
    if slots is not None:
        if K > slots:
            raise InputError(f"a row has {K} entries; the packed matrix has {slots} slots")
        K = slots
    K0 = K if main is None else int(main)
    if ranks is None:
        ranks = _ell_layout_ranks(counts, K0)
    return _EllLayout(indptr, cols, vals, bool(keep_zeros), not diagonal, int(row_offset), counts, K, K0,
                      np.asarray(ranks, dtype=np.int64))


def pack_ell(mats: Sequence[sp.spmatrix | sp.sparray], size: tuple[int, int], *,
             diagonal: bool, keep_zeros: bool = False, row_offset: int = 0, slots: int | None = None) -> EllPack:
    """The :class:`EllPack` of the ``rows x cols`` matrices ``mats`` (three channels; rows laid
    out in the ``size`` textures). ``diagonal=False``: the diagonal gets no slot (a system
    matrix: ``a_ii`` goes to its own texture); ``True``: every entry does (restriction,
    prolongation, a dense inverse). Entries zero in all channels get no slot unless
    ``keep_zeros`` (a pattern whose values change in place keeps its slots); ``cols`` must be
    at most 2^24 (exact float indices). ``row_offset``: ``mats`` are the rows from that one on
    of a larger matrix (a band re-packed after an update, ``slots`` its ``K``). Compiled loops
    (:func:`_ell_counts`, :func:`_ell_fill`: one pass over the entries and one write of every
    texel: 0.35 -> 0.12 s CPU for the bunny's multigrid levels against the numpy scatter they
    replaced, the same bits)."""
    W, H = size
    lay = _ell_layout(mats, size, diagonal=diagonal, keep_zeros=keep_zeros, row_offset=row_offset, slots=slots)
    return EllPack(lay.fill(0, H * W)[0].reshape(lay.layers, H, W, 4), lay.slots, lay.counts)


# ---- GPU: uploaded slot layers and the gather pass -----------------------------------------
@dataclass
class GatherMatrix:
    """An :class:`EllPack` on the GPU: the texture array and ``slots`` (``K``, the longest row);
    where rows spill (:func:`upload_packed`), ``layers`` of them in ``texture`` and the rest of
    the longer rows in ``spill`` (``spill_slots`` layers, ``spill_width`` texels wide; a spilled
    row's rank, its texel there, in ``ranks``, -1 for the others)."""

    texture: moderngl.TextureArray
    slots: int
    layers: int = 0
    spill: moderngl.TextureArray | None = None
    spill_slots: int = 0
    spill_width: int = 1
    ranks: NDArray[np.int32] | None = None

    def __post_init__(self) -> None:
        self.layers = self.layers or max(self.slots, 1)


def _slot_texture(ctx: moderngl.Context, size: tuple[int, int], slots: int, data: NDArray[np.float32] | None,
                  resources: gl.Resources, hint: str = "") -> moderngl.TextureArray:
    """An RGBA32F texture array of ``max(slots, 1)`` layers of ``size`` (nearest, clamped; ``data``
    ``(layers, H, W, 4)`` or ``None``), owned by ``resources``.

    Raises
    ------
    InputError
        ``slots`` exceeds the context's ``GL_MAX_ARRAY_TEXTURE_LAYERS`` (``hint`` ends the message)."""
    max_layers = int(ctx.info.get("GL_MAX_ARRAY_TEXTURE_LAYERS", 256))
    if slots > max_layers:
        raise InputError(f"a row has {slots} entries in slots; this context's texture arrays "
                         f"hold at most {max_layers} layers{hint}")
    src = None if data is None else memoryview(np.ascontiguousarray(data))      # no bytes copy
    tex = ctx.texture_array((*size, max(slots, 1)), 4, src, dtype="f4", alignment=1)
    tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
    tex.repeat_x = tex.repeat_y = False
    return resources.add(tex)


def upload_ell(ctx: moderngl.Context, pack: EllPack, resources: gl.Resources) -> GatherMatrix:
    """Upload ``pack`` as an RGBA32F texture array (nearest, clamped), owned by ``resources``.

    Raises
    ------
    InputError
        ``K`` exceeds the context's ``GL_MAX_ARRAY_TEXTURE_LAYERS``."""
    L, H, W, _ = pack.coef.shape
    return GatherMatrix(_slot_texture(ctx, (W, H), pack.slots, pack.coef, resources), pack.slots)


def _write_texels(tex: moderngl.TextureArray, data: NDArray[np.float32], first: int) -> None:
    """Write ``data`` ``(layers, m, 4)`` to the texels ``first .. first + m - 1`` (row-major) of
    every layer of ``tex``: at most three rectangles (a partial row, whole rows, a partial row)."""
    W = tex.size[0]
    m, at = data.shape[1], 0
    while at < m:
        t = first + at
        x, y = t % W, t // W
        w = min(W - x, m - at) if x or m - at < W else W
        h = 1 if w < W else (m - at) // W
        block = data[:, at:at + w * h].reshape(data.shape[0], h, w, 4)
        tex.write(memoryview(np.ascontiguousarray(block)), viewport=(x, y, 0, w, h, data.shape[0]), alignment=1)
        at += w * h


def upload_packed(ctx: moderngl.Context, mats: Sequence[sp.spmatrix | sp.sparray], size: tuple[int, int],
                  resources: gl.Resources, *, diagonal: bool, keep_zeros: bool = False,
                  band_bytes: int = BAND_BYTES, hint: str = "", spill: bool = False
                  ) -> tuple[GatherMatrix, NDArray[np.int64]]:
    """:func:`pack_ell` and :func:`upload_ell` of ``mats`` band by band: the texture array made
    empty, then each band of texel rows (about ``band_bytes``) packed and written, so that the
    whole pack never exists in memory (the bunny's finest matrix alone is 73 MB of slots; the
    texture's content is the same bits). With ``spill`` the rows longer than
    :func:`spill_layers` go on in a texture of their own (``shaders/gather.frag`` follows their
    link; the same entries in the same order). Returns the matrix on the GPU and the used slots
    per row (:attr:`EllPack.row_slots`).

    Raises
    ------
    InputError
        As :func:`pack_ell` and :func:`upload_ell` (``hint`` ends the message of too many slots)."""
    W, H = size
    lay = _ell_layout(mats, size, diagonal=diagonal, keep_zeros=keep_zeros)
    if spill:
        lay.main = spill_layers(lay.counts, W * H, int(ctx.info["GL_MAX_TEXTURE_SIZE"]))
        lay.ranks = _ell_layout_ranks(lay.counts, lay.main)
    tex = _slot_texture(ctx, size, lay.main, None, resources, hint)
    out = GatherMatrix(tex, lay.slots, lay.layers)
    if lay.spill_slots:
        n_spill = int(lay.ranks.max()) + 1
        sw, sh = texture_width(n_spill, int(ctx.info["GL_MAX_TEXTURE_SIZE"]))
        out.spill = _slot_texture(ctx, (sw, sh), lay.spill_slots, None, resources, hint)
        out.spill.write(np.tile(np.array([0, 0, 0, -1], dtype=np.float32), (lay.spill_slots * sw * sh, 1)).tobytes(),
                        alignment=1)        # texels past the last spilled row: empty
        out.spill_slots, out.spill_width, out.ranks = lay.spill_slots, sw, lay.ranks.astype(np.int32)
    rows = max(1, band_bytes // (lay.layers * W * 16))       # texel rows per band
    for y in range(0, H, rows):
        h = min(rows, H - y)
        coef, rest, rank0 = lay.fill(y * W, h * W)
        tex.write(memoryview(coef), viewport=(0, y, 0, W, h, lay.layers), alignment=1)
        if rest.shape[1]:
            assert out.spill is not None
            _write_texels(out.spill, rest, rank0)
    return out, lay.counts


def write_band(matrix: GatherMatrix, band: Sequence[sp.spmatrix | sp.sparray], y: int, size: tuple[int, int], *,
               diagonal: bool, keep_zeros: bool = False) -> None:
    """Re-pack the rows of an uploaded gather that texel rows ``y ..`` of its ``size`` (``W``, rows)
    hold, from ``band``, those rows of matrices on the uploaded pattern (an in-place update),
    and write them (and the rest of their spilled rows) over the old ones."""
    W, h = size
    lay = _ell_layout(band, (W, h), diagonal=diagonal, keep_zeros=keep_zeros, row_offset=y * W,
                      slots=matrix.slots, main=matrix.layers,
                      ranks=None if matrix.ranks is None else matrix.ranks[y * W:y * W + band[0].shape[0]])
    coef, rest, rank0 = lay.fill(0, W * h)
    matrix.texture.write(coef.tobytes(), viewport=(0, y, 0, W, h, coef.shape[0]), alignment=1)
    if rest.shape[1]:
        assert matrix.spill is not None
        _write_texels(matrix.spill, rest, rank0)


def _ell_layout_ranks(counts: NDArray[np.int64], main: int) -> NDArray[np.int64]:
    """Each row's rank among the rows longer than ``main`` slots (-1 for the others)."""
    longer = counts > main
    return np.where(longer, np.cumsum(longer) - 1, -1)


class GatherProgram:
    """``shaders/gather.frag`` on a full-viewport quad: one pass per :meth:`draw` (module
    docstring; the modes are :data:`JACOBI`, :data:`RESIDUAL`, :data:`APPLY`, :data:`ADD`,
    :data:`MATVEC`).
    Its GPU objects go to ``resources``. Texture units: 0 ``u_src``, 1 ``u_self``, 2
    ``u_diag``, 3 ``u_b``, 4 ``u_coef``, 5 ``u_spill``."""

    def __init__(self, ctx: moderngl.Context, resources: gl.Resources) -> None:
        self.ctx = ctx
        self.prog = resources.add(gl.program(ctx, "quad.vert", "gather.frag"))
        gl.set_uniforms(self.prog, {"u_size": (1.0, 1.0), "u_src": 0, "u_self": 1, "u_diag": 2, "u_b": 3,
                                    "u_coef": 4, "u_spill": 5})
        self._vbo = resources.add(ctx.buffer(np.array([0, 0, 1, 0, 0, 1, 1, 1], dtype="f4").tobytes()))
        self.vao = resources.add(ctx.vertex_array(self.prog, [(self._vbo, "2f", "in_pos")]))
        self._u = {name: self.prog[name] for name in ("u_slots", "u_src_shift", "u_mode", "u_omega",
                                                      "u_spill_slots", "u_spill_shift") if name in self.prog}
        self._set: dict[str, float] = {}

    def _uniform(self, name: str, value: float) -> None:
        if name in self._u and self._set.get(name) != value:
            self._u[name].value = value
            self._set[name] = value

    def draw(self, mode: int, target: moderngl.Framebuffer, size: tuple[int, int], matrix: GatherMatrix,
             src: moderngl.Texture, src_size: tuple[int, int], own: moderngl.Texture | None = None,
             diag: moderngl.Texture | None = None, b: moderngl.Texture | None = None,
             omega: float = 1.0) -> None:
        """Render ``mode`` of ``matrix`` gathering ``src`` (``src_size`` texels, power-of-two
        width) into ``target`` (``size``); ``own`` (x at the target's nodes; default ``src``),
        ``diag`` and ``b`` as the mode needs them. The caller binds no framebuffer back: wrap
        passes in :func:`glsldiff.gl.keep_framebuffer`."""
        target.use()
        self.ctx.viewport = (0, 0, *size)
        src.use(0)
        (src if own is None else own).use(1)
        if diag is not None:
            diag.use(2)
        if b is not None:
            b.use(3)
        matrix.texture.use(4)
        (matrix.texture if matrix.spill is None else matrix.spill).use(5)     # a texture array there either way
        self._uniform("u_mode", mode)
        self._uniform("u_slots", matrix.layers)
        self._uniform("u_spill_slots", matrix.spill_slots)
        self._uniform("u_spill_shift", matrix.spill_width.bit_length() - 1)
        self._uniform("u_src_shift", src_size[0].bit_length() - 1)
        self._uniform("u_omega", float(omega))
        self.vao.render(moderngl.TRIANGLE_STRIP)


def parse_start(x0: Start, set_initial: Callable[[ArrayLike | None], None]) -> None:
    """The ``x0`` argument of a GLSL solve: :data:`CURRENT` leaves the GPU iterate, an array or
    ``None`` (zero) is written by ``set_initial``."""
    if isinstance(x0, str):
        if x0 != CURRENT:
            raise InputError(f"x0={x0!r}: give an (n, 3) array, None (zero) or {CURRENT!r}")
    else:
        set_initial(x0)


# ---- what both gather solvers share --------------------------------------------------------
class GatherSolver:
    """The common part of :class:`GlslSparse` and
    :class:`glsldiff.solve.gather_multigrid.GlslSparseMultigrid`: the right-hand side and the
    iterate on the GPU, the CPU system whose residual the solve checks, ``x0`` handling,
    read-back and lifetime. A subclass sets ``n``, ``ctx``, ``system`` and ``_gpu`` (the
    :class:`glsldiff.gl.Resources` it owns) and provides ``state`` (the iterate's ping-pong
    pair), ``_rhs`` (the fine right-hand-side texture) and ``_fine_size``."""

    n: int
    ctx: moderngl.Context
    system: LinearSystem
    state: gl.PingPong
    _gpu: gl.Resources

    @property
    def _rhs(self) -> moderngl.Texture:
        raise NotImplementedError

    @property
    def _fine_size(self) -> tuple[int, int]:
        raise NotImplementedError

    def _restart(self) -> None:
        """Hook: the right-hand side or the iterate was replaced (default: nothing to reset)."""

    def set_b(self, b: ArrayLike) -> None:
        """Replace the right-hand side (``(n, 3)``, or ``(n,)`` for all channels)."""
        gl.make_current(self.ctx)
        bb = node_rhs(b, self.n)
        self._rhs.write(pack_nodes(bb, self._fine_size).tobytes(), alignment=1)
        self.system.b = bb.T.reshape(-1)
        self._restart()

    def set_initial(self, x: ArrayLike | None) -> None:
        """Start the next iterations from ``x`` (``(n, 3)``) or from zero."""
        gl.make_current(self.ctx)
        if x is None:
            vals = np.zeros((self.n, 3))
        else:
            vals = np.asarray(x, dtype=np.float64)
            if vals.shape != (self.n, 3):
                raise InputError(f"x0 has shape {vals.shape}, expected ({self.n}, 3)")
            if not np.isfinite(vals).all():
                raise InputError("x0 has non-finite (NaN/inf) values")
        self.state.write(pack_nodes(vals, self._fine_size))
        self._restart()

    def unknown(self) -> NDArray[np.float64]:
        """The current (fine) iterate, ``(n, 3)`` float64."""
        gl.make_current(self.ctx)
        return self.state.read().reshape(-1, 4)[:self.n, :3].astype(np.float64)

    def _relax(self, step: Callable[[int], None], x0: Start, *, tol: float, maxiter: int, check_every: int,
               callback: Callback | None, residuals: list[float] | None, name: str,
               hint: Callable[[], str]) -> Relaxation:
        """Start from ``x0`` and drive ``step(k)`` (``k`` more iterations) through the shared
        solve loop :func:`glsldiff.oracle.solvers.relax`; a divergence is re-raised with ``hint()``."""
        parse_start(x0, self.set_initial)

        def advance(k: int) -> NDArray[np.float64]:
            step(k)
            return self.unknown().T.reshape(-1)

        try:
            return relax(self.system, advance, self.unknown().T.reshape(-1), tol=tol, maxiter=maxiter,
                         check_every=check_every, callback=callback, residuals=residuals, name=name)
        except SolverError as exc:
            raise SolverError(f"{exc}: {hint()}") from exc

    # ---- lifetime ---------------------------------------------------------------------------
    def _finish(self, method: str, result: Relaxation, t0: float, **extra: object
                ) -> tuple[NDArray[np.float64], SolveReport]:
        """The solution ``(n, 3)`` and report of a :meth:`_relax` ``result`` begun at ``t0``
        (``extra``: further :class:`SolveReport` fields, e.g. ``work``, ``levels``)."""
        rep = SolveReport(method, nodes=self.n, sweeps=result.iterations, residual=result.residual,
                          seconds=time.perf_counter() - t0, converged=result.converged, history=result.history,
                          status=result.status, error_estimate=result.error_estimate, **extra)
        return result.x.reshape(3, self.n).T.copy(), rep

    def release(self) -> None:
        """Free every GPU object this solver created."""
        gl.make_current(self.ctx)
        self._gpu.release()

    def __enter__(self: _S) -> _S:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


# ---- the solver -----------------------------------------------------------------------------
class GlslSparse(GatherSolver):
    """Damped Jacobi relaxation of ``A_c x_c = b_c`` (c = R, G, B) in one fragment shader
    (module docstring: packing, fetch count, the omega rule).

    GPU objects (textures, ping-pong pair, program, buffer, vertex array) belong to this
    object; call :meth:`release` (or use it as a context manager).

    Parameters
    ----------
    matrices
        One ``n x n`` sparse matrix (all channels) or three (R, G, B) with the same stored
        pattern; real, finite, positive diagonal (symmetric positive definite for the
        convergence guarantee; symmetric required for ``omega="auto"``).
    b
        ``(n, 3)`` right-hand side (``(n,)``: the same for all channels).
    ctx
        A moderngl context; default :func:`glsldiff.gl.get_context`.
    precision
        ``"fp32"`` (textures and arithmetic); nothing else.
    omega
        Damping in (0, 2), or ``"auto"`` (``min(1, 1.9 / lambda_max(D^-1 A))``).

    Attributes
    ----------
    n, slots
        Unknowns per channel; ``K``, the texture array's layers (most off-diagonals of a row).
    size
        ``(W, H)`` of the textures.
    omega
        The damping used.
    lambda_max
        The estimate of ``lambda_max(D^-1 A)`` (largest over the channels) behind
        ``omega="auto"``; ``None`` for a given omega.
    system
        The CPU :class:`~glsldiff.oracle.assembly.ChannelSystem` (block diagonal over channels,
        channel-major, kept as the channel matrices) whose residual the solve checks.
    """

    method = "glsl-gather"

    def __init__(self, matrices: Matrices, b: ArrayLike, ctx: moderngl.Context | None = None,
                 precision: str = "fp32", omega: float | str = "auto") -> None:
        if precision not in PRECISIONS:
            raise InputError(f"precision={precision!r}: GlslSparse supports only {PRECISIONS}")
        mats = channel_matrices(matrices)
        n = mats[0].shape[0]
        bb = node_rhs(b, n)
        w = parse_omega(omega)
        if w is None:
            check_symmetric(mats, "omega='auto' needs symmetric matrices (real eigenvalues of D^-1 A)",
                            "give omega as a number")
            self.lambda_max: float | None = max(jacobi_lambda_max(M) for M in distinct(mats))
            self.omega = auto_omega(self.lambda_max)
        else:
            self.lambda_max, self.omega = None, w
        self.precision, self.n = precision, n
        self.ctx = ctx if ctx is not None else gl.get_context()
        gl.make_current(self.ctx)
        self.size = texture_width(n, int(self.ctx.info["GL_MAX_TEXTURE_SIZE"]))
        diag = np.stack([M.diagonal() for M in mats], axis=1)
        self.system = ChannelSystem(mats, b=bb.T.reshape(-1), diag=diag.T.reshape(-1), active=np.arange(n))
        self._gpu = gl.Resources()
        try:
            self._coef, self._row_slots = upload_packed(self.ctx, mats, self.size, self._gpu, diagonal=False)
            self.slots = self._coef.slots
            self.fetches = 3 + 2 * self._row_slots.astype(np.float64) + (self._row_slots < self.slots)
            self._diag = self._gpu.add(gl.float_texture(self.ctx, self.size, pack_nodes(diag, self.size, pad=1.0)))
            self._b = self._gpu.add(gl.float_texture(self.ctx, self.size, pack_nodes(bb, self.size)))
            self.state = self._gpu.add(gl.PingPong.create(self.ctx, self.size, "fp32"))
            self._pass = GatherProgram(self.ctx, self._gpu)
        except Exception:
            self._gpu.release()
            raise
        self.sweeps_run = 0        # sweeps since creation
        self.sweep_seconds = 0.0   # wall time inside sweep(), GPU finished

    # ---- state ------------------------------------------------------------------------------
    @property
    def updated_nodes(self) -> int:
        """Nodes each sweep updates (all unknowns)."""
        return self.n

    @property
    def mean_fetches(self) -> float:
        """Texel fetches per node and sweep, averaged over the nodes (module docstring)."""
        return float(self.fetches.mean())

    @property
    def _rhs(self) -> moderngl.Texture:
        return self._b

    @property
    def _fine_size(self) -> tuple[int, int]:
        return self.size

    # ---- sweeps -----------------------------------------------------------------------------
    def sweep(self, n: int = 1) -> None:
        """Run ``n`` damped Jacobi sweeps (one full-screen quad each)."""
        gl.make_current(self.ctx)
        t0 = time.perf_counter()
        with gl.keep_framebuffer(self.ctx):
            for _ in range(n):
                self._pass.draw(JACOBI, self.state.dst, self.size, self._coef, self.state.src, self.size,
                                diag=self._diag, b=self._b, omega=self.omega)
                self.state.swap()
            self.sweeps_run += n
            self.ctx.finish()  # sweeps are timed: wait for the GPU
        self.sweep_seconds += time.perf_counter() - t0

    def solve(self, tol: float = RELAX_TOL, maxiter: int = MAXITER, x0: Start = None,
              callback: Callback | None = None, residuals: list[float] | None = None, *,
              check_every: int = 50) -> tuple[NDArray[np.float64], SolveReport]:
        """Relax until the Jacobi-scaled residual is <= ``tol`` or ``maxiter`` sweeps ran
        (:func:`glsldiff.oracle.solvers.relax`).

        ``x0``: ``(n, 3)`` initial iterate, ``None`` (zero) or :data:`CURRENT` (continue from
        the buffers); ``callback(x)`` after each check with the channel-major unknown vector;
        ``residuals`` gets the residual history. Returns ``x`` ``(n, 3)`` and the report
        (``method`` ``"glsl-gather-fp32(omega=...)"``, ``work`` = sweeps times ``n``).

        Raises
        ------
        SolverError
            The iteration diverged (``omega lambda_max(D^-1 A) >= 2``, or not positive definite).
        """
        t0 = time.perf_counter()
        lam = "" if self.lambda_max is None else f" (estimate {self.lambda_max:.4g})"
        result = self._relax(self.sweep, x0, tol=tol, maxiter=maxiter, check_every=check_every, callback=callback,
                             residuals=residuals, name=f"GLSL gather Jacobi (omega={self.omega:.4g})",
                             hint=lambda: ("damped Jacobi needs omega * lambda_max(D^-1 A) < 2 and A positive "
                                           f"definite; omega = {self.omega:.4g}{lam}; try omega='auto'"))
        return self._finish(f"{self.method}-{self.precision}(omega={self.omega:.4g})", result, t0,
                            work=result.iterations * self.n)


def distinct(mats: list[sp.csr_matrix]) -> list[sp.csr_matrix]:
    """The channel matrices, each distinct one once (one matrix given for all channels)."""
    out: list[sp.csr_matrix] = []
    for M in mats:
        if not any(np.array_equal(M.data, o.data) for o in out):
            out.append(M)
    return out


def sweep_rate(solver: object, sweeps: int = 50, repeats: int = 3) -> float:
    """Node updates per second of ``solver``'s sweeps on its context: the best of ``repeats``
    runs of ``sweeps`` sweeps (GPU finished, no read-backs) after one warm-up sweep. Works
    for any solver with ``sweep(n)``, ``updated_nodes``, ``unknown()`` and ``state`` (a
    :class:`glsldiff.gl.PingPong`): :class:`GlslSparse` and
    :class:`glsldiff.solve.jacobi.GlslDiffusion`. The iterate is restored afterwards."""
    if sweeps < 1 or repeats < 1:
        raise InputError(f"sweeps={sweeps}, repeats={repeats}: both must be >= 1")
    saved = solver.state.read()  # type: ignore[attr-defined]
    try:
        solver.sweep(1)  # type: ignore[attr-defined]
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            solver.sweep(sweeps)  # type: ignore[attr-defined]
            best = min(best, time.perf_counter() - t0)
    finally:
        solver.state.write(saved)  # type: ignore[attr-defined]
    return sweeps * int(solver.updated_nodes) / best  # type: ignore[attr-defined]
