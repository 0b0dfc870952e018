"""``glsldiff bench edit``: interactive material editing (Wang et al. 2008, section 5.4, Table III)
measured the way the viewer runs it, without a window.

Per model (converged solutions are not read from the disk cache: every solve is timed as it runs):
a first frame solved cold to ``tol`` (the grid's set-up excluded); a brush stroke of ``dabs`` dabs across the
object (``multiply mu 2`` within 2 mm below the visible surface, one :meth:`Renderer.edit` and
one frame each, pass 2 warm-started with ``frame_sweeps`` sweeps per frame: the frame rate while
editing); then frames until pass 2 meets ``tol`` again. Every frame after the last dab is
compared with a reference image of the edited material (saved as a node material, rendered by
a fresh renderer with the multigrid scheme to ``ref_tol``): relative L2 over the object's
pixels, so the time from the edit to a converged (0.5 %) image is read off the table. Peer in
the same run: a cold solve of the edited system (no frame coherence) by the same solver to the
scene's ``tol`` (the Jacobi-scaled residual; ``peer`` names the solver and tolerance,
``peer_residual`` the residual reached), run ``repeats`` times (``cold t_median_s``, ``cold
t_min_s``). Both it and the frames use the solver the first frame built: its set-up (shader
compilation, textures, hierarchy) is in no time but the first frame's.
On tetrahedral grids an edit re-assembles the P1 system and every frame solves it to ``tol``.
"""
from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.bench.peers import relax_label
from glsldiff.bench.timing import repeat
from glsldiff.core import io
from glsldiff.core.plotting import pyplot, save_figure
from glsldiff.physics.editing import NO_SURFACE, Brush, Edit
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import EDIT_LATTICE, HOLE_CUBES, MeshSpec, PolygridSpec, Scene, default_scene, tetrahedral
from glsldiff.system.problem import relative_l2

#: Wang et al. 2008, Table III (GeForce 8800 GTX): polygrid, fps and fps with frame coherence.
TABLE_III = {"bunny": ("253 x 16^3", 25.9, 34.7), "bunny-n8": ("253 x 16^3", 25.9, 34.7),
             "hole": ("36 x 12^3", 80.0, 160.4), "bunny-tetrahedral": ("253 x 16^3", 25.9, 34.7),
             "hole-tetrahedral": ("36 x 12^3", 80.0, 160.4)}
#: The benchmark's models (:func:`model_scenes`).
EDIT_MODELS = ("hole", "bunny", "bunny-n8", "bunny-tetrahedral", "hole-tetrahedral")
#: The image error that counts as converged (relative L2 over the object's pixels).
CONVERGED = 5e-3


def model_scenes(size: int = 512) -> dict[str, Scene]:
    """The benchmark's scenes: the default bunny on the viewer's editing lattice
    (:data:`~glsldiff.render.scene.EDIT_LATTICE`) and on the default lattice (253 cubes x 8^3, the
    paper's cube layout at half its n), the torus standing in for the paper's "Hole" (n = 12,
    36 cubes, as Table III), the default tetrahedral bunny and the torus on a tetrahedral grid
    (:data:`~glsldiff.render.scene.HOLE_CUBES` cubes, 45k nodes)."""
    base = default_scene()
    base = dataclasses.replace(base, output=dataclasses.replace(base.output, width=size, height=size))
    lat = EDIT_LATTICE
    return {"bunny": dataclasses.replace(base, polygrid=lat),
            "bunny-n8": dataclasses.replace(base, polygrid=PolygridSpec(8, 253, 3, "conservative")),
            "hole": dataclasses.replace(base, mesh=MeshSpec("torus", 100.0),
                                        polygrid=PolygridSpec(12, 36, 3, "conservative")),
            "bunny-tetrahedral": base,
            "hole-tetrahedral": tetrahedral(dataclasses.replace(base, mesh=MeshSpec("torus", 100.0)), HOLE_CUBES)}


def rel_l2(img: NDArray, ref: NDArray) -> float:
    """Relative L2 difference over the pixels the reference lights."""
    return relative_l2(img, ref, ref.sum(axis=-1) > 0)


def _stroke(view: Any, dabs: int, radius: float) -> list[tuple[float, float]]:
    """Dab centres across the middle of the object as seen (pixels)."""
    vis = view.surface < NO_SURFACE
    ys, xs = np.nonzero(vis)
    cu, cv = float(xs.mean()), float(ys.mean())
    half = min(2.0 * radius, 0.3 * float(np.ptp(xs)))
    return [(cu + t, cv) for t in np.linspace(-half, half, dabs)]


