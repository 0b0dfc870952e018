"""Tests of glsldiff.grids.weights: appendix-B Laplacian weights on polygrid stencils and the fallback."""
from __future__ import annotations

import numpy as np
import pytest

import glsldiff.grids.weights as W
from glsldiff.core.errors import InputError
from glsldiff.grids.weights import (
    NEIGHBOURS,
    WeightStats,
    appendix_b_weights,
    axis_weights,
    laplacian_weights,
    local_frames,
)

BASE = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=float)


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3, 3) random proper rotations."""
    q, r = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return q


def stencil_laplacian(w: np.ndarray, c: np.ndarray, v: np.ndarray, f) -> np.ndarray:
    return (w * (f(v) - f(c)[:, None])).sum(axis=1)


def reference_weights(c: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-node loop straight from the appendix-B recipe (frame, 6x6 matrix, inverse)."""
    w = np.empty((len(c), 6))
    cond = np.empty(len(c))
    for i in range(len(c)):
        ex = v[i, 1] - v[i, 0]
        ex /= np.linalg.norm(ex)
        ey = v[i, 3] - v[i, 2]
        ey -= ey @ ex * ex
        ey /= np.linalg.norm(ey)
        ez = np.cross(ex, ey)
        if ez @ (v[i, 5] - v[i, 4]) < 0:
            ez = -ez
        d = v[i] - c[i]
        scale = np.linalg.norm(d, axis=1).mean()
        loc = d @ np.array([ex, ey, ez]).T / scale
        a = np.column_stack([loc[:, 0], loc[:, 0] ** 2 / 2, loc[:, 1], loc[:, 1] ** 2 / 2,
                             loc[:, 2], loc[:, 2] ** 2 / 2])
        inv = np.linalg.inv(a)
        w[i] = (inv[1] + inv[3] + inv[5]) / scale**2
        cond[i] = np.linalg.cond(a)
    return w, cond


def perturbed(rng: np.random.Generator, n: int, h: float, eps: float) -> tuple[np.ndarray, np.ndarray]:
    c = rng.uniform(-5, 5, (n, 3))
    v = c[:, None, :] + h * (BASE + eps * rng.standard_normal((n, 6, 3)))
    return c, v


# --------------------------------------------------------------------------- regular grid
@pytest.mark.parametrize("h", [0.37, 1.0, 2.5e-3])
def test_regular_grid_gives_one_over_h2(h: float) -> None:
    rng = np.random.default_rng(1)
    c = rng.uniform(-10, 10, (50, 3))
    v = c[:, None, :] + h * BASE
    wb, cond = appendix_b_weights(c, v)
    np.testing.assert_allclose(wb, 1 / h**2, rtol=1e-12)
    np.testing.assert_allclose(cond, 2.0, rtol=1e-12)
    np.testing.assert_allclose(axis_weights(c, v), 1 / h**2, rtol=1e-12)
    np.testing.assert_allclose(local_frames(c, v), np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-15)
    for mode in W.FALLBACKS:
        w, stats = laplacian_weights(c, v, fallback=mode)
        np.testing.assert_allclose(w, 1 / h**2, rtol=1e-12)
        assert (stats.negative, stats.ill_conditioned, stats.nonfinite, stats.fallback) == (0, 0, 0, 0)
        assert stats.blend_max == 0.0 and stats.nodes == 50


def test_matches_per_node_reference() -> None:
    rng = np.random.default_rng(2)
    c, v = perturbed(rng, 200, 0.8, 0.25)
    # nearly coplanar stencils exercise the SVD path (cond > _REFINE_COND)
    for i, tilt in enumerate((1e-2, 1e-3, 1e-4, 1e-5)):
        v[i, :4] = c[i] + 0.8 * BASE[:4]
        v[i, 4] = c[i] + [0.3, 0.2, -tilt]
        v[i, 5] = c[i] + [-0.2, 0.4, tilt]
    wb, cond = appendix_b_weights(c, v)
    wr, cr = reference_weights(c, v)
    np.testing.assert_allclose(wb, wr, rtol=1e-9, atol=1e-9 * np.abs(wr).max())
    np.testing.assert_allclose(cond, cr, rtol=1e-8)
    assert cond.max() > 1e5 and (cond > W._REFINE_COND).sum() >= 4  # both paths ran


