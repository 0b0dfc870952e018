"""The first-collision volume source on a tetrahedral grid (``[options].source = "volume"``).

Per node: its depth below the grid's surface (the triangles of its surface nodes), the beams
of pass 1 (:func:`glsldiff.render.pass1.incident_light`) interpolated to its closest surface
point (barycentric, as pass 3 interpolates), the material at the node and at that point, and
the lumped node volume of the tetrahedra; and the same for the light entering on the far side
of the node's column: where the inward normal rays of the closest face's nodes leave the
object (:class:`SurfaceColumns`), at the remaining depth (thickness less the node's depth). A
thin part lit from behind (a back-lit slab, an ear) gets the light that crosses it at every
node along the way, not only at the nodes nearer the lit face (taking the closest surface
point alone lost about 10 % of the power through a slab: nodes past the mid-plane got none
and the conservation step put the light on the lit surface node, where much of it escapes); :func:`glsldiff.physics.collision.node_source` turns
them into the load ``V_i <Q>_i``. Nodes deeper than ``REACH`` mean free paths of the most
transparent channel get none (the reduced intensity there is below ``exp(-REACH)`` = 6e-6 of
its surface value). Depths are to the faces around each node's nearest surface node
(``closest_points(..., exact=False)``; the exact search cost 15x more on the bunny).

Conservation (:func:`column_totals`): the hat averages assume node layers ``h`` apart, but the
pillowed grid's first layer is thinner (on the 60 mm slab of ``glsldiff validate`` a surface
node's lumped volume is 0.37 of ``A h / 2``), so light that collides within the first layer
was under-counted: 7 % of the collided light at normal incidence, 16 % at incidence cosine 0.2.
Each surface node's area must see the light it lets in collide below it,
``A_s sum_k (sigma_s' / sigma_t') E_k (1 - exp(-sigma_t' T_s / t_k))`` (:func:`column_totals`,
``T_s`` the object's thickness along the inward normal, ray cast once per grid:
:class:`SurfaceColumns`, which the renderer keeps with the grid); the loads spread back onto
the surface nodes (the barycentric weights of each node's closest surface point) fall short of
it by what collided inside the thin first layer, and that shortfall is added to the surface
node itself. (Scaling the whole column up instead puts the missing shallow light deep: on a
5 mm slab back-lit through eta = 1.4, with the classic Robin constant, that made the
transmitted power 1.095x Monte Carlo's, the surface-node deposit 1.086x, against 1.062x for the
same diffusion model solved in 1-D, :mod:`glsldiff.oracle.slab_transport`; with the renderer's
Fresnel-moment constant the slab is 1.011x.) Where the loads exceed the column total (thin
parts, edges) nothing is taken away.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff.mesh import Mesh, vertex_areas
from glsldiff.mesh.closest import closest_on_triangles, closest_points
from glsldiff.mesh.raycast import first_hits
from glsldiff.physics.collision import T_MIN, node_source

__all__ = ["first_collision_load", "compress_beams", "column_totals", "NodeColumns", "node_columns", "SurfaceColumns",
           "surface_columns", "REACH",
           "T_BINS"]

#: Depth, in mean free paths of the most transparent channel, beyond which nodes get no source.
REACH = 12.0
#: Refracted-cosine bins the beams of a node are merged into (:func:`compress_beams`).
T_BINS = (0.0, 0.5, 0.65, 0.8, 0.9, 1.0 + 1e-9)
_CHUNK = 8192


def compress_beams(E: NDArray[np.float64], t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Beams ``E (S, K, 3)``, ``t (S, K)`` merged into at most ``len(T_BINS) - 1`` per node by
    refracted cosine: each bin's irradiance summed, its cosine the irradiance-weighted mean.
    (An area light brings ``samples^2`` beams; the attenuation ``exp(-sigma_t z / t)`` varies
    little across a bin, and the per-node work drops by that factor.)"""
    m = len(T_BINS) - 1
    if E.shape[1] <= m:
        return E, t
    which = np.clip(np.digitize(t, T_BINS) - 1, 0, m - 1)           # (S, K)
    w = E.sum(axis=2)
    Eb = np.zeros((len(E), m, 3))
    wt = np.zeros((len(E), m))
    wb = np.zeros((len(E), m))
    rows = np.repeat(np.arange(len(E)), E.shape[1])
    np.add.at(Eb, (rows, which.ravel()), E.reshape(-1, 3))
    np.add.at(wt, (rows, which.ravel()), (w * t).ravel())
    np.add.at(wb, (rows, which.ravel()), w.ravel())
    centre = 0.5 * (np.asarray(T_BINS[:-1]) + np.asarray(T_BINS[1:]))
    tb = np.where(wb > 0, wt / np.where(wb > 0, wb, 1.0), centre[None, :])
    return Eb, tb


