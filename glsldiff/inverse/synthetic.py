"""Synthetic ground truth for inverse diffusion: projector patterns, camera noise, rendered
measurements, and the figure-11 error E (the volumes: :mod:`glsldiff.physics.procedural`).

Measurements are rendered with the same discrete model the fit uses (an "inverse crime":
it tests the optimiser and the identifiability of the material, not the diffusion
approximation itself; camera noise is what keeps it honest).
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.checks import choice, real
from glsldiff.grids.regular import INTERIOR, RegularGrid
from glsldiff.inverse.measurements import SETUPS, Measurements, face_regions
from glsldiff.inverse.model import ForwardModel

Array = NDArray[np.float64]
#: ``synthetic_measurements`` setups: the two of :data:`SETUPS` and ``both`` (back-lit, both faces observed).
SYNTH_SETUPS = (*SETUPS, "both")


def region_patterns(grid: RegularGrid, face: str, n: int, intensity: float = 1.0) -> list[Array]:
    """``n x n`` projector patterns on ``face``: the face split into n x n regions, each lit
    alone with uniform ``intensity`` (paper: 4 x 4)."""
    out = []
    for rows, cols in face_regions(grid.face_shape(face), n):
        q = np.zeros(grid.face_shape(face))
        q[rows, cols] = intensity
        out.append(q)
    return out


def render(model: ForwardModel, kappa: Array, mu: Array, Q: Array, chunk: int = 32) -> Array:
    """Radiance ``(n_boundary, M)`` of one channel's material (volumes ``(nz, ny, nx)``): one
    factor or hierarchy, the sources solved ``chunk`` columns at a time (the unknowns of 256
    columns of a 1.3 M-node grid would take 2.7 GB per array of the block CG)."""
    fac = model.factorize(model.active_values(kappa), model.active_values(mu))
    return np.concatenate([fac.radiance(fac.solve(Q[:, i:i + chunk]), Q[:, i:i + chunk])
                           for i in range(0, max(Q.shape[1], 1), chunk)], axis=1)


def face_captures(model: ForwardModel, kappa: Array, mu: Array, Qs: list[Array], observed: str,
                  lit: str | None = None) -> tuple[Array, Array | None]:
    """The captures of the volume ``(kappa, mu)`` (``(nz, ny, nx, 3)``) for channel sources
    ``Qs`` (three ``(n_boundary, M)``): radiance on the ``observed`` face and, with ``lit``, the
    reflection on that face, as ``(M, a, b, 3)`` face stacks (reflection None without ``lit``)."""
    g, M = model.grid, Qs[0].shape[1]
    radiance = np.zeros((M,) + g.face_shape(observed) + (3,))
    reflected = None if lit is None else np.zeros((M,) + g.face_shape(lit) + (3,))
    for c in range(3):
        L = render(model, kappa[..., c], mu[..., c], Qs[c])
        radiance[..., c] = np.moveaxis(g.boundary_to_face(observed, L), -1, 0)
        if reflected is not None:
            reflected[..., c] = np.moveaxis(g.boundary_to_face(lit, L), -1, 0)
    return radiance, reflected


def camera_noise(L: Array, rng: np.random.Generator | int | None, rel: float = 0.01,
                 read: float = 1e-3) -> Array:
    """Poisson-Gaussian camera noise: variance ``rel^2 L_ref L + (read L_ref)^2`` with
    ``L_ref`` the 99th percentile of ``L`` (so ``rel`` is the relative shot noise at the
    bright end); the result is clipped at 0 like a black-subtracted HDR merge."""
    real(rel, "rel (relative camera noise)", 0.0)
    real(read, "read (read noise)", 0.0)
    gen = np.random.default_rng(rng)
    ref = float(np.percentile(L[L > 0], 99)) if np.any(L > 0) else 1.0
    sigma = np.sqrt(rel**2 * ref * np.maximum(L, 0.0) + (read * ref) ** 2)
    return np.maximum(L + sigma * gen.standard_normal(L.shape), 0.0)


def synthetic_measurements(kappa: Array, mu: Array, h: float, n: int, setup: str = "back",
                           noise: float = 0.01, read_noise: float = 1e-3, saturation: float | None = None,
                           seed: int = 0, stencil: str = "conservative", eta: float = 1.3) -> Measurements:
    """Render ``n x n`` region illuminations of the volume ``(kappa, mu)`` (``(nz, ny, nx, 3)``)
    in the ``back`` (thin: lit z-, observed z+), ``front`` (thick: observed z-, only nodes not
    lit) or ``both`` setup (back-lit, observed on both faces: transmission plus the lit face's
    reflection at the nodes not lit), add camera noise, and pack it as :class:`Measurements`."""
    choice(setup, "setup", SYNTH_SETUPS)
    both = setup == "both"
    setup = "back" if both else setup
    kappa, mu = np.asarray(kappa, dtype=np.float64), np.asarray(mu, dtype=np.float64)
    nz, ny, nx = kappa.shape[:3]
    grid = RegularGrid(nx, ny, nz, h=h)
    lit, observed = SETUPS[setup]
    patterns = region_patterns(grid, lit, n)
    model = ForwardModel(grid, stencil=stencil, eta=eta)
    Q = grid.face_to_boundary(lit, np.stack(patterns, axis=-1))
    radiance, reflected = face_captures(model, kappa, mu, [Q] * 3, observed, lit if both else None)
    incoming = np.repeat(np.stack(patterns)[..., None], 3, axis=-1)
    unlit = np.stack(patterns) == 0  # reflection: only nodes that are not directly lit
    mask = unlit if setup == "front" else None
    if mask is not None:
        radiance = np.where(mask[..., None], radiance, 0.0)
    if both:
        reflected = np.where(unlit[..., None], reflected, 0.0)
    gen = np.random.default_rng(seed)
    if noise > 0 or read_noise > 0:
        radiance = camera_noise(radiance, gen, noise, read_noise)
        if both:
            reflected = camera_noise(reflected, gen, noise, read_noise)
    if saturation is not None:
        radiance = np.minimum(radiance, saturation)
        reflected = None if reflected is None else np.minimum(reflected, saturation)
    return Measurements((nz, ny, nx), h, lit, observed, incoming, radiance, mask, eta=eta,
                        saturation=saturation, reflected=reflected, reflected_mask=unlit if both else None)


#: :func:`bssrdf_error` samples at most this many source nodes per face by default (stride 4,
#: or wider where a face has more than 16 x 16 such nodes): each costs a forward solve per
#: channel and volume (6 solves; at 1.3 M nodes about 1.5 s each on 2 cores).
BSSRDF_MAX_SOURCES = 256


def bssrdf_stride(face_shape: tuple[int, ...], max_sources: int = BSSRDF_MAX_SOURCES) -> int:
    """The smallest source stride >= 4 that samples at most ``max_sources`` nodes of a face."""
    stride = 4
    while math.ceil(face_shape[0] / stride) * math.ceil(face_shape[1] / stride) > max_sources:
        stride += 1
    return stride


def bssrdf_error(grid: RegularGrid, true: tuple[Array, Array], fitted: tuple[Array, Array],
                 sources: tuple[str, ...] = ("z-",), receivers: tuple[str, ...] = ("z+",),
                 stride: int | None = None, stencil: str = "conservative", eta: float = 1.3,
                 channels: tuple[int, ...] = (0, 1, 2), max_sources: int = BSSRDF_MAX_SOURCES) -> float:
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
        step = bssrdf_stride(sub.shape, max_sources) if stride is None else stride
        sub[step // 2::step, step // 2::step] = 1.0
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


def coefficient_errors(grid: RegularGrid, true: tuple[Array, Array], fitted: tuple[Array, Array]
                       ) -> list[dict[str, float]]:
    """Per RGB channel, over the interior nodes: the mean true and fitted sigma_a and sigma_s'
    (mm^-1, from ``(kappa, mu)``: sigma_a = mu, sigma_s' = 1/(3 kappa) - mu) and the median
    relative error of each node's value."""
    inner = grid.kind == INTERIOR
    rows = []
    for c in range(3):
        ta, fa = true[1][..., c][inner], fitted[1][..., c][inner]
        ts = 1.0 / (3.0 * true[0][..., c][inner]) - ta
        fs = 1.0 / (3.0 * fitted[0][..., c][inner]) - fa
        rows.append({"channel": "RGB"[c], "sigma_a_true": float(ta.mean()), "sigma_a_fit": float(fa.mean()),
                     "sigma_a_median_rel_err": float(np.median(np.abs(fa - ta) / np.maximum(ta, 1e-12))),
                     "sigma_s_true": float(ts.mean()), "sigma_s_fit": float(fs.mean()),
                     "sigma_s_median_rel_err": float(np.median(np.abs(fs - ts) / np.maximum(ts, 1e-12)))})
    return rows
