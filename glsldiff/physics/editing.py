"""Material edits (Wang et al. 2008, section 5.4): paint, multiply or add kappa (mm) or mu
(mm^-1) in a screen region, inside a pattern mask, within a depth range below the surface.

This module is the numpy implementation every path shares: ``glsldiff edit`` applies it to
block volumes and point volumes, the renderer to tetrahedral grids, and it is the oracle of
the GLSL pass of :mod:`glsldiff.render.editing` (``shaders/edit.frag``), which evaluates the
same formulas per texel of the packed material textures.

Where a node lands (:class:`EditView`)
    Node positions ``p`` (mm) are projected by a 4x4 world -> clip matrix to pixels
    ``(u, v)`` of a ``W x H`` plane (``u`` right, ``v`` down, pixel ``(i, j)`` spans
    ``[i, i + 1) x [j, j + 1)``): the viewer's camera, or for a block volume the orthographic
    top view of :func:`block_view` (one pixel per voxel). The node's distance along its view
    ray is ``|p - eye|`` (perspective) or ``(p - eye) . axis`` (orthographic); ``surface``
    (``H x W``, mm, the same distance of the visible surface per pixel, e.g. a depth render)
    turns it into the **depth below the visible surface** ``d = dist - surface[floor(v), floor(u)]``.

The weight of a node (:func:`edit_weights`) is the product of
    * the brush: 1 within ``radius (1 - feather)`` pixels of its centre, a smoothstep to 0 at
      ``radius`` (none: 1);
    * the mask: the pattern image stretched over the plane, bilinear between pixel centres,
      clamped at its edges (none: 1);
    * the depth window ``d0 <= d <= d1`` (compared in float32, as the GPU does; none: 1); a
      node whose pixel shows no surface has no depth and is left out;
    * ``strength``;
    and 0 for a node behind the eye, or outside the plane when a brush, mask or depth window
    is given.

The edit (:func:`apply_edit`): ``x' = x + w (op(x) - x)`` with ``op`` = ``set`` (the value),
``multiply`` or ``add``; then kappa is kept >= :data:`KAPPA_MIN` and mu >= 0 (the count is
reported).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError

OPS = ("set", "multiply", "add")
PROPERTIES = ("kappa", "mu")
#: Smallest kappa an edit leaves (mm): the solver divides by kappa (sigma_t = 1 / (3 kappa)
#: = 3.3e5 mm^-1 here, far beyond any material).
KAPPA_MIN = 1e-6
#: A surface distance at or above this means "no surface in this pixel" (the depth render's
#: clear value is 1e30).
NO_SURFACE = 1e29


@dataclass(frozen=True)
class Brush:
    """A disc in the edit plane: centre ``(u, v)`` and radius in pixels; the outer
    ``feather`` share of the radius falls smoothly to 0 (0: a hard edge)."""

    centre: tuple[float, float]
    radius: float
    feather: float = 0.25

    def __post_init__(self) -> None:
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise InputError(f"brush radius must be a positive number of pixels, got {self.radius!r}")
        if not 0.0 <= self.feather <= 1.0:
            raise InputError(f"brush feather must be in [0, 1] (share of the radius), got {self.feather!r}")
        if len(self.centre) != 2 or not np.all(np.isfinite(self.centre)):
            raise InputError(f"brush centre must be two finite pixel coordinates, got {self.centre!r}")

    @property
    def inner(self) -> float:
        """Radius (pixels) within which the weight is 1."""
        return self.radius * (1.0 - self.feather)


@dataclass(frozen=True, eq=False)
class Edit:
    """One material edit: ``prop`` (kappa | mu) ``op`` (set | multiply | add) ``value``
    (one number or RGB; mm for kappa, mm^-1 for mu; a factor for multiply), restricted by
    an optional brush, mask (``(h, w)`` in [0, 1], row 0 at the top) and depth window
    ``(d0, d1)`` mm below the visible surface, scaled by ``strength`` in [0, 1]."""

    prop: str
    op: str
    value: tuple[float, float, float]
    brush: Brush | None = None
    mask: NDArray[np.float32] | None = None
    depth: tuple[float, float] | None = None
    strength: float = 1.0

    def __post_init__(self) -> None:
        if self.prop not in PROPERTIES:
            raise InputError(f"edit property {self.prop!r}: choose one of {PROPERTIES}")
        if self.op not in OPS:
            raise InputError(f"edit operation {self.op!r}: choose one of {OPS}")
        v = np.broadcast_to(np.asarray(self.value, dtype=np.float64).reshape(-1), (3,)) \
            if np.size(self.value) in (1, 3) else None
        if v is None or not np.all(np.isfinite(v)):
            raise InputError(f"edit value must be 1 or 3 finite numbers, got {self.value!r}")
        given = f"{v[0]:g}" if np.all(v == v[0]) else " ".join(f"{x:g}" for x in v)   # as the user wrote it
        if self.op == "set" and self.prop == "kappa" and np.any(v <= 0):
            raise InputError(f"kappa must be set to a positive value (mm), got {given}")
        if self.op == "set" and self.prop == "mu" and np.any(v < 0):
            raise InputError(f"mu must be set to a value >= 0 (mm^-1), got {given}")
        if self.op == "multiply" and np.any(v < 0):
            raise InputError(f"a multiply factor must be >= 0, got {given}")
        object.__setattr__(self, "value", tuple(float(x) for x in v))
        if not 0.0 <= self.strength <= 1.0:
            raise InputError(f"edit strength must be in [0, 1], got {self.strength!r}")
        if self.depth is not None:
            d0, d1 = (float(x) for x in self.depth)
            if not (d0 <= d1) or np.isnan(d0) or np.isnan(d1):
                raise InputError(f"depth range {self.depth!r}: give d0 <= d1 in mm below the surface")
            object.__setattr__(self, "depth", (d0, d1))
        if self.mask is not None:
            m = np.asarray(self.mask, dtype=np.float32)
            if m.ndim != 2 or min(m.shape) < 1 or not np.all(np.isfinite(m)):
                raise InputError(f"edit mask must be a finite 2-D image, got shape {m.shape}")
            object.__setattr__(self, "mask", np.clip(m, 0.0, 1.0))

    @property
    def restricted(self) -> bool:
        """Whether the edit has a brush, mask or depth window (nodes off the plane are out)."""
        return self.brush is not None or self.mask is not None or self.depth is not None

    def describe(self) -> str:
        val = self.value[0] if len(set(self.value)) == 1 else list(self.value)
        parts = [f"{self.op} {self.prop} {val}"]
        if self.brush is not None:
            parts.append(f"brush at ({self.brush.centre[0]:.0f}, {self.brush.centre[1]:.0f}) px r {self.brush.radius:g}")
        if self.mask is not None:
            parts.append(f"mask {self.mask.shape[1]}x{self.mask.shape[0]}")
        if self.depth is not None:
            parts.append(f"depth {self.depth[0]:g}..{self.depth[1]:g} mm")
        if self.strength != 1.0:
            parts.append(f"strength {self.strength:g}")
        return ", ".join(parts)


@dataclass(frozen=True, eq=False)
class EditView:
    """The plane edits are drawn in: ``matrix`` (4x4 row-major world -> clip, mm), its size
    ``(W, H)`` in pixels, the ``eye`` (mm), orthographic ``axis`` (None: perspective) and the
    optional ``surface`` distance image ``(H, W)`` (mm along the view ray, row 0 at the top;
    >= :data:`NO_SURFACE` where no surface is seen)."""

    matrix: NDArray[np.float64]
    size: tuple[int, int]
    eye: NDArray[np.float64]
    axis: NDArray[np.float64] | None = None
    surface: NDArray[np.float32] | None = field(default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "matrix", np.asarray(self.matrix, dtype=np.float64).reshape(4, 4))
        object.__setattr__(self, "eye", np.asarray(self.eye, dtype=np.float64).reshape(3))
        if self.axis is not None:
            a = np.asarray(self.axis, dtype=np.float64).reshape(3)
            object.__setattr__(self, "axis", a / np.linalg.norm(a))
        W, H = (int(s) for s in self.size)
        if W < 1 or H < 1:
            raise InputError(f"edit view size must be positive pixels, got {self.size!r}")
        object.__setattr__(self, "size", (W, H))
        if self.surface is not None:
            s = np.asarray(self.surface, dtype=np.float32)
            if s.shape != (H, W):
                raise InputError(f"surface image has shape {s.shape}, the view is {H}x{W}")
            object.__setattr__(self, "surface", s)

    def pixels(self, positions: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """``(N, 2)`` pixel coordinates ``(u, v)`` of ``positions`` (mm) and whether each is in
        front of the eye (clip w > 0)."""
        p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        clip = np.concatenate([p, np.ones((len(p), 1))], axis=1) @ self.matrix.T
        w = clip[:, 3]
        front = w > 0
        ndc = clip[:, :2] / np.where(front, w, 1.0)[:, None]
        W, H = self.size
        return np.stack([(ndc[:, 0] + 1.0) * 0.5 * W, (1.0 - ndc[:, 1]) * 0.5 * H], axis=1), front

    def distance(self, positions: ArrayLike) -> NDArray[np.float64]:
        """Distance of ``positions`` along their view rays, mm."""
        d = np.asarray(positions, dtype=np.float64).reshape(-1, 3) - self.eye
        return d @ self.axis if self.axis is not None else np.linalg.norm(d, axis=1)


def block_view(shape: Sequence[int], h_mm: float) -> EditView:
    """The edit plane of a block volume ``(nz, ny, nx)`` of voxel size ``h_mm``: orthographic
    from above its captured face ``z = 0``, voxel ``(i, j)`` at pixel centre ``(i + .5, j + .5)``
    (so a mask image is stretched over the face), depth = ``z`` (the face is the surface)."""
    nz, ny, nx = (int(s) for s in shape[:3])
    h = float(h_mm)
    m = np.array([[2.0 / (nx * h), 0.0, 0.0, 1.0 / nx - 1.0],
                  [0.0, -2.0 / (ny * h), 0.0, 1.0 - 1.0 / ny],
                  [0.0, 0.0, 0.0, 0.0],
                  [0.0, 0.0, 0.0, 1.0]])
    return EditView(m, (nx, ny), np.zeros(3), np.array([0.0, 0.0, 1.0]), np.zeros((ny, nx), np.float32))


def block_positions(shape: Sequence[int], h_mm: float) -> NDArray[np.float64]:
    """``(nz * ny * nx, 3)`` voxel positions (x, y, depth) = (i, j, k) h_mm, in the
    volume's flat order (z slowest)."""
    nz, ny, nx = (int(s) for s in shape[:3])
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1) * float(h_mm)