@dataclass(frozen=True)
class SurfaceColumns:
    """What the load needs of a grid's surface and nothing of the light: the surface-node
    mesh (its BVH built once), each node's lumped area (mm^2) and the object's thickness along
    its inward normal (mm; inf where the ray leaves nothing). Geometry only: keep it with the
    grid (a ray cast per surface node costs 1.6 s on the bunny's 23k)."""

    surf: Mesh
    area: NDArray[np.float64]
    thickness: NDArray[np.float64]
    far_nodes: NDArray[np.int64]       # (S, 3) surface nodes of the face where the inward ray leaves (-1: none)
    far_weights: NDArray[np.float64]   # (S, 3) barycentric weights of that exit point


def surface_columns(pg: Any) -> SurfaceColumns:
    """The :class:`SurfaceColumns` of tetrahedral grid ``pg``."""
    surf = Mesh(np.asarray(pg.boundary_positions, dtype=np.float64), np.asarray(pg.surface_triangles, dtype=np.int64),
                name="surface nodes")
    scale = float(np.ptp(surf.vertices, axis=0).max())
    inward = -np.asarray(pg.normals)
    T, face = first_hits(surf, surf.vertices, inward, t_min=1e-6 * scale)
    hit = np.isfinite(T) & (face >= 0)
    far_nodes = np.full((len(T), 3), -1, dtype=np.int64)
    far_w = np.zeros((len(T), 3))
    if hit.any():
        tv = surf.faces[face[hit]]
        y = surf.vertices[hit] + T[hit, None] * inward[hit]
        far_nodes[hit] = tv
        far_w[hit] = closest_on_triangles(y, *(surf.vertices[tv[:, k]] for k in range(3)))
    return SurfaceColumns(surf, vertex_areas(surf.vertices, surf.faces), np.where(hit, T, np.inf), far_nodes, far_w)


@dataclass(frozen=True)
class NodeColumns:
    """Per active node, what the load needs of the geometry and nothing of the light or the
    material (computed once per grid, :func:`node_columns`): the nearest surface face's nodes
    ``tv`` ``(m, 3)``, the barycentric weights ``w`` of the node's closest point on it and the
    node's ``depth`` below it (mm); the far side of its column: the surface nodes ``far_nodes``
    ``(m, 9)`` (-1: none) and weights ``far_w`` of the points where the inward rays of ``tv``
    leave the object, and the remaining depth ``far_depth`` (mm)."""

    nodes: NDArray[np.int64]
    tv: NDArray[np.int64]
    w: NDArray[np.float64]
    depth: NDArray[np.float64]
    far_nodes: NDArray[np.int64]
    far_w: NDArray[np.float64]
    far_depth: NDArray[np.float64]


def node_columns(pg: Any, columns: SurfaceColumns) -> NodeColumns:
    """The :class:`NodeColumns` of the active nodes of tetrahedral grid ``pg``."""
    nodes = np.flatnonzero(np.asarray(pg.active))
    surf = columns.surf
    m = len(nodes)
    tv_all, w_all, d_all = np.zeros((m, 3), np.int64), np.zeros((m, 3)), np.zeros(m)
    for s in range(0, m, _CHUNK):
        idx = nodes[s:s + _CHUNK]
        cp, depth, tri, _ = closest_points(surf, pg.positions[idx], exact=False)
        tv = surf.faces[tri]
        tv_all[s:s + len(idx)] = tv
        w_all[s:s + len(idx)] = closest_on_triangles(cp, *(surf.vertices[tv[:, k]] for k in range(3)))
        d_all[s:s + len(idx)] = depth
    fn, fw = columns.far_nodes[tv_all], columns.far_weights[tv_all]                  # (m, 3, 3)
    has = fn >= 0
    far_w = np.where(has, w_all[:, :, None] * fw, 0.0).reshape(m, 9)
    far_nodes = np.where(has, fn, -1).reshape(m, 9)
    T = columns.thickness[tv_all]
    far_depth = np.maximum(np.einsum("mj,mj->m", w_all, np.where(np.isfinite(T), T, 0.0)) - d_all, 0.0)
    return NodeColumns(nodes, tv_all, w_all, d_all, far_nodes, far_w, far_depth)


