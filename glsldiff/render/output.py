"""Output files of a render: the EXR (linear radiance) path check and the EXR + tone-mapped PNG."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from glsldiff.core import io
from glsldiff.render.report import RenderReport
from glsldiff.render.scene import Scene


def check_output(path: str | os.PathLike) -> Path:
    """Refuse an output path that cannot be written, before any work (see :func:`glsldiff.core.io.check_output`)."""
    return io.check_output(path, (".exr",), "a tone-mapped .png and the report's .json are written beside it",
                           beside=(".png", ".json"))


def auto_exposure(img: NDArray) -> float:
    """Scale that maps the 99th percentile of the lit pixels' luminance to 0.9."""
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    lit = lum[lum > 0]
    return 0.9 / float(np.percentile(lit, 99)) if lit.size else 1.0


def save(img: NDArray, path: Path, scene: Scene, rep: RenderReport) -> tuple[Path, Path, float]:
    """EXR (linear radiance), a tone-mapped PNG and the full report as JSON beside it, written
    together (all or none)."""
    exposure = auto_exposure(img) if scene.output.exposure == "auto" else float(scene.output.exposure)
    attrs = {"glsldiff_scene": scene.source, "glsldiff_renderer": rep.renderer,
             "glsldiff_t1_t2_t3_ms": "/".join(f"{rep.seconds.get(k, 0) * 1e3:.1f}" for k in ("t1", "t2", "t3"))}
    report = {"scene": scene.source, "exposure": exposure, **rep.as_dict()}
    exr, png = io.write_exr_png(path, img, io.tonemap(img, exposure), attributes=attrs,
                                sidecar=json.dumps(report, indent=1, default=str) + "\n")
    return exr, png, exposure
