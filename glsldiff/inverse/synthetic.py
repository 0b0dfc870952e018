"""Synthetic ground truth for inverse diffusion: volumes, projector patterns, camera noise,
rendered measurements, and the figure-11 error E.

Measurements are rendered with the same discrete model the fit uses (an "inverse crime":
it tests the optimiser and the identifiability of the material, not the diffusion
approximation itself; camera noise is what keeps it honest).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import InputError
from glsldiff.grids.regular import RegularGrid
from glsldiff.inverse.measurements import Measurements
from glsldiff.inverse.model import ForwardModel
from glsldiff.physics.material import coefficients, marble_volume, preset

Array = NDArray[np.float64]
VOLUMES = ("layers", "veins", "inclusions", "mixed")
SETUPS = {"back": ("z-", "z+"), "front": ("z-", "z-")}


def _inclusions(shape: tuple[int, int, int], rng: np.random.Generator, count: int) -> Array:
    """Weights in [0, 1] of ``count`` soft balls at several depths (one per depth band)."""
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


def synthetic_volume(shape: tuple[int, int, int], kind: str = "mixed", seed: int = 0,
                     base: str = "marble") -> tuple[Array, Array]:
    """(kappa mm, mu mm^-1), each ``shape + (3,)``, of a heterogeneous block.

    ``layers``: three z-layers (base, 3x absorption with 0.6x scattering, 1.5x scattering);
    ``veins``: :func:`glsldiff.physics.material.marble_volume`; ``inclusions``: soft balls of
    5x absorption and 0.5x scattering at several depths; ``mixed``: veins plus inclusions.
    """
    if kind not in VOLUMES:
        raise InputError(f"volume kind {kind!r}; choose one of {VOLUMES}")
    shape = tuple(int(s) for s in shape)
    b = preset(base)
    rng = np.random.default_rng(seed)
    if kind == "veins":
        return marble_volume(shape, seed=seed, base=base, vein_absorption=10.0, vein_scattering=0.6)
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
    t = _inclusions(shape, rng, 3)[..., None]
    return coefficients(sa * (1 + 4 * t), ss * (1 - 0.5 * t))


def region_patterns(grid: RegularGrid, face: str, n: int, intensity: float = 1.0) -> list[Array]:
    """``n x n`` projector patterns on ``face``: the face split into n x n regions, each lit
    alone with uniform ``intensity`` (paper: 4 x 4)."""
    fy, fx = grid.face_shape(face)
    if not (isinstance(n, (int, np.integer)) and 1 <= n <= min(fy, fx)):
        raise InputError(f"n={n!r} regions per side must be an integer in [1, {min(fy, fx)}]")
    out = []
    for ys in np.array_split(np.arange(fy), n):
        for xs in np.array_split(np.arange(fx), n):
            q = np.zeros((fy, fx))
            q[np.ix_(ys, xs)] = intensity
            out.append(q)
    return out


def render(model: ForwardModel, kappa: Array, mu: Array, Q: Array) -> Array:
    """Radiance ``(n_boundary, M)`` of one channel's material (volumes ``(nz, ny, nx)``)."""
    fac = model.factorize(model.active_values(kappa), model.active_values(mu))
    return fac.radiance(fac.solve(Q), Q)


def camera_noise(L: Array, rng: np.random.Generator | int | None, rel: float = 0.01,
                 read: float = 1e-3) -> Array:
    """Poisson-Gaussian camera noise: variance ``rel^2 L_ref L + (read L_ref)^2`` with
    ``L_ref`` the 99th percentile of ``L`` (so ``rel`` is the relative shot noise at the
    bright end); the result is clipped at 0 like a black-subtracted HDR merge."""
    if rel < 0 or read < 0:
        raise InputError("noise levels must be >= 0")
    gen = np.random.default_rng(rng)
    ref = float(np.percentile(L[L > 0], 99)) if np.any(L > 0) else 1.0
    sigma = np.sqrt(rel**2 * ref * np.maximum(L, 0.0) + (read * ref) ** 2)
    return np.maximum(L + sigma * gen.standard_normal(L.shape), 0.0)


