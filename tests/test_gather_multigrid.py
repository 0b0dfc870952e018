"""Tests for glsldiff.solve.gather_multigrid (GlslSparseMultigrid: algebraic-multigrid V-cycles,
plain or as the preconditioner of conjugate gradients, every pass a gather fragment shader).

References: a numpy V-cycle written here (Galerkin operators recomputed from the solver's
prolongations, its per-level omegas, the coarsest level solved by LAPACK), a numpy
preconditioned CG with that V-cycle, scipy's sparse LU (converged solves), numpy damped
Jacobi (the single-level sweep counts). Systems: the P1 system of
glsldiff.oracle.fem.assemble_p1 on pillowed sphere grids (kappa, mu per channel), 3-D 7-point
Laplacians + mass + Robin diagonal (kappa per channel), with pyamg's hierarchy or with a
piecewise-constant aggregation given as ``prolongations``.
"""
from __future__ import annotations

import moderngl
import numpy as np
import pytest
import scipy.sparse as sp

from glsldiff.core.errors import InputError
from glsldiff.oracle.amg import jacobi_lambda_max
from glsldiff.solve.gather import GlslSparse, auto_omega, pack_ell
from glsldiff.solve.gather_multigrid import GlslSparseMultigrid
from glsldiff.system.report import CURRENT

from gather_systems import lit_laplacians, p1_system, rel, spsolve3   # tests/gather_systems.py

# ---- systems --------------------------------------------------------------------------------
def aggregation(m: int) -> sp.csr_matrix:
    """Piecewise-constant prolongation of an ``m^3`` grid from its ``(m/2)^3`` 2x2x2 blocks."""
    idx = np.indices((m, m, m)).reshape(3, -1) // 2
    c = m // 2
    agg = (idx[0] * c + idx[1]) * c + idx[2]
    return sp.csr_matrix((np.ones(m**3), (np.arange(m**3), agg)), shape=(m**3, c**3))


# ---- the numpy reference --------------------------------------------------------------------
def galerkin_levels(A: sp.csr_matrix, Ps: list[sp.csr_matrix]) -> list[sp.csr_matrix]:
    out = [A]
    for P in Ps:
        out.append((P.T @ out[-1] @ P).tocsr())
    return out


def numpy_vcycle(As, Ps, omegas, pre, post, b, x=None, l=0):
    """One V-cycle in float64 (``x = None``: from zero; the coarsest level solved exactly)."""
    A = As[l]
    if l == len(As) - 1:
        return np.linalg.solve(A.toarray(), b)
    d = A.diagonal()
    x = np.zeros_like(b) if x is None else x.copy()
    for _ in range(pre):
        x = x + omegas[l] * (b - A @ x) / d
    xc = numpy_vcycle(As, Ps, omegas, pre, post, Ps[l].T @ (b - A @ x), None, l + 1)
    x = x + Ps[l] @ xc
    for _ in range(post):
        x = x + omegas[l] * (b - A @ x) / d
    return x


def numpy_pcg(As, Ps, omegas, nu, b, x, iterations):
    """Conjugate gradients preconditioned by one V(nu, nu)-cycle from zero, float64."""
    M = lambda r: numpy_vcycle(As, Ps, omegas, nu, nu, r)  # noqa: E731
    A = As[0]
    r = b - A @ x
    z = M(r)
    p, rho = z.copy(), r @ z
    for _ in range(iterations):
        q = A @ p
        alpha = rho / (p @ q)
        x, r = x + alpha * p, r - alpha * q
        z = M(r)
        rho, rho_old = r @ z, rho
        p = z + rho / rho_old * p
    return x


def reference(s: GlslSparseMultigrid, mats, c: int):
    """Per channel: the Galerkin operators recomputed from the solver's P, its P and omegas."""
    Ps = [lv.P for lv in s.levels[:-1]]
    return galerkin_levels(mats[c], Ps), Ps, [lv.omega for lv in s.levels[:-1]]


