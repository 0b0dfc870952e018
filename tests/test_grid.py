"""Tests for glsldiff.grids.regular (RegularGrid) and the texel rectangles the GLSL solver draws on it
(glsldiff.solve.stencil.pass_primitives).

Reference: the definitions in the glsldiff.grids.regular module docstring (node kinds, face table,
tiled z-slice packing; Wang et al. 2008 section 5.2, figure 6), re-derived here with loops.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from glsldiff.solve.stencil import pass_primitives
from glsldiff.core.errors import InputError
from glsldiff.grids.regular import BOUNDARY, FACES, INACTIVE, INTERIOR, RegularGrid

# (nx, ny, nz): cubic, odd, one-interior-layer, long in one axis, nz > nx, ...
SHAPES = [(3, 3, 3), (5, 7, 11), (40, 3, 17), (4, 9, 3), (16, 16, 16), (7, 5, 30)]
FACE_TABLE = {  # module docstring: face -> (volume slice, face array shape)
    "z-": (np.s_[0, 1:-1, 1:-1], lambda nx, ny, nz: (ny - 2, nx - 2)),
    "z+": (np.s_[-1, 1:-1, 1:-1], lambda nx, ny, nz: (ny - 2, nx - 2)),
    "y-": (np.s_[1:-1, 0, 1:-1], lambda nx, ny, nz: (nz - 2, nx - 2)),
    "y+": (np.s_[1:-1, -1, 1:-1], lambda nx, ny, nz: (nz - 2, nx - 2)),
    "x-": (np.s_[1:-1, 1:-1, 0], lambda nx, ny, nz: (nz - 2, ny - 2)),
    "x+": (np.s_[1:-1, 1:-1, -1], lambda nx, ny, nz: (nz - 2, ny - 2)),
}


def _ids(shape):
    return "x".join(map(str, shape))


def _kind_by_definition(nx: int, ny: int, nz: int) -> np.ndarray:
    """Node kind from the docstring: 0 coordinates on a face -> interior, 1 -> boundary, else inactive."""
    kind = np.empty((nz, ny, nx), dtype=np.int8)
    for z, y, x in itertools.product(range(nz), range(ny), range(nx)):
        on = (x in (0, nx - 1)) + (y in (0, ny - 1)) + (z in (0, nz - 1))
        kind[z, y, x] = INTERIOR if on == 0 else BOUNDARY if on == 1 else INACTIVE
    return kind


def _texel_maps(g: RegularGrid) -> tuple[np.ndarray, np.ndarray]:
    """``node_at[ty, tx]`` = flat node index (-1 for padding) and ``texel_of[flat] = (tx, ty)``."""
    w, h = g.texture_size
    node_at = np.full((h, w), -1, dtype=np.int64)
    flat = np.arange(g.size).reshape(g.shape)
    texel_of = np.zeros((g.size, 2), dtype=np.int64)
    for z in range(g.nz):
        ox, oy = g.tile_origin(z)
        block = node_at[oy:oy + g.ny, ox:ox + g.nx]
        assert np.all(block == -1), f"z-slice {z} overlaps another slice in the texture"
        block[...] = flat[z]
        ys, xs = np.mgrid[0:g.ny, 0:g.nx]
        texel_of[flat[z].ravel()] = np.stack([ox + xs.ravel(), oy + ys.ravel()], axis=1)
    return node_at, texel_of


# ---------------------------------------------------------------- node kinds and links
@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
def test_node_kinds_and_counts(shape):
    """kind matches the docstring definition; n_interior/n_boundary/n_active count it."""
    g = RegularGrid(*shape)
    kind = _kind_by_definition(*shape)
    np.testing.assert_array_equal(g.kind, kind)
    assert g.shape == (shape[2], shape[1], shape[0])
    assert g.size == kind.size
    assert g.n_interior == int((kind == INTERIOR).sum())
    assert g.n_boundary == int((kind == BOUNDARY).sum())
    assert g.n_active == int(g.active.sum()) == int((kind != INACTIVE).sum())
    np.testing.assert_array_equal(g.active, kind != INACTIVE)


@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
def test_boundary_nodes_link_to_inward_interior_neighbour(shape):
    """Each boundary node's link is the interior node one step along the inward face normal."""
    g = RegularGrid(*shape)
    link = g.link
    assert np.all(link[g.kind != BOUNDARY] == -1)
    dims = g.shape  # (nz, ny, nx)
    for b in np.argwhere(g.kind == BOUNDARY):
        j = np.array(np.unravel_index(link[tuple(b)], dims))
        assert g.kind[tuple(j)] == INTERIOR
        d = j - b
        assert np.abs(d).sum() == 1, f"node {b} linked to non-neighbour {j}"
        axis = int(np.flatnonzero(d)[0])
        assert b[axis] in (0, dims[axis] - 1), "link must be along the face normal"
        assert d[axis] == (1 if b[axis] == 0 else -1), "link must point inward"