def synthetic_measurements(kappa: Array, mu: Array, h: float, n: int, setup: str = "back",
                           noise: float = 0.01, read_noise: float = 1e-3, saturation: float | None = None,
                           seed: int = 0, stencil: str = "conservative", eta: float = 1.3) -> Measurements:
    """Render ``n x n`` region illuminations of the volume ``(kappa, mu)`` (``(nz, ny, nx, 3)``)
    in the ``back`` (thin: lit z-, observed z+) or ``front`` setup (thick: observed z-, only
    nodes not lit), add camera noise, and pack it as :class:`Measurements`."""
    if setup not in SETUPS:
        raise InputError(f"setup={setup!r}; choose one of {tuple(SETUPS)}")
    kappa, mu = np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64)
    nz, ny, nx = kappa.shape[:3]
    grid = RegularGrid(nx, ny, nz, h=h)
    lit, observed = SETUPS[setup]
    patterns = region_patterns(grid, lit, n)
    model = ForwardModel(grid, stencil=stencil, eta=eta)
    Q = grid.face_to_boundary(lit, np.stack(patterns, axis=-1))
    radiance = np.zeros((len(patterns),) + grid.face_shape(observed) + (3,))
    for c in range(3):
        L = render(model, kappa[..., c], mu[..., c], Q)
        radiance[..., c] = np.moveaxis(grid.boundary_to_face(observed, L), -1, 0)
    incoming = np.repeat(np.stack(patterns)[..., None], 3, axis=-1)
    mask = None
    if setup == "front":
        mask = np.stack(patterns) == 0  # thick samples: only nodes that are not directly lit
        radiance = np.where(mask[..., None], radiance, 0.0)
    if noise > 0 or read_noise > 0:
        radiance = camera_noise(radiance, seed, noise, read_noise)
    if saturation is not None:
        radiance = np.minimum(radiance, saturation)
    return Measurements((nz, ny, nx), h, lit, observed, incoming, radiance, mask, eta=eta,
                        saturation=saturation)


def bssrdf_error(grid: RegularGrid, true: tuple[Array, Array], fitted: tuple[Array, Array],
                 sources: tuple[str, ...] = ("z-",), receivers: tuple[str, ...] = ("z+",),
                 stride: int = 4, stencil: str = "conservative", eta: float = 1.3,
                 channels: tuple[int, ...] = (0, 1, 2)) -> float:
    """Figure-11 error ``E = sum (R'_d - R_d)^2 / sum R_d^2`` of the diffuse BSSRDF between the
    fitted and the true volume (each ``(kappa, mu)`` of shape ``(nz, ny, nx, 3)``).

    ``R_d(x_i, x_j)`` is the radiance at boundary node ``x_j`` for unit incoming light at
    node ``x_i``; sources are every ``stride``-th node (in both face directions) of the
    ``sources`` faces, receivers every node of the ``receivers`` faces other than the source;
    summed over ``channels``. The default pairs are those a back-lit capture observes (lit z- to
    z+); pass both faces to both to include the reflectance the capture never saw.
    """
    model = ForwardModel(grid, stencil=stencil, eta=eta)
    bflat = sum(grid.face_to_boundary(face, np.ones(grid.face_shape(face))) for face in receivers) > 0
    src = np.zeros(grid.graph.boundary.size)
    for face in sources:
        sub = np.zeros(grid.face_shape(face))
        sub[stride // 2::stride, stride // 2::stride] = 1.0
        src += grid.face_to_boundary(face, sub)
    sources = np.flatnonzero(src > 0)
    Q = np.zeros((grid.graph.boundary.size, sources.size))
    Q[sources, np.arange(sources.size)] = 1.0
    keep = bflat[:, None] & (Q == 0)
    num = den = 0.0
    for c in channels:
        R = render(model, true[0][..., c], true[1][..., c], Q)
        Rf = render(model, fitted[0][..., c], fitted[1][..., c], Q)
        num += float(np.sum(((Rf - R) * keep) ** 2))
        den += float(np.sum((R * keep) ** 2))
    return num / den