# ---- 1. the operator ------------------------------------------------------------------------
@pytest.mark.parametrize("case, pre, post", [("p1", 2, 2), ("p1", 3, 1), ("laplacian", 0, 3)])
def test_one_vcycle_equals_numpy(ctx, fem_system, case, pre, post):
    """One GLSL V-cycle from a random iterate = the numpy V-cycle with the same P, Galerkin
    A_c, omegas and sweeps, per channel, to 1e-6 (measured ~1e-7, fp32). P1: pyamg's
    hierarchy (3 levels: 1663, 68 and a few unknowns with max_coarse 60); Laplacian 8^3: a given 2x2x2 aggregation, 3 levels (8^3, 4^3, 2^3),
    pre = 0 (the coarse iterates are cleared, not swept from zero)."""
    if case == "p1":
        mats, b = fem_system
        kw = {"max_coarse": 60}
    else:
        mats, b = lit_laplacians(8)
        kw = {"prolongations": [aggregation(8), aggregation(4)]}
    n = mats[0].shape[0]
    x0 = np.random.default_rng(2).uniform(-1, 1, (n, 3)).astype(np.float32).astype(np.float64)
    with GlslSparseMultigrid(mats, b, ctx=ctx, pre=pre, post=post, accel=None, **kw) as s:
        assert len(s.levels) == 3 and s.levels[-1].P is None
        for c in range(3):
            As, Ps, _ = reference(s, mats, c)
            for lv, A in zip(s.levels, As):       # the solver's coarse operators are Galerkin
                assert abs(lv.A[c] - A).max() <= 1e-12 * abs(A).max()
        for lv in s.levels[:-1]:                  # the report's per-level data
            K = np.diff((lv.A[0] != 0).astype(int).indptr).max() - 1
            assert lv.slots == K and 0 < lv.omega < 1.0 / lv.lambda_max * 2
        assert s.levels[-1].slots == s.levels[-1].n
        s.set_initial(x0)
        s.cycle(1)
        x1 = s.unknown()
        want = np.stack([numpy_vcycle(*reference(s, mats, c), pre, post, b[:, c], x0[:, c]) for c in range(3)],
                        axis=1)
    for c in range(3):
        assert rel(x1[:, c], want[:, c]) < 1e-6, c
        assert rel(x1[:, c] - x0[:, c], want[:, c] - x0[:, c]) < 1e-6, c


def test_pcg_iterations_equal_numpy(ctx, fem_system):
    """Three GLSL conjugate-gradient iterations (dot products reduced on the GPU, no read-back)
    from a random iterate = numpy PCG with the numpy V-cycle, per channel, to 2e-6 (measured
    ~2e-7)."""
    mats, b = fem_system
    n = mats[0].shape[0]
    x0 = np.random.default_rng(4).uniform(-1, 1, (n, 3)).astype(np.float32).astype(np.float64)
    with GlslSparseMultigrid(mats, b, ctx=ctx, accel="cg") as s:
        s.set_initial(x0)
        s.cycle(3)
        x3 = s.unknown()
        want = np.stack([numpy_pcg(*reference(s, mats, c), 2, b[:, c], x0[:, c], 3) for c in range(3)], axis=1)
    for c in range(3):
        assert rel(x3[:, c] - x0[:, c], want[:, c] - x0[:, c]) < 2e-6, c


# ---- 2. converged solves --------------------------------------------------------------------
@pytest.mark.parametrize("accel", ["cg", None])
def test_converged_p1_equals_spsolve(ctx, fem_system, accel):
    """P1 sphere system, kappa and mu per channel: the converged solve = sparse LU to 1e-4 in
    every channel (residual at the fp32 floor, ~1e-6); the report counts cycles and names the
    levels."""
    mats, b = fem_system
    with GlslSparseMultigrid(mats, b, ctx=ctx, accel=accel) as s:
        x, rep = s.solve(tol=1e-6)
    assert rep.status in ("converged", "stalled") and rep.residual < 1e-5, rep.summary()
    kind = "PCG,V(2,2)" if accel else "V(2,2)"
    assert rep.method == f"glsl-gather-multigrid-fp32({kind},levels={len(s.levels)})" and "cycles" in rep.summary()
    assert [lv["n"] for lv in rep.levels] == [lv.n for lv in s.levels]
    assert rep.levels[0]["sweeps"] == 4 * rep.sweeps and rep.levels[-1]["sweeps"] == rep.sweeps
    assert rep.levels[0]["slots"] == s.levels[0].slots and rep.levels[0]["omega"] == s.levels[0].omega
    ref = spsolve3(mats, b)
    for c in range(3):
        assert rel(x[:, c], ref[:, c]) < 1e-4, c


