"""The misleading or silent answers of issue 44's probes, each now one line naming the user's
option (exit 2) or a correct result: a demo size below its 4 x 4 regions, a scene path that
is a folder, a preset with coefficients, a light inside the object, a key the light kind does
not read, an OBJ face naming a missing vertex, a voxel size in the wrong unit, a bogus
GLSLDIFF_GL, a zero light direction, a stroke point with negative coordinates, numbers
written as numbers."""
from __future__ import annotations

import re

import numpy as np
import pytest

from glsldiff.commands.cli import build_parser, main
from glsldiff.core.errors import InputError
from glsldiff.mesh.load import load_mesh
from glsldiff.physics.editing import Edit
from glsldiff.render.scene import load_scene

SCENE = """[mesh]
source = "sphere"
size_mm = 20
[polygrid]
n = 4
cubes = 20
levels = 1
{material}
[[lights]]
{light}
[output]
width = 32
height = 32
"""
DIRECTIONAL = 'type = "directional"\ndirection = [0, 0, 1]'


def _one_error_line(capsys, code, expect):
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("glsldiff: error:") and expect in err[0], err


def _scene(tmp_path, material="", light=DIRECTIONAL):
    p = tmp_path / "s.toml"
    p.write_text(SCENE.format(material=material, light=light))
    return p


def test_demo_size_below_its_regions(tmp_path, capsys):
    _one_error_line(capsys, main(["demo", "--size", "3", "3", "3", "--out", str(tmp_path / "d")]),
                    "--size: NX and NY must be >= 4")
    assert not (tmp_path / "d").exists()


def test_scene_path_that_is_a_folder(tmp_path, capsys):
    _one_error_line(capsys, main(["render", str(tmp_path), "-o", str(tmp_path / "r.exr")]), "is a folder, not a file")


@pytest.mark.parametrize("material", ['preset = "marble"\nsigma_s_prime = [1, 1, 1]',
                                      'preset = "marble"\nsigma_a = [0.01, 0.01, 0.01]'])
def test_preset_with_coefficients(tmp_path, material):
    with pytest.raises(InputError, match="give either a preset or sigma_a/sigma_s_prime, not both"):
        load_scene(_scene(tmp_path, "[material]\n" + material))


@pytest.mark.parametrize("light, key", [
    ('type = "point"\nposition = [0, 0, 50]\ndirection = [0, 0, -1]', "a point light has no direction"),
    ('type = "directional"\ndirection = [0, 0, 1]\nposition = [0, 0, 5]', "a directional light has no position"),
    ('type = "directional"\ndirection = [0, 0, 1]\ncone_deg = 10', "a directional light has no cone_deg"),
])
def test_a_key_the_light_does_not_read_is_an_error(tmp_path, light, key):
    with pytest.raises(InputError, match=key):
        load_scene(_scene(tmp_path, light=light))


def test_light_inside_the_object(tmp_path, capsys):
    scene = _scene(tmp_path, light='type = "point"\nposition = [0, 0, 0]\nintensity = [1, 1, 1]')
    assert main(["render", str(scene), "-o", str(tmp_path / "r.exr")]) == 2
    err = capsys.readouterr().err.strip().splitlines()           # progress lines, then the error
    assert err[-1].startswith("glsldiff: error:") and "light 1 at (0, 0, 0) mm is inside the object" in err[-1]
    assert not (tmp_path / "r.exr").exists()


def test_obj_face_naming_a_missing_vertex(tmp_path):
    p = tmp_path / "t.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 99\n")
    with pytest.raises(InputError, match="line 8: face names vertex 99 but the file has 4 vertices"):
        load_mesh(str(p), size_mm=20)
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf -3 -2 -1\n")
    assert len(load_mesh(str(p), size_mm=20).faces) == 4      # negative (relative) indices are fine


