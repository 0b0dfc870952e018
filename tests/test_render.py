"""Three-pass rendering: passes against their CPU formulas, skipping, output files."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from glsldiff.core import io
from glsldiff.core.errors import InputError
from glsldiff.physics.lights import DirectionalLight, EnvironmentLight, PointLight, ProjectorLight, SpotLight
from glsldiff.physics.optics import boundary_constant, fdr
from glsldiff.physics.exitance import exitant_bracket, source_from_irradiance
from glsldiff.render.output import check_output, save
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import CameraSpec, MeshSpec, OutputSpec, PolygridSpec, Scene, SpecularSpec

pytestmark = pytest.mark.usefixtures("ctx")


def _scene(**kw) -> Scene:
    base = Scene(mesh=MeshSpec("sphere", 20.0), polygrid=PolygridSpec(6, 8, 2, "conservative"),   # the lattice
                 lights=(DirectionalLight((0.0, 0.0, 1.0), (1.0, 1.0, 1.0)),),
                 output=OutputSpec(48, 48), specular=SpecularSpec(0.0, 0.2))
    return dataclasses.replace(base, **kw)


@pytest.fixture(scope="module")
def renderer(_default_context):
    with Renderer(_default_context) as r:
        yield r


def test_moved_camera_skips_passes_1_and_2(renderer):
    s1 = _scene()
    img1, rep1 = renderer.render(s1)
    assert rep1.ran("setup") and rep1.ran("pass1") and rep1.ran("pass2") and rep1.ran("pass3")
    s2 = dataclasses.replace(s1, camera=CameraSpec(position=(30.0, 10.0, 50.0), target=(0.0, 0.0, 0.0)))
    img2, rep2 = renderer.render(s2)
    assert not rep2.ran("setup") and not rep2.ran("pass1") and not rep2.ran("pass2") and rep2.ran("pass3")
    assert "t1" not in rep2.seconds and "t2" not in rep2.seconds
    assert not np.allclose(img1, img2)          # the camera did move
    # a light change re-runs pass 1 and warm-starts pass 2, without re-packing
    s3 = dataclasses.replace(s2, lights=(DirectionalLight((0.1, 0.0, 1.0), (1.0, 1.0, 1.0)),))
    _, rep3 = renderer.render(s3)
    assert not rep3.ran("setup") and not rep3.ran("material") and rep3.ran("pass1") and rep3.ran("pass2")
    assert "warm start" in [p for p in rep3.passes if p["pass"] == "pass2"][0]["why"]


def test_lit_sphere_is_bright_on_the_lit_side_and_translucent_on_the_other(renderer):
    img, rep = renderer.render(_scene(camera=CameraSpec(position=(60.0, 0.0, 0.0), target=(0.0, 0.0, 0.0),
                                                        up=(0.0, 1.0, 0.0))))
    lum = img.mean(axis=2)
    assert np.all(np.isfinite(img)) and img.min() >= 0.0
    h, w = lum.shape
    row = lum[h // 2]
    obj = np.flatnonzero(row > 0)
    assert obj.size > 10
    # light along +z: seen from +x, the lit side is image left (z+ points left for a camera on +x)
    left, right = row[obj[: obj.size // 4]].mean(), row[obj[-obj.size // 4:]].mean()
    assert left > 3.0 * right > 0.0, (left, right)     # diffusion carries light round to the unlit side
    assert rep.solver is not None and rep.solver.converged


def test_exitant_formulas_match_their_closed_forms():
    phi, q = np.array([[2.0, 1.0, 0.5]]), np.array([[1.0, 1.0, 1.0]])
    eta = 1.3
    C = float(boundary_constant(eta))
    np.testing.assert_allclose(exitant_bracket(phi, q, eta, "arbree"), ((1 + 1 / C) * phi - q / C) / (4 * np.pi))
    np.testing.assert_allclose(exitant_bracket(phi, q, eta, "paper"), (phi - q) / (2 * np.pi))
    # p1: [phi + 3 E.n] / (4 pi eta^2), E.n = (phi - q) / (2 C)
    np.testing.assert_allclose(exitant_bracket(phi, q, eta, "p1"), (phi + 3 * (phi - q) / (2 * C)) / (4 * np.pi * eta**2))
    E = np.array([[1.0, 2.0, 0.0]])
    np.testing.assert_allclose(source_from_irradiance(E, eta, "p1"), 4 * E / (1 - float(fdr(eta))))
    np.testing.assert_allclose(source_from_irradiance(E, eta, "paper"), E)


def test_output_path_is_checked_before_work_and_files_are_whole(tmp_path, renderer):
    for bad, match in ((tmp_path / "x.png", r"\.exr"), (tmp_path / "no" / "x.exr", "does not exist"),
                       (tmp_path, r"\.exr")):
        with pytest.raises(InputError, match=match):
            check_output(bad)
    (tmp_path / "d.exr").mkdir()
    with pytest.raises(InputError, match="folder"):
        check_output(tmp_path / "d.exr")
    scene = _scene()
    img, rep = renderer.render(scene)
    out = check_output(tmp_path / "r.exr")
    exr, png, exposure = save(img, out, scene, rep)
    back = io.read_exr(exr)
    np.testing.assert_allclose(back, img, rtol=1e-6)
    assert png.is_file() and exposure > 0
    assert not [p for p in Path(tmp_path).iterdir() if p.name.startswith(".")]   # no temporary left


def test_every_light_kind_single_scattering_and_procedural_materials(tmp_path, renderer):
    from glsldiff.render.scene import MaterialSpec, OptionsSpec

    env = np.zeros((16, 32, 3), np.float32)
    env[:8] = 0.2                                   # bright upper hemisphere
    io.write_exr(tmp_path / "env.exr", env)
    lights = (PointLight((0.0, 40.0, 40.0), (2000.0,) * 3),
              SpotLight((40.0, 0.0, 40.0), (-1.0, 0.0, -1.0), (2000.0,) * 3, cone_deg=20.0, falloff_deg=10.0),
              EnvironmentLight(io.read_exr(tmp_path / "env.exr")))
    base = dataclasses.replace(_scene(lights=lights, base_dir=tmp_path), specular=SpecularSpec(0.05, 0.2),
                               options=OptionsSpec(model="diffusion", single_scattering=False))
    off, rep_off = renderer.render(base)
    on, rep_on = renderer.render(dataclasses.replace(base, options=OptionsSpec(model="diffusion",
                                                                               single_scattering=True)))
    assert np.all(np.isfinite(on)) and on.min() >= 0.0
    assert not rep_on.ran("pass1") and not rep_on.ran("pass2")   # single scattering is part of pass 3
    assert np.all(on >= off - 1e-6) and on.sum() > off.sum()
    assert len([n for n in rep_off.notes if n.startswith("light:")]) == 3
    for kind in ("layers", "inclusions", "veins"):
        img, rep = renderer.render(dataclasses.replace(base, material=MaterialSpec(procedural=kind, seed=1)))
        assert rep.ran("material") and rep.ran("pass2") and not rep.ran("pass1")
        assert np.all(np.isfinite(img)) and img.max() > 0
    split, rep_split = renderer.render(dataclasses.replace(base, options=OptionsSpec()))   # the split: every light kind
    assert np.all(np.isfinite(split)) and split.min() >= 0.0 and split.sum() > 0.5 * off.sum()
    assert rep_split.model == "split (surface far field, single scattering 3-D march)"


@pytest.mark.parametrize("grid", [PolygridSpec(6, 8, 2, "conservative"), PolygridSpec(2, 300, 1, "fem")],
                         ids=["lattice", "fem"])
def test_block_volume_through_a_shell(tmp_path, renderer, grid):
    from glsldiff.physics.material import coefficients
    from glsldiff.render.scene import MaterialSpec

    sa = np.full((4, 8, 8, 3), 0.01)
    sa[:, :, 4:] = 0.5                               # half the block absorbs strongly
    kappa, mu = coefficients(sa, np.full_like(sa, 1.0))
    np.savez(tmp_path / "block.npz", kappa=kappa, mu=mu, h_mm=1.0)
    scene = _scene(material=MaterialSpec(preset=None, volume="block.npz", core="marble", sigma_a=None),
                   base_dir=tmp_path, polygrid=grid)
    img, rep = renderer.render(scene)
    assert any("via shell" in note for note in rep.notes) and np.all(np.isfinite(img)) and img.max() > 0
    np.savez(tmp_path / "bad.npz", kappa=kappa)
    with pytest.raises(InputError, match=r"\[material\].volume"):
        renderer.render(_scene(material=MaterialSpec(preset=None, volume="bad.npz"), base_dir=tmp_path))


def test_projector_lights_its_image_side_and_a_new_image_reruns_pass_1_only(tmp_path, renderer):
    from PIL import Image

    from glsldiff.render.scene import OptionsSpec

    half = np.zeros((16, 32, 3), np.uint8)
    half[:, :16] = 255                                 # white on the projector's left half
    Image.fromarray(half, "RGB").save(tmp_path / "left.png")
    io.write_exr(tmp_path / "right.exr", half[:, ::-1].astype(np.float32) / 255.0)
    # projector and camera on +z looking at the sphere: the projector's left is image left (-x)
    proj = ProjectorLight((0.0, 0.0, 60.0), (0.0, 0.0, -1.0), io.read_image(tmp_path / "left.png"), (4000.0,) * 3,
                          fov_deg=30.0)
    scene = _scene(lights=(proj,), base_dir=tmp_path, options=OptionsSpec(model="diffusion"),
                   camera=CameraSpec(position=(0.0, 0.0, 70.0), target=(0.0, 0.0, 0.0)))

    def halves(img, silhouette, margin):
        """Mean luminance of the object's left and right parts, ``margin`` columns off its middle."""
        lum = img.mean(axis=2)
        obj = silhouette.mean(axis=2) > 0
        cols = np.broadcast_to(np.arange(lum.shape[1]), lum.shape)
        mid = 0.5 * (cols[obj].min() + cols[obj].max())
        return lum[obj & (cols < mid - margin)].mean(), lum[obj & (cols > mid + margin)].mean()

    img, rep = renderer.render(scene)
    assert np.all(np.isfinite(img)) and img.min() >= 0.0
    left, right = halves(img, img, 2)
    assert left > 3.0 * right > 0.0, (left, right)     # lit half; diffusion carries some light across
    # pass 3: specular and single scattering (per-vertex image factor) stay on the lit side
    img2, rep2 = renderer.render(dataclasses.replace(scene, specular=SpecularSpec(0.05, 0.2),
                                                     options=OptionsSpec(single_scattering=True, model="diffusion")))
    assert not rep2.ran("pass1") and not rep2.ran("pass2")
    gain = halves(img2 - img, img, 4)                  # beyond the image edge's ramp (pixel + vertex)
    assert gain[0] > 0.01 * left and gain[1] == 0.0, gain
    # only the image changed: pass 1 runs again (pass 2 warm-started), no re-packing
    flipped = dataclasses.replace(scene, lights=(dataclasses.replace(proj, image=io.read_image(tmp_path / "right.exr")),))
    img3, rep3 = renderer.render(flipped)
    assert rep3.ran("pass1") and rep3.ran("pass2") and not rep3.ran("setup") and not rep3.ran("material")
    left3, right3 = halves(img3, img3, 2)
    assert right3 > 3.0 * left3 > 0.0, (left3, right3)
    np.testing.assert_allclose(img3, img[:, ::-1], rtol=0.05, atol=1e-3 * img.max())   # the mirror image