def test_converged_laplacian_equals_spsolve(ctx):
    """7-point Laplacian + mass + Robin diagonal, 12^3, kappa per channel: converged = sparse
    LU to 1e-4."""
    mats, b = lit_laplacians(12)
    with GlslSparseMultigrid(mats, b, ctx=ctx) as s:
        x, rep = s.solve(tol=1e-6)
    assert rep.status in ("converged", "stalled") and rep.residual < 1e-5, rep.summary()
    assert rel(x, spsolve3(mats, b)) < 1e-4


def test_zero_channel_stays_zero(ctx):
    """A channel without a source: its residual and dot products are 0, the CG updates guard
    the 0 / 0 (scale 0), so it stays exactly 0 while the others converge."""
    mats, b = lit_laplacians(12)
    b[:, 1] = 0.0
    with GlslSparseMultigrid(mats, b, ctx=ctx) as s:
        x, rep = s.solve(tol=1e-6)
    assert rep.status in ("converged", "stalled") and rep.residual < 1e-5 and not x[:, 1].any()
    ref = spsolve3(mats, b)
    for c in (0, 2):
        assert rel(x[:, c], ref[:, c]) < 1e-4


# ---- 3. warm starts -------------------------------------------------------------------------
@pytest.mark.parametrize("accel", ["cg", None])
def test_warm_starts_and_set_b(ctx, fem_system, accel):
    """x0 = the converged answer: 0 cycles; CURRENT continues where the last solve stopped (CG
    restarts its directions: at most 2 cycles more than a cold solve); set_b(2 b) doubles the
    answer."""
    mats, b = fem_system
    with GlslSparseMultigrid(mats, b, ctx=ctx, accel=accel) as s:
        x, rep = s.solve(tol=1e-5)
        assert rep.converged
        x2, rep2 = s.solve(tol=1e-5, x0=x)
        assert rep2.sweeps == 0 and rep2.converged and np.array_equal(x2, x)

        _, cold = s.solve(tol=1e-5)
        _, part = s.solve(tol=1e-2)
        _, cont = s.solve(tol=1e-5, x0=CURRENT)
        assert cont.history[0] == (0, pytest.approx(part.residual, rel=1e-6))
        assert cont.converged and cold.sweeps <= part.sweeps + cont.sweeps <= cold.sweeps + (2 if accel else 1)

        s.set_b(2.0 * b)
        x3, rep3 = s.solve(tol=1e-5, x0=CURRENT)
        assert rep3.history[0][1] > 0.1       # the old answer is far from the new one
        assert rel(x3, 2.0 * x) < 2e-4


