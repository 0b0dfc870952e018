"""Tests for glsldiff.solve.gather (GlslSparse: damped Jacobi of a general sparse system with RGB
channels in one fragment shader, ELLPACK slots in a texture array).

References: a numpy damped-Jacobi sweep written here (the operator), scipy's sparse LU solve
per channel (converged solves), a dense eigenvalue computation (the omega="auto" estimate).
Systems: random SPD matrices with one pattern and three different value sets, a 3-D 7-point
Laplacian + mass with a Robin-like boundary diagonal, the P1 system of
glsldiff.oracle.fem.assemble_p1 on a small pillowed sphere grid (whose D^-1 A has
lambda_max > 2: plain Jacobi diverges there), and a hand-made SPD matrix of positively coupled
4-cliques (lambda_max(D^-1 A) ~ 2.4).
"""
from __future__ import annotations

import moderngl
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from glsldiff import gl
from glsldiff.core.errors import InputError, SolverError
from glsldiff.oracle.amg import jacobi_lambda_max
from glsldiff.oracle.assembly import ChannelSystem, LinearSystem, channel_values
from glsldiff.solve.gather import (APPLY, GatherProgram, GlslSparse, channel_matrices, pack_ell, pack_nodes,
                                   sweep_rate, texture_width, upload_packed, write_band)
from glsldiff.system.report import CURRENT

from gather_systems import lit_laplacians, rel, spsolve3   # tests/gather_systems.py


# ---- systems --------------------------------------------------------------------------------
def random_spd(n: int, seed: int, density: float = 0.01) -> list[sp.csr_matrix]:
    """Three SPD matrices with one pattern (symmetric, strictly diagonally dominant), mixed-sign
    off-diagonals, different values per channel, rows of different lengths; one stored
    off-diagonal pair is zero in all channels (no slot) and one is zero in channel 1 only."""
    rng = np.random.default_rng(seed)
    P = sp.random(n, n, density=density, random_state=seed, format="coo")
    P = sp.coo_matrix((np.ones(P.nnz), (P.row, P.col)), shape=(n, n))
    P = ((P + P.T) > 0).astype(np.float64).tocoo()
    off = P.row != P.col
    r, c = P.row[off], P.col[off]
    up = r < c
    r, c = r[up], c[up]
    mats = []
    for ch in range(3):
        v = rng.uniform(-1.0, 0.6, r.size) * (1.0 + 0.3 * ch)
        v[0] = 0.0              # zero in every channel
        if ch == 1:
            v[1] = 0.0          # zero in one channel only
        d = np.bincount(np.r_[r, c], np.abs(np.r_[v, v]), minlength=n) + rng.uniform(0.2, 1.0, n)
        idx = np.arange(n)
        M = sp.csr_matrix((np.r_[v, v, d], (np.r_[r, c, idx], np.r_[c, r, idx])), shape=(n, n))
        M.sort_indices()
        mats.append(M)
    for M in mats[1:]:      # same stored pattern (explicit zeros kept)
        assert np.array_equal(M.indptr, mats[0].indptr) and np.array_equal(M.indices, mats[0].indices)
    return mats


def clique_spd(blocks: int, seed: int) -> list[sp.csr_matrix]:
    """SPD matrices of 4-cliques with positive couplings c (eigenvalues of D^-1 A near 1 + 3c
    and 1 - c), chained by weak negative links; c = 0.42 .. 0.5 per channel, random diagonal
    scaling (which leaves D^-1 A's spectrum unchanged)."""
    n = 4 * blocks
    mats = []
    for ch, c in enumerate((0.45, 0.5, 0.42)):
        S = sp.kron(sp.identity(blocks), (1 - c) * np.eye(4) + c * np.ones((4, 4)))
        a = np.arange(blocks - 1) * 4 + 3
        link = sp.coo_matrix((np.full(2 * a.size, -0.1), (np.r_[a, a + 1], np.r_[a + 1, a])), shape=(n, n))
        S = S + link + sp.diags(-np.asarray(link.sum(axis=1)).ravel())
        E = sp.diags(np.exp(np.random.default_rng(seed + ch).uniform(-1, 1, n)))
        mats.append((E @ S @ E).tocsr())
    return mats


