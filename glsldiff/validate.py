"""``glsldiff validate``: the diffusion renderer against Monte Carlo (Mitsuba 3) and the dipole.

Each case is rendered twice with the same mesh, camera, light and material: by
:class:`glsldiff.render.Renderer` (multiple scattering only: no specular, no single
scattering) and by Mitsuba 3's ``volpath`` (:mod:`glsldiff.mitsuba_ref`), whose image is split
into scattering orders so that its *multiple-scattering* part is what is compared. The
boundary is index matched (eta = 1, Mitsuba ``null`` BSDF): a directional light cannot be
reached through a smooth dielectric by next-event estimation, and scattering orders can only
be separated with a null boundary.

Error: relative RMSE ``sqrt(mean (L - L_mc)^2 / mean L_mc^2)`` over the pixels inside the
object in both images, one pixel away from the silhouette (anti-aliased edge pixels differ by
construction); also the ratio of the means (a global scale error) and the Monte Carlo noise
level (standard error of the mean image, from two half-sample renders).

The slab case also reports the face-centre radiance against the dipole's total diffuse
reflectance (``L = rho_dipole E / pi``; the slab is 20 transport mean free paths thick, so the
semi-infinite dipole applies).
"""
from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import binary_erosion

from glsldiff.errors import InputError
from glsldiff.scene import CameraSpec, LightSpec, MaterialSpec, MeshSpec, OutputSpec, PolygridSpec, Scene, SpecularSpec


@dataclass(frozen=True)
class Case:
    name: str
    mesh: str                       # "sphere" or "slab" or a sample name
    size_mm: float
    sigma_a: float
    sigma_s: float
    light: tuple[float, float, float]
    camera_dir: tuple[float, float, float]
    procedural: str | None = None
    n: int = 8
    cubes: int = 64


CASES = {
    "slab": Case("slab", "slab", 60.0, 0.005, 1.0, (0.0, 0.0, 1.0), (0.0, 0.35, 1.0), n=8, cubes=36),
    "sphere": Case("sphere", "sphere", 20.0, 0.005, 1.0, (1.0, 0.3, 0.6), (0.0, 0.0, 1.0)),
    "sphere-albedo0.9": Case("sphere-albedo0.9", "sphere", 20.0, 0.11, 1.0, (1.0, 0.3, 0.6), (0.0, 0.0, 1.0)),
    "sphere-veins": Case("sphere-veins", "sphere", 20.0, 0.005, 1.0, (1.0, 0.3, 0.6), (0.0, 0.0, 1.0),
                         procedural="veins"),
    "bunny-veins": Case("bunny-veins", "bunny", 60.0, 0.005, 1.0, (-0.4, 0.7, 0.6), (0.0, 0.2, 1.0),
                        procedural="veins", n=4, cubes=120),
}


def _scene(case: Case, mesh_path: str | None, size: int) -> Scene:
    return Scene(mesh=MeshSpec(mesh_path or case.mesh, case.size_mm),
                 polygrid=PolygridSpec(case.n, case.cubes, 3 if case.n >= 8 else (2 if case.n >= 6 else 1)),
                 material=MaterialSpec(preset=None, sigma_a=(case.sigma_a,) * 3, sigma_s_prime=(case.sigma_s,) * 3,
                                       eta=1.0, procedural=case.procedural),
                 lights=(LightSpec("directional", direction=case.light, irradiance=(1.0, 1.0, 1.0), shadows=True),),
                 camera=CameraSpec(fov_deg=30.0), output=OutputSpec(size, size), specular=SpecularSpec(0.0, 0.2))


def rmse(ours: NDArray, ref: NDArray, mask: NDArray) -> float:
    """Relative RMSE over ``mask``."""
    a, b = ours[mask], ref[mask]
    return float(math.sqrt(np.mean((a - b) ** 2) / np.mean(b ** 2)))


def _slab_file(folder: Path, size: float) -> str:
    from glsldiff.mesh import box_mesh

    m = box_mesh((size, size, size / 3.0), origin=(-size / 2, -size / 2, -size / 3.0))
    import trimesh

    path = folder / "slab.ply"
    trimesh.Trimesh(m.vertices, m.faces, process=False).export(path)
    return str(path)