def test_residual_on_the_gpu_equals_the_float64_one(ctx, fem_system):
    """residual_gpu (fp32, on the GPU) is the float64 Jacobi-scaled residual of the same iterate,
    from 1 down to 1e-5, within 1 % of its value (or 2e-6 absolute: the fp32 floor), also after
    a new right-hand side (its norm is kept until then); a zero
    channel of b does not count; plain V-cycles answer nan (no reducer: check on the CPU)."""
    mats, b = fem_system
    with GlslSparseMultigrid(mats, b, ctx=ctx) as s:
        seen = []
        for k in range(12):
            gpu = s.residual_gpu()
            cpu = s.system.residual(s.unknown().T.reshape(-1))
            assert gpu == pytest.approx(cpu, rel=1e-2, abs=2e-6), k
            seen.append(cpu)
            s.cycle(1)
        assert seen[0] == pytest.approx(1.0) and seen[-1] < 1e-5
        s.set_b(3.0 * b)            # a new right-hand side: ||D^-1 b|| is measured again
        assert s.residual_gpu() == pytest.approx(s.system.residual(s.unknown().T.reshape(-1)), rel=1e-2)
        s.cycle(1)                  # and conjugate gradients' own residual follows it
        assert s.residual_gpu() == pytest.approx(s.system.residual(s.unknown().T.reshape(-1)), rel=1e-2)
    b0 = b.copy()
    b0[:, 2] = 0.0
    with GlslSparseMultigrid(mats, b0, ctx=ctx) as s:
        s.cycle(2)
        assert s.residual_gpu() == pytest.approx(s.system.residual(s.unknown().T.reshape(-1)), rel=1e-2)
    with GlslSparseMultigrid(mats, b, ctx=ctx, accel=None) as s:
        assert np.isnan(s.residual_gpu())


# ---- 4. refinement --------------------------------------------------------------------------
def jacobi_sweeps(A: sp.csr_matrix, b: np.ndarray, tol: float = 1e-4, every: int = 10) -> int:
    """Damped Jacobi sweeps (GlslSparse's auto omega) to a Jacobi-scaled residual <= tol, in
    float64, counted in steps of ``every``."""
    omega = auto_omega(jacobi_lambda_max(A))
    d = A.diagonal()
    x, ref, k = np.zeros_like(b), np.linalg.norm(b / d), 0
    while np.linalg.norm((b - A @ x) / d) > tol * ref:
        for _ in range(every):
            x += omega * (b - A @ x) / d
        k += every
    return k


def test_cycles_flat_under_refinement(ctx, fem_system, record_property):
    """Cycles to 1e-4 as the grid is refined (h halved): Laplacian 16^3 -> 32^3 (kappa 0.5, mu
    0.001: diffusion length 22 mm > the 16 mm cube, so the Laplacian dominates) and the P1
    sphere n = 3 -> 6. Multigrid (both accelerations) grows by less than 2x, single-level
    Jacobi sweeps by more than 2.5x (measured in numpy on the Laplacian; ~4x asymptotically).
    Measured: Laplacian PCG 4 -> 4, V-cycles 6 -> 6, Jacobi 360 -> 1130 sweeps; sphere PCG
    5 -> 6, V-cycles 7 -> 10."""
    counts: dict[str, list[int]] = {}
    lap = [lit_laplacians(m, kappas=((0.5, 0.001),) * 3) for m in (16, 32)]
    sph = [fem_system, p1_system(3, 6)]
    for name, systems in (("laplacian", lap), ("sphere", sph)):
        for accel in ("cg", None):
            key = f"{name}-{accel or 'v'}"
            for mats, b in systems:
                with GlslSparseMultigrid(mats, b, ctx=ctx, accel=accel) as s:
                    _, rep = s.solve(tol=1e-4)
                assert rep.converged, rep.summary()
                counts.setdefault(key, []).append(rep.sweeps)
    counts["laplacian-jacobi"] = [jacobi_sweeps(mats[0], b[:, 0]) for mats, b in lap]
    record_property("cycles", counts)
    print(counts)
    for key, (coarse, fine) in counts.items():
        if key.endswith("jacobi"):
            assert fine > 2.5 * coarse, counts
        else:
            assert fine < 2 * coarse, counts


