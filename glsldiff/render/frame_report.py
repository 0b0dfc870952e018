"""The notes and warnings a frame's :class:`~glsldiff.render.report.RenderReport` gets after pass 3:
the grid backend's lines, the model that rendered it and how (the incidence of
:mod:`glsldiff.render.load`; the flux and the seconds of single scattering and unscattered
light of :class:`~glsldiff.render.terms.SurfaceTerms`), the
material and its regime, pass 1's light lines, and the warnings where the scene leaves what its
model was validated on (:mod:`glsldiff.physics.regime`: albedo, eta, thin parts, a grid coarser
than the mean free path under the volume source, a camera inside the object).

The ray casts these need (the object's thickness under surface nodes, whether the camera is
inside) run once per grid and per camera.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.core import cache
from glsldiff.mesh.inside import contains
from glsldiff.mesh.raycast import first_hits
from glsldiff.physics.material import regime
from glsldiff.physics.regime import regime_warnings
from glsldiff.render.report import RenderReport
from glsldiff.render.load import GATHER_MAX_H_SIGMA, h_sigma_t
from glsldiff.render.terms import FrameInputs, SurfaceTerms, key
from glsldiff.render.unscattered import sees_through

__all__ = ["FrameNotes", "THICKNESS_SAMPLES"]

#: Surface nodes whose thickness the regime check measures (a ray cast each, once per grid).
THICKNESS_SAMPLES = 4000


class FrameNotes:
    """Fills a frame's report after pass 3 (module docstring), keeping its ray casts."""

    def __init__(self) -> None:
        self._thickness: tuple[str | None, NDArray[np.int64], NDArray[np.float64]] | None = None   # key, nodes, mm
        self._inside: tuple[str, bool] | None = None
        self._regime: tuple[str, str, list[str]] | None = None   # key, the regime line, its warnings

    def fill(self, rep: RenderReport, f: FrameInputs, terms: SurfaceTerms, material: Any, model_note: str,
             light_info: Sequence[dict[str, Any]]) -> None:
        """Add the frame ``f``'s notes and warnings to ``rep``: ``terms`` rendered its pass 3,
        ``material`` names the node material, ``model_note`` says why the model differs from the
        scene's (or is empty), ``light_info`` holds pass 1's line per light."""
        scene, o = f.scene, f.scene.options
        rep.clamped_vertices, rep.clamped_depth, rep.clamped_deep = terms.clamped
        rep.notes.extend(f.backend.notes(scene))
        through = o.unscattered and sees_through(scene.lights)
        if o.split:
            sr = terms.split_result
            assert sr is not None
            rep.notes.append(f"{sr.info}; {sr.seconds:.2f} s")
            model = f"model: split; source: {o.source}; "
            rep.model = (f"split ({'gather' if o.source == 'volume' else 'surface'} far field, single "
                         f"scattering {'3-D march' if o.single_scattering else 'closed form'})")
        else:
            rep.model = f"diffusion ({o.source} source, {o.exitant})"
            model = (f"model: diffusion; exitant: {o.exitant}; source: {o.source}; incidence: "
                     f"{f.incidence.note}; flux: {terms.flux_used}; single scattering: "
                     f"{f'{terms.single_seconds:.2f} s' if o.single_scattering else 'off'}; ")
        if model_note:
            rep.notes.append(model_note)
        rep.notes.append(f"material: {material}; {model}"
                         f"unscattered light: {f'{terms.unscattered_seconds:.2f} s' if through else 'off'}; "
                         f"diffuse surface reflectance: "
                         f"{'off' if scene.material.reflectance is None else scene.material.reflectance}")
        line, warnings = self._material_regime(f)
        rep.notes.append(line)
        rep.warnings = list(warnings)
        eye = f.eye
        if self._camera_inside(f):
            rep.warnings.append(f"the camera at ({eye[0]:.4g}, {eye[1]:.4g}, {eye[2]:.4g}) mm is inside the object: "
                                "the image shows the inside of its surface, which no validated case covers (light "
                                "reaching a camera inside the medium is not modelled); move [camera].position out")
        for info in light_info:
            rep.notes.append("light: " + ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                                                   for k, v in info.items()))

    def _material_regime(self, f: FrameInputs) -> tuple[str, list[str]]:
        """The regime line and :meth:`regime_warnings`, kept while the geometry, the material
        (edits too), eta and the options stay (a camera move keeps them)."""
        k = key(f.geometry_key, f.material_key, f.edit_version, f.scene.material.eta, f.scene.options)
        if self._regime is None or self._regime[0] != k:
            self._regime = (k, regime(f.kappa, f.mu, f.backend.h, f.scene.options.model), self.regime_warnings(f))
        return self._regime[1], self._regime[2]

    def regime_warnings(self, f: FrameInputs) -> list[str]:
        """The scene's ways out of what its model was validated on (:mod:`glsldiff.physics.regime`):
        albedo, eta and thin parts, the object's thickness along the inward normal at up to
        :data:`THICKNESS_SAMPLES` surface nodes (ray cast once per grid) over the transport mean
        free path of their most transparent channel."""
        pick, T = self._thickness_samples(f)
        kappa, mu = f.boundary_material()
        st_min = (1.0 / (3.0 * kappa[pick])).min(axis=1)
        albedo = np.clip(1.0 - 3.0 * kappa * mu, 0.0, 1.0)
        o = f.scene.options
        out = regime_warnings("split" if o.split else "diffusion", albedo, f.scene.material.eta, T * st_min)
        hs = h_sigma_t(f.backend.h, f.kappa)
        if o.split and o.source == "volume" and hs > GATHER_MAX_H_SIGMA:
            out.append(f"source = \"volume\" on a grid coarser than the mean free path (node spacing x sigma_t' up "
                       f"to {hs:.2g}, resolved below {GATHER_MAX_H_SIGMA:g}): the gathered far field reads low there "
                       "(1-D: 0.93 of the converged value at 1, 0.85 at 2); leave [options].source to \"auto\" or "
                       "give [polygrid] cubes more")
        return out

    def _thickness_samples(self, f: FrameInputs) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """The sampled surface nodes and the object's thickness (mm) along their inward normals:
        ray casts once per grid, kept in the disk cache with it."""
        if self._thickness is None or self._thickness[0] != f.geometry_key:
            pg, mesh = f.backend.grid, f.geo["mesh"]
            S = len(pg.boundary_positions)
            pick = np.unique(np.linspace(0, S - 1, min(S, THICKNESS_SAMPLES)).astype(np.int64))
            p, n, h = pg.boundary_positions[pick], -np.asarray(pg.normals)[pick], f.backend.h
            k = cache.digest("thickness v1", mesh.vertices, mesh.faces, p, n, h)
            T = cache.memo("thickness", k, np.ndarray, lambda: first_hits(mesh, p, n, t_min=0.5 * h)[0])
            self._thickness = (f.geometry_key, pick, T)
        return self._thickness[1], self._thickness[2]

    def _camera_inside(self, f: FrameInputs) -> bool:
        """Whether the camera is inside the object (a ray cast: once per camera, not per frame)."""
        k = key(f.geometry_key, f.view)
        if self._inside is None or self._inside[0] != k:
            self._inside = (k, bool(contains(f.geo["mesh"], np.asarray(f.eye)[None, :])[0]))
        return self._inside[1]
