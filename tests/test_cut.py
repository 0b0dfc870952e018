"""TransCut cutting and painting in scenes (issue 20): ``[cut]`` / ``[[paint]]`` on an fTetWild
mesh, rendered through pass 3; ``glsldiff cut``."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.core.errors import InputError

pytest.importorskip("pytetwild")
from glsldiff.render.renderer import Renderer  # noqa: E402
from glsldiff.render.scene import parse_scene  # noqa: E402

W = 64


def _scene(cut=None, paint=None, light=(0.0, 0.0, 1.0), camera=True):
    d = {"mesh": {"source": "sphere", "size_mm": 20.0}, "material": {"preset": "marble"},
         "polygrid": {"discretisation": "tetwild", "edge_mm": 2.0},
         "lights": [{"type": "directional", "direction": list(light)}],
         "output": {"width": W, "height": W}}
    if camera:
        d["camera"] = {"position": [0, 0, 80], "target": [0, 0, 0], "fov_deg": 20.0}
    if cut is not None:
        d["cut"] = cut
    if paint is not None:
        d["paint"] = paint
    return parse_scene(d)


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    """Front-lit uncut and cut (z > 0 removed: the cut face looks at the camera and the light),
    back-lit cut, front-lit cut with an absorbing paint stroke at the face's centre, and a stroke
    cut down the middle of the image."""
    mp = pytest.MonkeyPatch()
    mp.setenv("GLSLDIFF_CACHE", str(tmp_path_factory.mktemp("cache")))
    out = {}
    try:
        with Renderer() as r:
            for name, scene in (("uncut", _scene()), ("cut", _scene({"plane": [0, 0, 2, 0]})),
                                ("back", _scene({"plane": [0, 0, 1, 0]}, light=(0.0, 0.0, -1.0))),
                                ("paint", _scene({"plane": [0, 0, 1, 0]}, paint=[
                                    {"points": [[0, 0, 0]], "radius_mm": 2.0, "sigma_a": [2.0, 2.0, 2.0]}])),
                                ("stroke", _scene({"stroke": [[W / 2, 0], [W / 2, W]]})),
                                ("plane_x", _scene({"plane": [1, 0, 0, 0]}))):
                img, rep = r.render(scene)
                out[name] = (img, rep, r.cut_report, r.polygrid)
    finally:
        mp.undo()
    return out


def test_the_cut_face_receives_light_like_any_surface(renders):
    uncut, _, none, _ = renders["uncut"]
    img, rep, cut, tm = renders["cut"]
    assert none is None and cut is not None and cut.tets_removed > 0
    assert any(n.startswith("cut: ") for n in rep.notes)
    assert tm.positions[:, 2].max() <= cut.max_past_cut + 1e-9 and cut.max_past_cut < 2.0   # mm past z = 0
    assert tm.cut_faces.sum() > 50 and np.all(np.isfinite(img)) and img.min() >= 0
    c = slice(W // 2 - 3, W // 2 + 3)
    centre_cut, centre_uncut = img[c, c].mean(), uncut[c, c].mean()
    # both lit at normal incidence at the centre; the cut face sits on a 10 mm deep half ball
    assert 0.85 < centre_cut / centre_uncut < 1.15, centre_cut / centre_uncut   # measured 1.007
    back = renders["back"][0][c, c].mean()                # light through 10 mm of marble
    assert 0.0 < back < 0.2 * centre_cut                   # measured 0.055


def test_paint_darkens_where_it_is_painted(renders):
    cut, paint = renders["cut"][0], renders["paint"][0]
    c = slice(W // 2 - 2, W // 2 + 2)
    edge = (slice(W // 2 - 2, W // 2 + 2), slice(W // 2 + 14, W // 2 + 18))   # 5-6 mm from the stroke
    assert paint[c, c].mean() < 0.6 * cut[c, c].mean()
    assert paint[edge].mean() > 0.8 * cut[edge].mean()
    assert "paint stroke" in " ".join(renders["paint"][1].notes)


def test_a_stroke_down_the_image_cuts_like_the_plane_through_the_eye(renders):
    """The stroke u = W/2 walked downwards has the image's right (+x) on its left: it removes
    x > 0, the same tetrahedra as the plane x = 0 (it passes through the eye), but for those
    with all vertices within rounding of the plane (fTetWild's sphere can put vertices on it;
    the stroke's side goes through the projection, the plane's does not)."""
    s, p = renders["stroke"][2], renders["plane_x"][2]
    assert p.tets_removed > 0 and abs(s.tets_removed - p.tets_removed) <= 0.01 * p.tets_removed
    assert renders["stroke"][3].positions[:, 0].max() < 2.0
    img = renders["stroke"][0]
    assert img[:, W // 2 + 8:].sum() < 0.5 * img[:, :W // 2 - 8].sum()   # the right half is flat, seen edge-on


def test_cut_and_paint_scene_errors():
    with pytest.raises(InputError, match=r"\[cut\]: cutting needs the fTetWild mesh"):
        parse_scene({"mesh": {"source": "sphere", "size_mm": 20.0}, "lights": [{"type": "directional",
                     "direction": [0, 0, 1]}], "cut": {"plane": [0, 0, 1, 0]}})
    with pytest.raises(InputError, match=r"\[cut\].plane: give exactly one"):
        _scene({"plane": [0, 0, 1, 0], "stroke": [[0, 0], [1, 1]]})
    with pytest.raises(InputError, match=r"\[cut\].plane: must be"):
        _scene({"plane": [0, 0, 0, 1]})
    with pytest.raises(InputError, match=r"\[cut\].stroke: a stroke is drawn in the camera"):
        _scene({"stroke": [[0, 0], [10, 10]]}, camera=False)
    with pytest.raises(InputError, match=r"\[paint.0\].sigma_a: give the target"):
        _scene(paint=[{"points": [[0, 0, 0]], "radius_mm": 1.0}])
    with pytest.raises(InputError, match=r"\[paint.0\].radius_mm: must be >"):
        _scene(paint=[{"points": [[0, 0, 0]], "radius_mm": 0.0, "sigma_a": 1.0}])
    with pytest.raises(InputError, match=r"\[paint.0\].points: must be a list"):
        _scene(paint=[{"points": [0, 0, 0], "radius_mm": 1.0, "sigma_a": 1.0}])


def test_cut_command(tmp_path, monkeypatch, capsys):
    from glsldiff.commands.cli import main
    monkeypatch.setenv("GLSLDIFF_CACHE", str(tmp_path / "cache"))
    scene = tmp_path / "s.toml"
    scene.write_text('[mesh]\nsource = "sphere"\nsize_mm = 20.0\n[[lights]]\ntype = "directional"\n'
                     'direction = [0, 0, 1]\n[output]\nwidth = 32\nheight = 32\n')
    assert main(["cut", str(scene), "--plane", "0", "0", "1", "0", "--edge", "2.5", "-o",
                 str(tmp_path / "c.exr")]) == 0
    cap = capsys.readouterr()
    assert "using an fTetWild mesh" in cap.err and "TransCut update" in cap.out and "total: cut + matrix + CG" in cap.out
    assert (tmp_path / "c.exr").is_file() and (tmp_path / "c.png").is_file()
    assert main(["cut", str(scene), "-o", str(tmp_path / "d.exr")]) == 2
    assert "exactly one of --plane" in capsys.readouterr().err
    assert main(["cut", str(scene), "--stroke", "1,2", "3", "-o", str(tmp_path / "d.exr")]) == 2
    assert "U,V" in capsys.readouterr().err
    assert main(["cut", str(scene), "--plane", "0", "0", "1", "-100", "--edge", "2.5",
                 "-o", str(tmp_path / "d.exr")]) == 2
    assert "removes the whole object" in capsys.readouterr().err