# ---- 5. bad input ---------------------------------------------------------------------------
def test_bad_input(ctx, fem_system):
    """One InputError per malformed input, before any GPU object is made."""
    mats, b = fem_system
    n = mats[0].shape[0]
    with pytest.raises(InputError, match="pre \\+ post must be >= 1"):
        GlslSparseMultigrid(mats, b, ctx=ctx, pre=0, post=0, accel=None)
    with pytest.raises(InputError, match="accel='cg' needs a symmetric V-cycle"):
        GlslSparseMultigrid(mats, b, ctx=ctx, pre=1, post=2)
    with pytest.raises(InputError, match="accel='bicg'"):
        GlslSparseMultigrid(mats, b, ctx=ctx, accel="bicg")
    with pytest.raises(InputError, match=r"omega=2.5 must be in \(0, 2\)"):
        GlslSparseMultigrid(mats, b, ctx=ctx, omega=2.5)
    with pytest.raises(InputError, match="max_coarse=4096 must be in 1 .."):
        GlslSparseMultigrid(mats, b, ctx=ctx, max_coarse=4096)
    asym = mats[0].tolil()
    asym[0, 1] = asym[0, 1] * 1.5
    with pytest.raises(InputError, match="needs symmetric matrices"):
        GlslSparseMultigrid(asym.tocsr(), b, ctx=ctx)
    with pytest.raises(InputError, match=rf"prolongations\[0\] is \({n - 1}, 10\)"):
        GlslSparseMultigrid(mats, b, ctx=ctx, prolongations=[sp.random(n - 1, 10, density=0.1, format="csr")])
    with pytest.raises(InputError, match="coarsest level of the given prolongations has 500"):
        GlslSparseMultigrid(mats, b, ctx=ctx, prolongations=[sp.random(n, 500, density=0.1, format="csr")])
    with pytest.raises(InputError, match=r"b has shape \(5, 3\)"):
        GlslSparseMultigrid(mats, b[:5], ctx=ctx)


# ---- 6. one level, lifetime -----------------------------------------------------------------
def test_single_level_release_and_profile(ctx):
    """n <= max_coarse: one level, a cycle is the dense solve (one cycle to the fp32 floor, both
    accelerations); release frees the GPU objects; profile times each level; GlslSparse (whose
    packing the multigrid shares) still matches."""
    mats, b = lit_laplacians(5)
    ref = spsolve3(mats, b)
    for accel in ("cg", None):
        with GlslSparseMultigrid(mats, b, ctx=ctx, accel=accel) as s:
            assert len(s.levels) == 1 and s.levels[0].slots == 125
            x, rep = s.solve(tol=1e-5)
            assert rep.converged and rep.sweeps == 1 and rel(x, ref) < 1e-5
            tex = s.state.textures[0]
        assert isinstance(tex.mglo, moderngl.InvalidObject)
    mats, b = lit_laplacians(10)
    with GlslSparseMultigrid(mats, b, ctx=ctx, max_coarse=100) as s:
        s.profile = True
        _, rep = s.solve(tol=1e-4)
        assert rep.converged and all(lv["seconds"] > 0 for lv in rep.levels) and "levels" in s.describe()
    with GlslSparse(mats, b, ctx=ctx) as g:
        x, _ = g.solve(tol=1e-6)
    assert rel(x, spsolve3(mats, b)) < 1e-4


# ---- in-place updates of the finest matrix (interactive editing) ------------------------------
@pytest.fixture(scope="module")
def editable():
    """A P1 system on a fixed pattern (oracle.fem_update.P1System) of a pillowed sphere and a
    local edit of its material: (P1System, kappa2, mu2)."""
    from glsldiff.grids.tetrahedral.fem_grid import build_fem_grid
    from glsldiff.mesh import sphere_mesh
    from glsldiff.oracle.fem import tet_geometry
    from glsldiff.oracle.fem_update import P1System
    g = build_fem_grid(sphere_mesh(10.0, subdivisions=2), n=4, cube_size=5.0)
    n = len(g.positions)
    kappa, mu = np.tile([0.3, 0.2, 0.45], (n, 1)), np.tile([0.05, 0.1, 0.02], (n, 1))
    P = P1System(tet_geometry(g), g.active, 2.0, kappa, mu)
    q = np.random.default_rng(5).uniform(0.5, 1.5, (P.n, 3)) * (g.positions[P.active, 2:3] > 6.0)
    P.set_rhs(q)
    near = np.linalg.norm(g.positions - [0.0, 0.0, 8.0], axis=1) < 3.0
    k2, m2 = kappa.copy(), mu.copy()
    k2[near] *= 0.4
    m2[near] *= 3.0
    return P, k2, m2