# --------------------------------------------------------------------------- exactness
def test_exact_for_axis_aligned_nonuniform_spacing() -> None:
    rng = np.random.default_rng(3)
    n = 100
    c = rng.uniform(-3, 3, (n, 3))
    lengths = rng.uniform(0.2, 3.0, (n, 6))
    v = c[:, None, :] + BASE * lengths[..., None]
    a, b, cc = rng.uniform(-2, 2, 3)
    g = rng.uniform(-2, 2, 3)

    def f(p: np.ndarray) -> np.ndarray:
        return a * p[..., 0] ** 2 + b * p[..., 1] ** 2 + cc * p[..., 2] ** 2 + p @ g + 0.7

    wb, _ = appendix_b_weights(c, v)
    np.testing.assert_allclose(stencil_laplacian(wb, c, v, f), 2 * (a + b + cc), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(axis_weights(c, v), wb, rtol=1e-11)
    w, stats = laplacian_weights(c, v)
    assert stats.fallback == 0
    np.testing.assert_array_equal(w, wb)


def test_exact_on_rotated_axes_and_axis_weights_agree() -> None:
    """Neighbours on the axes of a random frame: exact for quadratics without mixed terms in it."""
    rng = np.random.default_rng(4)
    n = 100
    rot = random_rotations(rng, n)  # rows: the frame axes
    c = rng.uniform(-3, 3, (n, 3))
    lengths = rng.uniform(0.3, 2.0, (n, 6))
    v = c[:, None, :] + np.einsum("nj,jk,nkd->njd", lengths, BASE, rot)
    coef = rng.uniform(-2, 2, (n, 3))
    g = rng.uniform(-2, 2, (n, 3))
    local = np.einsum("nkd,njd->njk", rot, v - c[:, None, :])
    df = (coef[:, None, :] * local**2).sum(-1) + (g[:, None, :] * local).sum(-1)
    wb, _ = appendix_b_weights(c, v)
    np.testing.assert_allclose((wb * df).sum(1), 2 * coef.sum(1), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(axis_weights(c, v), wb, rtol=1e-10)
    np.testing.assert_allclose(np.abs(local_frames(c, v)), np.abs(rot), atol=1e-12)


def test_exact_in_local_frame_for_perturbed_stencils() -> None:
    """Appendix B is exact for any quadratic without mixed terms in the local lattice frame."""
    rng = np.random.default_rng(5)
    c, v = perturbed(rng, 300, 0.5, 0.15)
    frames = local_frames(c, v)
    np.testing.assert_allclose(frames @ frames.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (300, 3, 3)),
                               atol=1e-12)
    assert (np.linalg.det(frames) > 0).all()
    coef = rng.uniform(0.5, 2, (300, 3))
    g = rng.uniform(-1, 1, (300, 3))
    local = np.einsum("nkd,njd->njk", frames, v - c[:, None, :])
    df = (coef[:, None, :] * local**2).sum(-1) + (g[:, None, :] * local).sum(-1)
    wb, _ = appendix_b_weights(c, v)
    np.testing.assert_allclose((wb * df).sum(1), 2 * coef.sum(1), rtol=1e-8)


def test_perturbed_grid_error_is_second_order() -> None:
    def f(p: np.ndarray) -> np.ndarray:
        return p[..., 0] ** 2 + 2 * p[..., 1] ** 2 + 3 * p[..., 2] ** 2

    errors = []
    for eps in (0.1, 0.01, 0.001):
        c, v = perturbed(np.random.default_rng(6), 500, 0.5, eps)
        wb, _ = appendix_b_weights(c, v)
        errors.append(np.abs(stencil_laplacian(wb, c, v, f) - 12.0).max())
    assert errors[0] < 2.0
    assert errors[1] < errors[0] / 30 and errors[2] < errors[1] / 30, errors


# --------------------------------------------------------------------------- invariance
@pytest.mark.parametrize("reflect", [False, True])
def test_rotation_invariance(reflect: bool) -> None:
    rng = np.random.default_rng(7)
    c, v = perturbed(rng, 200, 0.7, 0.2)
    wb, cond = appendix_b_weights(c, v)
    rot = random_rotations(rng, 200)
    if reflect:
        rot[:, 2] *= -1
    shift = rng.uniform(-50, 50, (200, 3))
    c2 = np.einsum("nij,nj->ni", rot, c) + shift
    v2 = np.einsum("nij,nkj->nki", rot, v) + shift[:, None, :]
    wb2, cond2 = appendix_b_weights(c2, v2)
    np.testing.assert_allclose(wb2, wb, rtol=1e-9, atol=1e-9 * np.abs(wb).max())
    np.testing.assert_allclose(cond2, cond, rtol=1e-8)
    np.testing.assert_allclose(axis_weights(c2, v2), axis_weights(c, v), rtol=1e-12)
    # and scaling all lengths by k scales the weights by 1/k^2, cond unchanged
    wb3, cond3 = appendix_b_weights(3 * c, 3 * v)
    np.testing.assert_allclose(wb3, wb / 9, rtol=1e-9, atol=1e-9 * np.abs(wb).max())
    np.testing.assert_allclose(cond3, cond, rtol=1e-8)


# --------------------------------------------------------------------------- fallback
def sheared(shift: float) -> tuple[np.ndarray, np.ndarray]:
    """The y neighbours displaced by ``shift`` along +x: w[x+] = 1 - shift^2 < 0 for shift > 1."""
    v = BASE.copy()
    v[2, 0] = v[3, 0] = shift
    return np.zeros((1, 3)), v[None]


def test_skewed_stencil_blend_is_minimal() -> None:
    c, v = sheared(1.5)
    wb, cond = appendix_b_weights(c, v)
    wa = axis_weights(c, v)
    assert wb.min() < 0 and np.isfinite(cond).all() and cond[0] < 1e4
    assert (wa > 0).all()
    floor = 0.05
    w, stats = laplacian_weights(c, v, floor=floor)
    assert (stats.negative, stats.fallback, stats.ill_conditioned, stats.nonfinite) == (1, 1, 0, 0)
    assert (w >= floor * wa).all()
    t = stats.blend_max
    assert 0 < t < 1 and stats.blend_mean == t
    np.testing.assert_allclose(w, (1 - t) * wb + t * wa, rtol=1e-12)
    assert np.isclose(np.min(w / wa), floor, rtol=1e-12)  # the floor is met with equality
    smaller = (1 - t * (1 - 1e-6)) * wb + t * (1 - 1e-6) * wa
    assert (smaller < floor * wa).any()
    assert stats.min_weight == pytest.approx(w.min()) and stats.max_weight == pytest.approx(w.max())


def test_skewed_stencil_axis_and_none_modes() -> None:
    c, v = sheared(1.5)
    wb, _ = appendix_b_weights(c, v)
    wa = axis_weights(c, v)
    w, stats = laplacian_weights(c, v, fallback="axis")
    np.testing.assert_array_equal(w, wa)
    assert stats.fallback == 1 and stats.blend_max == 1.0
    w, stats = laplacian_weights(c, v, fallback="none")
    np.testing.assert_array_equal(w, wb)
    assert stats.negative == 1 and stats.fallback == 0 and stats.min_weight < 0


def test_mixed_batch_only_bad_nodes_change() -> None:
    rng = np.random.default_rng(8)
    c, v = perturbed(rng, 400, 1.0, 0.4)  # heavy distortion: some negative weights
    wb, cond = appendix_b_weights(c, v)
    wa = axis_weights(c, v)
    floor = 0.1
    w, stats = laplacian_weights(c, v, floor=floor, max_cond=1e3)
    bad = (wb < floor * wa).any(axis=1) | (cond > 1e3)
    assert 0 < stats.fallback == bad.sum() < 400
    assert stats.negative == (wb < floor * wa).any(axis=1).sum()
    assert stats.ill_conditioned == (cond > 1e3).sum()
    np.testing.assert_array_equal(w[~bad], wb[~bad])
    assert (w >= floor * wa).all()
    np.testing.assert_array_equal(w[cond > 1e3], wa[cond > 1e3])
    assert stats.max_cond == cond.max()


def test_floor_extremes() -> None:
    c, v = sheared(1.5)
    wa = axis_weights(c, v)
    w, stats = laplacian_weights(c, v, floor=1.0)
    np.testing.assert_array_equal(w, wa)
    assert stats.blend_max == 1.0
    w, stats = laplacian_weights(c, v, floor=0.0)
    assert (w >= 0).all() and w.min() < 1e-12 and 0 < stats.blend_max < 1


# --------------------------------------------------------------------------- degenerate
def test_coplanar_neighbours_are_singular() -> None:
    c = np.zeros((2, 3))
    v = np.stack([BASE, BASE])
    v[0, 4] = [0.3, 0.2, 0.0]  # z neighbours in the xy plane
    v[0, 5] = [-0.2, 0.4, 0.0]
    wb, cond = appendix_b_weights(c, v)
    assert np.isnan(wb[0]).all() and cond[0] == np.inf
    assert cond[1] == pytest.approx(2.0)
    w, stats = laplacian_weights(c, v)
    assert (stats.nonfinite, stats.ill_conditioned, stats.fallback, stats.negative) == (1, 1, 1, 0)
    np.testing.assert_array_equal(w[0], axis_weights(c, v)[0])
    np.testing.assert_allclose(w[1], 1.0, rtol=1e-12)
    assert stats.max_cond == np.inf and np.isfinite(w).all()
    w, stats = laplacian_weights(c, v, fallback="none")
    assert np.isnan(w[0]).all() and stats.nonfinite == 1
    assert "1 non-finite" in stats.summary()


def test_nearly_coplanar_is_ill_conditioned_not_singular() -> None:
    c = np.zeros((1, 3))
    v = BASE.copy()
    v[4] = [0.3, 0.2, -1e-3]
    v[5] = [-0.2, 0.4, 1e-3]
    wb, cond = appendix_b_weights(c, v[None])
    assert np.isfinite(wb).all() and 1e4 < cond[0] < np.inf
    w, stats = laplacian_weights(c, v[None])
    assert (stats.ill_conditioned, stats.nonfinite, stats.fallback) == (1, 0, 1)
    np.testing.assert_array_equal(w, axis_weights(c, v[None]))
    _, stats = laplacian_weights(c, v[None], max_cond=np.inf)
    assert stats.ill_conditioned == 0


def test_coincident_neighbours_and_degenerate_axes() -> None:
    c = np.zeros((3, 3))
    v = np.stack([BASE, BASE, BASE])
    v[0, 1] = v[0, 3] = [1.0, 1.0, 0.0]  # x+ and y+ coincide: two equal rows
    v[1, 0] = v[1, 1] = [0.0, 0.0, 1.0]  # x- and x+ coincide: no x axis
    v[2, 2], v[2, 3] = [-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]  # y axis parallel to the x axis
    frames = local_frames(c, v)
    assert np.isfinite(frames[0]).all() and np.isnan(frames[1:]).all()
    wb, cond = appendix_b_weights(c, v)
    assert np.isnan(wb).all() and (cond == np.inf).all()
    w, stats = laplacian_weights(c, v)
    assert stats.nonfinite == 3 and stats.fallback == 3 and (w > 0).all()


def test_coincident_with_node_raises() -> None:
    c = np.zeros((5, 3))
    v = np.broadcast_to(BASE, (5, 6, 3)).copy()
    v[2, 3] = 0.0
    v[4, 0] = 1e-15
    for fn in (appendix_b_weights, axis_weights, local_frames, laplacian_weights):
        with pytest.raises(InputError, match=r"2 node\(s\).*node 2, neighbour 'y\+'"):
            fn(c, v)


def test_chunk_boundaries(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(W, "_CHUNK", 7)
    rng = np.random.default_rng(9)
    c, v = perturbed(rng, 50, 1.0, 0.4)
    wb, cond = appendix_b_weights(c, v)
    wr, cr = reference_weights(c, v)
    np.testing.assert_allclose(wb, wr, rtol=1e-9, atol=1e-9 * np.abs(wr).max())
    np.testing.assert_allclose(cond, cr, rtol=1e-8)
    w_small, s_small = laplacian_weights(c, v)
    monkeypatch.setattr(W, "_CHUNK", 1 << 14)
    w_big, s_big = laplacian_weights(c, v)
    np.testing.assert_array_equal(w_small, w_big)
    assert s_small == s_big
    v[33, 5] = c[33]
    monkeypatch.setattr(W, "_CHUNK", 7)
    with pytest.raises(InputError, match=r"1 node\(s\).*node 33, neighbour 'z\+'"):
        laplacian_weights(c, v)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("center", "nbrs", "field"),
    [
        (np.zeros((4, 2)), np.zeros((4, 6, 3)), "center"),
        (np.zeros(3), np.zeros((1, 6, 3)), "center"),
        (np.zeros((4, 3)), np.zeros((4, 5, 3)), "nbrs"),
        (np.zeros((4, 3)), np.zeros((4, 6, 2)), "nbrs"),
        (np.zeros((4, 3)), np.zeros((3, 6, 3)), "nbrs"),
        (np.zeros((4, 3)), np.zeros((4, 18)), "nbrs"),
        (np.full((1, 3), np.nan), BASE[None], "center"),
        (np.zeros((1, 3)), np.where(np.arange(6)[None, :, None] == 4, np.inf, BASE[None]), "nbrs"),
        ([["a", "b", "c"]], BASE[None], "center"),
        (np.zeros((1, 3)), [[["x"] * 3] * 6], "nbrs"),
    ],
)
def test_bad_input_raises(center, nbrs, field: str) -> None:
    for fn in (appendix_b_weights, axis_weights, local_frames, laplacian_weights):
        with pytest.raises(InputError, match=field):
            fn(center, nbrs)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"fallback": "clamp"}, "fallback"),
        ({"floor": -0.1}, "floor"),
        ({"floor": 1.5}, "floor"),
        ({"floor": float("nan")}, "floor"),
        ({"max_cond": 0.5}, "max_cond"),
        ({"max_cond": float("nan")}, "max_cond"),
        ({"max_cond": "big"}, "max_cond"),
    ],
)
def test_bad_parameters_raise(kwargs: dict, field: str) -> None:
    with pytest.raises(InputError, match=field):
        laplacian_weights(np.zeros((1, 3)), BASE[None], **kwargs)


