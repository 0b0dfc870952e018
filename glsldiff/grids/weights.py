"""Laplacian weights on a polygrid (paper appendix B) with a safe fallback.

Every interior polygrid node ``v0`` has six neighbours ``v_j`` in the lattice order
:data:`NEIGHBOURS` (``x-, x+, y-, y+, z-, z+``). The Laplacian is approximated as

    lap f(v0) ~= sum_j w_j (f(v_j) - f(v0))          (w_j in mm^-2, lengths in mm)

Appendix B of Wang et al. (2008) drops the mixed second-derivative terms of the Taylor
expansion, which leaves the 6x6 system with rows ``(dx_j, dx_j^2/2, dy_j, dy_j^2/2,
dz_j, dz_j^2/2)`` for the unknowns ``(f_x, f_xx, f_y, f_yy, f_z, f_zz)``; with ``W``
its inverse, ``w_j = W[1, j] + W[3, j] + W[5, j]``. Dropping the mixed terms makes the
result depend on the frame the deltas are written in, so they are expressed in a local
frame aligned with the lattice directions at ``v0`` (:func:`local_frames`); the weights
are then invariant under rotations (and reflections) of the neighbourhood and exact for
every quadratic without mixed terms in that frame.

On distorted stencils some appendix-B weights can be negative (or the 6x6 system
ill-conditioned), and the Jacobi iteration of the diffusion system may then diverge.
:func:`laplacian_weights` detects such nodes and falls back, by default blending
towards the per-axis three-point weights of :func:`axis_weights`, which are always
positive.

(About 450 lines, over the usual 400: one algorithm, the weights and their fallback, whose
vectorised 6x6 solves and the checks that keep them safe belong together.)
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.checks import choice, finite_array, real
from glsldiff.core.errors import InputError
from glsldiff.grids.graph import NEIGHBOURS

__all__ = [
    "NEIGHBOURS",
    "FALLBACKS",
    "WeightStats",
    "local_frames",
    "appendix_b_weights",
    "axis_weights",
    "laplacian_weights",
]

FALLBACKS = ("blend", "axis", "none")

_CHUNK = 1 << 14  # nodes per batch of 6x6 linear algebra (keeps the temporaries in cache)
_REFINE_COND = 1e3  # above this estimated condition number, recompute cond and w by SVD
_SINGULAR_RTOL = 6 * np.finfo(np.float64).eps  # sigma_min <= this * sigma_max: singular
_FRAME_RTOL = 1e-12  # |y axis minus its x component| <= this * |y axis|: no frame
_COINCIDENT_RTOL = 1e-12  # link length <= this * longest link of the node: coincident
_E = np.array([0.0, 1.0, 0.0, 1.0, 0.0, 1.0])  # selects f_xx + f_yy + f_zz


# --------------------------------------------------------------------------- helpers
def _slices(n: int) -> list[slice]:
    return [slice(s0, min(s0 + _CHUNK, n)) for s0 in range(0, n, _CHUNK)]


def _deltas(c: NDArray[np.float64], v: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Links ``v_j - v0`` (N, 6, 3) and their lengths (N, 6), mm."""
    d = v - c[:, None, :]
    return d, np.sqrt(np.einsum("njd,njd->nj", d, d))


