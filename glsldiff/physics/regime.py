"""Where the renderer's models were validated, and warnings for scenes outside it.

``glsldiff validate`` compares renders with the scene defaults against all-order Monte Carlo
(Mitsuba 3). :data:`VALIDATED` holds the edges of what it covered and the errors measured at
those edges (the numbers of the validation table, docs/validation.md); a scene
beyond an edge gets one ``WARNING`` line naming the cause and what was measured at the edge
(:func:`warnings`). Nothing is refused here: a render outside the table is still the model's
best answer.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["VALIDATED", "Validated", "regime_warnings", "THIN_MFP"]


@dataclass(frozen=True)
class Validated:
    """The validated range of one model and the errors measured at its edges (relative RMSE or
    L2, and mean or power ratio, against Monte Carlo; ``glsldiff validate`` case named)."""

    albedo_min: float
    albedo_edge: str             # what was measured at albedo_min
    thickness_mfp: float         # thinnest slab validated, transport mean free paths
    thickness_edge: str
    eta: tuple[float, float]
    eta_edge: str


#: Below this many transport mean free paths a surface point counts as thin.
THIN_MFP = 2.0
#: The validated ranges, per model (numbers: the validation run of the closing note of the issue
#: that made the split the default; docs/validation.md).
VALIDATED = {
    "split": Validated(0.3, "front-lit sphere at albedo 0.3 (sphere-albedo0.3): relative RMSE 0.03, mean 1.00",
                       2.0, "slab 2 mean free paths thick, back-lit by a touching patch (slab-backlit-2mfp): "
                            "relative L2 0.03, power 0.96",
                       (1.0, 1.4), "environment-lit spheres at eta 1.3 (sphere-eta1.3-*) within 3 %, slab-patch at 1.4 (relative L2 0.06)"),
    "diffusion": Validated(0.95, "front-lit sphere at albedo 0.95: relative RMSE 0.10, mean 0.92; at 0.8: 0.43 and "
                                 "0.57; below 2/3 the P1 exitance is negative on lit surfaces (clamped to 0)",
                           5.0, "slab-patch-tuned (5 mm, volume source): relative L2 0.07",
                           (1.0, 1.4), "environment-lit spheres at eta 1.3 within 4 %"),
}


def regime_warnings(model: str, albedo: ArrayLike, eta: float, thickness_mfp: ArrayLike | None = None) -> list[str]:
    """One line per way the scene leaves what ``model`` was validated on: ``albedo`` per node and
    channel (the reduced albedo), ``eta``, and ``thickness_mfp``, the object's thickness at
    sampled surface points in transport mean free paths of their most transparent channel (None:
    not measured)."""
    v = VALIDATED[model]
    out = []
    a = np.asarray(albedo, dtype=np.float64)
    floor = v.albedo_min - 1e-6          # the validated albedo itself, up to round-off, is in
    if a.size and float(a.min()) < floor:
        low = float((a < floor).reshape(len(a), -1).any(axis=1).mean()) if a.ndim > 1 else 1.0
        channels = "".join(c for c, col in zip("RGB", a.reshape(-1, a.shape[-1]).T if a.ndim > 1 else [a])
                           if float(np.min(col)) < floor)
        out.append(f"albedo down to {a.min():.3g} ({channels or 'grey'}; {100 * low:.0f} % of nodes) is below the "
                   f"validated {v.albedo_min:g} of model {model}; measured there: {v.albedo_edge}")
    if not v.eta[0] <= eta <= v.eta[1]:
        out.append(f"eta = {eta:g} is outside the validated {v.eta[0]:g}-{v.eta[1]:g} of model {model}; measured "
                   f"there: {v.eta_edge}")
    if thickness_mfp is not None:
        t = np.asarray(thickness_mfp, dtype=np.float64)
        t = t[np.isfinite(t)]
        if t.size and float(t.min()) < v.thickness_mfp:
            share = float((t < v.thickness_mfp).mean())
            if share >= 0.01:
                out.append(f"{100 * share:.0f} % of the surface is thinner than {v.thickness_mfp:g} transport mean free "
                           f"paths (down to {t.min():.2g}), below what model {model} was validated on; measured at "
                           f"{v.thickness_mfp:g}: {v.thickness_edge}")
    return out