# --------------------------------------------------------------------------- stats, misc
def test_stats_and_empty_input() -> None:
    c, v = sheared(1.5)
    _, stats = laplacian_weights(c, v)
    d = stats.as_dict()
    assert list(d) == ["nodes", "negative", "ill_conditioned", "nonfinite", "fallback", "blend_mean",
                       "blend_max", "min_weight", "max_weight", "max_cond"]
    assert all(isinstance(x, (int, float)) for x in d.values())
    line = stats.summary()
    assert "\n" not in line and "1 nodes" in line and "mm^-2" in line
    w, stats = laplacian_weights(np.zeros((0, 3)), np.zeros((0, 6, 3)))
    assert w.shape == (0, 6) and stats.nodes == 0 and stats.fallback == 0
    assert isinstance(stats, WeightStats) and stats.summary()
    wb, cond = appendix_b_weights(np.zeros((0, 3)), np.zeros((0, 6, 3)))
    assert wb.shape == (0, 6) and cond.shape == (0,)
    assert NEIGHBOURS == ("x-", "x+", "y-", "y+", "z-", "z+")


def test_accepts_lists_and_float32() -> None:
    w, stats = laplacian_weights([[0.0, 0.0, 0.0]], (2 * BASE[None]).tolist())
    np.testing.assert_allclose(w, 0.25, rtol=1e-12)
    wb, _ = appendix_b_weights(np.zeros((1, 3), np.float32), (2 * BASE[None]).astype(np.float32))
    assert wb.dtype == np.float64
    np.testing.assert_allclose(wb, 0.25, rtol=1e-12)
