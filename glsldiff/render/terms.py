"""Pass 3's per-vertex terms (Wang et al. 2008, section 5; Table III): numpy arrays of passes 1
and 2 in, per-vertex arrays of the render mesh out, for :func:`glsldiff.render.shading.shade`.

Per vertex:

* the **multiple-scattering** term, interpolated from the boundary nodes (the shader multiplies
  it by ``F_t(eta, n.w_o)``): with ``[options].model = "diffusion"`` the exitant bracket
  ``a phi - b q`` (:func:`glsldiff.physics.exitance.exitant_bracket`, the conventions of
  ``[options].exitant``), its ``(phi, q)`` as ``[options].flux`` says
  (:meth:`SurfaceTerms.bracket_fields`) and its ``q`` less the local term of ``[options].incidence
  = "local"`` or ``"transport"`` (the half-space's transport per incidence and view,
  :class:`glsldiff.render.load.Incidence`). On lit surfaces the bracket of ``p1``/``arbree`` can dip below
  zero where the diffusion solution undershoots (low albedo); such vertices are clamped to 0 and
  counted in the report. With the transport split (``"split"``) this term is 0 and the split's
  subsurface radiance (:mod:`glsldiff.render.split_frame`, view-dependent, >= 0 by construction)
  is added with the terms below;
* optional **single scattering** of every light in reflection and transmission
  (:mod:`glsldiff.render.single`, ``[options].single_scattering``; the split has its own);
* the **unscattered** light of area and environment lights seen through the object
  (:mod:`glsldiff.render.unscattered`, ``[options].unscattered``, default on);
* an optional measured **diffuse surface reflectance** ``rho_d / pi * E``
  (``[material].reflectance``, :mod:`glsldiff.inverse.reflectance`; ``E`` the incident
  irradiance with shadows);
* per shader light (Ward specular): the **shadow visibility**, times a projector's image factor
  (:func:`glsldiff.physics.lights.projector_factor`) as its channel mean, so the highlight takes
  the intensity's colour.

The renderer hands :class:`SurfaceTerms` a :class:`FrameInputs` each frame; every term is kept
while the stage keys (and the camera) it depends on stay the same.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence, Union

import moderngl
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff.mesh import screened_smoothing
from glsldiff.physics.exitance import bracket_smoothing_lengths, exitance_coefficients, exitant_bracket, local_bracket
from glsldiff.physics.lights import AreaLight, DirectLight, EnvironmentLight, ProjectorLight, projector_factor
from glsldiff.physics.optics import refracted_cosine
from glsldiff.render.backends import GridBackend
from glsldiff.render.load import Incidence, boundary_C
from glsldiff.render.materials import node_material, surface_reflectance
from glsldiff.render.pass1 import incident_light, visibility
from glsldiff.render.scene import Scene
from glsldiff.render.shading import MAX_SHADER_LIGHTS
from glsldiff.render.shadows import DepthRenderer
from glsldiff.render.single import light_beams, medium_lattice, scattering_frame
from glsldiff.render.split_frame import (SplitInputs, SplitResult, SplitStatic, split_again, split_radiance,
                                         split_repaint, vertex_terms)
from glsldiff.render.unscattered import sees_through, unscattered

__all__ = ["FrameInputs", "SurfaceTerms", "LIT_SHARE", "key", "lit_distance", "shader_lights"]

Array = NDArray[np.float64]
#: ``(sigma_a, sigma_s')`` RGB (mm^-1), or a function of points ``(M, 3)`` returning both ``(M, 3)``.
Medium = Union[tuple[Array, Array], Callable[[Array], tuple[Array, Array]]]

#: Surface nodes with more than this share of the largest transmitted irradiance count as lit (the
#: split's gather far field measures each node's distance to them).
LIT_SHARE = 1e-3


def key(*parts: Any) -> str:
    """A cache key: the ``repr`` of ``parts`` (a result is kept while its key stays)."""
    return repr(parts)


def shader_lights(scene: Scene) -> list[DirectLight]:
    """The lights pass 3 shades per light (all but environment and area lights, at most
    :data:`~glsldiff.render.shading.MAX_SHADER_LIGHTS`)."""
    return [lt for lt in scene.lights if not isinstance(lt, (EnvironmentLight, AreaLight))][:MAX_SHADER_LIGHTS]


def lit_distance(points: Array, E_t: Array) -> Array:
    """``(n,)`` distance (mm) of each surface node at ``points`` to the nearest lit one (transmitted
    irradiance ``E_t`` above :data:`LIT_SHARE` of its largest); 1e30 where none is lit."""
    Et = E_t.sum(axis=1)
    lit = Et > LIT_SHARE * max(float(Et.max()), 1e-300)
    return cKDTree(points[lit]).query(points)[0] if lit.any() else np.full(len(Et), 1e30)


@dataclass(frozen=True)
class FrameInputs:
    """What pass 3's terms take from the renderer for one frame (arrays are not copied)."""

    scene: Scene                    # with its options made concrete for the grid (source, single scattering)
    backend: GridBackend            # the grid family's set-up: grid, boundary values, surface triangles, h (mm)
    geo: dict[str, Any]             # set-up: "mesh", "vertices" (V, 3) mm, "normals" (V, 3), "interp" (V x n_boundary)
    kappa: Array                    # node material, backend.material_shape + (3,): mm
    mu: Array                       # mm^-1
    edited: bool                    # the node material differs from the scene's (edits, undo)
    E_t: Array                      # (n_boundary, 3) pass 1's transmitted irradiance
    incidence: Incidence            # the diffusion's load q (n_boundary, 3; 0: volume) and the local term's inputs
    beams: Sequence[tuple[Array, Array]]   # pass 1's beams: E (n_boundary, 3), refracted cosine (n_boundary,)
    phi_b: Array                    # (n_boundary, 3) pass 2's fluence at the boundary nodes
    geometry_key: str | None        # the renderer's stage keys
    material_key: str | None
    light_key: str | None
    solve_key: str | None
    solution: int                   # pass 2's solution count: a new fluence each
    edit_version: int
    eye: Array                      # (3,) the camera position, mm
    depth: DepthRenderer            # the renderer's map-keeping DepthRenderer of geo["mesh"] (shadows.py)

    @property
    def view(self) -> tuple[float, ...]:
        """The camera position as a key."""
        return tuple(np.round(np.asarray(self.eye, dtype=np.float64), 9))

    @property
    def q(self) -> Array:
        """``(n_boundary, 3)`` the diffusion's load."""
        return self.incidence.q

    def boundary_material(self) -> tuple[Array, Array]:
        """``(kappa, mu)`` ``(n_boundary, 3)`` at the surface (boundary) nodes."""
        return self.backend.boundary(self.kappa), self.backend.boundary(self.mu)


