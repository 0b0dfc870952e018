"""Interactive editing on the tetrahedral grid (glsldiff.render.backends.tetrahedral): edits update the P1
system and the GPU multigrid's finest level in place; frames converge to the from-scratch
answer; undo gives back the first image; the kept hierarchy's iteration counts stay bounded."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from glsldiff.physics.editing import NO_SURFACE, Brush, Edit
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import parse_scene
from glsldiff.system.problem import relative_l2

TOL = 1e-6


@pytest.fixture(scope="module")
def scene():
    return parse_scene({"mesh": {"source": "sphere", "size_mm": 30.0},
                        "polygrid": {"n": 2, "cubes": 1500},
                        "material": {"preset": "marble"},
                        "lights": [{"type": "directional", "direction": [0.3, 0.4, 1.0], "irradiance": [1, 1, 1]}],
                        "options": {"tol": TOL},
                        "output": {"width": 96, "height": 96}})


def _dabs(r: Renderer, scene, n: int, prop: str = "mu", factor: float = 2.5) -> None:
    view = r.edit_view(scene)
    ys, xs = np.nonzero(view.surface < NO_SURFACE)
    cu, cv = float(xs.mean()), float(ys.mean())
    for i, du in enumerate(np.linspace(-12.0, 12.0, n)):
        r.edit(Edit(prop, "multiply", factor, brush=Brush((cu + du, cv), 10.0, 0.4), depth=(-1.0, 2.0), strength=0.5),
               view, history=i == 0)
        r.render(scene)


def _converge(r: Renderer, scene, frames: int = 60):
    img = None
    for _ in range(frames):
        img, _ = r.render(scene)
        if r.converged:
            return img
    raise AssertionError(f"not converged after {frames} frames")


def _rel(a, b) -> float:
    return relative_l2(a, b, b.sum(axis=-1) > 0)


def test_stroke_converges_to_a_cold_render_and_undo_returns(scene, tmp_path):
    with Renderer(frame_sweeps=10, cache_solutions=False, allow_unconverged=True) as r:
        first, _ = r.render(scene)
        solver = r.pass2_solver
        _dabs(r, scene, 4)
        assert not r.converged                     # painting frames stop at their budget
        edited = _converge(r, scene)
        assert r.pass2_solver is solver            # the multigrid was kept across the edits
        assert r.fem_system is not None
        assert _rel(edited, first) > 1e-3          # the stroke shows
        path = r.save_material(tmp_path / "edited.npz")
        kappa, mu = (x.copy() for x in r.node_material)
        assert r.undo()
        back = _converge(r, scene)
        assert _rel(back, first) < 1e-4
    mat = dataclasses.replace(scene.material, nodes=str(path), preset=None, procedural=None)
    with Renderer(frame_sweeps=10, cache_solutions=False) as cold:
        ref, _ = cold.render(dataclasses.replace(scene, material=mat))
        k2, m2 = cold.node_material
        np.testing.assert_allclose(k2, kappa, rtol=1e-12)
        np.testing.assert_allclose(m2, mu, rtol=1e-12)
    assert _rel(edited, ref) < 1e-4


def test_kept_hierarchy_iterations_stay_bounded(scene):
    """Ten strokes of kappa and mu edits, each solved to tol: the stale hierarchy needs at most
    a few more conjugate-gradient iterations than a fresh one."""
    with Renderer(cache_solutions=False) as r:
        _, rep = r.render(scene)
        cold = rep.solver.sweeps
        solver = r.pass2_solver
        counts = []
        for k in range(10):
            _dabs(r, scene, 2, prop="kappa" if k % 2 else "mu", factor=0.6 if k % 2 else 1.8)
            _, rep = r.render(scene)
            counts.append(rep.solver.sweeps)
            assert rep.solver.converged
        assert r.pass2_solver is solver
    assert max(counts) <= cold + 3, (cold, counts)


def test_interactive_first_frame_from_the_cache_prepares_the_solver(scene, tmp_path, monkeypatch):
    """With the disk cache on, an interactive renderer serves a cached answer and still builds
    its multigrid at once (the first edit costs a frame); a second renderer reads the
    aggregation and damping back (no pyamg) and solves the same edit to the same image."""
    monkeypatch.setenv("GLSLDIFF_CACHE", str(tmp_path))
    images, solvers = [], []
    for _ in range(2):
        with Renderer(frame_sweeps=10, allow_unconverged=True) as r:
            r.render(scene)
            s = r.pass2_solver
            assert s is not None
            solvers.append((s.setup_seconds["pyamg"], s.omegas, [lv.n for lv in s.levels]))
            _dabs(r, scene, 2)
            images.append(_converge(r, scene))
    assert list(tmp_path.glob("multigrid-*"))
    (t1, w1, n1), (t2, w2, n2) = solvers
    assert n1 == n2 and np.allclose(w1[:-1], w2[:-1], rtol=0, atol=0)
    assert t2 < 0.1 * t1
    assert _rel(images[1], images[0]) < 1e-4


def test_the_right_hand_side_follows_every_new_source(scene):
    """Light after light (and incidence modes that replace the load), the P1 system's right-hand
    side is the current source's: a stale one (kept by an id that a new array reused) would
    solve the previous light silently."""
    from glsldiff.oracle.fem import tet_rhs
    from glsldiff.physics.lights import DirectionalLight
    with Renderer(cache_solutions=False) as r:
        for k, d in enumerate([(0.3, 0.4, 1.0), (-0.5, 0.2, 1.0), (0.0, -0.6, 1.0), (0.3, 0.4, 1.0)]):
            s = dataclasses.replace(scene, lights=(DirectionalLight(np.array(d) / np.linalg.norm(d), (1.0, 1.0, 1.0)),),
                                    options=dataclasses.replace(scene.options, incidence="transport" if k % 2 else "marshak",
                                                                model="diffusion"))
            r.render(s)
            b = tet_rhs(r.fem_problem(s)).T.reshape(-1)
            np.testing.assert_allclose(r.fem_system.b, b, rtol=1e-12, atol=0)
            assert r.pass2_solver is None or np.allclose(r.pass2_solver.system.b, b, rtol=1e-12)


def test_converging_frames_keep_the_split_static_terms(scene):
    """Frames that only change the fluence reuse the split's fluence-independent terms (the
    same SplitStatic object frame after frame) and shade the same image as terms made afresh."""
    from glsldiff.render.terms import SurfaceTerms
    opts = dataclasses.replace(scene.options, source="surface")      # the split's surface far field
    sc = dataclasses.replace(scene, options=opts)
    with Renderer(frame_sweeps=10, cache_solutions=False, allow_unconverged=True) as r:
        r.render(sc)
        _dabs(r, sc, 2)
        kept = r._terms.split_result.static
        assert kept is not None
        img = _converge(r, sc)
        assert r._terms.split_result.static is kept           # converging frames: only the fluence changed
        r._terms = SurfaceTerms(r.ctx)                         # every pass-3 term afresh, same solution
        again, rep = r.render(sc)
        assert not rep.ran("pass2") and r._terms.split_result.static is not kept
        assert _rel(img, again) < 1e-9


def test_camera_moves_keep_the_view_independent_terms(scene):
    """A camera move of the marching split keeps the vertex terms (material and beams at the
    vertices), the march's medium and beams and the shader's GL objects, and its image equals
    the same camera's with every pass-3 term and the shader made afresh; the regime notes stay."""
    from glsldiff.render.shading import Shader
    from glsldiff.render.terms import SurfaceTerms
    sc = dataclasses.replace(scene, options=dataclasses.replace(scene.options, single_scattering=True))
    with Renderer(frame_sweeps=10, cache_solutions=False, allow_unconverged=True) as r:
        _converge(r, sc)
        eye = np.array([60.0, 25.0, 70.0])
        kept = None
        for turn in (0.0, 0.3, 0.6):
            c, s_ = np.cos(turn), np.sin(turn)
            moved = dataclasses.replace(sc, camera=dataclasses.replace(
                sc.camera, position=(c * eye[0] + s_ * eye[2], eye[1], -s_ * eye[0] + c * eye[2]), target=(0, 0, 0)))
            img, rep = r.render(moved)
            assert not rep.ran("pass1") and not rep.ran("pass2")
            vt = r._terms._kept["split vertex terms"]
            assert kept is None or vt is kept                   # one VertexTerms across the moves
            kept = vt
        r._terms, r._shader = SurfaceTerms(r.ctx), Shader(r.ctx)
        again, rep2 = r.render(moved)
        assert r._terms._kept["split vertex terms"] is not kept
        np.testing.assert_array_equal(again, img)
        assert rep2.warnings == rep.warnings
        assert [n for n in rep2.notes if n.startswith("regime")] == [n for n in rep.notes if n.startswith("regime")]