# --------------------------------------------------------------------------- validation
def _validate(center: ArrayLike, nbrs: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Check shapes, finiteness and link lengths; return float64 copies-or-views."""
    c = finite_array(center, "center (node positions, mm)", (3,))
    v = finite_array(nbrs, f"nbrs (neighbour positions in the order {', '.join(NEIGHBOURS)}, mm)", (6, 3))
    if v.shape[0] != c.shape[0]:
        raise InputError(f"nbrs has {v.shape[0]} nodes but center has {c.shape[0]}; they must match")
    bad_nodes, example = 0, None
    for sl in _slices(c.shape[0]):
        _, length = _deltas(c[sl], v[sl])
        bad = length <= _COINCIDENT_RTOL * length.max(axis=1, keepdims=True)
        rows = np.flatnonzero(bad.any(axis=1))
        if rows.size and example is None:
            example = (sl.start + int(rows[0]), int(np.flatnonzero(bad[rows[0]])[0]))
        bad_nodes += rows.size
    if example is not None:
        raise InputError(
            f"nbrs: {bad_nodes} node(s) have a neighbour coincident with the node itself "
            f"(zero-length link), e.g. node {example[0]}, neighbour {NEIGHBOURS[example[1]]!r}; "
            "remove or merge coincident polygrid nodes"
        )
    return c, v


# --------------------------------------------------------------------------- frames
def _frames(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Local frames from validated neighbours; NaN rows where the axes are degenerate."""
    ax = v[:, 1] - v[:, 0]
    ay = v[:, 3] - v[:, 2]
    az = v[:, 5] - v[:, 4]
    nx = np.sqrt(np.einsum("ni,ni->n", ax, ax))
    ny = np.sqrt(np.einsum("ni,ni->n", ay, ay))
    with np.errstate(invalid="ignore", divide="ignore"):
        ex = ax / nx[:, None]
        ey = ay - np.einsum("ni,ni->n", ay, ex)[:, None] * ex
        nyp = np.sqrt(np.einsum("ni,ni->n", ey, ey))
        ey = ey / nyp[:, None]
    ez = np.cross(ex, ey)
    flip = np.einsum("ni,ni->n", ez, az) < 0
    ez[flip] *= -1.0
    frames = np.stack([ex, ey, ez], axis=1)
    bad = ~(nx > 0) | ~(nyp > _FRAME_RTOL * ny)
    frames[bad] = np.nan
    return frames


def local_frames(center: ArrayLike, nbrs: ArrayLike) -> NDArray[np.float64]:
    """Orthonormal frame aligned with the lattice directions at each node.

    Parameters
    ----------
    center
        ``(N, 3)`` node positions, mm.
    nbrs
        ``(N, 6, 3)`` neighbour positions, mm, in the order :data:`NEIGHBOURS`.

    Returns
    -------
    ``(N, 3, 3)`` frames, rows ``e_x, e_y, e_z`` (unit vectors): ``e_x`` along
    ``v[x+] - v[x-]``, ``e_y`` that of ``v[y+] - v[y-]`` orthogonalised against ``e_x``,
    ``e_z = e_x x e_y`` flipped to point along ``v[z+] - v[z-]``. Nodes whose x axis has
    zero length or whose y axis is parallel to it have no frame: their rows are NaN.

    Raises
    ------
    InputError
        Bad shapes, non-finite coordinates or zero-length links.
    """
    c, v = _validate(center, nbrs)
    out = np.empty((c.shape[0], 3, 3))
    for sl in _slices(c.shape[0]):
        out[sl] = _frames(v[sl])
    return out


# --------------------------------------------------------------------------- appendix B
def _solve_block(a: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Appendix-B weights (in units of the scaled coordinates) and cond for a batch of 6x6."""
    n = a.shape[0]
    w = np.full((n, 6), np.nan)
    cond = np.full(n, np.inf)
    # Fast path: eigenvalues of A^T A give cond to ~eps * cond^2 relative accuracy, plenty
    # below _REFINE_COND; the rest (ill-conditioned, singular) is redone by SVD.
    lam = np.linalg.eigvalsh(a.transpose(0, 2, 1) @ a)
    with np.errstate(divide="ignore", invalid="ignore"):
        est = np.sqrt(lam[:, -1] / lam[:, 0])
    fast = (lam[:, 0] > 0) & (est <= _REFINE_COND)
    refine = ~fast
    if fast.any():
        af = a[fast]
        try:
            w[fast] = np.linalg.solve(af.transpose(0, 2, 1), _E[:, None])[..., 0]
            cond[fast] = est[fast]
        except np.linalg.LinAlgError:  # pragma: no cover - cannot happen for cond <= 1e3
            refine = np.ones(n, dtype=bool)
    if refine.any():
        u, s, vt = np.linalg.svd(a[refine])
        ok = s[:, -1] > _SINGULAR_RTOL * s[:, 0]
        c = np.full(s.shape[0], np.inf)
        wr = np.full((s.shape[0], 6), np.nan)
        if ok.any():
            c[ok] = s[ok, 0] / s[ok, -1]
            # A^-1 = V S^-1 U^T, so w^T = e^T A^-1 = ((e^T V) / s) U^T
            ev = vt[ok] @ _E  # (e^T V)_k = sum_i e_i vt[k, i]
            wr[ok] = np.einsum("nk,njk->nj", ev / s[ok], u[ok])
        w[refine] = wr
        cond[refine] = c
    return w, cond


def _appendix_b_chunk(
    d: NDArray[np.float64], length: NDArray[np.float64], v: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Appendix-B weights (mm^-2) and cond for one chunk of validated links."""
    n = d.shape[0]
    w = np.full((n, 6), np.nan)
    cond = np.full(n, np.inf)
    frames = _frames(v)
    ok = np.isfinite(frames).all(axis=(1, 2))
    if not ok.all():
        if not ok.any():
            return w, cond
        d, length, frames = d[ok], length[ok], frames[ok]
    scale = length.mean(axis=1)  # mean link length, mm
    # scaled local coordinates s[n, j, k] = e_k . d_j / scale
    s = d @ (frames.transpose(0, 2, 1) / scale[:, None, None])
    a = np.empty((s.shape[0], 6, 6))
    a[..., 0::2] = s
    a[..., 1::2] = 0.5 * s * s
    wb, cb = _solve_block(a)
    wb /= (scale * scale)[:, None]  # second derivatives in scaled units -> mm^-2
    if ok.all():
        return wb, cb
    w[ok] = wb
    cond[ok] = cb
    return w, cond


def _appendix_b(
    c: NDArray[np.float64], v: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Appendix-B weights and cond for validated input (see :func:`appendix_b_weights`)."""
    n = c.shape[0]
    w = np.empty((n, 6))
    cond = np.empty(n)
    for sl in _slices(n):
        d, length = _deltas(c[sl], v[sl])
        w[sl], cond[sl] = _appendix_b_chunk(d, length, v[sl])
    return w, cond


def appendix_b_weights(
    center: ArrayLike, nbrs: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Laplacian weights of paper appendix B in the lattice-aligned local frame.

    Parameters
    ----------
    center
        ``(N, 3)`` node positions, mm.
    nbrs
        ``(N, 6, 3)`` neighbour positions, mm, in the order :data:`NEIGHBOURS`.

    Returns
    -------
    w
        ``(N, 6)`` weights, mm^-2 (``1/h^2`` each on a regular grid of spacing ``h``);
        may be negative on distorted stencils. NaN where the system is not invertible
        (numerically singular, or no local frame, see :func:`local_frames`).
    cond
        ``(N,)`` 2-norm condition number of the 6x6 matrix built from the local deltas
        divided by the node's mean link length (scale free; 2 on a regular grid);
        ``inf`` where not invertible. Relative accuracy ~1e-10 or better.

    Raises
    ------
    InputError
        Bad shapes, non-finite coordinates or zero-length links.
    """
    c, v = _validate(center, nbrs)
    return _appendix_b(c, v)


# --------------------------------------------------------------------------- fallback
def _axis_chunk(length: NDArray[np.float64]) -> NDArray[np.float64]:
    """Axis weights (mm^-2) from the (n, 6) link lengths (mm)."""
    lm, lp = length[:, 0::2], length[:, 1::2]
    total = lm + lp
    w = np.empty_like(length)
    w[:, 0::2] = 2.0 / (lm * total)
    w[:, 1::2] = 2.0 / (lp * total)
    return w


def axis_weights(center: ArrayLike, nbrs: ArrayLike) -> NDArray[np.float64]:
    """Per-axis non-uniform three-point second-derivative weights (the fallback).

    For each lattice axis with link lengths ``l-`` and ``l+`` (mm),
    ``w- = 2 / (l- (l- + l+))`` and ``w+ = 2 / (l+ (l- + l+))``.

    Parameters
    ----------
    center
        ``(N, 3)`` node positions, mm.
    nbrs
        ``(N, 6, 3)`` neighbour positions, mm, in the order :data:`NEIGHBOURS`.

    Returns
    -------
    ``(N, 6)`` weights, mm^-2, always > 0; equal to :func:`appendix_b_weights` when the
    neighbours lie on the local axes (on opposite sides of the node).

    Raises
    ------
    InputError
        Bad shapes, non-finite coordinates or zero-length links.
    """
    c, v = _validate(center, nbrs)
    out = np.empty((c.shape[0], 6))
    for sl in _slices(c.shape[0]):
        out[sl] = _axis_chunk(_deltas(c[sl], v[sl])[1])
    return out


@dataclass(frozen=True)
class WeightStats:
    """What :func:`laplacian_weights` found and changed.

    Attributes
    ----------
    nodes
        Number of nodes.
    negative
        Nodes with some finite appendix-B weight below ``floor`` times its axis weight
        (before the fallback; at ``floor > 0`` every negative or zero weight counts).
    ill_conditioned
        Nodes whose condition number exceeds ``max_cond`` (singular ones included).
    nonfinite
        Nodes whose appendix-B weights are not finite (singular system or no frame).
    fallback
        Nodes whose weights the fallback changed.
    blend_mean, blend_max
        Mean and max over all nodes of the blend factor ``t`` used (0: appendix B,
        1: axis weights; ``"axis"`` mode uses 1 at fallback nodes, ``"none"`` 0).
    min_weight, max_weight
        Smallest and largest finite returned weight, mm^-2 (NaN if there is none).
    max_cond
        Largest appendix-B condition number (``inf`` if some node is singular; NaN
        for no nodes).
    """

    nodes: int
    negative: int
    ill_conditioned: int
    nonfinite: int
    fallback: int
    blend_mean: float
    blend_max: float
    min_weight: float
    max_weight: float
    max_cond: float

    def summary(self) -> str:
        """One line for logs and reports."""
        return (
            f"laplacian weights: {self.nodes} nodes, {self.negative} below floor, "
            f"{self.ill_conditioned} ill-conditioned, {self.nonfinite} non-finite, "
            f"{self.fallback} fallback (blend t mean {self.blend_mean:.3g}, max {self.blend_max:.3g}); "
            f"w in [{self.min_weight:.4g}, {self.max_weight:.4g}] mm^-2, max cond {self.max_cond:.3g}"
        )

    def as_dict(self) -> dict[str, int | float]:
        """Plain ``dict`` of the fields (ints and floats)."""
        return asdict(self)


def _blend_factor(
    b: NDArray[np.float64], a: NDArray[np.float64], floor: float
) -> NDArray[np.float64]:
    """Smallest ``t`` in [0, 1] per node with ``(1-t) b_j + t a_j >= floor a_j`` for all j.

    For ``b_j < floor a_j`` (and ``a_j > 0``, ``floor <= 1``) the condition is
    ``t >= (floor a_j - b_j) / (a_j - b_j)``, whose denominator is > 0; otherwise
    ``t_j = 0``. Non-finite rows get ``t = 1``.
    """
    target = floor * a
    low = b < target
    with np.errstate(invalid="ignore", divide="ignore"):
        tj = np.where(low, (target - b) / np.where(low, a - b, 1.0), 0.0)
    t = np.clip(tj.max(axis=1), 0.0, 1.0)
    t[~np.isfinite(b).all(axis=1)] = 1.0
    return t


def laplacian_weights(
    center: ArrayLike,
    nbrs: ArrayLike,
    max_cond: float = 1e4,
    floor: float = 0.05,
    fallback: str = "blend",
) -> tuple[NDArray[np.float64], WeightStats]:
    """Appendix-B Laplacian weights made safe for the Jacobi iteration.

    Parameters
    ----------
    center
        ``(N, 3)`` node positions, mm.
    nbrs
        ``(N, 6, 3)`` neighbour positions, mm, in the order :data:`NEIGHBOURS`.
    max_cond
        Nodes whose appendix-B condition number (see :func:`appendix_b_weights`)
        exceeds this are ill-conditioned and get the axis weights (``>= 1``; with
        ``inf`` only singular nodes, which count as non-finite, get them).
    floor
        Relative floor in [0, 1]: every returned weight is ``>= floor`` times the axis
        weight of the same link (modes ``"blend"`` and ``"axis"``).
    fallback
        ``"blend"`` (default): ``w = (1-t) w_B + t w_A`` with ``w_A`` the
        :func:`axis_weights` and, per node, the smallest ``t`` in [0, 1] meeting the
        floor (``t = 1`` for ill-conditioned or non-finite nodes).
        ``"axis"``: ``w_A`` at every node that needs a fallback.
        ``"none"``: the appendix-B weights unchanged (only counted): negative, NaN or
        ill-conditioned weights remain and the Jacobi iteration may diverge.

    Returns
    -------
    w
        ``(N, 6)`` weights, mm^-2.
    stats
        :class:`WeightStats`.

    Raises
    ------
    InputError
        Bad shapes, non-finite coordinates, zero-length links or bad parameters.
    """
    choice(fallback, "fallback", FALLBACKS)
    try:
        cond_limit = float(max_cond)
    except (TypeError, ValueError):
        cond_limit = float("nan")
    if not cond_limit >= 1.0:  # also rejects NaN; inf is allowed
        raise InputError(f"max_cond must be a number >= 1 (a condition number; inf allowed), got {max_cond!r}")
    max_cond = cond_limit
    floor = real(floor, "floor (fraction of the axis weight)", 0.0, 1.0)
    c, v = _validate(center, nbrs)
    n = c.shape[0]
    w = np.empty((n, 6))
    t = np.zeros(n)
    cond = np.empty(n)
    low = np.empty(n, dtype=bool)
    finite = np.empty(n, dtype=bool)
    changed = np.zeros(n, dtype=bool)
    for sl in _slices(n):
        d, length = _deltas(c[sl], v[sl])
        wb, cond[sl] = _appendix_b_chunk(d, length, v[sl])
        wa = _axis_chunk(length)
        fin = np.isfinite(wb).all(axis=1)
        ill = cond[sl] > max_cond
        with np.errstate(invalid="ignore"):
            lo = fin & (wb < floor * wa).any(axis=1)
        finite[sl], low[sl] = fin, lo
        if fallback == "blend":
            tc = _blend_factor(wb, wa, floor)
            tc[ill] = 1.0
            wc = (1.0 - tc)[:, None] * wb + tc[:, None] * wa
            hit = tc == 1.0
            wc[hit] = wa[hit]  # exact axis weights (and no NaN * 0)
            np.maximum(wc, floor * wa, out=wc)  # guard the last ulp of the closed-form t
            w[sl], t[sl], changed[sl] = wc, tc, tc > 0
        elif fallback == "axis":
            need = lo | ill | ~fin
            w[sl] = np.where(need[:, None], wa, wb)
            t[sl], changed[sl] = need, need
        else:
            w[sl] = wb

    fw = w[np.isfinite(w)]
    stats = WeightStats(
        nodes=int(n),
        negative=int(low.sum()),
        ill_conditioned=int((cond > max_cond).sum()),
        nonfinite=int((~finite).sum()),
        fallback=int(changed.sum()),
        blend_mean=float(t.mean()) if n else 0.0,
        blend_max=float(t.max()) if n else 0.0,
        min_weight=float(fw.min()) if fw.size else float("nan"),
        max_weight=float(fw.max()) if fw.size else float("nan"),
        max_cond=float(cond.max()) if n else float("nan"),
    )
    return w, stats