def sample_mask(mask: NDArray, uv: NDArray, size: tuple[int, int]) -> NDArray[np.float64]:
    """The mask image stretched over a ``size = (W, H)`` plane at pixel coordinates ``uv``:
    bilinear between pixel centres, clamped at the edges (the shader's twin)."""
    hm, wm = mask.shape
    W, H = size
    mx = uv[:, 0].astype(np.float32) * np.float32(wm / W) - np.float32(0.5)
    my = uv[:, 1].astype(np.float32) * np.float32(hm / H) - np.float32(0.5)
    x0, y0 = np.floor(mx), np.floor(my)
    fx, fy = (mx - x0).astype(np.float64), (my - y0).astype(np.float64)
    xa, xb = (np.clip(x0 + d, 0, wm - 1).astype(np.int64) for d in (0, 1))
    ya, yb = (np.clip(y0 + d, 0, hm - 1).astype(np.int64) for d in (0, 1))
    m = np.asarray(mask, dtype=np.float64)
    return ((m[ya, xa] * (1 - fx) + m[ya, xb] * fx) * (1 - fy)
            + (m[yb, xa] * (1 - fx) + m[yb, xb] * fx) * fy)


def brush_weight(brush: Brush, uv: NDArray) -> NDArray[np.float64]:
    """1 inside the brush's inner radius, a smoothstep to 0 at its radius."""
    r = np.hypot(uv[:, 0] - brush.centre[0], uv[:, 1] - brush.centre[1])
    if brush.feather == 0.0:
        return (r <= brush.radius).astype(np.float64)
    t = np.clip((brush.radius - r) / (brush.radius - brush.inner), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def depth_below(view: EditView, positions: ArrayLike, uv: NDArray) -> NDArray[np.float64]:
    """Depth (mm) of each node below the visible surface along its view ray; +inf where its
    pixel is off the plane or shows no surface (no ``surface`` image: the view distance)."""
    dist = view.distance(positions)
    if view.surface is None:
        return dist
    W, H = view.size
    iu, iv = np.floor(uv[:, 0]), np.floor(uv[:, 1])
    inside = (iu >= 0) & (iu < W) & (iv >= 0) & (iv < H)
    s = np.full(len(uv), np.inf)
    s[inside] = view.surface[iv[inside].astype(np.int64), iu[inside].astype(np.int64)]
    s[s >= NO_SURFACE] = np.inf
    return dist - s


def edit_weights(edit: Edit, view: EditView | None, positions: ArrayLike,
                 pixels: tuple[NDArray[np.float64], NDArray[np.bool_]] | None = None) -> NDArray[np.float64]:
    """``(N,)`` weight in [0, 1] of ``edit`` at node ``positions`` (mm) seen in ``view``
    (module docstring). Without a view the edit must be unrestricted (weight = strength).
    ``pixels``: ``view.pixels(positions)`` when the caller already has it (the dabs of a stroke
    share one view)."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    w = np.full(len(p), float(edit.strength))
    if not edit.restricted:
        return w
    if view is None:
        raise InputError("a brush, mask or depth range needs a view to project the nodes into")
    uv, front = view.pixels(p) if pixels is None else pixels
    W, H = view.size
    on = front & (uv[:, 0] >= 0) & (uv[:, 0] <= W) & (uv[:, 1] >= 0) & (uv[:, 1] <= H)
    if edit.brush is not None:     # outside the brush's square the weight is 0: weigh the nodes inside only
        (cu, cv), r = edit.brush.centre, edit.brush.radius
        on &= (np.abs(uv[:, 0] - cu) <= r) & (np.abs(uv[:, 1] - cv) <= r)
    idx = np.flatnonzero(on)
    w_in, uv_in = w[idx], uv[idx]
    if edit.brush is not None:
        w_in *= brush_weight(edit.brush, uv_in)
    if edit.mask is not None:
        w_in *= sample_mask(edit.mask, uv_in, view.size)
    if edit.depth is not None:
        d = depth_below(view, p[idx], uv_in).astype(np.float32)
        d0, d1 = np.float32(edit.depth[0]), np.float32(edit.depth[1])
        w_in *= np.isfinite(d) & (d >= d0) & (d <= d1)   # no surface in its pixel: no depth
    out = np.zeros(len(p))
    out[idx] = w_in
    return out


@dataclass(frozen=True)
class EditResult:
    """What an edit changed: nodes with weight > 0, nodes clamped to kappa >= KAPPA_MIN or
    mu >= 0, nodes left with mu > 1 / (3 kappa) (sigma_s' < 0: more absorption than
    extinction, which the diffusion solver accepts but no real material has), seconds."""

    edited: int
    clamped: int
    unphysical: int
    seconds: float = 0.0

    def describe(self) -> str:
        s = f"{self.edited:,} nodes edited"
        if self.clamped:
            s += f", {self.clamped:,} clamped (kappa >= {KAPPA_MIN:g} mm, mu >= 0)"
        if self.unphysical:
            s += f", {self.unphysical:,} with mu > 1/(3 kappa) (sigma_s' < 0)"
        return s + (f", {self.seconds * 1e3:.1f} ms" if self.seconds else "")


def apply_values(edit: Edit, x: NDArray, w: NDArray) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """``x + w (op(x) - x)`` for ``(N, 3)`` values ``x`` and ``(N,)`` weights ``w``, clamped,
    and ``(N,)`` which nodes the clamp changed."""
    v = np.asarray(edit.value, dtype=np.float64)
    target = v if edit.op == "set" else (x * v if edit.op == "multiply" else x + v)
    y = x + w[:, None] * (target - x)
    out = np.maximum(y, KAPPA_MIN if edit.prop == "kappa" else 0.0)
    return out, np.any(out != y, axis=1)


def apply_edit(edit: Edit, kappa: ArrayLike, mu: ArrayLike, positions: ArrayLike,
               view: EditView | None = None, active: ArrayLike | None = None,
               pixels: tuple[NDArray[np.float64], NDArray[np.bool_]] | None = None
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], EditResult]:
    """``edit`` applied to per-node ``kappa`` (mm) and ``mu`` (mm^-1), both ``(..., 3)`` with one
    node per position ``(N, 3)`` mm; ``active`` (``(N,)``) limits it to those nodes; ``pixels``
    as :func:`edit_weights`. Returns new arrays of the input shapes and an :class:`EditResult`."""
    k = np.asarray(kappa, dtype=np.float64)
    m = np.asarray(mu, dtype=np.float64)
    shape = k.shape
    k2, m2 = k.reshape(-1, 3).copy(), m.reshape(-1, 3).copy()
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(p) != len(k2) or m2.shape != k2.shape:
        raise InputError(f"edit: {len(p)} positions for kappa {k.shape} and mu {m.shape}")
    w = edit_weights(edit, view, p, pixels)
    if active is not None:
        w = w * np.asarray(active, dtype=bool).reshape(-1)
    x = k2 if edit.prop == "kappa" else m2
    hit = np.flatnonzero(w > 0)            # nodes of weight 0 keep their values exactly
    x[hit], clamped_nodes = apply_values(edit, x[hit], w[hit])
    clamped = int(clamped_nodes.sum())
    unphysical = int(np.any(3.0 * k2[hit] * m2[hit] > 1.0 + 1e-9, axis=1).sum())
    return k2.reshape(shape), m2.reshape(shape), EditResult(int(hit.size), clamped, unphysical)