def edit_study(names: Sequence[str], dabs: int = 8, frame_sweeps: int = 10, radius: float = 30.0,
               ref_tol: float = 1e-7, size: int = 512, status: Any = None,
               repeats: int = 1) -> tuple[list[dict], list[dict]]:
    """(summary rows per model, per-frame rows): module docstring."""
    scenes = model_scenes(size)
    summary, frames = [], []
    say = status or (lambda line: None)
    for name in names:
        scene = scenes[name]
        say(f"bench edit: {name}")
        with Renderer(status=say, frame_sweeps=frame_sweeps, allow_unconverged=True, cache_solutions=False) as r:
            t0 = time.perf_counter()
            _, rep0 = r.render(scene)
            first = time.perf_counter() - t0 - rep0.seconds.get("setup", 0.0)   # the grid itself comes from the cache
            view = r.edit_view(scene)
            stroke_fps, t_edit, t2s, t3s = [], [], [], []
            last_edit = 0.0
            for i, (u, v) in enumerate(_stroke(view, dabs, radius)):
                edit = Edit("mu", "multiply", 2.0, brush=Brush((u, v), radius, 0.4), depth=(-1.0, 2.0), strength=0.5)
                last_edit = time.perf_counter()
                res = r.edit(edit, view, history=i == 0)
                te = time.perf_counter() - last_edit
                img, rep = r.render(scene)
                dt = time.perf_counter() - last_edit
                stroke_fps.append(1.0 / dt)
                t_edit.append(te)
                t2s.append(rep.seconds.get("t2", 0.0))
                t3s.append(rep.seconds.get("t3", 0.0))
                frames.append({"model": name, "phase": "stroke", "frame": i, "edit_ms": te * 1e3,
                               "frame_ms": dt * 1e3, "t2_ms": t2s[-1] * 1e3, "t3_ms": t3s[-1] * 1e3,
                               "nodes_edited": res.edited, "since_edit_s": dt, "rel_l2": np.nan})
            after = [(time.perf_counter() - last_edit, img)]
            k = 0
            while not r.converged:
                img, rep = r.render(scene)
                after.append((time.perf_counter() - last_edit, img))
                k += 1
            converged_s = after[-1][0]
            solver = r.pass2_solver      # None when a tetrahedral frame came from the solution cache
            peer: dict[str, Any] = {"peer": "none (the frame came from the solution cache)", "cold t_median_s": np.nan,
                                    "cold t_min_s": np.nan, "repeats": 0, "cold sweeps": np.nan}
            if solver is not None:
                cold_t = repeat(lambda: solver.solve(tol=scene.options.tol, x0=None), repeats)
                cold = cold_t.result[1]
                peer = {"peer": relax_label(f"cold re-solve, {cold.method}", scene.options.tol),
                        "cold t_median_s": cold_t.median, "cold t_min_s": cold_t.min, "repeats": cold_t.repeats,
                        "cold sweeps": cold.sweeps, "peer_tol": scene.options.tol, "peer_residual": cold.residual}
            with tempfile.TemporaryDirectory() as tmp:
                path = r.save_material(Path(tmp) / "edited.npz")
                mat = dataclasses.replace(scene.material, nodes=str(path), preset=None, procedural=None)
                opts = dataclasses.replace(scene.options, tol=ref_tol,
                                           scheme="multigrid" if scene.polygrid.discretisation != "fem" else scene.options.scheme)
                with Renderer(status=say, frame_sweeps=frame_sweeps) as rr:   # the same model options; cold: to tol
                    ref, _ = rr.render(dataclasses.replace(scene, material=mat, options=opts))
        errs = [rel_l2(im, ref) for _, im in after]
        for j, ((t, _), e) in enumerate(zip(after, errs)):
            frames.append({"model": name, "phase": "after stroke", "frame": j, "edit_ms": np.nan, "frame_ms": np.nan,
                           "t2_ms": np.nan, "t3_ms": np.nan, "nodes_edited": np.nan, "since_edit_s": t, "rel_l2": e})
        hit = [t for (t, _), e in zip(after, errs) if e <= CONVERGED]
        paper = TABLE_III.get(name, ("", np.nan, np.nan))
        summary.append({"model": name, "nodes": rep0.nodes, "first frame s (cold)": first,
                        "edit ms": 1e3 * float(np.median(t_edit)), "t2 ms/frame": 1e3 * float(np.median(t2s)),
                        "t3 ms/frame": 1e3 * float(np.median(t3s)), "fps editing": float(np.median(stroke_fps)),
                        "to 0.5 % s": hit[0] if hit else np.nan, "to tol s": converged_s,
                        "err at tol": errs[-1], **peer,
                        "paper polygrid": paper[0], "paper fps": paper[1], "paper fps coherent": paper[2]})
    return summary, frames


def save_edit_study(summary: list[dict], frames: list[dict], out: str | Path) -> tuple[Path, Path, Path]:
    """CSV of the summary and of the frames, and a PNG: image error against time after the last dab."""
    out = Path(out)
    s = io.write_csv(out / "edit_summary.csv", summary)
    f = io.write_csv(out / "edit_frames.csv", frames)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for name in dict.fromkeys(r["model"] for r in frames):
        pts = [(r["since_edit_s"], r["rel_l2"]) for r in frames if r["model"] == name and r["phase"] == "after stroke"]
        if pts:
            t, e = zip(*pts)
            ax.semilogy(t, np.maximum(e, 1e-6), "o-", ms=3, label=name)
    ax.axhline(CONVERGED, color="grey", ls="--", lw=0.8, label="0.5 %")
    ax.set_xlabel("seconds after the last edit (edit + frames, pass 2 warm-started)")
    ax.set_ylabel("image error vs converged (rel. L2)")
    ax.set_title("Editing: frame-coherent convergence after a brush stroke")
    ax.legend(fontsize=8)
    png = out / "edit_convergence.png"
    save_figure(fig, png)
    return s, f, png
