"""The viewer in a real window (Xvfb, Mesa's GLX on the CPU), driven by synthetic input events in
a child process: a brush stroke changes the image where it was painted and nowhere else, undo
and redo give back each image, the material saves, the window closes cleanly; and a failed GL
start is one line naming what to install. The input state (orbit, light, tool) headless."""
from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from glsldiff.core import io
from glsldiff.render.scene import default_scene
from glsldiff.viewer.controls import Orbit, Tool, turn_light

DRIVER = r'''
import dataclasses, json, sys
import numpy as np
import pyglet
pyglet.options["debug_gl"] = True          # the strict setting: a GL error left by moderngl would raise
from pyglet.window import key, mouse
from glsldiff.render.scene import MeshSpec, default_scene, tetrahedral
from glsldiff.viewer.presets import lattice
from glsldiff.viewer.window import Viewer

out, kind = sys.argv[1], sys.argv[2]
sphere = dataclasses.replace(default_scene(), mesh=MeshSpec("sphere", 40.0))
scene = tetrahedral(sphere, 1500) if kind == "tetrahedral" else lattice(sphere, n=8, cubes=20, levels=2)
v = Viewer([("sphere", scene)], 320, 240, save_path=out + "/edited.npz", shots=out)
win = v.window

def pump():
    v.step()
    while v.dirty:
        v.step()

def shot():
    return v.shown                            # the window's pixels, read back before the flip

pump()
v.show_overlay = False
v.dirty = True
pump()
a = shot()
v.screenshot(out + "/before.png")
win.dispatch_event("on_key_press", key.E, 0)                  # edit mode: multiply mu, depth -1..2 mm
x, y = 120, 130                                               # window coordinates (y up)
win.dispatch_event("on_mouse_press", x, y, mouse.LEFT, 0)
for k in range(1, 4):
    win.dispatch_event("on_mouse_drag", x + 2 * k, y, 2, 0, mouse.LEFT, 0)
win.dispatch_event("on_mouse_release", x + 6, y, mouse.LEFT, 0)
pump()
b = shot()
v.screenshot(out + "/after.png")
frames_while_editing = list(v.frame_times)
win.dispatch_event("on_key_press", key.Z, key.MOD_CTRL)
pump()
c = shot()
win.dispatch_event("on_key_press", key.Y, key.MOD_CTRL)
pump()
d = shot()
win.dispatch_event("on_key_press", key.S, key.MOD_CTRL)
pump()
win.dispatch_event("on_key_press", key.E, 0)                  # back to viewing: a drag orbits
win.dispatch_event("on_mouse_drag", 160, 120, 30, 0, mouse.LEFT, 0)
pump()
e = shot()
np.savez(out + "/shots.npz", a=a, b=b, c=c, d=d, e=e, brush=np.array([x + 3, 240 - y, v.tool.radius]))
json.dump({"undo": v.renderer.edit_counts, "frames": frames_while_editing, "message": v.message},
          open(out + "/state.json", "w"))
win.dispatch_event("on_close")                                # the window's close button
v.run()
print("closed cleanly")
'''