def _volume(scene: Scene, pg: Any, cells: int = 48) -> dict[str, Any]:
    """The scene's procedural material on a regular grid spanning the nodes' bounding box
    (the same unit box :mod:`glsldiff.volume` evaluates it in), for Mitsuba."""
    from glsldiff.volume import node_material

    lo, hi = pg.positions.min(axis=0), pg.positions.max(axis=0)
    axes = [np.linspace(lo[i], hi[i], cells) for i in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    kappa, mu, _ = node_material(scene, pts, pg)
    sa = mu.reshape(cells, cells, cells, 3)
    ss = np.maximum(1.0 / (3.0 * kappa) - mu, 0.0).reshape(cells, cells, cells, 3)
    h = (hi - lo) / (cells - 1)
    return {"sigma_a": sa, "sigma_s": ss, "bbox_min": lo - h / 2, "bbox_max": hi + h / 2}


def run_case(case: Case, size: int = 64, spp: int = 256, seed: int = 0) -> tuple[dict[str, Any], dict[str, NDArray]]:
    """One case: (row of numbers, images {"diffusion", "mc_multiple", "mc_full"})."""
    from glsldiff.mitsuba_ref import McCamera, render_scattering_orders
    from glsldiff.optics import dipole_total_reflectance
    from glsldiff.render import Renderer, frame_camera

    with tempfile.TemporaryDirectory() as tmp:
        mesh_path = _slab_file(Path(tmp), case.size_mm) if case.mesh == "slab" else None
        scene = _scene(case, mesh_path, size)
        d = np.asarray(case.camera_dir, float)
        with Renderer() as r:
            _, rep1 = r.render(scene)             # set-up, passes 1-3 (camera framed automatically)
            eye, target, up = frame_camera(scene, r.mesh.vertices)
            dist = float(np.linalg.norm(eye - target))
            eye = target + dist * d / np.linalg.norm(d)
            scene = replace(scene, camera=CameraSpec(tuple(eye), tuple(target), tuple(up), scene.camera.fov_deg))
            ours, rep = r.render(scene)           # the compared view: pass 3 only
            rep.seconds.update({k: rep1.seconds[k] for k in ("t1", "t2") if k in rep1.seconds})
            rep.solver = rep1.solver
            ours_s = rep.frame_seconds
            pg, mesh = r.polygrid, r.mesh
            volume = _volume(scene, pg) if case.procedural else None
    cam = McCamera(tuple(eye), tuple(target), tuple(up), scene.camera.fov_deg, size, size)
    light = {"type": "directional", "direction": case.light, "irradiance": (1.0, 1.0, 1.0)}
    sa, ss = (None, None) if volume else ((case.sigma_a,) * 3, (case.sigma_s,) * 3)
    half = max(spp // 2, 1)
    img_a, info = render_scattering_orders(mesh, sa, ss, 1.0, cam, light, spp=half, seed=seed, volume=volume)
    img_b, info_b = render_scattering_orders(mesh, sa, ss, 1.0, cam, light, spp=half, seed=seed + 1, volume=volume)
    mc = {k: 0.5 * (img_a[k] + img_b[k]) for k in img_a}
    mc_s = info["seconds_total"] + info_b["seconds_total"]
    inside = binary_erosion((ours.sum(axis=2) > 0) & (mc["full"].sum(axis=2) > 0), iterations=1)
    if inside.sum() < 16:
        raise InputError(f"case {case.name}: the object covers too few pixels ({int(inside.sum())}) to compare")
    noise = 0.5 * rmse(img_a["multiple"], img_b["multiple"], inside)   # of the mean of the two halves
    albedo = case.sigma_s / (case.sigma_s + case.sigma_a)
    row: dict[str, Any] = {
        "case": case.name, "albedo": albedo, "material": case.procedural or "homogeneous",
        "nodes": rep.nodes, "pixels": int(inside.sum()),
        "rmse_vs_mc_multiple": rmse(ours, mc["multiple"], inside),
        "rmse_vs_mc_all_scattering": rmse(ours, mc["single"] + mc["multiple"], inside),
        "mean_ratio": float(ours[inside].mean() / mc["multiple"][inside].mean()),
        "mc_noise": noise, "single_share": float(mc["single"][inside].sum() /
                                                 max((mc["single"] + mc["multiple"])[inside].sum(), 1e-30)),
        "diffusion_s": ours_s, "t1_t2_t3_ms": "/".join(f"{rep.seconds.get(k, 0) * 1e3:.0f}" for k in ("t1", "t2", "t3")),
        "mc_s": mc_s, "spp": 2 * half, "solver_residual": rep.solver.residual if rep.solver else math.nan,
    }
    if case.mesh == "slab":
        c = size // 2
        patch = (slice(c - 2, c + 3), slice(c - 2, c + 3))
        rho = float(np.asarray(dipole_total_reflectance(case.sigma_a, case.sigma_s, 1.0)))
        row["centre_diffusion"] = float(ours[patch].mean())
        row["centre_mc_multiple"] = float(mc["multiple"][patch].mean())
        row["centre_dipole"] = rho * 1.0 * abs(case.light[2]) / np.linalg.norm(case.light) / math.pi
    return row, {"diffusion": ours, "mc_multiple": mc["multiple"], "mc_full": mc["full"]}


def validate(cases: Sequence[str], out: Path, size: int = 64, spp: int = 256) -> list[dict[str, Any]]:
    """Run ``cases``; write validation.csv and one PNG per case (diffusion | MC multiple | MC all)."""
    from glsldiff import io

    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise InputError(f"unknown validation case {unknown[0]!r}; valid: {', '.join(CASES)}")
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in cases:
        row, imgs = run_case(CASES[name], size, spp)
        rows.append(row)
        expo = 0.8 / max(float(np.percentile(imgs["mc_full"], 99)), 1e-12)
        sheet = io.contact_sheet([imgs["diffusion"], imgs["mc_multiple"], imgs["mc_full"]], 3, expo, scale=2)
        io.write_png(out / f"validation_{name}.png", sheet)
        io.write_exr(out / f"validation_{name}_diffusion.exr", imgs["diffusion"])
        io.write_exr(out / f"validation_{name}_mc_multiple.exr", imgs["mc_multiple"])
        io.write_csv(out / "validation.csv", rows)
    return rows
