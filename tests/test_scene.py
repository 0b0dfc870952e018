"""Scene files: every field validated with a one-line error naming it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from glsldiff.core import io
from glsldiff.core.errors import InputError
from glsldiff.physics.lights import DirectionalLight, EnvironmentLight, ProjectorLight, SpotLight
from glsldiff.render.scene import LIGHT_KEYS, default_scene, load_scene, parse_scene

GOOD = """
[mesh]
source = "sphere"
size_mm = 20.0

[polygrid]
discretisation = "conservative"
n = 4
cubes = 8
levels = 2

[material]
preset = "skin1"

[[lights]]
type = "directional"
direction = [0, 1, 1]

[camera]
fov_deg = 40.0

[output]
width = 64
height = 48
"""


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


def test_good_scene_and_defaults(tmp_path):
    s = load_scene(_write(tmp_path, GOOD))
    assert s.mesh.source == "sphere" and s.mesh.size_mm == 20.0
    assert s.polygrid.n == 4 and s.polygrid.levels == 2
    assert s.material.preset == "skin1" and s.material.eta == 1.3
    assert isinstance(s.lights[0], DirectionalLight) and s.lights[0].irradiance == (1.0, 1.0, 1.0)
    np.testing.assert_allclose(s.lights[0].direction, np.array([0, 1, 1]) / np.sqrt(2), rtol=1e-15)
    assert (s.output.width, s.output.height) == (64, 48)
    assert s.options.scheme == "hierarchical" and s.options.exitant == "p1"
    d = default_scene()
    assert d.mesh.source == "bunny" and d.material.procedural == "veins" and d.lights
    assert (d.polygrid.discretisation, d.polygrid.n, d.polygrid.cubes, d.polygrid.levels) == ("fem", 2, 15000, 1)


@pytest.mark.parametrize("edit, field", [
    ('source = "sphere"', "[mesh].source"),                                        # replaced below: missing mesh file
    ('preset = "skin1"', "[material].preset"),                                     # unknown preset
    ("size_mm = 20.0", "[mesh].size_mm"),                                          # negative size
    ("n = 4", "[polygrid].n"),                                                     # odd n
    ("cubes = 8", "[polygrid].cubes"),                                             # over the node budget
    ("fov_deg = 40.0", "[camera].fov_deg"),                                        # out of range
    ("width = 64", "[output].width"),                                              # not an integer
    ('type = "directional"', "[lights.0].type"),                                   # unknown light
    ("direction = [0, 1, 1]", "[lights.0].direction"),                             # zero vector
])
def test_bad_fields_name_the_field(tmp_path, edit, field):
    bad = {'source = "sphere"': 'source = "no_such_mesh.obj"', 'preset = "skin1"': 'preset = "unobtainium"',
           "size_mm = 20.0": "size_mm = -5.0", "n = 4": "n = 5", "cubes = 8": "cubes = 2000000", "fov_deg = 40.0": "fov_deg = 200.0",
           "width = 64": 'width = "wide"', 'type = "directional"': 'type = "laser"',
           "direction = [0, 1, 1]": "direction = [0, 0, 0]"}[edit]
    with pytest.raises(InputError) as e:
        load_scene(_write(tmp_path, GOOD.replace(edit, bad)))
    msg = str(e.value)
    assert field in msg and "\n" not in msg, msg


def test_unreadable_environment_map_and_other_errors(tmp_path):
    (tmp_path / "env.exr").write_bytes(b"not an exr file")
    text = GOOD + '\n[[lights]]\ntype = "environment"\npath = "env.exr"\n'
    with pytest.raises(InputError, match=r"\[lights.1\].path.*not a readable OpenEXR"):
        load_scene(_write(tmp_path, text))
    with pytest.raises(InputError, match=r"\[lights.1\].path.*does not exist"):
        load_scene(_write(tmp_path, GOOD + '\n[[lights]]\ntype = "environment"\npath = "none.exr"\n'))
    with pytest.raises(InputError, match="unknown table"):
        load_scene(_write(tmp_path, GOOD + "\n[lighting]\nx = 1\n"))
    with pytest.raises(InputError, match=r"\[material\].colour.*unknown key"):
        load_scene(_write(tmp_path, GOOD.replace('preset = "skin1"', 'colour = "red"')))
    with pytest.raises(InputError, match="not valid TOML"):
        load_scene(_write(tmp_path, "[mesh\nsource="))
    with pytest.raises(InputError, match="does not exist"):
        load_scene(tmp_path / "missing.toml")
    with pytest.raises(InputError, match=r"\[mesh\]: missing"):
        parse_scene({})
    with pytest.raises(InputError, match="no light"):
        load_scene(_write(tmp_path, GOOD.split("[[lights]]")[0]))
    with pytest.raises(InputError, match=r"\[material\].sigma_s_prime"):
        load_scene(_write(tmp_path, GOOD.replace('preset = "skin1"', "sigma_a = [0.1, 0.1, 0.1]")))
    with pytest.raises(InputError, match=r"\[polygrid\].levels"):
        load_scene(_write(tmp_path, GOOD.replace("levels = 2", "levels = 4")))


def test_relative_paths_resolve_against_the_scene_folder(tmp_path):
    env = np.ones((8, 16, 3), np.float32)
    env[0] = 3.0
    io.write_exr(tmp_path / "env.exr", env)
    s = load_scene(_write(tmp_path, GOOD + '\n[[lights]]\ntype = "environment"\npath = "env.exr"\nscale = 0.5\n'))
    light = s.lights[1]
    assert isinstance(light, EnvironmentLight) and light.scale == 0.5 and light.visibility
    np.testing.assert_array_equal(light.image, env)          # read when the scene is parsed


def test_light_kinds_parse_into_the_physics_types(tmp_path):
    """Each [[lights]] table becomes the light type of its kind, with the scene's defaults;
    the keys a light table may have are unchanged, and a bad one is named."""
    text = GOOD + ('\n[[lights]]\ntype = "spot"\nposition = [0, 0, 50]\ndirection = [0, 0, -2]\ncone_deg = 20\n'
                   '\n[[lights]]\ntype = "point"\nposition = [1, 2, 3]\nshadows = false\n')
    s = load_scene(_write(tmp_path, text))
    spot, point = s.lights[1:]
    assert isinstance(spot, SpotLight) and spot.direction == (0.0, 0.0, -1.0)
    assert (spot.cone_deg, spot.falloff_deg, spot.intensity) == (20.0, 20.0, (1e4, 1e4, 1e4))
    assert point.position == (1.0, 2.0, 3.0) and not point.shadows
    assert set(LIGHT_KEYS) == {"type", "direction", "position", "irradiance", "intensity", "cone_deg",
                               "falloff_deg", "path", "scale", "shadows", "image", "up", "fov_deg", "size", "radiance",
                               "samples"}
    with pytest.raises(InputError, match=r"\[lights.1\].colour: unknown key; valid keys: cone_deg, direction"):
        load_scene(_write(tmp_path, text.replace("cone_deg = 20", "colour = 1")))
    from PIL import Image

    Image.fromarray(np.zeros((2, 2, 3), np.uint8), "RGB").save(tmp_path / "ok.png")
    tiny = GOOD + PROJECTOR.format(image="ok.png").replace("direction = [0, 0, -1]", "direction = [0, 0, -1e-14]")
    with pytest.raises(InputError, match=r"\[lights.1\].direction: ProjectorLight.direction .*non-zero"):
        load_scene(_write(tmp_path, tiny))                  # not zero, but too short for the light type


PROJECTOR = '\n[[lights]]\ntype = "projector"\nposition = [0, 0, 60]\ndirection = [0, 0, -1]\nimage = "{image}"\n'


def test_projector_light_parses_and_its_png_is_decoded_from_srgb(tmp_path):
    from PIL import Image

    rgb8 = np.array([[[255, 0, 0], [0, 128, 0]], [[0, 0, 10], [255, 255, 255]]], np.uint8)
    Image.fromarray(rgb8, "RGB").save(tmp_path / "pattern.png")
    s = load_scene(_write(tmp_path, GOOD + PROJECTOR.format(image="pattern.png")))
    lt = s.lights[1]
    assert isinstance(lt, ProjectorLight) and lt.up == (0.0, 1.0, 0.0) and lt.fov_deg == 30.0
    img = io.read_image(tmp_path / "pattern.png")
    np.testing.assert_array_equal(lt.image, img)
    c = rgb8 / 255.0                                          # sRGB decode, in RGB order
    np.testing.assert_allclose(img, np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4), rtol=1e-12)
    assert img[0, 0, 0] == 1.0 and img[0, 0, 1] == 0.0 and abs(img[0, 1, 1] - 0.2158605) < 1e-6
    # an OpenEXR image is taken as linear, with up and fov_deg given
    io.write_exr(tmp_path / "pattern.exr", np.full((3, 4, 3), 2.5, np.float32))
    s = load_scene(_write(tmp_path, GOOD + PROJECTOR.format(image="pattern.exr") + "up = [1, 0, 0]\nfov_deg = 50\n"))
    assert s.lights[1].up == (1.0, 0.0, 0.0) and s.lights[1].fov_deg == 50.0
    np.testing.assert_array_equal(s.lights[1].image, 2.5)


@pytest.mark.parametrize("extra, image, field, match", [
    ("", "none.png", "image", "projector image .* does not exist"),
    ("", "broken.png", "image", "not a readable OpenEXR, PNG or JPEG file"),
    ("", "broken.exr", "image", "not a readable OpenEXR, PNG or JPEG file"),
    ("fov_deg = 180.0\n", "ok.png", "fov_deg", "must be < 180"),
    ("fov_deg = 0\n", "ok.png", "fov_deg", "must be >"),
    ("up = [0, 0, 2]\n", "ok.png", "up", "parallel to direction"),
])
def test_bad_projector_fields(tmp_path, extra, image, field, match):
    from PIL import Image

    Image.fromarray(np.zeros((2, 2, 3), np.uint8), "RGB").save(tmp_path / "ok.png")
    (tmp_path / "broken.png").write_bytes(b"not a png")
    (tmp_path / "broken.exr").write_bytes(b"not an exr")
    with pytest.raises(InputError, match=rf"\[lights\.1\]\.{field}: .*{match}") as e:
        load_scene(_write(tmp_path, GOOD + PROJECTOR.format(image=image) + extra))
    assert "\n" not in str(e.value)


def test_projector_needs_an_image_and_a_default_up_across_its_axis(tmp_path):
    with pytest.raises(InputError, match=r"\[lights\.1\]\.image: a projector light needs image"):
        load_scene(_write(tmp_path, GOOD + PROJECTOR.replace('image = "{image}"\n', "")))
    from PIL import Image

    Image.fromarray(np.zeros((2, 2, 3), np.uint8), "RGB").save(tmp_path / "ok.png")
    text = GOOD + PROJECTOR.format(image="ok.png").replace("direction = [0, 0, -1]", "direction = [0, -2, 0]")
    with pytest.raises(InputError, match=r"\[lights\.1\]\.up: .*\(the default\) is parallel"):
        load_scene(_write(tmp_path, text))


@pytest.mark.parametrize("value, match", [
    ("1.5", "in \\[0, 1\\]"),
    ("[0.1, -0.1, 0.2]", "negative"),
    ('"rho.exr"', "give \\[material\\].volume too"),
])
def test_bad_reflectance(tmp_path, value, match):
    text = GOOD.replace('preset = "skin1"', f'preset = "skin1"\nreflectance = {value}')
    with pytest.raises(InputError, match=match) as e:
        load_scene(_write(tmp_path, text))
    assert "[material].reflectance" in str(e.value) and "\n" not in str(e.value)


def test_reflectance_constant_and_map(tmp_path):
    s = load_scene(_write(tmp_path, GOOD.replace('preset = "skin1"', 'preset = "skin1"\nreflectance = 0.04')))
    assert s.material.reflectance == (0.04, 0.04, 0.04)
    np.savez(tmp_path / "block.npz", kappa=np.ones((2, 3, 3, 3)), mu=np.zeros((2, 3, 3, 3)), h_mm=1.0)
    text = GOOD.replace('preset = "skin1"', 'volume = "block.npz"\nreflectance = "rho.exr"')
    with pytest.raises(InputError, match="reflectance map .* does not exist"):
        load_scene(_write(tmp_path, text))
    io.write_exr(tmp_path / "rho.exr", np.full((3, 3, 3), 0.05, np.float32))
    assert load_scene(_write(tmp_path, text)).material.reflectance == "rho.exr"
