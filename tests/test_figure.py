"""glsldiff.figures: headless polygrid pictures (translucent mesh + node dots + links)."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff import figures as figure
from glsldiff.core.errors import InputError

trimesh = pytest.importorskip("trimesh")

RED, BLUE, GREEN = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.7, 0.0)
FRONT = figure.View(azimuth_deg=0.0, elevation_deg=0.0)  # camera on +z, image right = +x, up = +y


@pytest.fixture(scope="module")
def icosphere():
    """Icosphere of radius 10 mm."""
    m = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.fixture(scope="module")
def lattice():
    """Regular lattice nodes (spacing 1.5 mm) strictly inside radius 7 mm."""
    ax = np.arange(-7.0, 7.01, 1.5) + 0.25
    p = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    return p[np.linalg.norm(p, axis=1) < 7.0]


def _redness(img):
    f = img.astype(float)
    return f[..., 0] - np.maximum(f[..., 1], f[..., 2])


def _blueness(img):
    f = img.astype(float)
    return f[..., 2] - np.maximum(f[..., 0], f[..., 1])


def _greenness(img):
    f = img.astype(float)
    return f[..., 1] - np.maximum(f[..., 0], f[..., 2])


def test_sphere_with_boundary_and_interior_nodes(bctx, icosphere, lattice):
    v, f = icosphere
    img = figure.render_nodes(v, f, [(v, (0.9, 0.1, 0.1)), (lattice, (0.1, 0.2, 0.9))],
                              size=(160, 140), point_size_px=4.0, ctx=bctx)
    assert img.shape == (140, 160, 3) and img.dtype == np.uint8
    assert (_redness(img) > 80).sum() > 50, "red boundary nodes missing"
    assert (_blueness(img) > 60).sum() > 30, "blue interior nodes missing"
    for corner in (img[0, 0], img[0, -1], img[-1, 0], img[-1, -1]):
        assert tuple(corner) == (255, 255, 255)

    bare = figure.render_nodes(v, f, [], size=(160, 140), ctx=bctx)
    covered = np.any(bare != 255, axis=2)
    assert covered[70, 80], "the mesh must cover the image centre"
    assert tuple(bare[0, 0]) == (255, 255, 255)
    # a sphere fitted into 140 px (6 % margin): disc area between 55 % and 80 % of the square
    assert 0.55 * 140 ** 2 < covered.sum() < 0.80 * 140 ** 2
    assert np.all(bare[covered].max(axis=1) < 250), "the surface must be visibly non-white"


def test_node_behind_surface_is_dimmed(ctx, icosphere):
    v, f = icosphere
    in_front = np.array([[-4.0, 0.0, 11.0]])  # outside the sphere, between it and the camera
    inside = np.array([[4.0, 0.0, 0.0]])      # behind the camera-facing surface
    pts = [(in_front, RED), (inside, RED)]
    img = figure.render_nodes(v, f, pts, size=(120, 120), view=FRONT, point_size_px=6.0, ctx=ctx)
    red = _redness(img)
    left, right = red[:, :60].max(), red[:, 60:].max()
    assert left > 240, "the node in front of the surface keeps its full colour"
    assert 80 < right < left - 40, f"the node behind the surface is visible but dimmer ({right})"
    no_dots = figure.render_nodes(v, f, [], size=(120, 120), view=FRONT, ctx=ctx)
    assert _redness(no_dots).max() < 20

    opaque = figure.render_nodes(v, f, pts, size=(120, 120), view=FRONT, point_size_px=6.0,
                                 mesh_alpha=1.0, ctx=ctx)
    assert _redness(opaque)[:, :60].max() > 240
    assert _redness(opaque)[:, 60:].max() < 20, "an opaque surface hides the inner node"


def test_image_orientation(ctx, icosphere):
    v, f = icosphere
    pts = [(np.array([[0.0, 5.0, 11.0]]), RED), (np.array([[5.0, 0.0, 11.0]]), GREEN)]
    img = figure.render_nodes(v, f, pts, size=(100, 100), view=FRONT, point_size_px=6.0, ctx=ctx)
    rows, cols = np.nonzero(_redness(img) > 150)
    assert rows.size and rows.max() < 50 and abs(cols.mean() - 50) < 3, "+y is up, row 0 is top"
    rows, cols = np.nonzero(_greenness(img) > 100)
    assert cols.size and cols.min() > 50 and abs(rows.mean() - 50) < 3, "+x is right"
    cam = figure.camera(v, FRONT, (100, 100), np.vstack([p for p, _ in pts]))
    (cx, cy), = cam.project([[5.0, 0.0, 11.0]])
    assert abs(cx - (cols.mean() + 0.5)) < 1.0 and abs(cy - (rows.mean() + 0.5)) < 1.0


def test_clip_planes(ctx, icosphere, lattice):
    v, f = icosphere
    size = (120, 120)
    full = figure.render_nodes(v, f, [(lattice, BLUE)], size=size, view=FRONT, ctx=ctx)
    cols = np.nonzero(_blueness(full) > 60)[1]
    assert cols.min() < 45 and cols.max() > 75

    half = figure.render_nodes(v, f, [(lattice, BLUE), (np.array([[5.0, 0.0, 0.0]]), RED, False)],
                               size=size, view=FRONT, clip=((1.0, 0.0, 0.0), 0.0),
                               point_size_px=5.0, ctx=ctx)
    cols = np.nonzero(_blueness(half) > 60)[1]
    assert cols.min() < 45 and cols.max() <= 61, "no clipped node on the positive side (x > 0)"
    assert (_redness(half)[:, 62:] > 80).any(), "a set marked clipped=False ignores the plane"

    slab = figure.render_nodes(v, f, [(lattice, BLUE)], size=size, view=FRONT,
                               clip=[((1.0, 0.0, 0.0), 2.0), ((-1.0, 0.0, 0.0), 2.0)], ctx=ctx)
    cols = np.nonzero(_blueness(slab) > 60)[1]
    kept = lattice[np.abs(lattice[:, 0]) <= 2.0]
    px = figure.camera(v, FRONT, size, lattice).project(kept)[:, 0]
    assert cols.size and px.min() - 3 <= cols.min() and cols.max() <= px.max() + 3

    cut = figure.render_nodes(v, f, [], size=size, view=FRONT, clip=((1.0, 0.0, 0.0), 0.0),
                              clip_mesh=True, ctx=ctx)
    assert tuple(cut[60, 90]) == (255, 255, 255) and tuple(cut[60, 30]) != (255, 255, 255)


def test_lines_are_thin_and_coloured(ctx, icosphere):
    v, f = icosphere
    seg = np.array([[[-6.0, 0.0, 10.5], [6.0, 0.0, 10.5]]])
    img = figure.render_nodes(v, f, [], size=(100, 100), view=FRONT, lines=[(seg, GREEN)],
                              line_width_px=2.0, ctx=ctx)
    rows, cols = np.nonzero(_greenness(img) > 60)
    assert cols.max() - cols.min() > 30, "the segment spans the picture"
    assert np.ptp(rows) <= 3, "the segment is thin"


@pytest.mark.parametrize("view", [
    figure.View(), figure.View(0.0, 90.0), figure.View(45.0, -90.0, 50.0),
    figure.View(200.0, 35.0, 20.0, up=(0.0, 0.0, 1.0)),
])
def test_camera_fits_the_mesh(view):
    v = np.asarray(trimesh.creation.box(extents=(30.0, 10.0, 5.0)).vertices) + 100.0
    px = figure.camera(v, view, (200, 100)).project(v)
    assert np.all(px >= 0.0) and np.all(px[:, 0] <= 200.0) and np.all(px[:, 1] <= 100.0)
    ndc = np.abs(px / [100.0, 50.0] - 1.0)
    assert ndc.max() > 0.9, "tight fit: some vertex lies near the border"


def test_gl_state_restored(bctx, icosphere, lattice):
    v, f = icosphere
    previous = bctx.fbo if bctx.fbo is not None else bctx.detect_framebuffer(0)
    rb = bctx.renderbuffer((17, 9))
    mine = bctx.framebuffer(color_attachments=[rb])
    try:
        mine.use()
        figure.render_nodes(v, f, [(lattice, BLUE)], size=(64, 64), ctx=bctx,
                            lines=[(np.stack([lattice[:5], lattice[5:10]], 1), GREEN)],
                            clip=((0.0, 0.0, 1.0), 0.0))
        assert bctx.error == "GL_NO_ERROR"
        assert bctx.fbo is mine
        assert bctx.detect_framebuffer().glo == mine.glo, "the caller's framebuffer is bound in GL"
        assert tuple(mine.viewport) == (0, 0, 17, 9)
    finally:
        previous.use()
        mine.release()
        rb.release()


@pytest.mark.parametrize("change, match", [
    ({"vertices": np.zeros((4, 2))}, "vertices"),
    ({"vertices": np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]])}, "non-finite"),
    ({"faces": np.zeros((0, 3), int)}, "empty mesh"),
    ({"faces": np.array([[0, 1, 3]])}, "indices"),
    ({"faces": np.array([[0.0, 1.5, 2.0]])}, "integer"),
    ({"faces": np.array([[0, 0, 1]])}, "degenerate"),
    ({"points": [(np.zeros((3, 2)), RED)]}, "points"),
    ({"points": [(np.array([[0.0, np.inf, 0.0]]), RED)]}, "non-finite"),
    ({"points": [(np.zeros((1, 3)), (255, 0, 0))]}, "colour"),
    ({"points": np.zeros((3, 3))}, "sequence"),
    ({"lines": [(np.zeros((2, 3)), RED)]}, "lines"),
    ({"size": (0, 10)}, "size"),
    ({"mesh_alpha": 1.5}, "mesh_alpha"),
    ({"point_size_px": -1.0}, "point_size_px"),
    ({"clip": ((0.0, 0.0, 0.0), 1.0)}, "clip"),
    ({"clip": [((1.0, 0.0, 0.0), 0.0)] * 5}, "clip"),
    ({"view": figure.View(fov_deg=0.0)}, "fov"),
    ({"background": (1.0, 1.0)}, "background"),
    ({"vertices": np.ones((3, 3)), "faces": np.array([[0, 1, 2]])}, "degenerate"),
])
def test_bad_input(ctx, change, match):
    args = dict(vertices=np.eye(3), faces=np.array([[0, 1, 2]]), points=[(np.zeros((1, 3)), RED)])
    args.update(change)
    with pytest.raises(InputError, match=match):
        figure.render_nodes(ctx=ctx, **args)


def test_save_png(ctx, icosphere, lattice, tmp_path):
    from PIL import Image

    v, f = icosphere
    pts = [(v, RED), (lattice, BLUE)]
    path = figure.save_nodes_png(tmp_path / "sub" / "nodes.png", v, f, pts, size=(64, 48))
    assert path == tmp_path / "sub" / "nodes.png"
    with Image.open(path) as im:
        assert im.size == (64, 48) and im.mode == "RGB"
        data = np.asarray(im)
    np.testing.assert_array_equal(data, figure.render_nodes(v, f, pts, size=(64, 48), ctx=ctx))