def reference_lambda_max(M: sp.csr_matrix) -> float:
    """Largest eigenvalue of D^-1 M (of the similar symmetric D^-1/2 M D^-1/2): dense up to 600
    unknowns, else ARPACK to 1e-10 with a larger Krylov space than the solver's."""
    s = sp.diags(M.diagonal() ** -0.5)
    S = (s @ M @ s).tocsr()
    if S.shape[0] <= 600:
        return float(np.linalg.eigvalsh(S.toarray()).max())
    return float(spla.eigsh(S, k=1, which="LA", tol=1e-10, ncv=60, return_eigenvectors=False)[0])


# ---- 1. the operator ------------------------------------------------------------------------
def test_one_sweep_equals_numpy_damped_jacobi(ctx):
    """One GLSL sweep from a random iterate = x + omega D^-1 (b - A x) in float64 per channel
    (n = 777: a padded last texture row; rows of 0 .. K off-diagonals; a slot dropped)."""
    n, omega = 777, 0.7
    mats = random_spd(n, seed=1)
    rng = np.random.default_rng(2)
    b = rng.uniform(-1, 1, (n, 3))
    x0 = rng.uniform(-1, 1, (n, 3)).astype(np.float32).astype(np.float64)
    with GlslSparse(mats, b, ctx=ctx, omega=omega) as s:
        nz = sum(abs(M) for M in mats) - sp.diags(sum(M.diagonal() for M in mats))
        nz.eliminate_zeros()        # off-diagonals non-zero in some channel: the slots
        k = np.diff(nz.indptr)
        assert s.size[0] * s.size[1] > n and s.slots == k.max()
        assert s.mean_fetches == pytest.approx(np.mean(3 + 2 * k + (k < k.max())))
        s.set_initial(x0)
        s.sweep(1)
        x1 = s.unknown()
    want = np.stack([x0[:, c] + omega * (b[:, c] - M @ x0[:, c]) / M.diagonal() for c, M in enumerate(mats)], axis=1)
    assert rel(x1, want) < 1e-6
    assert rel(x1 - x0, want - x0) < 3e-6     # the increment itself, per channel
    for c in range(3):
        assert rel(x1[:, c] - x0[:, c], want[:, c] - x0[:, c]) < 3e-6, c


def test_pack_ell_rectangular_and_union_pattern():
    """The shared packing: a rectangular matrix with every entry in a slot, channels with
    different stored patterns (the union is packed, an entry zero in all channels gets no
    slot); unpacking the layers gives the matrices back (float32), rows in node order."""
    A = sp.random(50, 30, density=0.1, random_state=3, format="csr")
    B = A.tolil()
    B[3, 7] = 2.0              # only in channel 1
    B[10, :] = 0.0             # a row empty in channel 1
    B = B.tocsr()
    B.eliminate_zeros()
    C = (3.0 * A).tolil()
    C[3, 7] = 0.0
    C = C.tocsr()              # stores an explicit zero at (3, 7)
    pack = pack_ell([A, B, C], (8, 7), diagonal=True)
    counts = np.diff((abs(A) + abs(B) + abs(C)).tocsr().indptr)
    assert pack.slots == counts.max() and np.array_equal(pack.row_slots, counts)
    coef = pack.coef.reshape(pack.coef.shape[0], -1, 4)
    assert coef.shape[1] == 56 and (coef[:, 50:, 3] == -1).all()      # padding rows: no slots
    out = np.zeros((3, 50, 30))
    for k, i in zip(*np.nonzero(coef[..., 3] >= 0)):
        out[:, i, int(coef[k, i, 3])] += coef[k, i, :3]
    for c, M in enumerate((A, B, C)):
        assert np.allclose(out[c], M.toarray(), rtol=1e-7, atol=0)
    assert pack_nodes(np.ones((50, 3)), (8, 7), pad=2.0)[6, 7, 0] == 2.0


