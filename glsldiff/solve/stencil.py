"""What the GLSL passes draw and read, built from a grid's node graph and texture mosaic
(Wang et al. 2008, section 5.2, figures 6-7); numpy only.

Every grid the solvers take (:class:`~glsldiff.grids.regular.RegularGrid`,
:class:`~glsldiff.grids.polygrid.Polygrid`) exposes ``graph`` (:class:`~glsldiff.grids.graph.NodeGraph`)
and ``mosaic`` (:class:`~glsldiff.packing.Mosaic`); from those alone come

* the rasterisation primitives of the interior pass and of the boundary pass
  (:func:`pass_primitives`: quads, lines and points carrying the texel offsets to the nodes a
  row reads; a regular grid's interior is one quad per z-slice, its side faces lines), or the
  same offsets per texel for the ``"texels"`` packing (:func:`offset_textures`: one quad per
  sweep reads them from two integer textures);
* the weight textures T_w1 / T_w2 (:func:`weight_textures`: scaled Laplacian weights and the
  row scale, mm^2, at interior nodes; the partner distance d, mm, at boundary nodes), or the
  two uniforms that replace them on a regular grid (:func:`uniform_weights`);
* the slot layers of a grid transfer (:func:`transfer_slots`: a sparse matrix as a gather).
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from glsldiff.grids.graph import NodeGraph
from glsldiff.packing import Mosaic, Primitives, decompose

PASSES = ("interior", "boundary")


class PackedGrid(Protocol):
    """What the GLSL solvers need of a grid (both grid types provide it)."""

    graph: NodeGraph
    mosaic: Mosaic
    size: int


def pass_primitives(grid: PackedGrid, update: NDArray[np.bool_] | None = None) -> dict[str, Primitives]:
    """Quad/line/point decomposition of the interior pass and of the boundary pass, over the
    nodes where ``update`` (``(N,)`` flat node mask; default all) is true."""
    ti, off_i, tb, off_b = _pass_offsets(grid, update)
    return {"interior": decompose(ti, off_i), "boundary": decompose(tb, off_b[:, None, :])}


def primitive_count(primitives: dict[str, Primitives]) -> int:
    """Quads, lines and points of all passes together (the draws of one ``"primitives"`` sweep)."""
    return sum(sum(p.kinds.values()) for p in primitives.values())


def _pass_offsets(grid: PackedGrid, update: NDArray[np.bool_] | None
                  ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Texels of the updated interior rows, their ``(m, 6, 2)`` offsets to the six neighbours,
    texels of the updated boundary rows and their ``(m, 2)`` offsets to the partner."""
    g, mosaic = grid.graph, grid.mosaic
    si = slice(None) if update is None else update[g.interior]
    sb = slice(None) if update is None else update[g.boundary]
    ti = mosaic.texel(g.interior[si])
    tb = mosaic.texel(g.boundary[sb])
    return ti, mosaic.texel(g.neighbours[si]) - ti[:, None, :], tb, mosaic.texel(g.link[sb]) - tb


#: How the sweeps reach each texel's neighbour offsets: ``"primitives"`` (the paper's quads,
#: lines and points with the offsets as vertex attributes) or ``"texels"`` (per-texel offset
#: textures, one quad per sweep).
PACKINGS = ("primitives", "texels")
_BIAS = 32768


def _pack_offsets(off: NDArray[np.int64]) -> NDArray[np.int64]:
    """``(..., 2)`` texel offsets -> one int each, ``(dx + 32768) << 16 | (dy + 32768)``."""
    if off.size and np.abs(off).max() >= _BIAS:
        raise ValueError("texel offsets beyond +-32767 do not fit the texels packing")
    return ((off[..., 0] + _BIAS) << 16) | (off[..., 1] + _BIAS)


