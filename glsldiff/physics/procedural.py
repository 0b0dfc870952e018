"""Procedural heterogeneous volumes: smooth noise, the weight ``t`` in [0, 1] of a second
material (veins, layers, inclusions), and the volumes built from them, as kappa [mm] and
mu [mm^-1] per node and RGB channel.

Two materials are blended on their optical coefficients, ``(1 - t) base + t second`` for
sigma_a and sigma_s' [mm^-1] (:func:`blend`), and kappa and mu are derived from the blend
(:func:`glsldiff.physics.material.coefficients`), so every node stays physical.

Generators come in two families, one per domain; each is pinned by tests, fits and
benchmarks, so the variants are kept as they are, side by side, rather than merged:

========== ================================================ ==========================================
weight     node grid ``S = (nz, ny, nx)`` (1-3 axes)        scattered nodes ``(N, 3)`` mm (scenes)
========== ================================================ ==========================================
noise      :func:`lattice_noise`: octaves over the grid     :func:`point_noise`: one octave at points
veins      :func:`vein_weight` (sin-turbulence marble)      :func:`marble_volume` on a lattice, sampled
layers     ``synthetic_volume("layers")``: three z-layers   :func:`layer_weight`: noisy bands along +y
inclusions :func:`depth_inclusions`: balls in depth bands   :func:`inclusion_weight`: 5 % random balls
========== ================================================ ==========================================

Grid volumes: :func:`marble_volume` (veins), :func:`synthetic_volume` (the inverse fit's
ground truth: layers, veins, inclusions, mixed), :func:`random_volume` (white-noise solver
tests). Scene weights at nodes: :func:`point_weight`, in unit coordinates of the nodes'
bounding box (:func:`unit_box`).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from glsldiff.core.checks import choice, real
from glsldiff.core.errors import InputError
from glsldiff.physics.material import Preset, coefficients, preset

__all__ = ["VEIN_ABSORPTION", "VEIN_SCATTERING", "SYNTHETIC_KINDS", "POINT_KINDS", "lattice_noise",
           "point_noise", "unit_box", "vein_weight", "layer_weight", "inclusion_weight",
           "depth_inclusions", "sphere_weight", "point_weight", "default_vein", "blend", "marble_volume",
           "random_volume", "synthetic_volume"]

Array = NDArray[np.float64]
Pair = tuple[Array, Array]  # (sigma_a, sigma_s') [mm^-1], each (3,)

VEIN_ABSORPTION = 20.0  # default second material: base sigma_a times this ...
VEIN_SCATTERING = 0.5   # ... and base sigma_s' times this (darker, more absorbing)
SYNTHETIC_KINDS = ("layers", "veins", "inclusions", "mixed", "bands")
POINT_KINDS = ("layers", "inclusions", "sphere")


def _grid_shape(shape: tuple[int, ...] | int) -> tuple[int, ...]:
    return (int(shape),) if np.isscalar(shape) else tuple(int(n) for n in shape)


# ---- noise ---------------------------------------------------------------------------
def lattice_noise(shape: tuple[int, ...], rng: np.random.Generator, octaves: int, cells: int) -> Array:
    """Sum of ``octaves`` octaves of cubic-upsampled lattice noise over a node grid, in about
    [-1, 1]: octave ``o`` has ``cells * 2^o`` cells across the longest axis, amplitude 2^-o."""
    total = np.zeros(shape)
    for o in range(octaves):
        n = cells * 2**o  # lattice cells across the longest axis
        lattice = [max(2, int(np.ceil(n * s / max(shape))) + 1) for s in shape]
        field = ndimage.zoom(rng.uniform(-1.0, 1.0, lattice), [s / l for s, l in zip(shape, lattice)],
                             order=3, mode="nearest")
        total += 0.5**o * field[tuple(slice(0, s) for s in shape)]
    return total


def point_noise(u: Array, seed: int, cells: int = 6) -> Array:
    """One octave of cubic lattice noise in about [-1, 1] at unit coordinates ``u`` ``(N, 3)``
    (``cells`` cells per unit, lattice seeded by ``seed``)."""
    g = np.random.default_rng(seed).uniform(-1.0, 1.0, (cells + 1,) * 3)
    return ndimage.map_coordinates(g, (u * cells).T[::-1], order=3, mode="nearest")


def unit_box(positions: ArrayLike) -> Array:
    """``(N, 3)`` positions (mm) in unit coordinates [0, 1]^3 of their bounding box."""
    positions = np.asarray(positions)
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    return (positions - lo) / np.maximum(hi - lo, 1e-9)


# ---- weights ---------------------------------------------------------------------------
def vein_weight(shape: tuple[int, ...], seed: int, stripes: float = 3.0, turbulence: float = 5.0,
                sharpness: float = 6.0, octaves: int = 4) -> Array:
    """Marble vein weight ``t = (1 - |sin(2 pi stripes u + turbulence n)|)^sharpness`` over a
    node grid ``shape``: ``u`` runs along a fixed oblique direction (0 to 1 across the longest
    axis), ``n`` is :func:`lattice_noise` (``octaves`` octaves from 2 cells, seeded)."""
    rng = np.random.default_rng(seed)
    axes = np.meshgrid(*[np.arange(s) / max(max(shape) - 1, 1) for s in shape], indexing="ij")
    direction = np.array([0.3, 0.5, 1.0][-len(shape):])  # (z, y, x) weights: vein sheets roughly normal to x
    u = sum(w * x for w, x in zip(direction / np.linalg.norm(direction), axes))
    phase = 2.0 * np.pi * stripes * u + turbulence * lattice_noise(shape, rng, octaves, 2)
    return (1.0 - np.abs(np.sin(phase))) ** sharpness


def layer_weight(u: Array, seed: int) -> Array:
    """Scene layers at unit coordinates ``u`` ``(N, 3)``: 8 bands along +y, bent by
    :func:`point_noise`, with soft (tanh) edges."""
    s = np.sin(2.0 * np.pi * (8.0 * u[:, 1] + 0.8 * point_noise(u, seed)))
    return 0.5 + 0.5 * np.tanh(3.0 * s)


def inclusion_weight(u: Array, seed: int) -> Array:
    """Scene inclusions at unit coordinates ``u`` ``(N, 3)``: random balls (radii 3-8 % of
    the box, centres in [0.1, 0.9]^3) until they fill 5 % of the box, soft over 20 % of r."""
    rng = np.random.default_rng(seed)
    t = np.zeros(len(u))
    vol, k = 0.0, 0
    while vol < 0.05 and k < 400:
        c, r = rng.uniform(0.1, 0.9, 3), rng.uniform(0.03, 0.08)
        t = np.maximum(t, np.clip((r - np.linalg.norm(u - c, axis=1)) / (0.2 * r), 0.0, 1.0))
        vol += 4.0 / 3.0 * np.pi * r ** 3
        k += 1
    return t


def sphere_weight(positions: ArrayLike, radius_share: float = 0.3, soft: float = 0.1) -> Array:
    """One ball at the centre of the bounding box of ``positions`` ``(N, 3)`` mm, radius
    ``radius_share`` of the box's smallest extent, soft (linear) over ``soft`` of the radius
    (validate's absorbing inclusion)."""
    p = np.asarray(positions, dtype=np.float64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    r = radius_share * float(np.min(hi - lo))
    d = np.linalg.norm(p - 0.5 * (lo + hi), axis=1)
    return np.clip((r - d) / max(soft * r, 1e-12) + 0.5, 0.0, 1.0)


def depth_inclusions(shape: tuple[int, int, int], rng: np.random.Generator, count: int) -> Array:
    """Weights over a node grid ``(nz, ny, nx)`` of ``count`` soft balls at several depths
    (one per depth band; radii 12-22 % of the smaller face side, stretched to nz/3 in z)."""
    nz, ny, nx = shape
    z, y, x = np.meshgrid(*[np.arange(s, dtype=float) for s in shape], indexing="ij")
    t = np.zeros(shape)
    for i in range(count):
        cz = (i + 0.5) / count * (nz - 1)  # depths spread through the slab
        cy, cx = rng.uniform(0.2, 0.8) * (ny - 1), rng.uniform(0.2, 0.8) * (nx - 1)
        r = rng.uniform(0.12, 0.22) * min(nx, ny)
        d = np.sqrt(((x - cx) / r) ** 2 + ((y - cy) / r) ** 2 + ((z - cz) / max(r, nz / 3)) ** 2)
        t = np.maximum(t, np.clip(1.5 - d, 0.0, 1.0))
    return t


def point_weight(kind: str, positions: ArrayLike, seed: int) -> Array:
    """Weight ``t`` in [0, 1] of a scene's second material at node ``positions`` ``(N, 3)`` mm:
    ``kind`` "layers" (:func:`layer_weight`), "inclusions" (:func:`inclusion_weight`) or
    "sphere" (:func:`sphere_weight`, one ball at the centre; ``seed`` unused)."""
    choice(kind, "procedural volume", POINT_KINDS)
    if kind == "sphere":
        return sphere_weight(positions)
    u = unit_box(positions)
    return layer_weight(u, seed) if kind == "layers" else inclusion_weight(u, seed)


# ---- blending --------------------------------------------------------------------------
def default_vein(base: Pair, absorption: float = VEIN_ABSORPTION, scattering: float = VEIN_SCATTERING) -> Pair:
    """The default second material of ``base`` (sigma_a, sigma_s') [mm^-1]: ``absorption``
    times its absorption and ``scattering`` times its reduced scattering."""
    return base[0] * absorption, base[1] * scattering


def blend(base: Pair, second: Pair, t: ArrayLike) -> tuple[Array, Array]:
    """(kappa [mm], mu [mm^-1]) of ``(1 - t) base + t second`` on (sigma_a, sigma_s') [mm^-1];
    ``t`` broadcasts against the (3,) RGB coefficients (give it a trailing axis of 1)."""
    return coefficients((1.0 - t) * base[0] + t * second[0], (1.0 - t) * base[1] + t * second[1])


# ---- grid volumes ----------------------------------------------------------------------
def marble_volume(shape: tuple[int, ...], seed: int = 0, base: str | Preset = "marble",
                  vein: str | Preset | None = None, *, vein_absorption: float = VEIN_ABSORPTION,
                  vein_scattering: float = VEIN_SCATTERING, stripes: float = 3.0, turbulence: float = 5.0,
                  sharpness: float = 6.0, octaves: int = 4) -> tuple[Array, Array]:
    """Deterministic synthetic "marble with veins" volume (sin-turbulence marble).

    Vein weight t of :func:`vein_weight` in [0, 1]. sigma_a and sigma_s' [mm^-1] blend
    linearly from `base` (t = 0) to `vein` (t = 1), so kappa and mu stay within the two
    materials' values. vein=None means base.sigma_a * vein_absorption and
    base.sigma_s_prime * vein_scattering (a darker, more absorbing material).

    Returns
    -------
    (kappa [mm], mu [mm^-1]), each of shape shape + (3,); identical for equal arguments.
    """
    shape = _grid_shape(shape)
    if not 1 <= len(shape) <= 3 or min(shape) < 1:
        raise InputError(f"shape must be 1 to 3 positive grid sizes (nz, ny, nx), got {shape}")
    for name, v in (("vein_absorption", vein_absorption), ("vein_scattering", vein_scattering),
                    ("sharpness", sharpness)):
        real(v, name, 0.0, lo_open=True)
    b = preset(base)
    pair = (b.sigma_a, b.sigma_s_prime)
    second = default_vein(pair, vein_absorption, vein_scattering) if vein is None else \
        (preset(vein).sigma_a, preset(vein).sigma_s_prime)
    t = vein_weight(shape, seed, stripes, turbulence, sharpness, octaves)[..., None]
    return blend(pair, second, t)


def random_volume(shape: tuple[int, ...], rng: np.random.Generator | int | None,
                  kappa_contrast: float = 100.0, mu_max: float = 10.0,
                  kappa_min: float = 0.01) -> tuple[Array, Array]:
    """Random (kappa, mu) volume of shape shape + (3,) for solver tests.

    kappa is log-uniform in [kappa_min, kappa_min * kappa_contrast] (mm) and mu uniform in
    [0, mu_max] (mm^-1), independently per node and channel. Pairs need not be physical
    (3 kappa mu may exceed 1); `optical_properties` would reject those.
    """
    real(kappa_contrast, "kappa_contrast (a ratio)", 1.0)
    real(mu_max, "mu_max (mm^-1)", 0.0)
    real(kappa_min, "kappa_min (mm)", 0.0, lo_open=True)
    gen = np.random.default_rng(rng)
    full = _grid_shape(shape) + (3,)
    kappa = kappa_min * kappa_contrast ** gen.uniform(0.0, 1.0, full)
    return kappa, gen.uniform(0.0, mu_max, full)


def synthetic_volume(shape: tuple[int, int, int], kind: str = "mixed", seed: int = 0,
                     base: str = "marble") -> tuple[Array, Array]:
    """(kappa mm, mu mm^-1), each ``shape + (3,)``, of a heterogeneous block (the inverse
    fit's ground truth).

    ``layers``: three z-layers (base, 3x absorption with 0.6x scattering, 1.5x scattering);
    ``veins``: :func:`marble_volume`; ``inclusions``: soft balls of 5x absorption and 0.5x
    scattering at several depths (:func:`depth_inclusions`); ``mixed``: veins plus inclusions;
    ``bands``: broad soft marble bands (:func:`marble_volume` with 1.5 stripes, sharpness 1.5)
    of 5x absorption and 0.7x scattering, several mm wide (the scales surface data resolve best).
    """
    choice(kind, "volume kind", SYNTHETIC_KINDS)
    shape = tuple(int(s) for s in shape)
    b = preset(base)
    rng = np.random.default_rng(seed)
    if kind == "veins":
        return marble_volume(shape, seed=seed, base=base, vein_absorption=10.0, vein_scattering=0.6)
    if kind == "bands":
        return marble_volume(shape, seed=seed, base=base, vein_absorption=5.0, vein_scattering=0.7, stripes=1.5,
                             turbulence=2.0, sharpness=1.5)
    sa = np.broadcast_to(b.sigma_a, shape + (3,)).copy()
    ss = np.broadcast_to(b.sigma_s_prime, shape + (3,)).copy()
    if kind == "layers":
        zc = np.arange(shape[0])[:, None, None, None] / max(shape[0] - 1, 1)
        mid = (zc > 1 / 3) & (zc <= 2 / 3)
        deep = zc > 2 / 3
        sa = np.where(mid, 3.0 * sa, sa)
        ss = np.where(mid, 0.6 * ss, np.where(deep, 1.5 * ss, ss))
        return coefficients(sa, ss)
    if kind == "mixed":
        k, m = marble_volume(shape, seed=seed, base=base, vein_absorption=10.0, vein_scattering=0.6)
        sa, ss = m, 1.0 / (3.0 * k) - m
    t = depth_inclusions(shape, rng, 3)[..., None]
    return coefficients(sa * (1 + 4 * t), ss * (1 - 0.5 * t))