def test_painting_frames_repaint_the_split_where_the_brush_went(scene, monkeypatch):
    """A painting frame recomputes the split's half-space terms only at the vertices the brush
    changed (split_repaint), and its radiance equals every term made afresh."""
    from glsldiff.render.terms import SurfaceTerms
    opts = dataclasses.replace(scene.options, source="surface")
    sc = dataclasses.replace(scene, options=opts)
    original, seen = SurfaceTerms._split, []

    def checked(self, f, static=None, painted=None):
        out = original(self, f, static, painted)
        if painted is not None:
            fresh = original(self, f)
            seen.append(float(np.abs(out.radiance - fresh.radiance).max() / fresh.radiance.max()))
        return out

    monkeypatch.setattr(SurfaceTerms, "_split", checked)
    with Renderer(frame_sweeps=10, cache_solutions=False, allow_unconverged=True) as r:
        r.render(sc)
        _dabs(r, sc, 4)
    assert len(seen) >= 3 and max(seen) < 1e-12, seen


def test_stalled_frames_remake_the_coarse_levels_and_still_converge_to_the_cold_render(scene, tmp_path,
                                                                                      monkeypatch):
    """When converging frames stall (the residual after STALL_FRAMES frames above STALL_RATIO of
    the first's; forced here with a ratio of 0), the coarse levels are remade once from the
    edited matrices with the kept aggregation and damping, and the frames still converge to a
    cold render of the edited material; a gentle stroke at the real ratio remakes nothing."""
    import glsldiff.render.backends.tetrahedral as tb
    with Renderer(frame_sweeps=10, cache_solutions=False, allow_unconverged=True) as r:
        r.render(scene)
        _dabs(r, scene, 4, factor=2.5)
        _converge(r, scene)
        assert r._be.pass2.refreshes == 0
        monkeypatch.setattr(tb, "STALL_RATIO", 0.0)
        _dabs(r, scene, 4, factor=10.0)
        edited = _converge(r, scene)
        assert r._be.pass2.refreshes == 1
        path = r.save_material(tmp_path / "edited.npz")
    mat = dataclasses.replace(scene.material, nodes=str(path), preset=None, procedural=None)
    with Renderer(frame_sweeps=10, cache_solutions=False) as cold:
        ref, _ = cold.render(dataclasses.replace(scene, material=mat))
    assert _rel(edited, ref) < 1e-4