@pytest.mark.parametrize("h, ok", [(1e6, False), (1e-9, False), (0.5, True)])
def test_block_volume_voxel_size_in_mm(tmp_path, h, ok):
    vol = tmp_path / "v.npz"
    np.savez(vol, kappa=np.full((2, 2, 2, 3), 0.3), mu=np.full((2, 2, 2, 3), 0.01), h_mm=h)
    scene = _scene(tmp_path, '[material]\nvolume = "v.npz"')
    if ok:
        assert load_scene(scene).material.volume is not None
    else:
        with pytest.raises(InputError, match=re.escape(f"h_mm = {h:g} is not a voxel size in mm")):
            load_scene(scene)


def test_bogus_gl_backend_fails_info(capsys, monkeypatch):
    monkeypatch.setenv("GLSLDIFF_GL", "bogus")
    _one_error_line(capsys, main(["info"]), "GLSLDIFF_GL='bogus' is not a GL backend")


def test_zero_light_direction_before_meshing(tmp_path, capsys):
    _one_error_line(capsys, main(["tet", "sphere", "--light", "0", "0", "0", "--out", str(tmp_path / "t")]),
                    "--light 0 0 0: give a finite, non-zero direction")
    assert not (tmp_path / "t").exists()


def test_stroke_points_with_negative_coordinates_are_values():
    args = build_parser().parse_args(["cut", "--stroke", "-500,-500", "-1.5,2", "3,-4", "-o", "c.exr"])
    assert args.stroke == [(-500.0, -500.0), (-1.5, 2.0), (3.0, -4.0)]


def test_edit_values_read_as_numbers():
    with pytest.raises(InputError, match=r"mu must be set to a value >= 0 \(mm\^-1\), got -1$"):
        Edit("mu", "set", (-1.0, -1.0, -1.0))
    with pytest.raises(InputError, match=r"got -2 0 1$"):
        Edit("mu", "multiply", (-2.0, 0.0, 1.0))


def test_render_prints_a_short_report_and_writes_the_full_one(tmp_path, capsys):
    """``glsldiff render``: about ten lines on stdout (grid, model, material, solver, times, the
    files), the full report in the .json beside the image (written with the EXR and PNG); -v
    prints the full report."""
    import json
    scene = _scene(tmp_path)
    assert main(["render", str(scene), "-o", str(tmp_path / "r.exr")]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) <= 10 and out[0].startswith("scene:") and any(l.startswith("solver:") for l in out), out
    assert any(l.startswith("time: frame") for l in out) and "r.json" in out[-1]
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["nodes"] > 0 and report["passes"] and any(l.startswith("t1/t2/t3") for l in report["report"])
    assert main(["render", str(scene), "-o", str(tmp_path / "v.exr"), "-v"]) == 0
    verbose = capsys.readouterr().out
    assert "t1/t2/t3" in verbose and "  pass2" in verbose
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.exr", "r.json", "r.png", "s.toml", "v.exr", "v.json",
                                                          "v.png"]


@pytest.mark.parametrize("signame, code, word", [("SIGINT", 130, "interrupted"), ("SIGTERM", 143, "terminated")])
def test_ctrl_c_inside_ftetwild_is_honoured(tmp_path, signame, code, word):
    """A real SIGINT (or SIGTERM) while fTetWild meshes (``tet``; ``cut`` meshes the same way):
    exit 130 (143) within 2 s with the one-line message, no output folder and no fTetWild scratch
    folder left (fTetWild used to end the program with no word, leaving both). The signal comes
    3 s after meshing started: the child process is meshing by then."""
    rc, seconds, err = _interrupt(tmp_path, ["tet", "bunny", "--edge", "1.5", "--out", "o"], "tetwild: meshing", 3.0,
                                  signame)
    assert rc == code and seconds < 2.0, err
    assert word in err.strip().splitlines()[-1] and "Traceback" not in err, err
    assert not (tmp_path / "o").exists() and list((tmp_path / "tmp").iterdir()) == []


