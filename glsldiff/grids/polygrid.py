"""The polygrid: a polycube lattice mapped into the object (Wang et al. 2008, section 5.1).

:func:`build_polygrid` runs the whole construction from a closed mesh::

    mesh --polycube_from_mesh--> Polycube --Lattice.build--> Lattice
         --map_to_mesh--> node positions --laplacian_weights--> Polygrid

and :func:`box_polygrid` / :func:`lattice_polygrid` keep the lattice positions (no mesh):
on an axis-aligned box that is exactly the regular grid of :mod:`glsldiff.grids.regular`.

A :class:`Polygrid` is a grid for :class:`glsldiff.system.problem.DiffusionProblem`: node arrays
have shape ``(cubes, n, n, n)`` (``[cube, z, y, x]``, texture order), the boundary source
``q`` and the exitant radiance are ``(n_boundary, 3)`` arrays in boundary-node order.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core.errors import InputError, SolverError
from glsldiff.grids.graph import BOUNDARY, INACTIVE, INTERIOR, NodeGraph
from glsldiff.grids.lattice import Lattice
from glsldiff.grids.mapping import MappingStats, link_variance, map_to_mesh
from glsldiff.grids.polycube import Polycube, polycube_from_mesh
from glsldiff.grids.weights import WeightStats, laplacian_weights
from glsldiff.mesh import Mesh
from glsldiff.packing import Mosaic

__all__ = ["Polygrid", "build_polygrid", "box_polygrid", "lattice_polygrid", "INTERIOR", "BOUNDARY", "INACTIVE"]

logger = logging.getLogger(__name__)


@dataclass(eq=False)
class Polygrid:
    """Nodes, links and Laplacian weights of a polygrid.

    Attributes
    ----------
    lattice
        Node kinds and connectivity (:class:`glsldiff.grids.lattice.Lattice`).
    positions
        ``(N, 3)`` node positions in the object, mm (removed nodes: lattice position).
    normals
        ``(n_boundary, 3)`` outward unit normals at the boundary nodes.
    weights
        ``(n_interior, 6)`` Laplacian weights, mm^-2 (after any fallback).
    """

    lattice: Lattice
    positions: NDArray[np.float64]
    normals: NDArray[np.float64]
    weights: NDArray[np.float64]
    weight_stats: WeightStats | None = None
    mapping: MappingStats | None = None
    mesh: Mesh | None = None
    polycube: Polycube | None = None
    seconds: dict[str, float] = field(default_factory=dict)
    max_texture_size: int = 16384
    kept_blocks: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        self.mosaic  # validates the texture size

    # ---- shape and kinds -----------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int, int]:
        """Node array shape ``(cubes, n, n, n)``."""
        return self.lattice.shape

    @property
    def n(self) -> int:
        return self.lattice.n

    @property
    def size(self) -> int:
        return self.lattice.size_nodes

    @cached_property
    def kind(self) -> NDArray[np.int8]:
        return self.lattice.kind.reshape(self.shape)

    @cached_property
    def active(self) -> NDArray[np.bool_]:
        return self.kind != INACTIVE

    @property
    def n_boundary(self) -> int:
        return self.lattice.n_boundary

    @property
    def n_interior(self) -> int:
        return self.lattice.n_interior

    @property
    def n_active(self) -> int:
        return self.n_boundary + self.n_interior

    @property
    def boundary_positions(self) -> NDArray[np.float64]:
        """``(n_boundary, 3)`` positions of the boundary nodes, mm."""
        return self.positions[self.lattice.boundary]

    # ---- the discrete system ---------------------------------------------------------
    @cached_property
    def d(self) -> NDArray[np.float64]:
        """``(n_boundary,)`` distance of each boundary node to its partner along the inward
        normal, mm: ``(p_b - p_j) . n_b`` (paper: "the distance ... along the inward normal
        direction"). It equals the full distance where the partner lies on the normal; a
        partner shared by two or three boundary nodes at a polycube edge lies off their
        normals, and the normal component keeps ``(phi_b - phi_j) / d`` an approximation of
        the normal derivative. Clamped below at 5 % of the full distance."""
        lat = self.lattice
        delta = self.positions[lat.boundary] - self.positions[lat.link]
        full = np.linalg.norm(delta, axis=1)
        normal = np.einsum("ij,ij->i", delta, self.normals)
        return np.maximum(normal, 0.05 * full)

    @cached_property
    def graph(self) -> NodeGraph:
        """Connectivity with scaled weights ``w_j * 6 / sum_j w_j`` and row scale ``6 / sum_j w_j``."""
        lat = self.lattice
        total = self.weights.sum(axis=1)
        bad = ~(total > 0)
        if bad.any():
            raise SolverError(f"the Laplacian weights of {int(bad.sum())} interior nodes sum to <= 0 or NaN "
                              "(distorted stencils without a fallback); build the weights with "
                              "fallback='blend' or 'axis'")
        scale = 6.0 / total
        g = NodeGraph(lat.kind, lat.neighbours, self.weights * scale[:, None], scale, lat.link, self.d)
        g.check()
        return g

    # ---- texture packing (figure 6) ----------------------------------------------------
    @cached_property
    def mosaic(self) -> Mosaic:
        """x-y slices of each cube as ``n x n`` blocks, cubes in order, slices by increasing z;
        only the :attr:`kept_blocks` where given (see :meth:`with_blocks`)."""
        return Mosaic(self.n, self.n, self.shape[0] * self.n, self.max_texture_size, self.kept_blocks)

    def with_blocks(self, kept: NDArray[np.bool_] | None) -> "Polygrid":
        """The same polygrid packed with only the ``kept`` blocks (``(cubes * n,)`` bool, block
        ``cube * n + z``; ``None``: all): node arrays keep their shape, the textures drop the
        other blocks, whose nodes no solver pass may then read. Cached derived data is shared."""
        out = replace(self, kept_blocks=None if kept is None else np.asarray(kept, dtype=bool))
        for name in ("graph", "d"):
            if name in self.__dict__:
                out.__dict__[name] = self.__dict__[name]
        return out

    @property
    def texture_size(self) -> tuple[int, int]:
        return self.mosaic.texture_size

    def pack(self, nodes: ArrayLike, components: int = 4) -> NDArray[np.float32]:
        """Node array (``shape`` or ``shape + (c,)``) -> packed float32 texture."""
        arr = np.asarray(nodes)
        if arr.shape[:4] != self.shape:
            raise InputError(f"node array shape {arr.shape} does not match the polygrid {self.shape}")
        return self.mosaic.pack(arr.reshape(self.size, -1), components)

    def unpack(self, texture: ArrayLike, channels: int = 3) -> NDArray[np.float32]:
        """Packed texture -> ``shape + (channels,)``."""
        return self.mosaic.unpack(texture, channels).reshape(self.shape + (channels,))  # dropped blocks: 0

    # ---- boundary data -------------------------------------------------------------------
    def source_volume(self, q: ArrayLike | None) -> NDArray[np.float64]:
        """Boundary source as a ``shape + (3,)`` node array, 0 off the boundary.

        ``q`` is a scalar or RGB triple (every boundary node), a ``(n_boundary,)`` or
        ``(n_boundary, 3)`` array in boundary-node order, or a full node array that is
        zero off the boundary; ``None`` is zero. Negative values are allowed (adjoint sources).
        """
        nb = self.n_boundary
        arr = np.asarray(0.0 if q is None else q, dtype=np.float64)
        out = np.zeros((self.size, 3))
        if arr.ndim == 0 or arr.shape == (3,):
            out[self.lattice.boundary] = arr
        elif arr.shape in ((nb,), (nb, 1), (nb, 3)):
            out[self.lattice.boundary] = arr.reshape(nb, -1)
        elif arr.shape in (self.shape, self.shape + (1,), self.shape + (3,)):
            full = np.broadcast_to(arr.reshape(self.size, -1), (self.size, 3))
            off = (self.lattice.kind != BOUNDARY) & np.any(full != 0, axis=1)
            if off.any():
                raise InputError(f"q is non-zero at {int(off.sum())} nodes that are not boundary nodes "
                                 f"(e.g. node {int(np.flatnonzero(off)[0])})")
            out[:] = full
        else:
            raise InputError(f"q has shape {arr.shape}; expected a scalar, (3,), ({nb},), ({nb}, 3) "
                             f"or a node array {self.shape}[+(3,)]")
        bad = ~np.isfinite(out)
        if bad.any():
            raise InputError(f"q has {int(bad.any(axis=1).sum())} boundary nodes with non-finite values")
        return out.reshape(self.shape + (3,))

    def boundary_values(self, nodes: ArrayLike) -> NDArray:
        """``(n_boundary, c)`` values of a node array at the boundary nodes."""
        arr = np.asarray(nodes)
        return arr.reshape(self.size, -1)[self.lattice.boundary]

    # ---- report ------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Counts, geometry and weight quality (see ``glsldiff polygrid``)."""
        lat = self.lattice
        var = link_variance(self.positions, lat.interior, lat.neighbours) / lat.h ** 2
        out: dict[str, Any] = {**lat.counts(), "h_mm": lat.h, "cube_mm": lat.size,
                               "texture": "x".join(map(str, self.texture_size)),
                               "d_mm_mean": float(self.d.mean()),
                               "link_variance_mean_h2": float(var.mean()),
                               "link_variance_max_h2": float(var.max()),
                               "weight_min": float(self.weights.min()), "weight_max": float(self.weights.max())}
        if self.weight_stats is not None:
            out.update({f"weights_{k}": v for k, v in self.weight_stats.as_dict().items()})
        if self.mapping is not None:
            out.update({f"map_{k}": v for k, v in self.mapping.as_dict().items() if k != "seconds"})
        out.update({f"seconds_{k}": v for k, v in self.seconds.items()})
        return out


def node_weights(positions: NDArray, lattice: Lattice, **options: Any) -> tuple[NDArray, WeightStats]:
    """Laplacian weights of every interior node (options of :func:`glsldiff.grids.weights.laplacian_weights`)."""
    return laplacian_weights(positions[lattice.interior], positions[lattice.neighbours], **options)


def lattice_polygrid(lattice: Lattice, max_texture_size: int = 16384, **weight_options: Any) -> Polygrid:
    """The polygrid at the lattice positions (no mesh): boundary nodes one step ``h``
    outside their partners, weights ``1/h^2``."""
    t0 = time.perf_counter()
    pos = lattice.lattice_positions.copy()
    w, ws = node_weights(pos, lattice, **weight_options)
    return Polygrid(lattice, pos, lattice.outward.copy(), w, ws, seconds={"total": time.perf_counter() - t0},
                    max_texture_size=max_texture_size)


def box_polygrid(cubes: tuple[int, int, int], n: int, size: float = 1.0, **kwargs: Any) -> Polygrid:
    """Axis-aligned box of ``cx x cy x cz`` cubes at lattice positions: the same system as
    ``RegularGrid(cx n, cy n, cz n, h=size/n)``."""
    cx, cy, cz = cubes
    z, y, x = np.meshgrid(np.arange(cz), np.arange(cy), np.arange(cx), indexing="ij")
    cube_list = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    return lattice_polygrid(Lattice.build(cube_list, n, size), **kwargs)


#: Lattice nodes a polygrid may have: its arrays take roughly 150 bytes a node on the CPU
#: (positions, links, weights, packing), so 3e7 nodes are about 4.5 GB (the paper's bunny,
#: 253 cubes of 16^3, has 1e6).
MAX_NODES = 30_000_000


def node_budget_problem(cubes: int, n: int, limit: int = MAX_NODES, bytes_per_node: int = 150) -> str | None:
    """Why ``cubes`` cubes of ``n^3`` nodes exceed ``limit`` (default :data:`MAX_NODES`; the
    tetrahedral grid's is :data:`glsldiff.grids.tetrahedral.fem_grid.FEM_MAX_NODES`) and what fits, or None."""
    nodes = int(cubes) * int(n) ** 3
    if nodes <= limit:
        return None
    n_max = int((limit / max(int(cubes), 1)) ** (1.0 / 3.0) + 1e-9)
    fix = f"use n <= {n_max} or fewer cubes" if n_max >= 2 else f"use fewer cubes (at most {limit // n ** 3} of n = {n})"
    return (f"{cubes} cubes of n = {n} nodes per edge make {nodes:.3g} lattice nodes (about "
            f"{max(nodes * bytes_per_node / 2**30, 1):.0f} GiB); the limit is {limit:.0e}: {fix}")


def check_node_budget(cubes: int, n: int, what: str = "polygrid", limit: int = MAX_NODES,
                      bytes_per_node: int = 150) -> None:
    """Raise :class:`InputError` (``"<what>: ..."``) if :func:`node_budget_problem` finds one."""
    problem = node_budget_problem(cubes, n, limit, bytes_per_node)
    if problem:
        raise InputError(f"{what}: {problem}")


def build_polygrid(mesh: Mesh, n: int = 16, cube_size: float | None = None, n_cubes: int | None = None,
                   threshold: float = 0.5, polycube: Polycube | None = None,
                   mapping: dict[str, Any] | None = None, weights: dict[str, Any] | None = None,
                   max_texture_size: int = 16384) -> Polygrid:
    """Polycube, lattice, mapping and weights for a closed mesh.

    Parameters
    ----------
    mesh
        Closed, manifold, single-component mesh (mm), see :func:`glsldiff.mesh.load_mesh`.
    n
        Nodes per cube edge (paper: 16 for the bunny, 12 for the hole model).
    cube_size, n_cubes
        Cube edge in mm, or a target cube count (paper's bunny: 253); ignored when an
        explicit ``polycube`` is given.
    threshold
        Inside-volume fraction a cube needs (see :func:`glsldiff.grids.polycube.polycube_from_mesh`).
    mapping, weights
        Options of :func:`glsldiff.grids.mapping.map_to_mesh` and
        :func:`glsldiff.grids.weights.laplacian_weights`.
    """
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    if n_cubes is not None and polycube is None and cube_size is None:
        check_node_budget(n_cubes, n)  # the target count: before the polycube search
    if polycube is None:
        polycube = polycube_from_mesh(mesh, cube_size=cube_size, n_cubes=n_cubes, threshold=threshold)
    check_node_budget(len(polycube.cubes), n)
    seconds["polycube"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    lattice = Lattice.build(polycube.cubes, n, polycube.size, polycube.origin)
    lattice.kind, lattice.surface_pairs  # noqa: B018  (classify now, timed)
    seconds["lattice"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    pos, normals, mstats = map_to_mesh(lattice, mesh, **(mapping or {}))
    seconds["mapping"] = time.perf_counter() - t2
    t3 = time.perf_counter()
    w, wstats = node_weights(pos, lattice, **(weights or {}))
    seconds["weights"] = time.perf_counter() - t3
    seconds["total"] = time.perf_counter() - t0
    pg = Polygrid(lattice, pos, normals, w, wstats, mstats, mesh, polycube, seconds, max_texture_size)
    logger.info("polygrid: %s", {k: pg.stats()[k] for k in ("cubes", "interior", "boundary", "removed")})
    return pg


def with_weights(pg: Polygrid, **weight_options: Any) -> Polygrid:
    """The same nodes with weights rebuilt under other options (e.g. another fallback)."""
    w, ws = node_weights(pg.positions, pg.lattice, **weight_options)
    return replace(pg, weights=w, weight_stats=ws)