@pytest.fixture(scope="module")
def xdisplay():
    """A private Xvfb display (the viewer needs a real X server); skipped without Xvfb, except in CI."""
    exe = shutil.which("Xvfb")
    if exe is None:
        if os.environ.get("CI"):
            pytest.fail("Xvfb is not installed: .ci/install installs the xvfb package")
        pytest.skip("Xvfb not installed (apt-get install xvfb)")
    num = 90 + os.getpid() % 400
    proc = subprocess.Popen([exe, f":{num}", "-screen", "0", "800x600x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sock = Path(f"/tmp/.X11-unix/X{num}")
    for _ in range(100):
        if sock.exists():
            break
        time.sleep(0.05)
    else:
        proc.kill()
        pytest.fail(f"Xvfb :{num} did not start")
    yield f":{num}"
    proc.terminate()
    proc.wait(10)


def _env(display: str) -> dict[str, str]:
    env = dict(os.environ, DISPLAY=display)
    env.pop("WAYLAND_DISPLAY", None)
    return env


@pytest.mark.parametrize("kind", ["tetrahedral", "lattice"])
def test_viewer_edits_in_a_real_window(xdisplay, tmp_path, kind):
    """Both grid families: the tetrahedral default (edits update its P1 system in place) and the
    lattice (edits are a GPU pass over its material textures)."""
    run = subprocess.run([sys.executable, "-c", DRIVER, str(tmp_path), kind], env=_env(xdisplay), capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "closed cleanly" in run.stdout and "Traceback" not in run.stderr
    z = np.load(tmp_path / "shots.npz")
    a, b, c, d, e = (z[k].astype(int) for k in "abcde")
    u, v, r = z["brush"]
    assert a.shape == (240, 320, 3) and a.max() > 100                      # the sphere is on screen
    diff = np.abs(b - a).sum(axis=-1)
    yy, xx = np.mgrid[0:240, 0:320]
    dist = np.hypot(xx - u, yy - v)
    assert (diff[dist < r] > 6).mean() > 0.3                               # changed where painted ...
    # ... and nowhere else: light diffuses past the brush (marble's diffusion length is ~8 mm, one
    # brush radius here), so 2.5 radii out the change is below one 8-bit level per channel
    assert diff[dist > 2.5 * r].max() <= 3
    lum_a, lum_b = a.mean(-1), b.mean(-1)
    assert lum_b[dist < r].mean() < lum_a[dist < r].mean() - 3             # more absorption: darker
    assert np.abs(c - a).max() <= 2                                        # undo
    assert np.abs(d - b).max() <= 2                                        # redo
    assert np.abs(e - d).max() > 20                                        # the orbit drag moved the camera
    state = (tmp_path / "state.json").read_text()
    assert '"undo": [1, 0]' in state                                       # one stroke = one undo step
    assert (tmp_path / "edited.npz").is_file() and (tmp_path / "before.png").is_file()


def test_failed_window_start_is_one_line(tmp_path):
    run = subprocess.run([sys.executable, "-m", "glsldiff.commands.cli", "view", "--seconds", "1"],
                         env=_env(":4321"), capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "xvfb" in lines[0].lower() and "Traceback" not in run.stderr, run.stderr


# ---------------------------------------------------------------- input state, headless
def test_orbit_round_trip_drag_and_zoom():
    o = Orbit.of(np.array([10.0, 20.0, 30.0]), np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(o.eye, [10.0, 20.0, 30.0], atol=1e-12)
    o2 = o.dragged(100.0, 0.0)
    assert math.isclose(np.linalg.norm(o2.eye - np.array(o.target)), o.distance)
    assert math.isclose(o2.azimuth, o.azimuth - 1.0)
    assert o.dragged(0.0, -1e6).elevation < math.pi / 2                    # never over the pole
    assert math.isclose(o.zoomed(2).distance, 0.81 * o.distance)


def test_light_turns_and_tool_cycles():
    s = default_scene()
    s2, ok = turn_light(s, 50.0, 0.0)
    d0, d1 = np.asarray(s.lights[0].direction), np.asarray(s2.lights[0].direction)
    assert ok and math.isclose(np.linalg.norm(d1), 1.0) and not np.allclose(d0, d1)
    t = Tool()
    assert t.cycled("prop").prop == "kappa" and t.cycled("op").op == "add"
    e = t.dab(10.0, 20.0)
    assert e.brush.centre == (10.0, 20.0) and e.depth == t.depth and e.prop == "mu"


def test_view_command_opens_renders_and_closes(xdisplay, tmp_path):
    scene = tmp_path / "sphere.toml"
    scene.write_text('[mesh]\nsource = "sphere"\nsize_mm = 30.0\n'
                     '[polygrid]\ndiscretisation = "conservative"\nn = 8\ncubes = 20\nlevels = 2\n'
                     '[[lights]]\ntype = "directional"\ndirection = [0, 0, 1]\n')
    run = subprocess.run([sys.executable, "-m", "glsldiff.commands.cli", "view", str(scene), "--seconds", "1",
                          "--size", "160", "120", "--shots", str(tmp_path)], env=_env(xdisplay), capture_output=True,
                         text=True, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "viewer closed:" in run.stdout and "Traceback" not in run.stderr


def test_view_screenshot_from_the_command_line(xdisplay, tmp_path):
    """``view --screenshot shot.png``: the first converged frame, window-sized, no overlay, then
    the window closes by itself (no --seconds); ``--save`` with a PNG name says what it is."""
    scene = tmp_path / "sphere.toml"
    scene.write_text('[mesh]\nsource = "sphere"\nsize_mm = 30.0\n'
                     '[polygrid]\ndiscretisation = "conservative"\nn = 8\ncubes = 20\nlevels = 2\n'
                     '[[lights]]\ntype = "directional"\ndirection = [0, 0, 1]\n')
    shot = tmp_path / "shot.png"
    run = subprocess.run([sys.executable, "-m", "glsldiff.commands.cli", "view", str(scene), "--size", "160", "120",
                          "--screenshot", str(shot)], env=_env(xdisplay), capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    assert f"screenshot {shot}" in run.stdout
    img = io.read_image(shot)
    assert img.shape[:2] == (120, 160) and img.max() > 0.1             # the lit sphere
    assert img[:12, :].max() < 0.02                                    # no overlay text in the top rows
    bad = subprocess.run([sys.executable, "-m", "glsldiff.commands.cli", "view", "--save", "shot.png"],
                         env=_env(xdisplay), capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert bad.returncode == 2 and "a screenshot is --screenshot" in bad.stderr