def test_textures_are_the_level_packs_and_the_finest_is_not_copied(ctx, editable):
    """Every gather texture, packed and written level by level, matrix by matrix, a band of texel
    rows at a time, is pack_ell's pack of that level's matrices, bit for bit (the textures of the
    whole packs uploaded at once). A P1 system's matrices (one pattern, one values array) are
    the finest level and the CPU system as they are, not copied."""
    P, _, _ = editable
    mats = P.matrices()
    with GlslSparseMultigrid(mats, P.system.b.reshape(3, -1).T, ctx=ctx) as s:
        assert len(s.levels) >= 2
        assert all(A is M for A, M in zip(s.levels[0].A, mats))
        assert all(A is M for A, M in zip(s.system.blocks, mats))
        for l, (lv, g) in enumerate(zip(s.levels, s._levels)):
            diag = np.stack([A.diagonal() for A in lv.A], axis=1)
            want = {"A": (lv.A, lv.size, {"diagonal": False, "keep_zeros": l == 0})}
            if lv.coarsest:
                want["inverse"] = ([sp.csr_matrix(M) for M in lv.inverse], lv.size, {"diagonal": True})
                if l > 0:
                    del want["A"]
            else:
                want["P"] = ([lv.P] * 3, lv.size, {"diagonal": True})
                want["R"] = ([sp.csr_matrix(lv.P.T)] * 3, s.levels[l + 1].size, {"diagonal": True})
                want["first"] = ([sp.diags(lv.omega / diag[:, c]).tocsr() for c in range(3)], lv.size,
                                 {"diagonal": True})
            for name, (ms, size, kw) in want.items():
                pack, m = pack_ell(ms, size, **kw), getattr(g, name)
                assert m.slots == pack.slots and np.array_equal(_unspilled(m), pack.coef), (l, name)


def _unspilled(m) -> np.ndarray:
    """``(K, H, W, 4)``: the slots of an uploaded gather as one pack_ell pack (the spilled rows'
    rest, read from the spill texture at their link's texel, after their main slots)."""
    W, H = m.texture.size[:2]
    main = np.frombuffer(m.texture.read(alignment=1), dtype=np.float32).reshape(m.layers, H * W, 4)
    out = np.zeros((max(m.slots, 1), H * W, 4), dtype=np.float32)
    out[:, :, 3] = -1.0
    out[:m.layers] = main
    if m.spill is not None:
        rest = np.frombuffer(m.spill.read(alignment=1), dtype=np.float32).reshape(m.spill_slots, -1, 4)
        link = np.flatnonzero(main[-1, :, 3] < -1.5)
        assert np.array_equal(-2 - main[-1, link, 3].astype(np.int64), np.arange(link.size))   # ranks in row order
        out[m.layers - 1:m.layers - 1 + m.spill_slots, link] = rest[:, :link.size]
        assert m.layers < m.slots and np.all(rest[:, link.size:, 3] == -1.0)
    return out.reshape(-1, H, W, 4)


def _assert_stale_vcycle(s, P, Ps, stale, omegas, b, seed):
    """One GPU V-cycle of ``s`` from a random start equals the numpy V-cycle with ``P``'s current
    fine matrices and the ``stale`` coarse operators (2e-5); returns the start."""
    x0 = np.random.default_rng(seed).uniform(0.0, 1.0, (P.n, 3))
    s.set_initial(x0)
    s.cycle(1)
    got = s.unknown()
    for c, A in enumerate(P.matrices()):
        ref = numpy_vcycle([A] + [lv[c] for lv in stale[1:]], Ps, omegas, 2, 2, b[:, c], x0[:, c])
        assert rel(got[:, c], ref) < 2e-5
    return x0


