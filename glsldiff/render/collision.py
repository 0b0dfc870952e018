"""The first-collision volume source on a tetrahedral grid (``[options].source = "volume"``).

Per node: its depth below the grid's surface (the triangles of its surface nodes), the beams
of pass 1 (:func:`glsldiff.render.pass1.incident_light`) interpolated to its closest surface
point (barycentric, as pass 3 interpolates), the material at the node and at that point, and
the lumped node volume of the tetrahedra; :func:`glsldiff.physics.collision.node_source` turns
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

__all__ = ["first_collision_load", "compress_beams", "column_totals", "SurfaceColumns", "surface_columns", "REACH",
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


def surface_columns(pg: Any) -> SurfaceColumns:
    """The :class:`SurfaceColumns` of tetrahedral grid ``pg``."""
    surf = Mesh(np.asarray(pg.boundary_positions, dtype=np.float64), np.asarray(pg.surface_triangles, dtype=np.int64),
                name="surface nodes")
    scale = float(np.ptp(surf.vertices, axis=0).max())
    T, _ = first_hits(surf, surf.vertices, -np.asarray(pg.normals), t_min=1e-6 * scale)
    return SurfaceColumns(surf, vertex_areas(surf.vertices, surf.faces), np.where(np.isfinite(T), T, np.inf))


def first_collision_load(pg: Any, kappa: NDArray[np.float64], mu: NDArray[np.float64],
                         beams: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
                         volumes: NDArray[np.float64], columns: SurfaceColumns | None = None) -> NDArray[np.float64]:
    """``(n, 3)`` load of the first-collision source at every node of the tetrahedral grid
    ``pg`` (``kappa`` mm, ``mu`` mm^-1 per node ``(n, 3)``; ``beams`` per boundary node;
    ``volumes`` the lumped node volumes, mm^3,
    :attr:`glsldiff.oracle.fem.TetGeometry.node_volumes`; ``columns``: the grid's
    :func:`surface_columns`, made here when not given)."""
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
    # nodes within reach of a lit surface node (the k-d distance bounds the surface distance from above)
    dist, _ = cKDTree(bpos[lit]).query(pg.positions, distance_upper_bound=reach + 2.0 * pg.h)
    near = np.isfinite(dist) & pg.active
    nodes = np.flatnonzero(near)
    columns = surface_columns(pg) if columns is None else columns
    surf = columns.surf
    st_surf = sigma_t[pg.surface_nodes]
    spread_tv, spread_w = np.zeros((len(nodes), 3), dtype=np.int64), np.zeros((len(nodes), 3))
    for s in range(0, len(nodes), _CHUNK):
        idx = nodes[s:s + _CHUNK]
        cp, depth, tri, _ = closest_points(surf, pg.positions[idx], exact=False)
        tv = surf.faces[tri]
        w = closest_on_triangles(cp, *(surf.vertices[tv[:, k]] for k in range(3)))   # (m, 3) barycentrics
        Ek = np.einsum("mj,mjkc->mkc", w, E[tv])
        tk = np.einsum("mj,mjk->mk", w, t[tv])
        path_st = 0.5 * (sigma_t[idx] + np.einsum("mj,mjc->mc", w, st_surf[tv]))
        out[idx] = node_source(depth, volumes[idx], Ek, tk, sigma_s[idx], path_st, pg.h)
        spread_tv[s:s + len(idx)], spread_w[s:s + len(idx)] = tv, w
    # conservation: the light the thin first layer missed collides there: the surface node gets it
    got = np.zeros((len(bpos), 3))
    np.add.at(got, spread_tv, spread_w[:, :, None] * out[nodes][:, None, :])
    want = column_totals(columns, E, t, sigma_s[pg.surface_nodes], st_surf)
    out[pg.surface_nodes] += np.maximum(want - got, 0.0)
    return out


def column_totals(columns: SurfaceColumns, E: NDArray[np.float64], t: NDArray[np.float64],
                  sigma_s: NDArray[np.float64], sigma_t: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(S, 3)`` first-collision total below each surface node: its lumped area times
    ``sum_k (sigma_s / sigma_t) E_k (1 - exp(-sigma_t T / t_k))``, ``T`` the thickness of
    ``columns``. ``E`` ``(S, K, 3)``, ``t`` ``(S, K)``; ``sigma_s``, ``sigma_t`` ``(S, 3)`` at the nodes."""
    T = columns.thickness[:, None, None]
    ok = t > T_MIN
    ts = np.where(ok, t, 1.0)[:, :, None]
    with np.errstate(over="ignore"):
        through = -np.expm1(-sigma_t[:, None, :] * T / ts)                       # (S, K, 3)
    col = np.where(ok[:, :, None], E * through, 0.0).sum(axis=1)
    return columns.area[:, None] * sigma_s / sigma_t * col