# ---------------------------------------------------------------- faces
@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
def test_face_shapes_and_slices(shape):
    """face_shape / face follow the module-docstring table and cover exactly the boundary nodes."""
    g = RegularGrid(*shape)
    vol = np.arange(g.size, dtype=float).reshape(g.shape)
    seen = np.zeros(g.shape, dtype=int)
    for name, (sl, want) in FACE_TABLE.items():
        assert g.face_shape(name) == want(*shape)
        np.testing.assert_array_equal(g.face(vol, name), vol[sl])
        seen[sl] += 1
    np.testing.assert_array_equal(seen, (g.kind == BOUNDARY).astype(int))
    assert set(FACES) == set(FACE_TABLE)


def test_face_volume_accepts_scalar_rgb_and_face_arrays():
    """face_volume scatters scalar, (3,), face-shaped and face+(3,) arrays; other nodes stay 0."""
    g = RegularGrid(6, 5, 4)
    rng = np.random.default_rng(0)
    fx = rng.random(g.face_shape("x+"))
    fy = rng.random(g.face_shape("y-") + (3,))
    vol = g.face_volume({"z-": 2.0, "z+": [1.0, 2.0, 3.0], "x+": fx, "y-": fy})
    assert vol.shape == g.shape + (3,)
    np.testing.assert_array_equal(g.face(vol, "z-"), np.full(g.face_shape("z-") + (3,), 2.0))
    np.testing.assert_array_equal(g.face(vol, "z+"), np.broadcast_to([1.0, 2.0, 3.0], g.face_shape("z+") + (3,)))
    np.testing.assert_array_equal(g.face(vol, "x+"), np.repeat(fx[..., None], 3, axis=-1))
    np.testing.assert_array_equal(g.face(vol, "y-"), fy)
    touched = np.zeros(g.shape, bool)
    for name in ("z-", "z+", "x+", "y-"):
        touched[FACE_TABLE[name][0]] = True
    assert np.all(vol[~touched] == 0.0)


@pytest.mark.parametrize("bad", [np.zeros((3, 3)), np.zeros((4, 3, 2)), np.zeros((2,))])
def test_face_volume_rejects_wrong_shape(bad):
    """A face array that fits neither (ny-2, nx-2)[, c] nor a scalar/(3,) is an InputError naming the face."""
    g = RegularGrid(6, 5, 4)
    with pytest.raises(InputError, match=r"face 'z-' array has shape"):
        g.face_volume({"z-": bad})


# ---------------------------------------------------------------- texture packing
@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_pack_unpack_round_trip(shape, channels):
    """unpack(pack(v)) == v (float32) for 1, 3 and 4 channels; grey volumes pack too."""
    g = RegularGrid(*shape)
    rng = np.random.default_rng(1)
    vol = rng.standard_normal(g.shape + (channels,)).astype(np.float32)
    tex = g.pack(vol)
    w, h = g.texture_size
    assert tex.shape == (h, w, 4) and tex.dtype == np.float32
    np.testing.assert_array_equal(g.unpack(tex, channels), vol)
    if channels == 1:
        np.testing.assert_array_equal(g.unpack(g.pack(vol[..., 0]), 1)[..., 0], vol[..., 0])


@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
def test_pack_layout_follows_tile_origin(shape):
    """Node (x, y, z) sits at texel tile_origin(z) + (x, y); slices do not overlap; padding is 0."""
    g = RegularGrid(*shape)
    vol = (np.arange(g.size, dtype=np.float32) + 1.0).reshape(g.shape)
    tex = g.pack(vol)[..., 0]
    node_at, _ = _texel_maps(g)
    np.testing.assert_array_equal(tex[node_at >= 0], node_at[node_at >= 0] + 1.0)
    assert np.all(tex[node_at < 0] == 0.0)
    tx, ty = g.tiles
    assert (tx - 1) * ty < g.nz <= tx * ty, "more tile rows than needed"