def first_collision_load(pg: Any, kappa: NDArray[np.float64], mu: NDArray[np.float64],
                         beams: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
                         volumes: NDArray[np.float64], columns: SurfaceColumns | None = None,
                         node_cols: NodeColumns | None = None) -> NDArray[np.float64]:
    """``(n, 3)`` load of the first-collision source at every node of the tetrahedral grid
    ``pg`` (``kappa`` mm, ``mu`` mm^-1 per node ``(n, 3)``; ``beams`` per boundary node;
    ``volumes`` the lumped node volumes, mm^3,
    :attr:`glsldiff.oracle.fem.TetGeometry.node_volumes`; ``columns`` and ``node_cols``: the
    grid's :func:`surface_columns` and :func:`node_columns`, made here when not given)."""
    n = len(pg.positions)
    out = np.zeros((n, 3))
    if not beams:
        return out
    sigma_t = 1.0 / (3.0 * kappa)
    sigma_s = np.maximum(sigma_t - mu, 0.0)
    E, t = compress_beams(np.stack([b[0] for b in beams], axis=1), np.stack([b[1] for b in beams], axis=1))
    lit = np.abs(E).sum(axis=(1, 2)) > 0
    if not lit.any():
        return out
    bpos = pg.boundary_positions
    reach = REACH / float(sigma_t[pg.surface_nodes].min())
    columns = surface_columns(pg) if columns is None else columns
    nc = node_columns(pg, columns) if node_cols is None else node_cols
    # nodes within reach of a lit surface node (the k-d distance bounds the surface distance from above)
    dist, _ = cKDTree(bpos[lit]).query(pg.positions[nc.nodes], distance_upper_bound=reach + 2.0 * pg.h)
    rows = np.flatnonzero(np.isfinite(dist))
    st_surf = sigma_t[pg.surface_nodes]
    got = np.zeros((len(bpos), 3))
    for s in range(0, len(rows), _CHUNK):
        r = rows[s:s + _CHUNK]
        idx = nc.nodes[r]
        tv, w = nc.tv[r], nc.w[r]
        Ek = np.einsum("mj,mjkc->mkc", w, E[tv])
        tk = np.einsum("mj,mjk->mk", w, t[tv])
        path_st = 0.5 * (sigma_t[idx] + np.einsum("mj,mjc->mc", w, st_surf[tv]))
        near = node_source(nc.depth[r], volumes[idx], Ek, tk, sigma_s[idx], path_st, pg.h)
        np.add.at(got, tv, w[:, :, None] * near[:, None, :])
        # the light entering on the far side of the node's column (a thin part lit from behind)
        fn, wf = np.maximum(nc.far_nodes[r], 0), nc.far_w[r]
        cover = wf.sum(axis=1)
        ok = (cover > 0.5) & (nc.far_depth[r] > 0.0)
        far = np.zeros_like(near)
        if ok.any():
            fo, wo, co = fn[ok], wf[ok], cover[ok][:, None]
            Ef = np.einsum("mj,mjkc->mkc", wo, E[fo])
            tf = np.einsum("mj,mjk->mk", wo, t[fo]) / co
            path_f = 0.5 * (sigma_t[idx[ok]] + np.einsum("mj,mjc->mc", wo, st_surf[fo]) / co)
            far[ok] = node_source(nc.far_depth[r][ok], volumes[idx[ok]], Ef, tf, sigma_s[idx[ok]],
                                  np.maximum(path_f, 1e-12), pg.h)
        out[idx] = near + far
    # conservation: the light the thin first layer missed collides there: the surface node gets it.
    # The nodes closest to a surface node hold the near half of its column; the far half's light
    # went to the nodes nearer the other side (deep for them: no thin layer to make up for)
    want = column_totals(columns, E, t, sigma_s[pg.surface_nodes], st_surf, half=True)
    out[pg.surface_nodes] += np.maximum(want - got, 0.0)
    return out


def column_totals(columns: SurfaceColumns, E: NDArray[np.float64], t: NDArray[np.float64],
                  sigma_s: NDArray[np.float64], sigma_t: NDArray[np.float64], half: bool = False) -> NDArray[np.float64]:
    """``(S, 3)`` first-collision total below each surface node: its lumped area times
    ``sum_k (sigma_s / sigma_t) E_k (1 - exp(-sigma_t T / t_k))``, ``T`` the thickness of
    ``columns`` (``half``: half of it, the part of the column nearer this surface node).
    ``E`` ``(S, K, 3)``, ``t`` ``(S, K)``; ``sigma_s``, ``sigma_t`` ``(S, 3)`` at the nodes."""
    T = columns.thickness[:, None, None] * (0.5 if half else 1.0)
    ok = t > T_MIN
    ts = np.where(ok, t, 1.0)[:, :, None]
    with np.errstate(over="ignore"):
        through = -np.expm1(-sigma_t[:, None, :] * T / ts)                       # (S, K, 3)
    col = np.where(ok[:, :, None], E * through, 0.0).sum(axis=1)
    return columns.area[:, None] * sigma_s / sigma_t * col