def numpy_pack_ell(mats, size, *, diagonal, keep_zeros=False, row_offset=0, slots=None):
    """The numpy packing the compiled loops replaced: ``(coef, K, row_slots)``."""
    W, H = size
    mats = [sp.csr_matrix(M, dtype=np.float64) for M in mats]
    for M in mats:
        M.sum_duplicates()
        M.sort_indices()
    n_rows, n_cols = mats[0].shape
    keys = [np.repeat(np.arange(n_rows, dtype=np.int64), np.diff(M.indptr)) * n_cols + M.indices for M in mats]
    union = np.unique(np.concatenate(keys))
    vals = np.zeros((union.size, 3))
    for c, (k, M) in enumerate(zip(keys, mats)):
        vals[np.searchsorted(union, k), c] = M.data
    rows, cols = union // n_cols, union % n_cols
    keep = np.ones(len(rows), dtype=bool) if keep_zeros else np.any(vals != 0.0, axis=1)
    if not diagonal:
        keep &= cols != rows + row_offset
    rows, cols, vals = rows[keep], cols[keep], vals[keep]
    counts = np.bincount(rows, minlength=n_rows)
    K = int(counts.max()) if counts.size else 0
    K = K if slots is None else slots
    slot = np.arange(rows.size) - np.concatenate([[0], np.cumsum(counts)[:-1]])[rows]
    coef = np.zeros((max(K, 1), H * W, 4), dtype=np.float32)
    coef[..., 3] = -1.0
    coef[slot, rows, :3] = vals
    coef[slot, rows, 3] = cols
    return coef.reshape(max(K, 1), H, W, 4), K, counts


def pack_cases() -> list[tuple[list[sp.csr_matrix], tuple[int, int], dict]]:
    """``(mats, size, pack_ell keywords)``: a system matrix with stored zeros (kept or not,
    diagonal dropped), a rectangular one, channels on different patterns (the union), a band of
    rows (``row_offset``, ``slots``) and an all-diagonal one (no slots)."""
    rng = np.random.default_rng(7)
    A = sp.random(300, 300, density=0.03, random_state=1, format="csr")
    A = (A + A.T + sp.eye(300)).tocsr()
    A.data[::7] = 0.0                                              # stored zeros
    three = [A, A.multiply(2.0).tocsr(), A.multiply(rng.uniform(0.5, 1.5, A.shape)).tocsr()]
    three[2].data[::5] = 0.0
    R = sp.random(60, 300, density=0.05, random_state=2, format="csr")
    B = sp.random(300, 300, density=0.02, random_state=3, format="csr")
    return [(three, (32, 10), {"diagonal": False}), (three, (32, 10), {"diagonal": False, "keep_zeros": True}),
            (three, (16, 19), {"diagonal": True}), ([R, 2 * R, R], (8, 8), {"diagonal": True}),
            ([A, B, 3 * A], (32, 10), {"diagonal": False}),
            ([M[40:90] for M in three], (32, 2), {"diagonal": False, "keep_zeros": True, "row_offset": 40,
                                                  "slots": 40}),
            ([sp.diags(rng.uniform(1, 2, 300)).tocsr()] * 3, (32, 10), {"diagonal": False})]


def test_pack_ell_equals_numpy():
    """The compiled packing (:func:`pack_ell`'s loops) equals the numpy scatter it replaced, bit
    for bit, on every :func:`pack_cases` case."""
    for mats, size, kw in pack_cases():
        got, (coef, K, counts) = pack_ell(mats, size, **kw), numpy_pack_ell(mats, size, **kw)
        assert got.slots == K and np.array_equal(got.row_slots, counts), kw
        assert got.coef.dtype == np.float32 and np.array_equal(got.coef, coef), kw


def test_upload_packed_equals_pack_ell(ctx):
    """upload_packed (the slots packed and written a band of texel rows at a time, never the
    whole pack) gives the texture of pack_ell, bit for bit, and its slots per row: bands of one
    texel row, of three, and one band for all."""
    res = gl.Resources()
    try:
        for mats, size, kw in pack_cases():
            if "row_offset" in kw:
                continue                    # a band re-packed in place: pack_ell alone
            want = pack_ell(mats, size, **kw)
            row_bytes = want.coef.shape[0] * size[0] * 16
            for band in (1, 3 * row_bytes, 1 << 30):
                m, rows = upload_packed(ctx, mats, size, res, band_bytes=band, **kw)
                got = np.frombuffer(m.texture.read(alignment=1), dtype=np.float32).reshape(want.coef.shape)
                assert m.slots == want.slots and np.array_equal(rows, want.row_slots), (kw, band)
                assert np.array_equal(got, want.coef), (kw, band)
    finally:
        res.release()