def _march_scenes(scene):
    """The scene with the 3-D march (surface far field), it with the camera moved, and that with
    the light turned."""
    opts = dataclasses.replace(scene.options, source="surface", single_scattering=True)
    sc = dataclasses.replace(scene, options=opts)
    moved = dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, position=(40.0, 25.0, 70.0)))
    relit = dataclasses.replace(moved, lights=(dataclasses.replace(sc.lights[0], direction=(-0.5, 0.2, 0.8)),))
    return sc, moved, relit


def test_march_frames_keep_the_lights_maps_and_equal_fresh_renders(scene):
    """With the 3-D march, a camera move keeps the lights' depth maps and the medium lattice
    (the same objects) and shades what a fresh renderer shades at the new camera; a light
    change makes new maps (a kept map would shade the old light); its pass 2 starts from the
    last solution, so it equals the fresh render to the solver's tolerance."""
    sc, moved, relit = _march_scenes(scene)
    with Renderer(cache_solutions=False) as r:
        r.render(sc)
        beams, medium = r._terms._kept["march beams"], r._terms._kept["march medium"]
        img_moved, rep = r.render(moved)
        assert not rep.ran("pass2")
        assert r._terms._kept["march beams"] is beams and r._terms._kept["march medium"] is medium
        img_relit, _ = r.render(relit)
        assert r._terms._kept["march beams"] is not beams and r._terms._kept["march medium"] is medium
    for s, img, tol in ((moved, img_moved, 1e-9), (relit, img_relit, 10 * TOL)):
        with Renderer(cache_solutions=False) as fresh:
            ref, _ = fresh.render(s)
        assert _rel(img, ref) < tol


def test_a_frame_renders_each_lights_map_once(scene, monkeypatch):
    """Pass 1, the shading visibility and the 3-D march share one shadow map per light (the
    march adds its faces): one depth render and one face render per light change, none for a
    camera move; the map of a light no longer in the scene is dropped."""
    from glsldiff.render.shadows import DepthRenderer
    calls = {"depth": 0, "faces": 0}
    render, faces = DepthRenderer.render, DepthRenderer._render_faces

    def counted_render(self, *a, **k):
        calls["depth"] += 1
        return render(self, *a, **k)

    def counted_faces(self, *a, **k):
        calls["faces"] += 1
        return faces(self, *a, **k)
    monkeypatch.setattr(DepthRenderer, "render", counted_render)
    monkeypatch.setattr(DepthRenderer, "_render_faces", counted_faces)
    sc, moved, relit = _march_scenes(scene)
    with Renderer(cache_solutions=False) as r:
        r.render(sc)
        assert calls == {"depth": 1, "faces": 1}
        r.render(moved)
        assert calls == {"depth": 1, "faces": 1}
        r.render(relit)
        assert calls == {"depth": 2, "faces": 2}
        assert len(r._depth._kept) == 1
