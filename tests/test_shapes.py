"""Shape quality of tetrahedra and the shape step of the fem grid (glsldiff.grids.tetrahedral.shapes)."""
from __future__ import annotations

import numpy as np

from glsldiff.grids.tetrahedral.pillow import KUHN, signed_volumes
from glsldiff.grids.tetrahedral.shapes import SHAPE_TARGET, improve_shapes, shape_quality


def _kuhn_block(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes of an m^3 block of unit cubes, each split into 6 Kuhn tetrahedra, its top-face
    (z = m) triangles, and the node grid index (x, y, z)."""
    idx = np.arange((m + 1) ** 3).reshape(m + 1, m + 1, m + 1)     # [z, y, x]
    z, y, x = np.meshgrid(*(np.arange(m + 1),) * 3, indexing="ij")
    X = np.stack([x, y, z], axis=-1).reshape(-1, 3).astype(float)
    tets = []
    for k in range(m):
        for j in range(m):
            for i in range(m):
                corners = [idx[k + ((b >> 2) & 1), j + ((b >> 1) & 1), i + (b & 1)] for b in range(8)]
                tets += [[corners[c] for c in t] for t in KUHN]
    T = np.array(tets, dtype=np.int64)
    T[signed_volumes(X, T) < 0] = T[signed_volumes(X, T) < 0][:, [1, 0, 2, 3]]
    top = []
    for j in range(m):
        for i in range(m):
            a, b, c, d = idx[m, j, i], idx[m, j, i + 1], idx[m, j + 1, i], idx[m, j + 1, i + 1]
            top += [[a, b, d], [a, d, c]]
    return X, T, np.array(top, dtype=np.int64)


def test_shape_quality_of_regular_flat_and_inverted_tetrahedra():
    X = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    T = np.array([[0, 1, 2, 3]])
    if signed_volumes(X, T)[0] < 0:
        T = T[:, [1, 0, 2, 3]]
    assert abs(shape_quality(X, T)[0] - 1.0) < 1e-12
    assert abs(shape_quality(X, T[:, [1, 0, 2, 3]])[0] + 1.0) < 1e-12       # inverted: -1
    flat = X.copy()
    flat[3] = flat[:3].mean(axis=0)
    assert abs(shape_quality(flat, T)[0]) < 1e-12


def test_improve_shapes_lifts_flat_tetrahedra_without_making_any_worse():
    """A 3^3 Kuhn block with an interior node pushed almost onto a face of its cells and a top
    node slid along the top face: the step lifts every tetrahedron above the target, moves
    only free and sliding nodes, keeps the sliding ones on their surface (z = 3) within the
    slide limit, and no tetrahedron ends below the worst one before."""
    X, T, top = _kuhn_block(3)
    inner = 1 * 16 + 1 * 4 + 1                        # node (1, 1, 1)
    surf = 3 * 16 + 1 * 4 + 2                         # node (2, 1, 3) on the top face
    X[inner] = [1.95, 1.95, 1.02]
    X[surf] = [2.95, 1.05, 3.0]
    q0 = shape_quality(X, T)
    assert q0.min() > 0 and (q0 < SHAPE_TARGET).sum() > 4
    on_box = np.all((X > 0) & (X < 3), axis=1)
    free = on_box.copy()
    sliding = np.zeros(len(X), dtype=bool)
    sliding[top.ravel()] = True
    sliding &= (X[:, 0] > 0) & (X[:, 0] < 3) & (X[:, 1] > 0) & (X[:, 1] < 3)   # top face, not its rim
    start = X.copy()
    calls = []

    def onto_top(p: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        calls.append(len(nodes))
        assert sliding[nodes].all()
        return np.c_[p[:, :2], np.full(len(p), 3.0)]

    rep = improve_shapes(X, T, free, sliding, top, onto_top, max_slide=0.8)
    q = shape_quality(X, T)
    assert rep.below_before == int((q0 < SHAPE_TARGET).sum()) and rep.below_after == int((q < SHAPE_TARGET).sum())
    assert rep.below_after == 0 and q.min() >= SHAPE_TARGET
    assert rep.worst_after == q.min() > rep.worst_before == q0.min()
    moved = np.any(X != start, axis=1)
    assert moved[inner] and not (moved & ~free & ~sliding).any()
    assert np.all(X[sliding, 2] == 3.0) and calls
    assert np.linalg.norm(X[sliding] - start[sliding], axis=1).max() <= 0.8 + 1e-12


def test_fixed_nodes_keep_a_flat_tetrahedron_flat():
    """With every node fixed, nothing moves and the report says so."""
    X, T, top = _kuhn_block(2)
    X[13] = [1.0, 1.0, 0.02]                  # node (1, 1, 1) onto the bottom face's plane
    none = np.zeros(len(X), dtype=bool)
    start = X.copy()
    rep = improve_shapes(X, T, none, none, top, lambda p, nodes: p)
    assert np.array_equal(X, start) and rep.smoothed == rep.searched == 0
    assert rep.below_after == rep.below_before > 0


def test_improve_shapes_untangles_a_node_pushed_through_its_cells():
    """Node (1, 1, 1) pushed past the opposite corner of its cube: 6 tetrahedra inverted; the
    step moves it back (every tetrahedron regular-Kuhn again, quality 0.707)."""
    X, T, top = _kuhn_block(3)
    X[21] = [2.2, 2.2, 2.2]
    q0 = shape_quality(X, T)
    assert (q0 <= 0).sum() == 6
    free = np.all((X > 0) & (X < 3), axis=1)
    rep = improve_shapes(X, T, free, np.zeros(len(X), dtype=bool), top, lambda p, nodes: p)
    q = shape_quality(X, T)
    assert (q <= 0).sum() == 0 and rep.worst_after > 0.7


def test_compiled_search_takes_scipys_nelder_mead_steps():
    """The compiled search (``shapes._nelder_mead``) = ``scipy.optimize.minimize(method=
    "Nelder-Mead")`` on the same objective, bit for bit: a free node in 3-D and a sliding node
    in a plane, with a slide limit that cuts some of the steps off (objective +inf there), at
    budgets that end inside a reflection, a contraction and a shrink."""
    import scipy.optimize as so

    from glsldiff.grids.tetrahedral.pillow import node_tets
    from glsldiff.grids.tetrahedral.shapes import _nelder_mead

    X, T, _ = _kuhn_block(3)
    rng = np.random.default_rng(5)
    X = X + rng.uniform(-0.3, 0.3, X.shape)
    incident = node_tets(T, len(X))
    for v, basis, slide in ((21, np.eye(3), np.inf), (22, np.eye(3)[:2], 0.15), (37, np.eye(3)[[0, 2]], 0.05)):
        own = T[incident.indices[incident.indptr[v]:incident.indptr[v + 1]]]
        old, start = X[v].copy(), X[v].copy()
        d = len(basis)
        simplex = np.vstack([np.zeros(d), 0.2 * np.eye(d)])

        def f(u: np.ndarray) -> float:
            p = old + u @ basis
            if np.linalg.norm(p - start) > slide:
                return np.inf
            Y = X.copy()
            Y[v] = p
            return -float(shape_quality(Y, own).min())

        for fev in (5, 9, 14, 80):
            ref = so.minimize(f, np.zeros(d), method="Nelder-Mead",
                              options={"initial_simplex": simplex, "maxfev": fev, "xatol": 1e-3, "fatol": 1e-6}).x
            got = _nelder_mead(X.copy(), own, v, old, np.ascontiguousarray(basis), simplex, fev, 1e-3, 1e-6,
                               bool(np.isfinite(slide)), start, float(slide))
            assert np.array_equal(got, ref), (v, fev, got, ref)