def test_channel_matrices_compact_form():
    """channel_matrices gives the three channels one pattern and one (3, nnz) values array:
    separate matrices (or one for all channels) are copied into that form, matrices already in
    it (a P1 system's) come back as they are, not copied. The ChannelSystem of them computes the
    Jacobi step of the block-diagonal system bit for bit, and its ``A``, made on demand, views
    their values."""
    mats = random_spd(60, seed=4, density=0.08)
    out = channel_matrices(mats)
    values = channel_values(out)
    assert values is not None and values.shape == (3, mats[0].nnz)
    assert not any(np.shares_memory(values, M.data) for M in mats)
    assert all(abs(M - O).max() == 0.0 for M, O in zip(mats, out))
    again = channel_matrices(out)
    assert all(a is o for a, o in zip(again, out))
    assert channel_values(channel_matrices(mats[0])) is not None
    assert channel_values(mats) is None
    rng = np.random.default_rng(3)
    b, x = rng.uniform(0, 1, 180), rng.uniform(-1, 1, 180)
    diag = np.concatenate([M.diagonal() for M in out])
    s = ChannelSystem(out, b, diag, np.arange(60))
    ref = LinearSystem(sp.block_diag(out, format="csr"), b, diag, np.arange(60))
    assert np.array_equal(s.jacobi_step(x), ref.jacobi_step(x)) and s.residual(x) == ref.residual(x)
    assert abs(s.A - ref.A).max() == 0.0 and np.shares_memory(s.A.data, values)
    assert s.block(1)[0] is out[1] and np.array_equal(s.block(1)[1], b[60:120])
    s.set_blocks(mats)
    assert s.A.nnz == ref.A.nnz and not np.shares_memory(s.A.data, values)


# ---- 2. converged solves --------------------------------------------------------------------
def test_converged_laplacian_equals_spsolve(ctx):
    """7-point Laplacian + mass + Robin diagonal (12^3 nodes, K = 6), kappa per channel:
    converged GLSL = sparse LU to 1e-4. lambda_max(D^-1 A) = 1.95 < 2 (plain Jacobi would
    converge; auto damps it to 1.9 / 1.95)."""
    mats, b = lit_laplacians(12)
    with GlslSparse(mats, b, ctx=ctx) as s:
        lam = max(reference_lambda_max(M) for M in mats)
        assert s.slots == 6 and 1.9 < lam < 2.0 and s.lambda_max == pytest.approx(lam, rel=1e-3)
        assert s.omega == pytest.approx(1.9 / s.lambda_max)
        x, rep = s.solve(tol=1e-6)
    assert rep.status in ("converged", "stalled") and rep.residual < 2e-6, rep.summary()
    assert rep.method == f"glsl-gather-fp32(omega={s.omega:.4g})"
    assert rep.nodes == 12**3 and rep.work == rep.sweeps * 12**3
    assert rel(x, spsolve3(mats, b)) < 1e-4


def test_converged_p1_equals_spsolve(ctx, fem_system):
    """P1 system on the small sphere grid (positive off-diagonals on distorted tetrahedra;
    lambda_max(D^-1 A) measured 2.0-2.2, so omega auto < 1): the converged GLSL solve = sparse LU to
    1e-4 in every channel."""
    mats, b = fem_system
    with GlslSparse(mats, b, ctx=ctx) as s:
        lam = max(reference_lambda_max(M) for M in mats)
        assert s.lambda_max == pytest.approx(lam, rel=1e-3) and s.omega == pytest.approx(min(1.0, 1.9 / lam), rel=1e-3)
        assert 6 <= s.slots <= 40
        x, rep = s.solve(tol=1e-6, check_every=25)
    assert rep.status in ("converged", "stalled") and rep.residual < 2e-6, rep.summary()
    ref = spsolve3(mats, b)
    for c in range(3):
        assert rel(x[:, c], ref[:, c]) < 1e-4, c