@pytest.mark.parametrize("shape, limit", [((10, 10, 30), 64), ((3, 3, 200), 64), ((40, 3, 17), 4096),
                                          ((64, 64, 64), 1024), ((5, 7, 11), 16384)])
def test_texture_size_within_limit(shape, limit):
    """The packed texture never exceeds max_texture_size in either direction."""
    g = RegularGrid(*shape, max_texture_size=limit)
    w, h = g.texture_size
    assert w <= limit and h <= limit
    assert w * h >= g.size


@pytest.mark.parametrize("shape, limit, what", [((40, 40, 40), 64, "texture"), ((100, 5, 5), 64, "z-slice")])
def test_texture_over_limit_is_input_error(shape, limit, what):
    """A grid whose packing cannot fit the limit is rejected up front (InputError naming the limit)."""
    with pytest.raises(InputError, match=rf"{what}.*limit {limit}"):
        RegularGrid(*shape, max_texture_size=limit)


# ---------------------------------------------------------------- GPU primitives
@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
def test_grid_primitives_cover_each_texel_once(shape):
    """Rasterised in numpy, the interior pass covers each interior texel once, the boundary pass
    each boundary texel once, and neither touches inactive nodes or padding; a z-slice's interior
    is one rectangle."""
    g = RegularGrid(*shape)
    node_at, _ = _texel_maps(g)
    kind_tex = np.full(node_at.shape, -1)
    kind_tex[node_at >= 0] = g.kind.ravel()[node_at[node_at >= 0]]
    prims = pass_primitives(g)
    for name, want in (("interior", INTERIOR), ("boundary", BOUNDARY)):
        cover = np.zeros(node_at.shape, dtype=int)
        for x0, y0, x1, y1 in prims[name].rects:
            assert 0 <= x0 < x1 <= cover.shape[1] and 0 <= y0 < y1 <= cover.shape[0]
            cover[y0:y1, x0:x1] += 1
        np.testing.assert_array_equal(cover, (kind_tex == want).astype(int))
    assert len(prims["interior"].rects) == g.nz - 2


@pytest.mark.parametrize("shape", SHAPES, ids=_ids)
def test_grid_primitives_offsets_reach_the_right_nodes(shape):
    """Interior rectangles: texel + offset j is the node's neighbour x-, x+, y-, y+, z-, z+ (the
    stencil of eq. 8). Boundary rectangles: texel + offset 0 is the linked interior node."""
    g = RegularGrid(*shape)
    node_at, texel_of = _texel_maps(g)
    link = g.link.ravel()
    steps = (-1, 1, -g.nx, g.nx, -g.nx * g.ny, g.nx * g.ny)
    prims = pass_primitives(g)
    for (x0, y0, x1, y1), offs in zip(prims["interior"].rects, prims["interior"].offsets):
        nodes = node_at[y0:y1, x0:x1].ravel()
        for off, step in zip(offs, steps):
            np.testing.assert_array_equal(texel_of[nodes] + off, texel_of[nodes + step])
    for (x0, y0, x1, y1), offs in zip(prims["boundary"].rects, prims["boundary"].offsets):
        nodes = node_at[y0:y1, x0:x1].ravel()
        np.testing.assert_array_equal(texel_of[nodes] + offs[0], texel_of[link[nodes]])


def test_face_to_boundary_roundtrip_matches_face_volume() -> None:
    grid = RegularGrid(6, 5, 4)
    rng = np.random.default_rng(0)
    for name in ("x-", "z+", "y-"):
        a = rng.uniform(size=grid.face_shape(name) + (2,))
        b = grid.face_to_boundary(name, a)
        np.testing.assert_array_equal(grid.boundary_to_face(name, b), a)
        vol = grid.face_volume({name: a[..., 0]}, 1).reshape(-1)[grid.graph.boundary]
        np.testing.assert_array_equal(b[:, 0], vol)
    with pytest.raises(InputError, match="unknown face"):
        grid.face_to_boundary("w+", np.zeros((3, 4)))