class SurfaceTerms:
    """Pass 3's per-vertex terms (module docstring), each kept while its inputs stay the same.

    What the report says of the last frame: :attr:`flux_used`, :attr:`clamped`, :attr:`split_result`,
    :attr:`single_seconds`, :attr:`unscattered_seconds`."""

    def __init__(self, ctx: moderngl.Context) -> None:
        self.ctx = ctx
        self._keys: dict[str, str] = {}          # each kept result's key
        self._kept: dict[str, Any] = {}          # the results: see _cached
        self._local: tuple[Incidence, tuple[float, ...], Array] | None = None   # the bracket's q, per load and view
        self._flux_fields: tuple[Array, Array] | None = None   # (phi, q) of the exitant bracket
        self._flux_kind: str | None = None        # the [options].flux that _flux_fields were made for
        self._flux_solution = -1                  # the pass-2 solution they were made from
        self.flux_used = ""                       # what the last bracket took its flux from
        self.clamped: tuple[int, float, int] = (0, 0.0, 0)   # vertices, depth, deep (RenderReport.clamped_*)
        self.single_seconds = 0.0
        self.unscattered_seconds = 0.0

    def _cached(self, name: str, k: str, make: Callable[[], Any]) -> Any:
        """The result ``name``: ``make()``'s, kept while the key ``k`` stays."""
        if self._keys.get(name) != k:
            self._kept[name] = make()
            self._keys[name] = k
        return self._kept[name]

    @property
    def split_result(self) -> SplitResult | None:
        """The last split frame's result (None before one)."""
        return self._kept.get("split")

    # -- the diffusion's exitant bracket ----------------------------------------------------
    def bracket_q(self, f: FrameInputs) -> Array:
        """The ``q`` of the exitant bracket: the load, less the local term of ``incidence =
        "local"`` or ``"transport"`` over ``b`` (it depends on the view: recomputed when the
        camera moves)."""
        inc = f.incidence
        if inc.beta is None:
            return inc.q
        if self._local is None or self._local[0] is not inc or self._local[1] != f.view:
            pg = f.backend.grid
            eta = f.scene.material.eta
            d = np.asarray(f.eye, dtype=np.float64)[None, :] - pg.boundary_positions
            cos = np.einsum("ij,ij->i", d, pg.normals) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
            view = np.where(cos > 0.0, refracted_cosine(eta, np.clip(cos, 0.0, 1.0)), 1.0)
            local = local_bracket(f.beams, inc.kappa, inc.mu, view, inc.beta, inc.deep)
            b = exitance_coefficients(eta, f.scene.options.exitant, boundary_C(f.scene))[1]
            self._local, self._flux_fields = (inc, f.view, inc.q - local / b), None
        return self._local[2]

    def bracket_fields(self, f: FrameInputs) -> tuple[Array, Array]:
        """The ``(phi, q)`` of the exitant bracket ``a phi - b q`` per surface node. ``[options].flux =
        "smoothed"`` (tetrahedral grids, the default): both smoothed along the surface, ``q`` over
        half a transport mean free path and ``phi`` over an eighth
        (:func:`glsldiff.physics.exitance.bracket_smoothing_lengths`): a hard light edge then leaves
        no ring and no mottle; the local fields where no light enters through the surface (the
        volume source). ``"boundary"``: the local fields (the boundary condition's flux ``(phi -
        q) / (2C)``). ``"gradient"``: ``q`` such that that expression equals the outward flux
        ``-kappa dphi/dn`` of the solution's recovered gradient (volume-weighted mean of the
        tetrahedra's gradients at each surface node)."""
        flux, be = f.scene.options.flux, f.backend
        if self._flux_solution != f.solution:      # a new pass-2 solution
            self._flux_fields, self._flux_solution = None, f.solution
        flat = be.surface_triangles is None
        if flux == "boundary" or flat or (flux == "smoothed" and not f.q.any()):
            self.flux_used = (flux if flux != "smoothed" else
                              "boundary (the lattice has no surface triangles to smooth on)" if flat
                              else "smoothed: no light enters through the surface here (volume source), so the "
                                   "local bracket")
            return f.phi_b, self.bracket_q(f)
        q_bracket = self.bracket_q(f)        # before the cache check: a new view drops the cache
        if self._flux_kind != flux:          # the kept fields are the other option's
            self._flux_fields, self._flux_kind = None, flux
        if self._flux_fields is None and flux == "smoothed":
            smooth_phi, smooth_q, _ = self._cached("smoother", key(f.geometry_key, f.material_key),
                                                   lambda: self._smoothers(f))
            self._flux_fields = (smooth_phi(f.phi_b), smooth_q(q_bracket))
        elif self._flux_fields is None:
            normal_flux = -f.boundary_material()[0] * be.normal_gradient()
            self._flux_fields = (f.phi_b, f.phi_b - 2.0 * boundary_C(f.scene) * normal_flux - (f.q - q_bracket))
        self.flux_used = self._kept["smoother"][2] if flux == "smoothed" else flux
        return self._flux_fields

    @staticmethod
    def _smoothers(f: FrameInputs) -> tuple[Callable[[Array], Array], Callable[[Array], Array], str]:
        """The smoothing of ``phi`` and of ``q`` along the surface (flux = "smoothed") and their
        report line (lengths, set-up seconds)."""
        t0 = time.perf_counter()
        lam_phi, lam_q = bracket_smoothing_lengths(f.boundary_material()[0])
        pg = f.backend.grid
        smooth_phi, smooth_q = (screened_smoothing(pg.boundary_positions, pg.surface_triangles, lam)
                                for lam in (lam_phi, lam_q))
        return smooth_phi, smooth_q, (f"smoothed along the surface, q over {lam_q.min():.3g}-{lam_q.max():.3g} mm "
                                      "(half a mean free path), phi over a quarter of that; set-up "
                                      f"{time.perf_counter() - t0:.2f} s")

    def multiple(self, f: FrameInputs) -> Array:
        """``(V, 3)`` the diffusion's exitant bracket per vertex, clamped to >= 0 (:attr:`clamped`
        counts what was below); 0 with the split (its radiance is in :meth:`added`)."""
        if f.scene.options.split:
            self.clamped = (0, 0.0, 0)
            return np.zeros_like(f.geo["vertices"])
        o = f.scene.options
        B = exitant_bracket(*self.bracket_fields(f), f.scene.material.eta, o.exitant, boundary_C(f.scene))
        ms = f.geo["interp"] @ B
        top = max(float(ms.max()), 1e-300)
        self.clamped = (int(np.any(ms < 0.0, axis=1).sum()), float(max(-ms.min(), 0.0) / top),
                        int(np.any(ms < -0.01 * top, axis=1).sum()))
        return np.maximum(ms, 0.0)

    # -- what the shader adds ---------------------------------------------------------------
    def added(self, f: FrameInputs, split_part: str | None = None) -> Array:
        """``(V, 3)`` radiance the shader adds per vertex: the split's subsurface radiance (only its
        ``split_part`` "single" or "multiple" when given) or the diffusion's single scattering,
        the diffuse surface reflection and the unscattered light."""
        o = f.scene.options
        ss = np.zeros_like(f.geo["vertices"])
        if o.split:
            sr = self.split(f)
            ss = {"single": sr.single, "multiple": sr.multiple}.get(split_part or "", sr.radiance)
            self.clamped = sr.clamped            # the split clamps the diffusion's fluence, not its exitance
        elif o.single_scattering:
            ss = self.single(f)
        if f.scene.material.reflectance is not None:
            ss = ss + self.surface_diffuse(f)
        if o.unscattered and sees_through(f.scene.lights):
            ss = ss + self.unscattered(f)
        return ss

    def visibility(self, f: FrameInputs) -> Array:
        """``(V, MAX_SHADER_LIGHTS)`` per shader light (:func:`shader_lights`): shadow visibility
        times the channel mean of its image factor (1 but for projectors); kept while the
        geometry and the lights stay."""
        def make() -> Array:
            v, nrm, mesh = f.geo["vertices"], f.geo["normals"], f.geo["mesh"]
            vis, tint = np.ones((len(v), MAX_SHADER_LIGHTS)), np.ones((len(v), MAX_SHADER_LIGHTS, 3))
            for i, light in enumerate(shader_lights(f.scene)):
                if light.shadows:
                    vis[:, i] = visibility(mesh, v, light, ctx=self.ctx, normals=nrm, depth=f.depth)
                if isinstance(light, ProjectorLight):
                    tint[:, i] = projector_factor(light, v)
            return vis * tint.mean(axis=2)     # the shader's visibility is one number per light
        return self._cached("vis", key(f.geometry_key, f.scene.lights), make)

    def split(self, f: FrameInputs) -> SplitResult:
        """The transport split's subsurface radiance per vertex (:mod:`glsldiff.render.split_frame`),
        kept while the solution, the lights, the material and the camera stay the same."""
        return self._cached("split", key(f.solve_key, f.solution, f.light_key, f.edit_version, f.view),
                            lambda: self._split(f, *self._split_static(f)))

    def _split_static(self, f: FrameInputs) -> tuple[SplitStatic | None, SplitStatic | None]:
        """The last split's fluence-independent terms: as the first item when only the fluence
        changed since (a frame converging after an edit or a light change), as the second when
        only edits changed the material too (painting: the same lights, camera and options)."""
        last = self._kept.get("split")
        kept = None if last is None else last.static
        same = key(f.material_key, f.light_key, f.edit_version, f.view, f.scene.options)
        painted = key(f.material_key, f.light_key, f.view, f.scene.options)
        fluence_only = self._keys.get("split static") == same
        edits_only = self._keys.get("split painted") == painted
        self._keys["split static"], self._keys["split painted"] = same, painted
        return (kept if fluence_only else None), (kept if edits_only and not fluence_only else None)

    def _split(self, f: FrameInputs, static: SplitStatic | None = None,
               painted: SplitStatic | None = None) -> SplitResult:
        """:func:`~glsldiff.render.split_frame.split_radiance` of the frame: the surface far field, or the
        gather's (volume source) with each node's distance to the light in mean free paths;
        ``static``: the surface far field's terms kept from the last frame (only the fluence
        changed); ``painted``: the same when edits changed the material at a few vertices
        (:func:`~glsldiff.render.split_frame.split_repaint`)."""
        geo, o = f.geo, f.scene.options
        if static is not None and o.source != "volume":
            return split_again(static, geo["interp"], f.phi_b)
        far = "gather" if o.source == "volume" else "surface"
        fluence, thick = None, None
        kappa, mu = f.boundary_material()
        if far == "gather":
            pg = f.backend.grid
            fluence = f.backend.fluence_lattice()
            dist = self._cached("lit", key(f.light_key), lambda: lit_distance(pg.boundary_positions, f.E_t))
            thick = dist[:, None] / (3.0 * kappa)   # to where light enters, in mean free paths
        march = bool(o.single_scattering) or far == "gather"
        inp = SplitInputs(far=far, march=march, eta=f.scene.material.eta,
                          C=boundary_C(f.scene), interp=geo["interp"], vertices=geo["vertices"],
                          normals=geo["normals"], beams=f.beams, kappa=kappa, mu=mu, phi=f.phi_b,
                          q=f.q, source_distance_mfp=thick, fluence=fluence, mesh=geo["mesh"], lights=f.scene.lights,
                          **(self._march_inputs(f) if march else {}))
        again = split_repaint(painted, inp) if painted is not None else None
        if again is not None:
            return again
        inp.at_vertices = self._cached("split vertex terms", key(f.geometry_key, f.material_key, f.edit_version,
                                                                 f.light_key, f.scene.material.eta),
                                       lambda: vertex_terms(inp))
        return split_radiance(inp, f.eye)

    def _march_inputs(self, f: FrameInputs) -> dict[str, Any]:
        """The 3-D march's medium lattice and the lights' beams (depth maps), kept while the
        material, respectively the lights and the geometry, stay (a camera move re-marches the
        view rays only)."""
        mesh = f.geo["mesh"]
        medium = self._cached("march medium", key(f.material_key, f.edit_version, f.geometry_key),
                              lambda: medium_lattice(self.medium(f), mesh))

        beams = self._cached("march beams", key(f.geometry_key, f.light_key),   # pass 1's maps, faces added
                             lambda: light_beams(f.scene.lights, f.depth))
        return {"medium": medium, "march_beams": beams}

    def single(self, f: FrameInputs) -> Array:
        """Per-vertex single scattering of every light, reflection and transmission
        (:mod:`glsldiff.render.single`), kept while the camera, lights, material and geometry
        stay the same; its time is :attr:`single_seconds`."""
        def make() -> Array:
            t0, geo, m = time.perf_counter(), f.geo, self._march_inputs(f)
            out = scattering_frame(geo["mesh"], geo["vertices"], geo["normals"], f.eye, f.scene.material.eta,
                                   f.scene.lights, m["medium"], None, beams=m["march_beams"])[0]
            self.single_seconds = time.perf_counter() - t0
            return out
        return self._cached("single", key(f.material_key, f.light_key, f.edit_version, f.view), make)

    def unscattered(self, f: FrameInputs) -> Array:
        """Per-vertex unscattered light seen through the object (:mod:`glsldiff.render.unscattered`),
        kept while the camera, lights, material and geometry stay the same; its time is
        :attr:`unscattered_seconds`."""
        def make() -> Array:
            t0, geo, medium = time.perf_counter(), f.geo, self.medium(f)
            sigma_t: Any = (lambda p: np.add(*medium(p))) if callable(medium) else medium[0] + medium[1]
            out = unscattered(geo["mesh"], geo["vertices"], geo["normals"], f.eye, f.scene.material.eta,
                              f.scene.lights, sigma_t, float((1.0 / (3.0 * f.kappa)).min()))
            self.unscattered_seconds = time.perf_counter() - t0
            return out
        return self._cached("unscattered", key(f.material_key, f.light_key, f.edit_version, f.view), make)

    def surface_diffuse(self, f: FrameInputs) -> Array:
        """Per-vertex measured diffuse surface reflection ``rho_d / pi * E`` (Lambertian), with
        ``E`` the incident irradiance of all lights (shadows, environment visibility);
        kept until the lights, the geometry or the reflectance change (a change of the
        reflectance alone re-runs neither the material stage nor pass 1-2)."""
        geo, mat = f.geo, f.scene.material
        rho_key = key(f.geometry_key, mat.reflectance, mat.volume)
        rho = self._cached("rho", rho_key, lambda: geo["interp"] @ surface_reflectance(f.scene, f.backend.grid))
        return self._cached("diffuse", key(rho_key, f.light_key), lambda: rho * incident_light(
            geo["mesh"], geo["vertices"], geo["normals"], f.scene.lights, None, ctx=self.ctx, depth=f.depth)[0]
            / math.pi)

    def medium(self, f: FrameInputs) -> Medium:
        """The material for path integrals through the object: ``(sigma_a, sigma_s')`` RGB
        arrays (mm^-1) when homogeneous, else a function of points ``(M, 3)`` returning both
        ``(M, 3)``, evaluated in the nodes' unit box; after edits, the edited node material at
        the nearest node (and so for a block volume or a node material: their values exist at the
        nodes only)."""
        scene, pg = f.scene, f.backend.grid
        lo, hi = pg.positions.min(axis=0), pg.positions.max(axis=0)
        if f.edited or scene.material.volume or scene.material.nodes:
            nodes = np.flatnonzero(f.backend.active)
            tree = self._cached("node_tree", key(f.geometry_key),      # once per grid, not per edit
                                lambda: cKDTree(np.asarray(pg.positions).reshape(-1, 3)[nodes]))
            k_all, m_all = (a.reshape(-1, 3)[nodes] for a in (f.kappa, f.mu))

            def edited(p: NDArray) -> tuple[NDArray, NDArray]:
                _, i = tree.query(p)
                return m_all[i], np.maximum(1.0 / (3.0 * k_all[i]) - m_all[i], 0.0)
            return edited

        def material(p: NDArray) -> tuple[NDArray, NDArray]:
            kappa, mu, _ = node_material(scene, np.vstack([lo, hi, p]), pg)   # same unit box as the nodes
            kappa, mu = kappa[2:], mu[2:]
            return mu, np.maximum(1.0 / (3.0 * kappa) - mu, 0.0)

        if scene.material.procedural:
            return material
        sa, ss = material(f.geo["vertices"][:1])
        return sa[0], ss[0]