# ---- 3. warm starts -------------------------------------------------------------------------
def test_warm_starts_and_set_b(ctx, fem_system):
    """x0 = the converged answer: 0 sweeps; CURRENT continues where the last solve stopped;
    set_b(2 b) doubles the answer."""
    mats, b = fem_system
    with GlslSparse(mats, b, ctx=ctx) as s:
        x, rep = s.solve(tol=1e-5, check_every=10)
        assert rep.converged
        x2, rep2 = s.solve(tol=1e-5, x0=x)
        assert rep2.sweeps == 0 and rep2.converged and np.array_equal(x2, x)

        _, cold = s.solve(tol=1e-5, check_every=10)
        _, part = s.solve(tol=1e-3, check_every=10)
        _, cont = s.solve(tol=1e-5, x0=CURRENT, check_every=10)
        assert cont.history[0] == (0, pytest.approx(part.residual, rel=1e-6))
        assert cont.converged and abs(part.sweeps + cont.sweeps - cold.sweeps) <= 10

        s.set_b(2.0 * b)
        x3, rep3 = s.solve(tol=1e-5, x0=CURRENT, check_every=10)
        assert rep3.history[0][1] > 0.1       # the old answer is far from the new one
        assert rel(x3, 2.0 * x) < 2e-4


# ---- 4. damping -----------------------------------------------------------------------------
def test_auto_omega_converges_where_plain_jacobi_diverges(ctx):
    """lambda_max(D^-1 A) ~ 2.4 (4-cliques with positive couplings): omega = 1 raises the shared
    loop's SolverError; "auto" estimates lambda_max (Lanczos: within 1e-3 of the dense value; n = 480)
    and converges to the sparse LU answer."""
    mats = clique_spd(120, seed=7)
    n = mats[0].shape[0]
    b = np.random.default_rng(8).uniform(0, 1, (n, 3))
    lam = [reference_lambda_max(M) for M in mats]
    assert min(lam) > 2.0
    with GlslSparse(mats, b, ctx=ctx, omega=1.0) as s:
        with pytest.raises(SolverError, match="diverged.*omega = 1"):
            s.solve(tol=1e-6, check_every=10)
    with GlslSparse(mats, b, ctx=ctx, omega="auto") as s:
        assert s.lambda_max == pytest.approx(max(lam), rel=1e-3)
        assert s.omega == pytest.approx(1.9 / max(lam), rel=1e-3)
        assert f"(omega={s.omega:.4g})" in s.solve(tol=1e-6, maxiter=0)[1].method
        x, rep = s.solve(tol=1e-6, check_every=10)
    assert rep.status in ("converged", "stalled") and rep.residual < 2e-6
    assert rel(x, spsolve3(mats, b)) < 1e-4
    small = mats[1][:40, :40]     # the dense branch of the estimate
    assert jacobi_lambda_max(small) == pytest.approx(reference_lambda_max(small))


# ---- 5. bad input ---------------------------------------------------------------------------
def test_bad_input(ctx):
    """One InputError per malformed input, before any GPU object is made."""
    mats = random_spd(60, seed=4, density=0.08)
    b = np.ones((60, 3))

    other = mats[1].tolil()
    i, j = next((i, j) for i in range(60) for j in range(60) if i != j and other[i, j] == 0)
    other[i, j] = other[j, i] = 1e-3
    with pytest.raises(InputError, match=f"share one sparsity pattern.*channel 1 .* row {min(i, j)}"):
        GlslSparse([mats[0], other.tocsr(), mats[2]], b, ctx=ctx)

    with pytest.raises(InputError, match=r"shape \(60, 59\).*square"):
        GlslSparse(mats[0][:, :59], b, ctx=ctx)

    nan = mats[2].copy()
    nan.data[5] = np.nan
    with pytest.raises(InputError, match="channel 2 has 1 non-finite"):
        GlslSparse([mats[0], mats[1], nan], b, ctx=ctx)

    for value, word in ((0.0, "a_ii = 0"), (-2.0, "a_ii = -2")):
        bad = mats[0].tolil()
        bad[7, 7] = value
        with pytest.raises(InputError, match=f"channel 0 has 1 zero or negative diagonal.*row 7, {word}"):
            GlslSparse(bad.tocsr(), b, ctx=ctx)

    with pytest.raises(InputError, match="precision='fp16'.*only"):
        GlslSparse(mats, b, ctx=ctx, precision="fp16")
    with pytest.raises(InputError, match=r"omega=2.5 must be in \(0, 2\)"):
        GlslSparse(mats, b, ctx=ctx, omega=2.5)
    with pytest.raises(InputError, match=r"b has shape \(59, 3\)"):
        GlslSparse(mats, b[:59], ctx=ctx)
    with pytest.raises(InputError, match="b has 1 non-finite"):
        GlslSparse(mats, np.where(np.arange(180).reshape(60, 3) == 4, np.inf, b), ctx=ctx)
    asym = mats[0].tolil()
    asym[i, j] = -0.5 if asym[i, j] == 0 else asym[i, j] * 1.5
    with pytest.raises(InputError, match="omega='auto' needs symmetric"):
        GlslSparse(asym.tocsr(), b, ctx=ctx)


