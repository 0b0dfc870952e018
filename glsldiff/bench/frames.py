"""``glsldiff bench frames``: what a frame of the default scene costs when nothing, only the camera
or a light changed, in the viewer's mode and in ``glsldiff render``'s (the frames of an
interactive session, Wang et al. 2008 section 5.4).

Per mode, on the default (tetrahedral) bunny, pass 2 frame-coherent (``frame_sweeps`` sweeps or
one CG iteration per frame, as the viewer runs it):

* ``viewer``: single scattering in the half-space's closed form (``single_scattering = "auto"``
  in interactive frames); ``render``: the 3-D march along the refracted view rays
  (:mod:`glsldiff.render.single`; ``single_scattering = true``, what ``glsldiff render``
  marches);
* the first frame of a fresh renderer after another renderer filled the disk caches (grid,
  solution, thickness casts): ``glsldiff render``'s (``render`` only: the cached answer, no
  solver built) and the interactive renderer's (which also builds the GPU multigrid that later
  frames iterate with), each with its set-up (grid from the cache, render mesh, surface map);
* ``unchanged``: frames with nothing changed; ``camera``: an orbit of ``orbit`` steps of
  ``step_deg`` about the vertical axis through the target (each frame a new eye);
* ``light``: the light's direction changed, then frames until pass 2 meets ``tol``; each frame's
  image compared with a reference of the new light rendered by a fresh renderer to ``ref_tol``
  (relative L2 over the lit pixels): the time to 0.5 % (:data:`CONVERGED`) is read off.

Times are wall clock around :meth:`Renderer.render`, median and fastest of the frames.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from glsldiff.bench.edit import CONVERGED, rel_l2
from glsldiff.core import io
from glsldiff.core.plotting import pyplot, save_figure
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import Scene, default_scene

#: The modes: the viewer's (closed-form single scattering) and ``glsldiff render``'s (the 3-D march).
MODES = ("viewer", "render")
#: The light change: towards the light, from the upper right (the default comes from the front).
NEW_LIGHT = (0.4, 0.7, 0.6)


def mode_scene(mode: str, size: int = 512) -> Scene:
    """The default scene at ``size`` squared pixels, single scattering as ``mode`` has it."""
    base = default_scene()
    single: bool | str = "auto" if mode == "viewer" else True
    return dataclasses.replace(base, output=dataclasses.replace(base.output, width=size, height=size),
                               options=dataclasses.replace(base.options, single_scattering=single))


def _orbit(scene: Scene, eye: np.ndarray, target: np.ndarray, up: np.ndarray, deg: float) -> Scene:
    """``scene`` with its eye turned by ``deg`` about the axis ``up`` through ``target``."""
    a = np.radians(deg)
    u = up / np.linalg.norm(up)
    r = eye - target
    turned = r * np.cos(a) + np.cross(u, r) * np.sin(a) + u * (u @ r) * (1.0 - np.cos(a))
    cam = dataclasses.replace(scene.camera, position=tuple(target + turned), target=tuple(target), up=tuple(u))
    return dataclasses.replace(scene, camera=cam)


def _timed(r: Renderer, scene: Scene) -> tuple[float, Any, Any]:
    t0 = time.perf_counter()
    img, rep = r.render(scene)
    return time.perf_counter() - t0, img, rep


def _row(mode: str, phase: str, k: int, s: float, since: float, err: float, rep: Any) -> dict[str, Any]:
    """A per-frame row: the frame's seconds ``s``, seconds ``since`` its phase's change, the
    image error (NaN: not measured) and the passes it ran."""
    return {"mode": mode, "phase": phase, "frame": k, "s": s, "since_change_s": since, "rel_l2": err,
            "passes": " ".join(p["pass"] for p in rep.passes if p["ran"])}


def frames_study(modes: Sequence[str] = MODES, size: int = 512, orbit: int = 6, step_deg: float = 5.0,
                 unchanged: int = 3, frame_sweeps: int = 10, ref_tol: float = 1e-7, max_frames: int = 100,
                 status: Any = None) -> tuple[list[dict], list[dict]]:
    """(summary rows per mode, per-frame rows): module docstring."""
    say = status or (lambda line: None)
    summary, frames = [], []
    for mode in modes:
        scene = mode_scene(mode, size)
        say(f"bench frames: {mode}: filling the caches")
        with Renderer(status=say, frame_sweeps=frame_sweeps, allow_unconverged=True) as warm:
            warm.render(scene)
        plain: dict[str, float] = {}
        if mode == "render":
            with Renderer(status=say) as once:
                dt, _, rep = _timed(once, scene)
            plain = {"glsldiff render first frame s": dt, "of it set-up s": rep.seconds.get("setup", 0.0)}
        with Renderer(status=say, frame_sweeps=frame_sweeps, allow_unconverged=True) as r:
            first, _, rep = _timed(r, scene)
            setup = rep.seconds.get("setup", 0.0)
            frames.append(_row(mode, "first", 0, first, first, np.nan, rep))
            t_same = []
            for k in range(unchanged):
                dt, _, rep = _timed(r, scene)
                t_same.append(dt)
                frames.append(_row(mode, "unchanged", k, dt, dt, np.nan, rep))
            eye, target, up = r.framing(scene)
            t_cam = []
            for k in range(1, orbit + 1):
                moved = _orbit(scene, eye, target, up, k * step_deg)
                dt, _, rep = _timed(r, moved)
                t_cam.append(dt)
                frames.append(_row(mode, "camera", k, dt, dt, np.nan, rep))
            relit = dataclasses.replace(moved, lights=(dataclasses.replace(
                scene.lights[0], direction=tuple(np.asarray(NEW_LIGHT) / np.linalg.norm(NEW_LIGHT))),))
            say(f"bench frames: {mode}: the reference of the new light (to {ref_tol:g})")
            with Renderer(status=say, frame_sweeps=frame_sweeps) as rr:
                ref, _ = rr.render(dataclasses.replace(relit, options=dataclasses.replace(relit.options, tol=ref_tol)))
            t0, last, light_rows = time.perf_counter(), 0.0, []
            for k in range(max_frames):
                img, rep = r.render(relit)
                since = time.perf_counter() - t0
                light_rows.append(_row(mode, "light", k, since - last, since, rel_l2(img, ref), rep))
                last = since
                if r.converged:
                    break
            frames += light_rows
        hit = [row["since_change_s"] for row in light_rows if row["rel_l2"] <= CONVERGED]
        summary.append({"mode": mode, "single scattering": "closed form" if mode == "viewer" else "3-D march",
                        "glsldiff render first frame s": np.nan, "of it set-up s": np.nan, **plain,
                        "interactive first frame s": first, "its set-up s": setup,
                        "unchanged ms": 1e3 * float(np.median(t_same)), "unchanged min ms": 1e3 * min(t_same),
                        "camera ms": 1e3 * float(np.median(t_cam)), "camera min ms": 1e3 * min(t_cam),
                        "light to 0.5 % s": hit[0] if hit else np.nan,
                        "light to tol s": light_rows[-1]["since_change_s"] if r.converged else np.nan,
                        "light frames": len(light_rows), "err at end": light_rows[-1]["rel_l2"]})
    return summary, frames


def save_frames_study(summary: list[dict], frames: list[dict], out: str | Path) -> tuple[Path, Path, Path]:
    """CSV of the summary and of the frames, and a PNG: frame times per phase, and the image error
    against the time since the light changed."""
    out = Path(out)
    s = io.write_csv(out / "frames_summary.csv", summary)
    f = io.write_csv(out / "frames_frames.csv", frames)
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10.0, 4.0))
    modes = list(dict.fromkeys(r["mode"] for r in summary))
    phases = ("unchanged", "camera")
    for i, mode in enumerate(modes):
        med = [np.median([r["s"] for r in frames if r["mode"] == mode and r["phase"] == p]) * 1e3 for p in phases]
        a1.bar(np.arange(len(phases)) + 0.4 * i, med, width=0.38, label=mode)
        pts = [(r["since_change_s"], r["rel_l2"]) for r in frames if r["mode"] == mode and r["phase"] == "light"]
        if pts:
            t, e = zip(*pts)
            a2.semilogy(t, np.maximum(e, 1e-6), "o-", ms=3, label=mode)
    a1.axhline(100.0, color="grey", ls="--", lw=0.8, label="100 ms")
    a1.set_xticks(np.arange(len(phases)) + 0.2, phases)
    a1.set_ylabel("frame time, ms (median)")
    a1.legend(fontsize=8)
    a2.axhline(CONVERGED, color="grey", ls="--", lw=0.8, label="0.5 %")
    a2.set_xlabel("seconds after the light changed")
    a2.set_ylabel("image error vs converged (rel. L2)")
    a2.legend(fontsize=8)
    fig.suptitle("Frames of the default scene: camera and light changes")
    png = out / "frames.png"
    save_figure(fig, png)
    return s, f, png
