"""Material editing (Wang et al. 2008 sec. 5.4): the GLSL pass of glsldiff.render.editing against
its numpy twin glsldiff.physics.editing, operation by operation, on a packed polygrid level;
the block-volume command; the renderer's edit/undo/redo and saved volumes."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.core.camera import look_at, perspective
from glsldiff.core.errors import InputError
from glsldiff.grids.polygrid import box_polygrid
from glsldiff.physics.editing import (Brush, Edit, EditView, apply_edit, block_positions, block_view,
                                      edit_weights)
from glsldiff.render.editing import GpuMaterialEditor
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.system.problem import DiffusionProblem


def _level(ctx):
    pg = box_polygrid((2, 2, 1), 8, 10.0)            # 20 x 20 x 10 mm
    p = pg.positions.reshape(pg.shape + (3,))
    u = (p - pg.positions.min(0)) / np.ptp(pg.positions, axis=0)
    kappa = np.stack([0.3 + 0.1 * u[..., 0], 0.25 + 0.1 * u[..., 1], 0.2 + 0.05 * u[..., 2]], axis=-1)
    mu = 0.01 + 0.02 * u
    prob = DiffusionProblem(pg, kappa, mu, np.ones((pg.n_boundary, 3)), stencil="conservative")
    return pg, GlslDiffusion(prob, ctx)


def _camera_view(pg, size=(64, 48), surface=None):
    centre = 0.5 * (pg.positions.min(0) + pg.positions.max(0))
    eye = centre + np.array([8.0, 12.0, 60.0])
    mvp = perspective(35.0, size[0] / size[1], 10.0, 120.0) @ look_at(eye, centre, np.array([0.0, 1.0, 0.0]))
    return EditView(mvp, size, eye, surface=surface)


def _mask(h=17, w=23):
    y, x = np.mgrid[0:h, 0:w]
    return np.clip(0.2 + np.sin(0.7 * x) * np.cos(0.5 * y), 0.0, 1.0).astype(np.float32)   # zero in places


EDITS = {
    "set kappa, brush": lambda v: Edit("kappa", "set", (0.9, 0.8, 0.7), brush=Brush((30.0, 22.0), 14.0, 0.5)),
    "multiply mu, mask": lambda v: Edit("mu", "multiply", 3.0, mask=_mask()),
    "add mu, brush + mask + strength": lambda v: Edit("mu", "add", (0.05, 0.0, 0.02), brush=Brush((20.0, 30.0), 25.0),
                                                      mask=_mask(5, 9), strength=0.6),
    "multiply kappa, depth": lambda v: Edit("kappa", "multiply", 0.25, depth=(2.05, 6.05)),
    "add mu everywhere": lambda v: Edit("mu", "add", -0.02),     # clamps at 0
}


@pytest.mark.parametrize("name", list(EDITS))
def test_gpu_edit_matches_numpy(ctx, name):
    pg, lv = _level(ctx)
    view = _camera_view(pg)
    # a visible-surface distance image with an empty border (no surface: no depth there)
    surf = np.full((48, 64), 1e30, np.float32)
    surf[4:44, 6:60] = 55.0 + 0.1 * np.arange(6, 60)[None, :]
    view = _camera_view(pg, surface=surf)
    edit = EDITS[name](view)
    k0, m0 = lv.problem.kappa.copy(), lv.problem.mu.copy()
    with lv, GpuMaterialEditor(lv, pg.positions) as ed:
        ed.apply(edit, view)
        k_gpu, m_gpu = ed.read()
    k_np, m_np, res = apply_edit(edit, k0, m0, pg.positions, view, pg.active.reshape(-1))
    act = pg.active
    assert res.edited > 50                                   # the edit reached nodes ...
    assert res.edited < act.sum() or not edit.restricted     # ... and a restricted one not all
    np.testing.assert_allclose(k_gpu[act], k_np[act], rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(m_gpu[act], m_np[act], rtol=2e-6, atol=1e-7)
    changed = np.any((k_np != k0) | (m_np != m0), axis=-1)[act]
    assert changed.sum() == res.edited or edit.op == "add" and res.clamped


def test_depth_window_uses_the_visible_surface():
    """A node's depth is its ray distance minus the surface image's: with a surface 50 mm from
    the eye, a window 1..3 mm selects the nodes 51..53 mm from it."""
    pg = box_polygrid((1, 1, 1), 6, 6.0)
    eye = np.array([3.0, 3.0, 80.0])
    mvp = perspective(20.0, 1.0, 1.0, 200.0) @ look_at(eye, np.array([3.0, 3.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    view = EditView(mvp, (32, 32), eye, surface=np.full((32, 32), 76.0, np.float32))
    w = edit_weights(Edit("mu", "set", 1.0, depth=(1.0, 3.0)), view, pg.positions)
    d = np.linalg.norm(pg.positions - eye, axis=1) - 76.0
    assert np.array_equal(w > 0, (d >= 1.0) & (d <= 3.0))
    assert (w > 0).any() and not (w > 0).all()


def test_block_view_maps_voxels_to_pixels():
    pos = block_positions((3, 4, 5), 0.5)
    v = block_view((3, 4, 5), 0.5)
    uv, front = v.pixels(pos)
    assert front.all()
    np.testing.assert_allclose(uv[:5], [[0.5, 0.5], [1.5, 0.5], [2.5, 0.5], [3.5, 0.5], [4.5, 0.5]])
    np.testing.assert_allclose(v.distance(pos)[::20], [0.0, 0.5, 1.0])


@pytest.mark.parametrize("bad", [dict(prop="sigma"), dict(op="divide"), dict(value=(1, 2)),
                                 dict(op="set", prop="kappa", value=0.0), dict(op="multiply", value=-1.0),
                                 dict(depth=(2.0, 1.0)), dict(strength=1.5)])
def test_bad_edits_are_input_errors(bad):
    args = dict(prop="mu", op="set", value=0.1) | bad
    with pytest.raises(InputError):
        Edit(**args)


# ---------------------------------------------------------------- the renderer's edits
def _lattice_scene(**kw):
    import dataclasses

    from glsldiff.physics.lights import DirectionalLight
    from glsldiff.render.scene import MeshSpec, OutputSpec, PolygridSpec, Scene, SpecularSpec
    base = Scene(mesh=MeshSpec("sphere", 20.0), polygrid=PolygridSpec(6, 8, 2, "conservative"),
                 lights=(DirectionalLight((0.0, 0.3, 1.0), (1.0, 1.0, 1.0)),),
                 output=OutputSpec(64, 64), specular=SpecularSpec(0.0, 0.2))
    return dataclasses.replace(base, **kw)


@pytest.mark.parametrize("discretisation", ["conservative", "fem"])
def test_renderer_edit_undo_redo_and_save(_default_context, tmp_path, discretisation):
    """A brush edit on the GPU (lattice) or in numpy (tetrahedra) darkens the image under the
    brush, the next frame is warm-started, undo gives back the first image, redo the edited
    one, and the saved node material renders the edited image again."""
    import dataclasses

    from glsldiff.render.renderer import Renderer
    from glsldiff.render.scene import PolygridSpec
    grid = PolygridSpec(6, 8, 2, "conservative") if discretisation == "conservative" else PolygridSpec(2, 2000, 1, "fem")
    scene = _lattice_scene(polygrid=grid)
    with Renderer(_default_context, cache_solutions=False) as r:    # solved here: the edit re-uses the solver
        img0, rep0 = r.render(scene)
        solver = r.pass2_solver
        view = r.edit_view(scene)
        assert view.surface.shape == (64, 64) and (view.surface < 1e29).mean() > 0.2
        res = r.edit(Edit("mu", "multiply", 20.0, brush=Brush((22.0, 32.0), 9.0, 0.3), depth=(-1.0, 4.0)), view)
        assert res.edited > 10
        img1, rep1 = r.render(scene)
        why = [p for p in rep1.passes if p["pass"] == "pass2"][0]["why"]
        assert "material edited" in why or discretisation == "fem"
        if discretisation == "fem":     # updated in place, the hierarchy kept (stale), warm: no more cycles than cold
            assert r.pass2_solver is solver and rep1.solver.sweeps <= rep0.solver.sweeps
        lum0, lum1 = img0.mean(-1), img1.mean(-1)
        under = lum0[28:37, 18:27].mean()
        assert lum1[28:37, 18:27].mean() < 0.8 * under          # darker under the brush
        far = lum0[26:38, 44:52]
        assert abs(lum1[26:38, 44:52].mean() - far.mean()) < 0.05 * far.mean()   # the far side hardly changes
        assert r.edit_counts == (1, 0)
        assert r.undo() and not r.undo()
        img2, _ = r.render(scene)
        np.testing.assert_allclose(img2, img0, rtol=0, atol=3e-3 * img0.max())
        assert r.redo() and r.edit_counts == (1, 0)
        img3, _ = r.render(scene)
        np.testing.assert_allclose(img3, img1, rtol=0, atol=3e-3 * img0.max())
        saved = r.save_material(tmp_path / "edited.npz")
    mat = dataclasses.replace(scene.material, nodes=str(saved), preset=None)
    with Renderer(_default_context) as r2:
        img4, rep4 = r2.render(dataclasses.replace(scene, material=mat))
    assert "nodes edited.npz" in " ".join(rep4.notes)
    np.testing.assert_allclose(img4, img1, rtol=0, atol=3e-3 * img0.max())


# ---------------------------------------------------------------- glsldiff edit
def _cli(*argv):
    from glsldiff.commands.cli import main
    return main([str(a) for a in argv])


def test_edit_command_block_volume_mask_depth_brush(tmp_path, capsys):
    """``glsldiff edit`` = the numpy edit on the block's voxels; the output keeps the input's other
    arrays, reads back as a scene volume (h_mm) and as ``glsldiff fit --truth``."""
    from PIL import Image

    from glsldiff.commands.inverse import _load_truth
    from glsldiff.render.scene import block_volume
    from glsldiff.core.io import read_mask
    rng = np.random.default_rng(1)
    kappa = rng.uniform(0.2, 0.4, (6, 10, 12, 3))
    mu = rng.uniform(0.005, 0.02, (6, 10, 12, 3))
    np.savez(tmp_path / "fit.npz", kappa=kappa, mu=mu, h=0.5, method="lbfgs")     # as glsldiff fit writes it
    mask = (np.arange(12)[None, :] * 20 + np.arange(10)[:, None] * 5).astype(np.uint8)
    Image.fromarray(mask).save(tmp_path / "pattern.png")
    rc = _cli("edit", tmp_path / "fit.npz", "--multiply", "mu", 2, "--mask", tmp_path / "pattern.png",
              "--depth", "0.5:1.5", "--brush", 3.0, 2.5, 2.0, "-o", tmp_path / "out.npz")
    assert rc == 0
    line = capsys.readouterr().out
    assert "voxels edited" in line or "nodes edited" in line
    k2, m2, h = block_volume(tmp_path / "out.npz", "edited")
    assert h == 0.5 and np.array_equal(k2, kappa)
    edit = Edit("mu", "multiply", 2.0, brush=Brush((3.0 / 0.5 + 0.5, 2.5 / 0.5 + 0.5), 4.0, 0.25),
                mask=read_mask(tmp_path / "pattern.png"), depth=(0.5, 1.5))
    _, m_ref, res = apply_edit(edit, kappa.reshape(-1, 3), mu.reshape(-1, 3), block_positions(kappa.shape, 0.5),
                               block_view(kappa.shape, 0.5))
    np.testing.assert_array_equal(m2, m_ref.reshape(mu.shape))
    changed = np.any(m2 != mu, axis=-1)
    assert 0 < changed.sum() <= res.edited      # (a weight of 1e-17 changes no float64)
    assert set(np.nonzero(changed)[0]) <= {1, 2, 3}                 # depth 0.5..1.5 mm = slices 1..3
    d = _load_truth(str(tmp_path / "out.npz"), (6, 10, 12))
    assert str(d["method"]) == "lbfgs" and "multiply mu 2" in str(d["edit_log"][-1])


def test_edit_command_node_material_and_bad_input(tmp_path, capsys):
    n = 50
    np.savez(tmp_path / "nodes.npz", kappa=np.full((n, 3), 0.3), mu=np.full((n, 3), 0.01),
             positions_mm=np.random.default_rng(0).normal(size=(n, 3)))
    assert _cli("edit", tmp_path / "nodes.npz", "--set", "kappa", 0.1, 0.2, 0.3, "-o", tmp_path / "o.npz") == 0
    z = np.load(tmp_path / "o.npz")
    np.testing.assert_allclose(z["kappa"], np.tile([0.1, 0.2, 0.3], (n, 1)))
    capsys.readouterr()
    bad = [("--multiply", "sigma", "2"), ("--multiply", "mu", "2", "--mask", "x.png"),
           ("--add", "mu", "1", "2"), ("--set", "kappa", "-1")]
    for args in bad:
        assert _cli("edit", tmp_path / "nodes.npz", *args, "-o", tmp_path / "p.npz") == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("glsldiff: error:"), err
    assert _cli("edit", tmp_path / "nodes.npz", "--add", "mu", "1", "-o", tmp_path / "nodes.npz") == 2
    assert _cli("edit", tmp_path / "missing.npz", "--add", "mu", "1", "-o", tmp_path / "q.npz") == 2


def test_scene_nodes_material_is_checked(tmp_path):
    from glsldiff.render.scene import parse_scene
    np.savez(tmp_path / "ok.npz", kappa=np.full((4, 3), 0.3), mu=np.zeros((4, 3)), positions_mm=np.zeros((4, 3)))
    np.savez(tmp_path / "bad.npz", kappa=np.full((4, 3), -0.3), mu=np.zeros((4, 3)), positions_mm=np.zeros((4, 3)))
    np.savez(tmp_path / "block.npz", kappa=np.ones((2, 3, 3, 3)), mu=np.zeros((2, 3, 3, 3)), h=1.0)
    light = [{"type": "directional", "direction": [0, 0, 1]}]
    s = parse_scene({"mesh": {"source": "sphere"}, "material": {"nodes": "ok.npz"}, "lights": light}, "t.toml", tmp_path)
    assert s.material.nodes == "ok.npz"
    s = parse_scene({"mesh": {"source": "torus"}, "material": {"volume": "block.npz"}, "lights": light}, "t.toml",
                    tmp_path)
    assert s.material.volume == "block.npz"       # a block with "h" (as glsldiff fit writes it) is read
    for mat, why in [({"nodes": "bad.npz"}, "kappa must be"), ({"nodes": "ok.npz", "preset": "marble"}, "leave out"),
                     ({"nodes": "ok.npz", "volume": "block.npz"}, "not both"), ({"nodes": "none.npz"}, "does not exist")]:
        with pytest.raises(InputError, match=why):
            parse_scene({"mesh": {"source": "sphere"}, "material": mat, "lights": light}, "t.toml", tmp_path)