def test_diffuse_surface_reflectance_adds_rho_E_over_pi_in_pass_3_only(tmp_path, renderer):
    """``[material].reflectance``: the image gains rho/pi * E (Lambertian, incident irradiance
    without Fresnel) and changing only the reflectance re-runs pass 3 alone."""
    from glsldiff.render.scene import MaterialSpec

    cam = CameraSpec(position=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0))
    base = _scene(camera=cam)
    img0, _ = renderer.render(base)
    lit = dataclasses.replace(base, material=dataclasses.replace(base.material, reflectance=(0.2, 0.1, 0.0)))
    img1, rep = renderer.render(lit)
    assert [p["pass"] for p in rep.passes if p["ran"]] == ["pass3"]
    assert any("diffuse surface reflectance: (0.2, 0.1, 0.0)" in n for n in rep.notes)
    h, w = img0.shape[:2]
    c = (slice(h // 2 - 2, h // 2 + 2), slice(w // 2 - 2, w // 2 + 2))   # faces the light and the camera
    added = (img1[c] - img0[c]).reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(added, np.array([0.2, 0.1, 0.0]) / np.pi, rtol=0.03, atol=1e-6)

    # a measured map tiles over the block's face: one pixel per voxel (h_mm), here two halves
    from glsldiff.physics.material import coefficients

    kappa, mu = coefficients(np.full((4, 8, 8, 3), 0.01), np.full((4, 8, 8, 3), 1.0))
    np.savez(tmp_path / "block.npz", kappa=kappa, mu=mu, h_mm=2.5)
    rho = np.zeros((8, 8, 3), np.float32)
    rho[:, :4] = 0.3
    io.write_exr(tmp_path / "rho.exr", rho)
    mat = MaterialSpec(preset=None, volume="block.npz", core="marble", reflectance="rho.exr")
    img2, _ = renderer.render(_scene(camera=cam, material=mat, base_dir=tmp_path))
    none, _ = renderer.render(_scene(camera=cam, material=dataclasses.replace(mat, reflectance=None),
                                     base_dir=tmp_path))
    diff = (img2 - none).mean(axis=2)
    assert diff.min() >= -1e-6 and 0.0 < diff.max() <= 0.3 / np.pi * 1.05
    obj = diff[none.mean(axis=2) > 0]       # both halves of the map show (exact layout: test_shellmap)
    assert 0.2 < (obj > 0.5 * obj.max()).mean() < 0.9 and (obj < 0.3 * obj.max()).mean() > 0.1


def test_hard_edged_spot_light(renderer):
    """falloff = cone (allowed by scenes) is a hard edge in pass 1 and in the pass-3 shader
    (GLSL's smoothstep is undefined for equal edges)."""
    spot = SpotLight((0.0, 0.0, 60.0), (0.0, 0.0, -1.0), (4000.0,) * 3, cone_deg=6.0, falloff_deg=6.0)
    scene = _scene(lights=(spot,), camera=CameraSpec(position=(0.0, 0.0, 60.0), target=(0.0, 0.0, 0.0)),
                   specular=SpecularSpec(0.5, 0.3))
    img, _ = renderer.render(scene)
    flat, _ = renderer.render(dataclasses.replace(scene, specular=SpecularSpec(0.0, 0.3)))
    spec = (img - flat).mean(axis=2)
    assert np.all(np.isfinite(img)) and spec.min() >= -1e-6
    h, w = spec.shape
    assert spec[h // 2, w // 2] > 0.0          # the highlight under the cone ...
    assert spec[h // 2, w // 2 + w // 4 + 1] == 0.0  # ... none outside it (7.5 mm off axis: 8 deg > 6)


def test_report_says_how_deep_the_clamped_exitance_went():
    """The default scene at tol 1e-4 clamps 2069 vertices, an exact solve of the same system 54
    (measured): the count alone does not tell undershoot from solver tolerance; how many are
    deep does."""
    from glsldiff.render.report import RenderReport
    lines = "\n".join(RenderReport(clamped_vertices=2069, clamped_depth=0.19, clamped_deep=30).lines())
    assert "clamped to 0 at 2069 vertices: 30 from below -1 % of the largest (down to -0.19" in lines
    assert "2039 within 1 %" in lines
    assert "clamped" not in "\n".join(RenderReport().lines())
    split = "\n".join(RenderReport(model="split (surface far field)", clamped_vertices=3, clamped_deep=1).lines())
    assert "fluence clamped to 0 at 3 vertices: 1 from below -1 %" in split