def test_update_fine_is_the_new_fine_level_with_the_old_coarse_ones(ctx, editable):
    P, k2, m2 = editable
    kappa0, mu0 = P.kappa.copy(), P.mu.copy()
    b = P.system.b.reshape(3, -1).T
    with GlslSparseMultigrid(P.matrices(), b, ctx=ctx, accel=None) as s:
        Ps = [lv.P for lv in s.levels if lv.P is not None]
        stale = [[A.copy() for A in lv.A] for lv in s.levels]
        omegas = s.omegas
        up = P.set_material(k2, m2)
        s.update_fine(P.matrices(), up.rows)
        assert s.levels[0].omega == omegas[0]
        # the CPU system the solve checks is the new one
        assert abs(s.system.A - P.system.A).max() == 0.0
        np.testing.assert_array_equal(s.system.diag, P.system.diag)
        x0 = _assert_stale_vcycle(s, P, Ps, stale, omegas, b, seed=1)
        # Jacobi sweeps of the new matrix (painting frames)
        s.set_initial(x0)
        s.smooth(3)
        got = s.unknown()
        for c, A in enumerate(P.matrices()):
            x = x0[:, c].copy()
            for _ in range(3):
                x = x + omegas[0] * (b[:, c] - A @ x) / A.diagonal()
            assert rel(got[:, c], x) < 2e-5
    P.set_material(kappa0, mu0)


def test_update_fine_converges_to_the_edited_system(ctx, editable):
    P, k2, m2 = editable
    kappa0, mu0 = P.kappa.copy(), P.mu.copy()
    b = P.system.b.reshape(3, -1).T
    with GlslSparseMultigrid(P.matrices(), b, ctx=ctx) as s:
        _, rep0 = s.solve(tol=1e-5)
        up = P.set_material(k2, m2)
        s.update_fine(P.matrices(), up.rows)
        x, rep = s.solve(tol=1e-5, x0=CURRENT)
        assert rep.converged and rep.sweeps <= rep0.sweeps + 2
        ref = spsolve3(P.matrices(), b)
        assert rel(x, ref) < 1e-4
        with pytest.raises(InputError, match="pattern"):
            s.update_fine([sp.identity(P.n, format="csr") for _ in range(3)], up.rows)
    P.set_material(kappa0, mu0)


def test_update_fine_of_the_diagonal_alone(ctx, editable):
    """An absorption edit changes the diagonal only: the off-diagonal slots are not rewritten,
    and one V-cycle is still the new matrix's."""
    P, _, m2 = editable
    kappa0, mu0 = P.kappa.copy(), P.mu.copy()
    b = P.system.b.reshape(3, -1).T
    with GlslSparseMultigrid(P.matrices(), b, ctx=ctx, accel=None) as s:
        Ps = [lv.P for lv in s.levels if lv.P is not None]
        stale = [[A.copy() for A in lv.A] for lv in s.levels]
        up = P.set_material(kappa0, m2)
        assert up.diagonal_only and up.tetrahedra == 0
        s.update_fine(P.matrices(), up.rows, diagonal_only=True)
        _assert_stale_vcycle(s, P, Ps, stale, s.omegas, b, seed=2)
    P.set_material(kappa0, mu0)


def test_level_omegas_need_their_prolongations(ctx, editable):
    P, _, _ = editable
    b = P.system.b.reshape(3, -1).T
    with GlslSparseMultigrid(P.matrices(), b, ctx=ctx) as s:
        Ps = [lv.P for lv in s.levels if lv.P is not None]
        w = s.omegas[:-1]
        with GlslSparseMultigrid(P.matrices(), b, ctx=ctx, prolongations=Ps, level_omegas=w) as t:
            assert t.omegas[:-1] == w and t.setup_seconds["omega"] < s.setup_seconds["omega"]
            x, rep = t.solve(tol=1e-5)
            assert rep.converged
    with pytest.raises(InputError, match="level_omegas"):
        GlslSparseMultigrid(P.matrices(), b, ctx=ctx, level_omegas=w)
    with pytest.raises(InputError, match="level_omegas"):
        GlslSparseMultigrid(P.matrices(), b, ctx=ctx, prolongations=Ps, level_omegas=[2.5] * len(Ps))
