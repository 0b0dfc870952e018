"""Texture packing and rasterisation primitives (Wang et al. 2008, section 5.2, figures 6-7).

:class:`Mosaic` lays equal ``bw x bh`` texel blocks (x-y slices of a grid) row by row into
one 2D texture, block ``k`` at ``((k % tiles_x) bw, (k // tiles_x) bh)``. A regular grid is
one cube (its z-slices are the blocks); a polygrid is many cubes in scan-line order, each
contributing its ``n`` slices by increasing z (figure 6). Node arrays are packed in flat
node order (block-major, then y, then x).

:func:`decompose` groups the texels of one solver pass by the texel offsets to their
neighbours and cuts every group into axis-aligned rectangles; :func:`primitive_vertices`
turns a rectangle into a quad (two triangles), a 1-texel-wide rectangle into a line and a
single texel into a point, all carrying the offsets as vertex attributes (figure 7).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError

# Vertex layout of the polygrid passes: texel-space position and six texel offsets.
VERTEX = np.dtype([("pos", "f4", 2), ("off", "i4", 12)])


@dataclass(frozen=True, eq=False)
class Mosaic:
    """``n_blocks`` blocks of ``bw x bh`` texels tiled into a texture of at most
    ``max_texture_size`` texels per edge.

    ``kept`` (``(n_blocks,)`` bool, default all) drops blocks from the texture: the kept
    ones are tiled in order and a dropped block has no texels (the adaptive scheme drops
    the blocks a level does not use, Wang et al. 2008 sec. 5.3)."""

    bw: int
    bh: int
    n_blocks: int
    max_texture_size: int = 16384
    kept: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        if self.kept is not None:
            kept = np.asarray(self.kept, dtype=bool)
            if kept.shape != (self.n_blocks,):
                raise InputError(f"kept has shape {kept.shape}, expected ({self.n_blocks},)")
            if not kept.any():
                raise InputError("a mosaic must keep at least one block")
            object.__setattr__(self, "kept", kept)
        if self.bw > self.max_texture_size or self.bh > self.max_texture_size:
            raise InputError(f"a z-slice block of {self.bw}x{self.bh} texels exceeds the texture size limit "
                             f"{self.max_texture_size}; use a coarser grid")
        w, h = self.texture_size
        if h > self.max_texture_size:
            raise InputError(f"{self.n_slots} blocks of {self.bw}x{self.bh} texels need a {w}x{h} "
                             f"texture, over the limit {self.max_texture_size}; use fewer nodes (a smaller n per cube "
                             "edge, fewer cubes, or a smaller grid)")

    @cached_property
    def slot(self) -> NDArray[np.int64]:
        """``(n_blocks,)`` tile slot of each block, -1 where dropped."""
        if self.kept is None:
            return np.arange(self.n_blocks, dtype=np.int64)
        return np.where(self.kept, np.cumsum(self.kept) - 1, -1).astype(np.int64)

    @property
    def n_slots(self) -> int:
        """Blocks held in the texture."""
        return self.n_blocks if self.kept is None else int(self.kept.sum())

    @cached_property
    def tiles(self) -> tuple[int, int]:
        """``(tiles_x, tiles_y)``: blocks per texture row and column (near-square texture)."""
        nb = self.n_slots
        tiles_x = max(1, min(nb, round(math.sqrt(nb * self.bh / self.bw)), self.max_texture_size // self.bw))
        return tiles_x, -(-nb // tiles_x)

    @property
    def texture_size(self) -> tuple[int, int]:
        """``(width, height)`` in texels."""
        tx, ty = self.tiles
        return tx * self.bw, ty * self.bh

    def block_origin(self, k: ArrayLike) -> NDArray[np.int64]:
        """Texel ``(x, y)`` of texel ``(0, 0)`` of block(s) ``k``; ``(-1, -1)`` for a dropped block."""
        s = self.slot[np.asarray(k, dtype=np.int64)]
        tx = self.tiles[0]
        origin = np.stack([(s % tx) * self.bw, (s // tx) * self.bh], axis=-1)
        return np.where(s[..., None] >= 0, origin, -1)

    def texel(self, flat: ArrayLike) -> NDArray[np.int64]:
        """Texel ``(x, y)`` of flat node index(es) (block-major, then y, then x); ``(-1, -1)``
        for a node of a dropped block."""
        flat = np.asarray(flat, dtype=np.int64)
        k, r = np.divmod(flat, self.bw * self.bh)
        y, x = np.divmod(r, self.bw)
        origin = self.block_origin(k)
        return np.where(origin >= 0, origin + np.stack([x, y], axis=-1), -1)

    def kept_nodes(self) -> NDArray[np.bool_]:
        """``(n_blocks * bh * bw,)`` flat mask of the nodes that have a texel."""
        return np.repeat(self.slot >= 0, self.bw * self.bh)

    def pack(self, nodes: ArrayLike, components: int = 4) -> NDArray[np.float32]:
        """``(n_blocks, bh, bw[, c])`` (or any shape with that many nodes first) ->
        ``(height, width, components)`` float32 texture, unused texels 0 (dropped blocks
        are left out)."""
        arr = np.asarray(nodes, dtype=np.float32)
        n = self.n_blocks * self.bh * self.bw
        if arr.size == n:
            arr = arr.reshape(n, 1)
        elif arr.size % n == 0 and arr.shape[-1] * n == arr.size:
            arr = arr.reshape(n, arr.shape[-1])
        else:
            raise InputError(f"node array of shape {arr.shape} does not hold {n} nodes")
        c = arr.shape[1]
        if c > components:
            raise InputError(f"node array has {c} channels, texture only {components}")
        if self.kept is not None:
            arr = arr[self.kept_nodes()]
        tx, ty = self.tiles
        pad = np.zeros((tx * ty * self.bh * self.bw, components), dtype=np.float32)
        pad[:arr.shape[0], :c] = arr
        w, h = self.texture_size
        return pad.reshape(ty, tx, self.bh, self.bw, components).transpose(0, 2, 1, 3, 4).reshape(h, w, components)

    def unpack(self, texture: ArrayLike, channels: int = 3, fill: float = 0.0) -> NDArray[np.float32]:
        """Inverse of :meth:`pack`: ``(height, width, c)`` -> ``(n_blocks, bh, bw, channels)``;
        the nodes of dropped blocks get ``fill``."""
        tex = np.asarray(texture)
        tx, ty = self.tiles
        blocks = tex.reshape(ty, self.bh, tx, self.bw, tex.shape[-1]).transpose(0, 2, 1, 3, 4)
        held = blocks.reshape(tx * ty, self.bh, self.bw, tex.shape[-1])[: self.n_slots, ..., :channels]
        if self.kept is None:
            return held
        out = np.full((self.n_blocks,) + held.shape[1:], fill, dtype=held.dtype)
        out[self.kept] = held
        return out


@dataclass(frozen=True)
class Primitives:
    """Rectangles ``(x0, y0, x1, y1)`` (end exclusive) of texels sharing one offset set.

    ``offsets[i]`` is the ``(6, 2)`` texel offset array of rectangle ``i``.
    """

    rects: NDArray[np.int64]
    offsets: NDArray[np.int64]

    @property
    def kinds(self) -> dict[str, int]:
        """Counts of quads, lines and points."""
        w = self.rects[:, 2] - self.rects[:, 0]
        h = self.rects[:, 3] - self.rects[:, 1]
        point = (w == 1) & (h == 1)
        line = ((w == 1) | (h == 1)) & ~point
        return {"quads": int((~point & ~line).sum()), "lines": int(line.sum()), "points": int(point.sum())}

    @property
    def texels(self) -> int:
        return int(((self.rects[:, 2] - self.rects[:, 0]) * (self.rects[:, 3] - self.rects[:, 1])).sum())


def _row_keys(rows: NDArray[np.int64]) -> NDArray[np.int64]:
    """``(m,)`` dense integer key per row of ``rows`` (``(m, c)`` ints), equal for equal rows
    and ordered like the rows (lexicographically); one 1D unique per column, which is much
    faster than ``np.unique(axis=0)`` on 1e6 rows."""
    key = np.zeros(rows.shape[0], dtype=np.int64)
    for col in rows.T:
        lo = col.min()
        span = int(col.max() - lo) + 1
        _, key = np.unique(key * span + (col - lo), return_inverse=True)
        key = key.ravel()
    return key


def decompose(texels: NDArray[np.int64], offsets: NDArray[np.int64]) -> Primitives:
    """Cut a set of texels into rectangles of equal offsets.

    Parameters
    ----------
    texels
        ``(m, 2)`` texel ``(x, y)`` of the nodes of one pass (distinct).
    offsets
        ``(m, k, 2)`` texel offsets from each node to the ``k`` nodes it reads.

    Runs of horizontally adjacent texels with identical offsets are found first, then
    equal runs on consecutive rows are merged into rectangles. Every texel is covered
    by exactly one rectangle whose offsets are its own.
    """
    m = texels.shape[0]
    k = offsets.shape[1]
    if m == 0:
        return Primitives(np.zeros((0, 4), np.int64), np.zeros((0, 6, 2), np.int64))
    key = _row_keys(offsets.reshape(m, -1))
    # horizontal runs: sort by (y, x), break where y, key or x-continuity changes
    order = np.lexsort((texels[:, 0], texels[:, 1]))
    x, y, kk = texels[order, 0], texels[order, 1], key[order]
    brk = np.ones(m, dtype=bool)
    brk[1:] = (y[1:] != y[:-1]) | (kk[1:] != kk[:-1]) | (x[1:] != x[:-1] + 1)
    starts = np.flatnonzero(brk)
    ends = np.append(starts[1:], m)
    runs = np.stack([x[starts], y[starts], x[ends - 1] + 1, kk[starts]], axis=1)
    first = order[starts]
    # vertical merge of equal runs (x0, x1, key) on consecutive rows
    o2 = np.lexsort((runs[:, 1], runs[:, 3], runs[:, 2], runs[:, 0]))
    r = runs[o2]
    same = np.ones(len(r), dtype=bool)
    same[0] = False
    same[1:] = ((r[1:, 0] == r[:-1, 0]) & (r[1:, 2] == r[:-1, 2]) & (r[1:, 3] == r[:-1, 3])
                & (r[1:, 1] == r[:-1, 1] + 1))
    gstart = np.flatnonzero(~same)
    gend = np.append(gstart[1:], len(r))
    rects = np.stack([r[gstart, 0], r[gstart, 1], r[gstart, 2], r[gend - 1, 1] + 1], axis=1)
    offs = np.zeros((len(rects), 6, 2), dtype=np.int64)
    offs[:, :k] = offsets[first[o2[gstart]]]
    return Primitives(rects.astype(np.int64), offs)


def primitive_vertices(prims: Primitives) -> dict[str, NDArray]:
    """Vertex arrays (``VERTEX``) per GL mode: ``"triangles"`` (two per quad), ``"lines"``
    (texel-centre to one-past-the-end centre: the half-open diamond-exit rule draws
    exactly the run) and ``"points"`` (texel centres)."""
    r = prims.rects
    w, h = r[:, 2] - r[:, 0], r[:, 3] - r[:, 1]
    point = (w == 1) & (h == 1)
    hline = (h == 1) & (w > 1)
    vline = (w == 1) & (h > 1)
    quad = (w > 1) & (h > 1)

    def verts(pos: NDArray, offs: NDArray) -> NDArray:
        out = np.zeros(len(pos), dtype=VERTEX)
        out["pos"] = pos
        out["off"] = offs.reshape(len(pos), 12)
        return out

    q = r[quad]
    corners = np.stack([q[:, [0, 1]], q[:, [2, 1]], q[:, [2, 3]], q[:, [0, 1]], q[:, [2, 3]], q[:, [0, 3]]], axis=1)
    tri = verts(corners.reshape(-1, 2), np.repeat(prims.offsets[quad], 6, axis=0))
    hl, vl = r[hline], r[vline]
    hpos = np.stack([np.stack([hl[:, 0] + 0.5, hl[:, 1] + 0.5], 1), np.stack([hl[:, 2] + 0.5, hl[:, 1] + 0.5], 1)], 1)
    vpos = np.stack([np.stack([vl[:, 0] + 0.5, vl[:, 1] + 0.5], 1), np.stack([vl[:, 0] + 0.5, vl[:, 3] + 0.5], 1)], 1)
    lines = verts(np.concatenate([hpos, vpos]).reshape(-1, 2),
                  np.repeat(np.concatenate([prims.offsets[hline], prims.offsets[vline]]), 2, axis=0))
    p = r[point]
    points = verts(p[:, :2] + 0.5, prims.offsets[point])
    return {"triangles": tri, "lines": lines, "points": points}