def offset_textures(grid: PackedGrid, update: NDArray[np.bool_] | None = None
                    ) -> tuple[NDArray[np.uint32], NDArray[np.uint32]]:
    """T_offA = (off0, off1, off2, kind), T_offB = (off3, off4, off5, 0) as ``(h, w, 4)`` uint32
    textures of the ``"texels"`` packing: per texel the packed offsets to the nodes its row reads
    (interior: the six neighbours; boundary: the partner, off0) and its kind (0: not updated,
    1: interior, 2: boundary), over the nodes where ``update`` is true. The same offsets as
    :func:`pass_primitives`."""
    w, h = grid.mosaic.texture_size
    a = np.zeros((h, w, 4), np.int64)
    b = np.zeros((h, w, 4), np.int64)
    ti, off_i, tb, off_b = _pass_offsets(grid, update)
    off_i, off_b = _pack_offsets(off_i), _pack_offsets(off_b)
    a[ti[:, 1], ti[:, 0], :3] = off_i[:, :3]
    a[ti[:, 1], ti[:, 0], 3] = 1
    b[ti[:, 1], ti[:, 0], :3] = off_i[:, 3:]
    a[tb[:, 1], tb[:, 0], 0] = off_b
    a[tb[:, 1], tb[:, 0], 3] = 2
    return a.astype(np.uint32), b.astype(np.uint32)


def weight_textures(grid: PackedGrid) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """T_w1 = (w_x-, w_x+, w_y-, row scale s) and T_w2 = (w_y+, w_z-, w_z+, 0) at interior nodes
    (scaled weights, s in mm^2), T_w1 = (d, 0, 0, 0) at boundary nodes (mm); packed textures.
    Interior texels are the ones with ``s > 0``, boundary ones those with ``s = 0, d > 0``."""
    g = grid.graph
    w1 = np.zeros((grid.size, 4))
    w2 = np.zeros((grid.size, 4))
    w1[g.interior, :3] = g.weights[:, :3]
    w1[g.interior, 3] = g.scale
    w2[g.interior, :3] = g.weights[:, 3:]
    w1[g.boundary, 0] = g.d
    return grid.mosaic.pack(w1), grid.mosaic.pack(w2)


def uniform_weights(graph: NodeGraph) -> dict[str, float]:
    """``{"u_scale": s, "u_d": d}`` (mm^2, mm) when every scaled weight is 1 and every row scale
    and partner distance the same (a regular grid): the shaders then take them as uniforms
    (``UNIFORM_WEIGHTS``) instead of fetching T_w1 / T_w2; else ``{}``."""
    if graph.interior.size == 0 or not np.all(graph.weights == 1.0) or np.ptp(graph.scale) != 0.0:
        return {}
    if graph.d.size and np.ptp(graph.d) != 0.0:
        return {}
    return {"u_scale": float(graph.scale[0]), "u_d": float(graph.d[0]) if graph.d.size else 1.0}


def transfer_slots(matrix: sp.spmatrix, target: Mosaic, source: Mosaic) -> NDArray[np.float32]:
    """A transfer matrix (``(N_target, N_source)``, e.g. a prolongation or a restriction of
    :class:`glsldiff.grids.hierarchy.Transfer`) as ``(K, height, width, 4)`` slot layers on the
    target's texture: layer ``k`` holds, at the texel of target node ``i``, the source texel and
    the weight of the ``k``-th entry of row ``i`` (``(x, y, w, 0)``; ``w = 0``: no entry).
    ``K`` is the longest row. Entries whose target or source has no texel (dropped blocks of
    an adaptive level) are left out: they belong to nodes no pass of that level reads."""
    m = sp.csr_matrix(matrix)
    m.eliminate_zeros()
    rows = np.repeat(np.arange(m.shape[0]), np.diff(m.indptr))
    src = source.texel(m.indices)
    ok = (target.texel(rows)[:, 0] >= 0) & (src[:, 0] >= 0)
    rows, src, vals = rows[ok], src[ok], m.data[ok]
    # slot of each entry: its rank within its row
    starts = np.searchsorted(rows, rows, side="left")
    slot = np.arange(rows.size) - starts
    k = int(slot.max()) + 1 if rows.size else 1
    w, h = target.texture_size
    out = np.zeros((k, h, w, 4), dtype=np.float32)
    dst = target.texel(rows)
    out[slot, dst[:, 1], dst[:, 0], 0] = src[:, 0]
    out[slot, dst[:, 1], dst[:, 0], 1] = src[:, 1]
    out[slot, dst[:, 1], dst[:, 0], 2] = vals
    return out