# ---- lifetime and throughput ----------------------------------------------------------------
def test_release_and_sweep_rate(ctx):
    """sweep_rate counts node updates per second and leaves the iterate as it was; release
    frees the GPU objects."""
    mats = random_spd(300, seed=9)
    with GlslSparse(mats, np.ones((300, 3)), ctx=ctx) as s:
        s.set_initial(np.full((300, 3), 0.25))
        rate = sweep_rate(s, sweeps=5, repeats=2)
        assert rate > 0 and np.array_equal(s.unknown(), np.full((300, 3), 0.25))
        assert 3 <= s.mean_fetches <= 3 + 2 * s.slots + 1
        tex = s.state.textures[0]
    assert isinstance(tex.mglo, moderngl.InvalidObject)


# ---- spilled rows ---------------------------------------------------------------------------
def _few_long_rows(n: int, seed: int) -> list[sp.csr_matrix]:
    """Three matrices on one pattern whose rows have 3-4 entries but one in 200 has 12-20: the
    layout where spilling the long rows saves texels (under SPILL_SHARE of them)."""
    rng = np.random.default_rng(seed)
    counts = np.where(rng.random(n) < 1 / 200, rng.integers(12, 21, n), rng.integers(3, 5, n))
    rows = np.repeat(np.arange(n), counts)
    cols = rng.integers(0, n, rows.size)
    pat = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    pat.sum_duplicates()
    return [sp.csr_matrix((rng.uniform(-1, 1, pat.nnz), pat.indices, pat.indptr), shape=(n, n)) for _ in range(3)]


def test_spilled_gather_is_the_same_product(ctx):
    """A gather whose long rows spill (upload_packed(spill=True)) gives the bits of the one that
    pads every row to the longest, in every mode's sum (APPLY here), and a band re-packed in place
    (write_band, an update) those of a new upload of the changed matrices."""
    n = 8000
    mats = _few_long_rows(n, 3)
    size = texture_width(n, int(ctx.info["GL_MAX_TEXTURE_SIZE"]))
    res = gl.Resources()
    try:
        prog = GatherProgram(ctx, res)
        v = np.random.default_rng(4).uniform(-1, 1, (n, 3))
        src = res.add(gl.float_texture(ctx, size, pack_nodes(v, size)))
        out = res.add(gl.float_texture(ctx, size))
        fbo = res.add(ctx.framebuffer(color_attachments=[out]))

        def apply(m) -> np.ndarray:
            with gl.keep_framebuffer(ctx):
                prog.draw(APPLY, fbo, size, m, src, size)
            return np.frombuffer(out.read(), dtype=np.float32).reshape(-1, 4)[:n, :3].copy()

        padded, _ = upload_packed(ctx, mats, size, res, diagonal=True)
        spilled, _ = upload_packed(ctx, mats, size, res, diagonal=True, spill=True, band_bytes=1 << 14)
        assert spilled.spill is not None and spilled.layers < padded.layers == spilled.slots
        got = apply(spilled)
        assert np.array_equal(got, apply(padded))
        assert rel(got, np.stack([M @ v[:, c] for c, M in enumerate(mats)], axis=1)) < 1e-6
        W = size[0]
        changed = [M.copy() for M in mats]
        for M in changed:
            M.data *= 1.5
        y0, y1 = 20, 40                                      # texel rows 20..39 re-packed
        write_band(spilled, [M[y0 * W:y1 * W] for M in changed], y0, (W, y1 - y0), diagonal=True)
        keep = [sp.vstack([M[:y0 * W], C[y0 * W:y1 * W], M[y1 * W:]]).tocsr() for M, C in zip(mats, changed)]
        fresh, _ = upload_packed(ctx, keep, size, res, diagonal=True, spill=True)
        assert np.array_equal(apply(spilled), apply(fresh))
    finally:
        res.release()
