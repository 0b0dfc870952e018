"""Per-node material of a scene: kappa (mm) and mu (mm^-1) at every polygrid node.

* homogeneous: a preset or ``sigma_a`` / ``sigma_s_prime``;
* procedural, evaluated over the nodes' bounding box (unit coordinates ``u`` in [0, 1]^3):
  ``veins`` (:func:`glsldiff.physics.procedural.marble_volume` on a 64^3 lattice, trilinear),
  ``layers`` and ``inclusions`` (:func:`glsldiff.physics.procedural.point_weight`: bands
  along +y bent by smooth noise, seeded spheres filling 5 % of the volume, or ``sphere``: one
  ball at the box centre, radius 0.3 of its smallest extent);
* a block volume file (``.npz`` with ``kappa``, ``mu`` of shape ``(nz, ny, nx, 3)`` and
  ``h_mm``), mapped through a shell layer (:func:`glsldiff.render.shellmap.map_shell`);
* a node material file (``[material].nodes``: the editor's saved material, ``kappa``, ``mu``,
  ``positions_mm`` of shape ``(N, 3)``): each node takes the nearest saved node's values
  (exact on the grid it was saved from).

Blending happens on the optical coefficients (sigma_a, sigma_s'), then kappa and mu are
derived, so every node stays physical.

:func:`surface_reflectance` gives the optional diffuse surface albedo at the boundary
nodes: a constant, or a measured map over the block's face tiled like the volume
(:func:`glsldiff.render.shellmap.map_surface`).
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import scipy
from numpy.typing import NDArray
from scipy.ndimage import map_coordinates
from scipy.spatial import cKDTree

from glsldiff.core import cache
from glsldiff.core.io import read_image
from glsldiff.physics import procedural
from glsldiff.physics.material import Preset, coefficients, preset
from glsldiff.physics.procedural import blend, default_vein, marble_volume, point_weight, unit_box
from glsldiff.render.scene import MaterialSpec, Scene, block_volume, node_volume
from glsldiff.render.shellmap import map_shell, map_surface


def _pair(spec: MaterialSpec) -> tuple[NDArray, NDArray]:
    """(sigma_a, sigma_s') of the base material, mm^-1."""
    if spec.sigma_a is not None:
        return np.asarray(spec.sigma_a, float), np.asarray(spec.sigma_s_prime, float)
    p = preset(spec.preset or "marble")
    return np.asarray(p.sigma_a, float), np.asarray(p.sigma_s_prime, float)


def _second(spec: MaterialSpec, base: tuple[NDArray, NDArray]) -> tuple[NDArray, NDArray]:
    if spec.vein is not None:
        p = preset(spec.vein)
        return np.asarray(p.sigma_a, float), np.asarray(p.sigma_s_prime, float)
    return default_vein(base)   # darker, more absorbing (as marble_volume's default vein)


@lru_cache(maxsize=4)
def _vein_lattice(cells: int, seed: int, sigma_a: tuple, sigma_s_prime: tuple, eta: float,
                  base_name: str | None, vein_name: str | None) -> tuple[NDArray, NDArray]:
    """The veins lattice, built once per material (single scattering samples the material
    many times per frame) and kept in the on-disk cache (:mod:`glsldiff.core.cache`; 0.3 s at
    64^3), keyed by the two materials' coefficients, the seed and the noise's code (the source
    of :mod:`glsldiff.physics.procedural`, numpy's and scipy's versions)."""
    base = preset(base_name) if base_name else Preset("custom", np.array(sigma_s_prime), np.array(sigma_a), eta)
    vein = preset(vein_name) if vein_name else None
    key = cache.digest("vein lattice", Path(procedural.__file__).read_bytes(), np.__version__, scipy.__version__,
                       cells, seed, base.sigma_s_prime, base.sigma_a, base.eta,
                       *(("default vein",) if vein is None else (vein.sigma_s_prime, vein.sigma_a)))
    return cache.memo("veins", key, tuple,
                      lambda: marble_volume((cells,) * 3, seed=seed, base=base, vein=vein))


def _block(scene: Scene) -> tuple[NDArray, NDArray, float]:
    """kappa, mu and h_mm of the scene's block volume file."""
    return block_volume(scene.resolve(scene.material.volume), f"{scene.source}: [material].volume: file")


def surface_reflectance(scene: Scene, polygrid: Any) -> NDArray[np.float64] | None:
    """``(n_boundary, 3)`` diffuse surface albedo at the boundary nodes, or ``None`` without
    ``[material].reflectance``. A map has one pixel per block voxel (``h_mm``) in x-y, e.g.
    the face nodes of :func:`glsldiff.inverse.reflectance.diffuse_reflectance`, and is tiled
    like the volume; values are clipped to [0, 1]."""
    r = scene.material.reflectance
    if r is None:
        return None
    nb = len(polygrid.boundary_positions)
    if not isinstance(r, str):
        return np.tile(np.asarray(r, dtype=np.float64), (nb, 1))
    _, _, h = _block(scene)
    img = read_image(scene.resolve(r), exr_only=True)[..., :3]
    rho = map_surface(polygrid, img, (img.shape[1] * h, img.shape[0] * h))
    return np.clip(rho, 0.0, 1.0)


def node_material(scene: Scene, positions: NDArray, polygrid: Any = None) -> tuple[NDArray, NDArray, dict]:
    """``(N, 3)`` kappa (mm) and mu (mm^-1) at ``positions`` (mm), and a small info dict."""
    spec = scene.material
    base = _pair(spec)
    n = len(positions)
    if spec.volume is not None:
        path = scene.resolve(spec.volume)
        kb, mb, h = _block(scene)
        core: Any = spec.core if spec.core == "mean" else preset(spec.core)
        kappa, mu, info = map_shell(polygrid, kb, mb, h, core=core, thickness_mm=spec.shell_mm)
        return kappa.reshape(-1, 3), mu.reshape(-1, 3), {"material": f"volume {path.name} via shell", **info}
    if spec.nodes is not None:
        path = scene.resolve(spec.nodes)
        ks, ms, ps = node_volume(path, f"{scene.source}: [material].nodes: file")
        dist, idx = cKDTree(ps).query(np.asarray(positions, dtype=np.float64))
        return ks[idx], ms[idx], {"material": f"nodes {path.name} ({len(ps):,} saved nodes, nearest within "
                                              f"{float(dist.max()):.3g} mm)"}
    if spec.procedural is None:
        kappa, mu = coefficients(base[0], base[1])
        return (np.broadcast_to(kappa, (n, 3)).copy(), np.broadcast_to(mu, (n, 3)).copy(),
                {"material": spec.preset or "coefficients"})
    if spec.procedural == "veins":
        cells = 64
        kv, mv = _vein_lattice(cells, spec.seed, tuple(base[0]), tuple(base[1]), spec.eta,
                               spec.preset if spec.sigma_a is None else None, spec.vein)
        coords = (unit_box(positions) * (cells - 1)).T[::-1]   # (z, y, x) lattice order
        kappa = np.stack([map_coordinates(kv[..., c], coords, order=1, mode="nearest") for c in range(3)], -1)
        mu = np.stack([map_coordinates(mv[..., c], coords, order=1, mode="nearest") for c in range(3)], -1)
        return kappa, mu, {"material": f"veins over {spec.preset or 'marble'}"}
    t = point_weight(spec.procedural, positions, spec.seed)[:, None]
    kappa, mu = blend(base, _second(spec, base), t)
    return np.asarray(kappa), np.asarray(mu), {"material": f"{spec.procedural}, second material share "
                                                           f"{float(t.mean()):.2f}"}