def test_interruptible_returns_and_raises():
    from glsldiff.core.interrupt import abandoned, interruptible
    assert interruptible(sum, [1, 2, 3], start=4) == 10
    with pytest.raises(ZeroDivisionError):
        interruptible(lambda: 1 / 0)
    assert not abandoned()


def test_ctrl_c_during_a_superlu_factorisation_is_honoured(tmp_path):
    """A real SIGINT 5 s into ``demo --size 96 96 24`` (inside the scipy reference's SuperLU
    factorisation, which held Ctrl-C off for about 40 s): exit 130 within 2 s, one message, no
    output folder left."""
    rc, seconds, err = _interrupt(tmp_path, ["demo", "--size", "96", "96", "24", "--out", "d"], None, 5.0)
    assert rc == 130 and seconds < 2.0, err
    assert err.strip().splitlines()[-1].startswith("glsldiff: interrupted") and "Traceback" not in err, err
    assert not (tmp_path / "d").exists()


def _interrupt(tmp_path, argv: list[str], wait_for: str | None, after: float,
               signame: str = "SIGINT") -> tuple[int, float, str]:
    """Run ``glsldiff ARGV`` in ``tmp_path`` (scratch folders under tmp_path/tmp), send a real
    ``signame`` ``after`` seconds after the stderr line starting with ``wait_for`` (or after the
    start); return the exit code, the seconds from the signal to the exit and stderr."""
    import os
    import signal
    import subprocess
    import sys
    import time
    scratch = tmp_path / "tmp"
    scratch.mkdir(exist_ok=True)
    env = dict(os.environ, GLSLDIFF_GL="osmesa", GLSLDIFF_CACHE="off", TMPDIR=str(scratch))
    p = subprocess.Popen([sys.executable, "-m", "glsldiff.commands.cli", *argv], cwd=tmp_path, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = []
    if wait_for is not None:
        for line in p.stderr:
            seen.append(line)
            if line.startswith(wait_for):
                break
    time.sleep(after)
    assert p.poll() is None, "".join(seen)
    p.send_signal(getattr(signal, signame))
    t0 = time.perf_counter()
    _, err = p.communicate(timeout=120)
    return p.returncode, time.perf_counter() - t0, "".join(seen) + err


@pytest.mark.parametrize("argv, wait_for, after", [
    (["cut", "--plane", "0", "0", "1", "52", "--edge", "1.5", "-o", "cut.exr"], "tetwild: meshing", 3.0),
    (["bench", "fit", "--size", "24", "24", "8", "--n", "2", "3", "--out", "out"], None, 8.0),
], ids=["cut", "bench-fit"])
def test_ctrl_c_ends_every_long_command(tmp_path, argv, wait_for, after):
    """A real SIGINT into ``cut`` (while fTetWild meshes) and ``bench fit`` (while it fits):
    exit 130 within 2 s, one message, nothing left behind (no output file or folder, no scratch)."""
    code, seconds, err = _interrupt(tmp_path, argv, wait_for, after)
    assert code == 130 and seconds < 2.0, err
    assert err.strip().splitlines()[-1].startswith("glsldiff: interrupted") and "Traceback" not in err, err
    assert [p.name for p in tmp_path.iterdir()] == ["tmp"] and list((tmp_path / "tmp").iterdir()) == []


def test_heartbeat_speaks_only_when_the_command_is_quiet(capsys):
    """No more than ``every`` seconds without a line: a quiet step gets "still working" naming
    the last line; a step that prints gets none; the streams are restored afterwards."""
    import sys
    import time
    from glsldiff.core.heartbeat import Heartbeat
    before = sys.stderr
    with Heartbeat(every=1.0):
        print("setup: building the grid", file=sys.stderr)
        time.sleep(2.6)
    err = capsys.readouterr().err.splitlines()
    beats = [line for line in err if line.startswith("glsldiff: still working")]
    assert len(beats) in (1, 2) and all("last: setup: building the grid" in b for b in beats), err
    with Heartbeat(every=1.0):
        for k in range(6):
            print(f"step {k}")
            time.sleep(0.4)
    assert "still working" not in capsys.readouterr().err
    assert sys.stderr is before


def test_tables_fit_100_columns_and_name_the_rest(capsys):
    """A wide table shows its leading columns within 100 characters and names every column it
    leaves out (and where they are); a narrow one is printed whole."""
    from glsldiff.core.tables import print_table
    rows = [{f"column_{k:02d}": float(k) + 0.123 for k in range(30)} | {"case": "a"}]
    print_table("wide", rows, first=("case", "column_29"), rest="all in x.csv")
    out = capsys.readouterr().out.splitlines()
    table = [line for line in out if not line.startswith("not shown")]
    header = next(line for line in table if "case" in line)
    assert max(len(line) for line in table) <= 100 and "column_29" in header and header.index("case") < header.index("column_29")
    (note,) = [line for line in out if line.startswith("not shown")]
    hidden = note.split(": ", 1)[1].removesuffix("; all in x.csv").split(", ")
    assert len(hidden) > 10 and all(f"column_{k:02d}" not in "".join(table) for k in range(30)
                                    if f"column_{k:02d}" in hidden)
    print_table("narrow", [{"a": 1.0, "b": "x"}])
    assert "not shown" not in capsys.readouterr().out


def _ortho_scene(tmp_path, name, camera):
    p = tmp_path / f"{name}.toml"
    p.write_text(SCENE.format(material="", light=DIRECTIONAL).replace("width = 32\nheight = 32", "width = 64\nheight = 64")
                 + "[camera]\n" + camera + "\n")
    return p


def test_orthographic_camera_shows_the_object_at_its_size(tmp_path, capsys):
    """``[camera] type = "orthographic"``: a 20 mm sphere in a 40 mm wide view covers a disc of
    32 px diameter in a 64 px image whatever the camera's distance, and the image is the
    distant pinhole's (parallel view rays); fov_deg with it, or width_mm without it, is refused."""
    from glsldiff.core import io as gio
    disc = {}
    for name, pos in (("near", 60), ("far", 600)):
        scene = _ortho_scene(tmp_path, name, f'type = "orthographic"\nwidth_mm = 40\nposition = [0, 0, {pos}]\n'
                                             'target = [0, 0, 0]')
        assert main(["render", str(scene), "-o", str(tmp_path / f"{name}.exr")]) == 0
        disc[name] = gio.read_exr(tmp_path / f"{name}.exr")
    capsys.readouterr()
    area = [(img.sum(axis=2) > 0).sum() for img in disc.values()]
    assert all(abs(a - np.pi * 16 ** 2) < 0.06 * np.pi * 16 ** 2 for a in area), area
    np.testing.assert_allclose(disc["near"], disc["far"], atol=0.02 * float(disc["far"].max()))
    pinhole = _ortho_scene(tmp_path, "pin", "fov_deg = 1.0\nposition = [0, 0, 2292]\ntarget = [0, 0, 0]")
    assert main(["render", str(pinhole), "-o", str(tmp_path / "pin.exr")]) == 0          # 40 mm wide at 2.3 m
    pin = gio.read_exr(tmp_path / "pin.exr")
    inner = (pin.sum(axis=2) > 0) & (disc["far"].sum(axis=2) > 0)
    assert abs(float(pin[inner].mean() / disc["far"][inner].mean()) - 1.0) < 0.03
    with pytest.raises(InputError, match="an orthographic camera has no field of view"):
        load_scene(_ortho_scene(tmp_path, "bad1", 'type = "orthographic"\nfov_deg = 20'))
    with pytest.raises(InputError, match="is the view width of an orthographic camera"):
        load_scene(_ortho_scene(tmp_path, "bad2", "width_mm = 20"))
