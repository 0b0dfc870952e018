"""A pillowed polycube complex mapped into a mesh: the tetrahedral grid of the consistent
(P1 finite-element) discretisation.

:func:`build_fem_grid` runs::

    mesh --polycube_from_mesh--> Polycube --Lattice--> PillowComplex --map_pillow--> FemGrid

Mapping (:func:`map_pillow`):

1. **Surface nodes** go to the closest mesh point of their reference position on the
   polycube surface, then a few rounds of Laplacian smoothing over the surface triangles,
   each followed by re-projection (as the paper's boundary relaxation, Turk 1992). Copies of
   polycube edges that land on a crease of the mesh are re-projected onto the creases, copies
   of polycube corners that land on a mesh corner stay there (:mod:`glsldiff.mesh.features`):
   a box keeps its edges and corners.
   **Coverage**: then a few rounds move each free surface node towards the centroid of the
   mesh surface it is the nearest node to (a restricted Lloyd step on area-uniform surface
   samples, with a little smoothing, re-projected), so that nodes spread into parts the
   polycube reaches only partly (ear tips, legs). Measured at n = 2: bunny (1600 cubes)
   largest vertex-to-node distance 2.9 h -> 1.8 h (99th percentile 1.75 h -> 0.82 h); cow
   (12,000 cubes) 2.6 h -> 1.6 h.
   **Tips**: a centroid never reaches an extreme point, so mesh vertices still more than
   :data:`TIP_REACH` h from every node (ends of horns, tails, ear tips) each get the nearest
   free node moved onto them, which then stays like a corner node (:func:`_snap_tips`).
   Parts thinner than a cube get cubes where the grid needs them (step 4). At the default
   15,000 cubes the cow went 3.91 h -> 1.39 h (167 cubes grown, 36 tip nodes), the bunny
   1.35 h -> 1.20 h (tips only).
2. **Lattice nodes**: the harmonic map with the surface nodes fixed: graph Laplacian of the
   lattice links plus the links from each outer lattice node to its surface copy, weighted 2
   (springs of half the length: the outer layer settles about half a spacing under the
   surface, as in the reference geometry). Thin parts need no special case: the nodes
   between two surface sheets settle between them. (Offsetting the outer layer along the
   inward normals instead gave 2-4x flatter worst tetrahedra on the sphere.)
3. **Untangling**: where tetrahedra are still inverted, the lattice nodes within two rings
   of them move to give every tetrahedron at least a tenth of its reference volume
   (:func:`untangle`). If some remain (a fold of the surface map itself), up to
   :data:`UNTANGLE_ROUNDS` rounds let the surface nodes slide as well, held near their tangent
   planes by a penalty on the normal part of their move, re-project them onto the mesh and
   untangle the lattice again (crease and corner nodes stay). Measured: bunny (1600 cubes of
   n = 2) 17 inverted tetrahedra -> 0, cow 33 -> 1. At the default 15,000 cubes (two builds
   each, measured while pyamg's unseeded set-up still made builds differ; pinned since, see
   :mod:`glsldiff.core.rng`), 3 free rounds ->
   8 tangent rounds: bunny 5, 5 -> 0, 1; bone 3, 5 -> 0, 0; cow 10, 12 -> 6, 8 (16 rounds:
   8); torus 0. Every one of the cow's 8 had two or three crease nodes, which do not slide.
   So, where tetrahedra stay inverted or flat (below :data:`DEGENERATE` of their target:
   three crease nodes on one crease line make a flat surface triangle), the crease and
   corner nodes within one ring of them are released to slide too, and the rounds run again
   (up to :data:`RELEASE_ATTEMPTS` times); the cow (with its thin parts grown): 0 inverted,
   40 nodes released. L-BFGS-B's stopping test is absolute for objectives below 1, so the
   shortfalls are measured in units of the median target (in mm^3 the optimiser stopped at
   once on small cells). Once the rounds stall (a round's count no lower than the last's),
   later rounds allow small sub-problems more L-BFGS iterations (:data:`UNTANGLE_WORK`).
   **Cost**: the objective and its gradient are a compiled loop over the tetrahedra touching
   the free nodes (:func:`_shortfall`, no copy of all nodes), L-BFGS-B runs with one BLAS
   thread (:mod:`glsldiff.core.blas`), only the surface nodes a round moved are re-projected.
   The elk (15,158 cubes, 842k tetrahedra; 1,103 inverted after the harmonic step, in a thin
   plate 2.4 h thick among them): 300 iterations per call left 2 inverted after 49 calls, so
   cubes 2 % larger and smaller were mapped too (1,568 s on 2 loaded cores, 0 inverted at the
   second retry); now 0 inverted in the first mapping, untangling 6.6 s of a 62 s build.
4. **Thin parts only where needed** (:func:`build_fem_grid`): the polycube is first mapped
   without growing into thin parts; only if that grid has inverted tetrahedra or leaves a
   mesh vertex more than :data:`COVERAGE_TARGET` h from every surface node is the grown
   polycube (:mod:`glsldiff.grids.polycube`, step 5) mapped too, and the better grid kept
   (:func:`_rank`). The bunny needs no growth (1.20 h, 0 inverted; growing 18 cubes at an
   ear tip gave 6 inverted); the cow does (ungrown 3.91 h and 8 inverted, grown 1.39 h and
   0), at twice the mapping time.
5. **Shapes** (after step 3, in every mapping; :mod:`glsldiff.grids.tetrahedral.shapes`): untangling
   only asks for a tenth of the reference volume, and tips, coverage moves and released
   creases leave flat tetrahedra (the bunny: worst quality 2.2e-3, 1,132 below 0.1). Every
   node of a tetrahedron below
   :data:`~glsldiff.grids.tetrahedral.shapes.SHAPE_TARGET` is moved if that raises the worst of its own
   tetrahedra without inverting another: towards its neighbours' mean, else by a Nelder-Mead
   search; surface nodes slide along the mesh (creases along the creases) by at most
   :data:`SHAPE_SLIDE` h, and nodes that are the nearest to a mesh vertex more than
   :data:`SHAPE_COVER` h away stay, so coverage does not get worse. Corner and tip nodes stay.
6. **Long edges split** (:mod:`glsldiff.grids.tetrahedral.split`): edges longer than
   :data:`SPLIT_LENGTH` h (the tetrahedra the tips and coverage moves stretch into thin
   parts) are split at their midpoints, in rounds, every tetrahedron and surface triangle on
   them cut in two (conforming; the boundary does not move; new surface nodes get the mesh
   normal of their closest point); edges of flat or inverted tetrahedra stay whole. Measured against each grid's 1:8 refinement
   (:mod:`glsldiff.oracle.refined`), back-lit bunny: +2.5 % nodes, 2.15 -> 1.81 % RMS of the
   exitance, max 24 -> 18 %. A split cuts a sliver along a diagonal into two flatter halves
   (the camel: 204 tetrahedra below the shape target before the split, 598 after), so the
   shape step runs again on the split grid with its interior nodes, old and new, free and
   every surface node in place (interior midpoints then leave their edges' midpoints; their
   reference positions stay there): the camel 375 below the target, worst 0.0042 -> 0.0063,
   its back-lit crease's lowest exact fluence -0.63 -> -0.40 % of the largest; +0.2 s.

7. **Cubes no larger than the mesh allows** (:func:`build_fem_grid`): n and the cube count (or
   size) set the lattice spacing h = cube / n. The cubes themselves play no further part in
   the P1 system (no texture blocks, no per-cube hierarchy), but they set how closely the
   polycube follows the mesh, and cubes of many nodes miss thin parts: at n = 8 (234 cubes,
   the default node budget) the bunny's ears and the cow's legs got no cube (mesh vertices
   11-12 h from every surface node) and 1-19 tetrahedra stayed inverted on four of six
   meshes. So a polycube of cubes of n > :data:`FINE_CUBE_NODES` nodes is mapped only if
   the mesh surface lies at most :data:`FINE_TRIGGER` h outside it and it fits the node
   budget, and kept only if its grid has no inverted tetrahedron and its coverage is within
   :data:`COVERAGE_TARGET` h; otherwise the grid is built from cubes of
   :data:`FINE_CUBE_NODES` nodes for the same request (a cube size ``n / 2`` times smaller, or
   ``(n / 2)^3`` times as many cubes: about the same h, exactly where a size was given), and
   :attr:`MappingQuality.fine_reason` says why. A request over the node budget once the
   search has snapped the cubes to the mesh (a 2 mm tile at n = 8: 2 mm cubes, 1.3 M nodes)
   falls back the same way, to the spacing the request meant, and so does one whose count
   the snap raised beyond :data:`OVERSHOOT` times the count asked for (the tile at n = 5-7).
8. **Retries** (:func:`build_fem_grid`): whether a thin part gets a cube, and whether a
   mapping leaves a tetrahedron inverted, turns on where the cube boundaries fall: at the
   default node budget the bunny built clean at 15,027 cubes of 2 nodes and left one
   tetrahedron inverted at 15,022; the cow reached every vertex within 1.25 h at 15,213
   and 3.46 h at 15,029. So a searched grid that misses either target is built again with
   cubes 2 % larger, 2 % smaller, 4 % larger and 4 % smaller (:data:`RETRY_SIZES`), until
   one meets both; the best is kept (:func:`_rank`), and :attr:`MappingQuality.retries` and
   :attr:`MappingQuality.size_factor` say what it took.
9. **Other repairs** (:func:`_map_candidates`): where no threshold's cubes had the mesh's
   topology and the search repaired them (:mod:`glsldiff.grids.bridges`), the repair that
   leaves out the least inside volume need not map best: which thin part keeps cubes and which
   near-contact is cut turns on the threshold. So before the retries of step 8, the other
   thresholds' repairs (:func:`~glsldiff.grids.polycube.polycube_candidates`, least inside
   volume left out first) are mapped in turn as in step 4 until one meets the targets, and the
   best grid is kept. CGAL's camel at 15,000 cubes: the first repair (threshold 0.7) left the
   tail's thin strand 1.53 h from every surface node; the repairs of 0.3, 0.6 and 0.4 missed
   too (1.57-1.97 h, or inverted tetrahedra), that of 0.2 (whose cubes reach into the strand)
   reached every vertex within 1.22 h with 0 inverted. The retries map the first repair only.

:class:`MappingQuality` reports inverted and the worst tetrahedra and the surface nodes'
spacing.
"""
from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import pyamg
import scipy.optimize as so
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from glsldiff.core.blas import blas_threads
from glsldiff.core.jit import kernel
from glsldiff.core.rng import pinned_global_rng
from glsldiff.core.errors import InputError
from glsldiff.grids.lattice import Lattice
from glsldiff.grids.graph import edge_adjacency, mean_operator
from glsldiff.grids.tetrahedral.pillow import (PillowComplex, signed_volumes, six_volumes, triangle_edges,
                                               unique_tet_edges)
from glsldiff.grids.polycube import Polycube, outside_distance, polycube_candidates
from glsldiff.grids.tetrahedral.shapes import improve_shapes, shape_quality
from glsldiff.grids.tetrahedral.split import EdgeSplit, split_long_edges
from glsldiff.grids.polygrid import check_node_budget, node_budget_problem
from glsldiff.mesh import Mesh, closest_points, surface_samples
from glsldiff.mesh.features import Features, mesh_features

__all__ = ["FEM_MAX_NODES", "FemGrid", "MappingQuality", "build_fem_grid", "map_pillow", "measure_quality"]

#: Largest distance (in lattice spacings h) from a mesh vertex to its nearest surface node
#: that a grid may leave before the polycube is grown into thin parts (step 4).
COVERAGE_TARGET = 1.5

#: Largest lattice node count (cubes x n^3) of a tetrahedral grid: about 5.5 tetrahedra and
#: ~2 kB of assembly, hierarchy and mapping memory per node (the default scene: 143k nodes).
FEM_MAX_NODES = 1_000_000
FEM_BYTES_PER_NODE = 2048

#: Nodes per edge of the cubes a tetrahedral grid falls back to where larger cubes cannot
#: carry the mesh (step 7; the default scene's n).
FINE_CUBE_NODES = 2
#: Largest distance (in h) the mesh surface may lie outside a polycube of larger cubes for it
#: to be mapped at all (step 7): a smooth surface lies up to ~0.47 cube edges outside, so
#: cubes of n <= 6 pass on smooth meshes and thin parts send larger ones to the fine cubes.
FINE_TRIGGER = 3.0
#: Step 7: a polycube of larger cubes whose count the search had to raise beyond this multiple
#: of the count asked for (cubes snapped to a thin box's thickness: the 2 mm tile at n = 7 got
#: 2,500 cubes for 350, 1.1 M nodes for a budget of 120,000) gives way to the fine cubes.
OVERSHOOT = 2.0
#: Step 8: cube sizes (relative to the first build's) tried, in turn, while a searched grid
#: has inverted tetrahedra or coverage beyond COVERAGE_TARGET.
RETRY_SIZES = (1.02, 0.98, 1.04, 0.96)


@dataclass
class MappingQuality:
    """What the mapping achieved (lengths mm, times s)."""

    tets: int = 0
    inverted: int = 0                       # tetrahedra with volume <= 0
    worst_quality: float = float("nan")     # smallest volume / (mean edge)^3 * 6 sqrt(2) (1: regular)
    quality_p1: float = float("nan")        # its 1st percentile
    surface_spacing: float = float("nan")   # mean surface edge length
    surface_spacing_cv: float = float("nan")
    untangled: int = 0                      # inverted or flat tetrahedra before the untangling step
    crease_nodes: int = 0                   # surface nodes kept on a mesh crease
    coverage_max: float = float("nan")      # largest mesh-vertex-to-nearest-surface-node distance / h
    coverage_p99: float = float("nan")      # its 99th percentile
    corner_nodes: int = 0                   # surface nodes kept on a mesh corner
    released: int = 0                       # crease / corner nodes let slide to untangle
    tip_nodes: int = 0                      # surface nodes moved onto mesh tips
    thin_cubes: int = 0                     # polycube cubes grown into thin parts
    poor_before: int = 0                    # tetrahedra below SHAPE_TARGET before the shape step
    poor: int = 0                           # ... and after it
    split_poor_before: int = 0              # tetrahedra below SHAPE_TARGET after the split (step 6)
    split_poor: int = 0                     # ... and after its shape step
    reshaped: int = 0                       # node moves of the shape step
    split_edges: int = 0                    # edges split after the mapping (new nodes)
    split_surface_nodes: int = 0            # ... of which on the surface
    requested_n: int = 0                    # n asked for, when cubes of FINE_CUBE_NODES were used instead (step 7)
    fine_reason: str = ""                   # ... and why
    retries: int = 0                        # builds tried with cubes a few percent off the first's (step 8)
    size_factor: float = 1.0                # this grid's cube size over the first build's
    seconds: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


@dataclass(eq=False)
class FemGrid:
    """A tetrahedral grid of a mesh's interior (see the module docstring).

    Attributes
    ----------
    complex
        The topology (:class:`glsldiff.grids.tetrahedral.pillow.PillowComplex`); node ``i < N`` is
        lattice node ``i``, node ``N + k`` the surface copy of lattice node ``complex.outer[k]``.
    positions
        ``(N + S + K, 3)`` node positions, mm (lattice nodes of no cell: lattice position);
        the last ``K`` are the nodes of the long edges split after the mapping (step 6): the
        midpoints of their edges on the surface, moved by the shape step inside.
    normals
        ``(S + S', 3)`` outward unit mesh normals at the surface nodes (:attr:`surface_nodes`
        order: the ``S`` copies, then the ``S'`` split midpoints on the surface).
    split
        The edge split of step 6 (:class:`glsldiff.grids.tetrahedral.split.EdgeSplit`), None if no edge was split.
    """

    complex: PillowComplex
    positions: NDArray[np.float64]
    normals: NDArray[np.float64]
    quality: MappingQuality
    mesh: Mesh | None = None
    polycube: Polycube | None = None
    split: EdgeSplit | None = None

    @property
    def tets(self) -> NDArray[np.int64]:
        return self.complex.tets if self.split is None else self.split.tets

    @property
    def surface(self) -> NDArray[np.int64]:
        return self.complex.surface if self.split is None else self.split.surface

    @cached_property
    def surface_nodes(self) -> NDArray[np.int64]:
        """``(S + S',)`` node indices of the surface nodes: ``N .. N+S-1``, then the split
        midpoints on the surface in node order."""
        copies = self.complex.n_lattice + np.arange(len(self.complex.outer))
        return copies if self.split is None else np.concatenate([copies, self.split.surface_midpoints])

    @property
    def active(self) -> NDArray[np.bool_]:
        """``(N + S + K,)`` nodes that belong to a tetrahedron."""
        a = np.ones(len(self.positions), dtype=bool)
        a[:self.complex.n_lattice] = False
        a[self.complex.used] = True
        return a

    @property
    def h(self) -> float:
        return self.complex.lattice.h

    @property
    def n_active(self) -> int:
        """Nodes that belong to a tetrahedron (the unknowns)."""
        return int(self.active.sum())

    @property
    def boundary_positions(self) -> NDArray[np.float64]:
        """``(S + S', 3)`` surface node positions, mm (the nodes that carry the source and the exitance)."""
        return self.positions[self.surface_nodes]

    @cached_property
    def surface_triangles(self) -> NDArray[np.int64]:
        """``(F, 3)`` the surface triangles with indices into the surface nodes (0 .. S+S'-1)."""
        if self.split is None:
            return self.surface - self.complex.n_lattice
        index = np.full(len(self.positions), -1, dtype=np.int64)
        index[self.surface_nodes] = np.arange(len(self.surface_nodes))
        return index[self.surface]

    def reference_positions(self) -> NDArray[np.float64]:
        """``(N + S + K, 3)`` every node in the polycube's reference geometry
        (:meth:`glsldiff.grids.tetrahedral.pillow.PillowComplex.reference_positions`; split midpoints: the
        midpoints of their edges there)."""
        ref = self.complex.reference_positions()
        return ref if self.split is None else self.split.extend(ref)

    @cached_property
    def outward_axes(self) -> NDArray[np.int64]:
        """``(S + S', 3)`` the polycube outward axes (+-1 / 0) of each surface node's outer
        faces (:attr:`glsldiff.grids.tetrahedral.pillow.PillowComplex.outward_axes`); a split midpoint takes
        its first parent's."""
        axes = np.asarray(self.complex.outward_axes)
        if self.split is None:
            return axes
        full = np.zeros((self.complex.n_nodes, 3))
        full[self.complex.n_lattice:] = axes
        return self.split.extend(full, weights=(1.0, 0.0))[self.surface_nodes]


def _surface_smoother(surface: NDArray[np.int64], offset: int, n: int) -> sp.csr_matrix:
    """Row-normalised adjacency (mean of edge neighbours) of the surface nodes."""
    return mean_operator(edge_adjacency(triangle_edges(surface) - offset, n))


def _feature_nodes(cx: PillowComplex, mesh: Mesh, xs: NDArray[np.float64], features: Features
                   ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Surface nodes that stay on a crease / a corner of the mesh during relaxation: copies of
    polycube edge nodes (two outward axes) whose projection lies on a crease, and copies of
    polycube corner nodes (three axes) whose projection is a mesh corner. (Face nodes that the
    projection funnels onto a crease stay free and spread back onto the faces.)"""
    tol = 1e-6 * float(np.ptp(mesh.vertices, axis=0).max())
    axes = np.count_nonzero(cx.outward_axes, axis=1)
    _, d_crease = features.closest_on_creases(xs)
    d_corner, _ = features.corner_distance(xs)
    corner = (axes >= 3) & (d_corner <= tol)
    crease = (axes >= 2) & (d_crease <= tol) & ~corner
    return crease, corner


def _harmonic_interior(cx: PillowComplex, X: NDArray[np.float64], copy_weight: float) -> NDArray[np.float64]:
    """Lattice node positions ``(N, 3)``: the harmonic map (graph Laplacian over the lattice
    links, weight 1, and the links from outer nodes to their surface copies, ``copy_weight``)
    with the surface nodes fixed at ``X[N:]``. Lattice nodes of no cell keep ``X[:N]``."""
    N, S = cx.n_lattice, len(cx.outer)
    nb = cx.lattice.lattice_neighbours
    rows, cols = np.repeat(np.arange(N), 6), nb.ravel()
    ok = cols >= 0
    copies = N + np.arange(S)
    r = np.r_[rows[ok], cx.outer, copies]
    c = np.r_[cols[ok], copies, cx.outer]
    w = np.r_[np.ones(int(ok.sum())), np.full(2 * S, float(copy_weight))]
    A = sp.csr_matrix((w, (r, c)), shape=(N + S, N + S))
    L = (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()
    used = cx.used
    out = X[:N].copy()
    Luu = L[used][:, used].tocsr()
    rhs = -(L[used][:, copies] @ X[N:])
    if len(used) <= 20_000:
        out[used] = spla.splu(Luu.tocsc()).solve(rhs)
    else:   # SuperLU fills in on 3-D Laplacians (47 s at 100k nodes): algebraic multigrid + CG
        # on one BLAS thread: the grid's last bits (which untangling amplifies) then do not depend
        # on the machine's core count, and on 2 busy cores it is 3-10x faster (core.blas)
        with pinned_global_rng(), blas_threads(1):   # pyamg's set-up draws random vectors: pinned
            ml = pyamg.smoothed_aggregation_solver(Luu, symmetry="symmetric")
            for k in range(3):
                out[used, k] = ml.solve(rhs[:, k], x0=out[used, k], tol=1e-10, accel="cg", maxiter=200)
    return out


#: Rounds of the untangling step in which the surface nodes slide (module docstring, step 3).
UNTANGLE_ROUNDS = 8
#: Times the crease and corner nodes at tetrahedra still flat or inverted are let slide.
RELEASE_ATTEMPTS = 2
#: A tetrahedron below this fraction of its untangling target counts as flat (the untangling
#: also lifts it).
DEGENERATE = 0.01


def _untangle_targets(reference_det: NDArray[np.float64], fraction: float) -> NDArray[np.float64]:
    """``6 V`` each tetrahedron should reach: ``fraction`` of its reference value (a quarter of
    the median where the reference is flatter, as at polycube saddle vertices)."""
    return fraction * np.maximum(reference_det, np.median(np.abs(reference_det)) * 0.25)


def _below_target(X: NDArray[np.float64], tets: NDArray[np.int64], target: NDArray[np.float64],
                  floor: float) -> NDArray[np.bool_]:
    """``(T,)`` tetrahedra whose ``6 V`` is at most ``floor`` of their untangling ``target``
    (``floor`` 0: the inverted ones)."""
    return six_volumes(X, tets) <= floor * target


def _near_nodes(n: int, tets: NDArray[np.int64], bad: NDArray[np.bool_], rings: int) -> NDArray[np.bool_]:
    """``(n,)`` nodes of the ``bad`` tetrahedra and of the ``rings`` tetrahedron rings around them."""
    near = np.zeros(n, dtype=bool)
    near[tets[bad].ravel()] = True
    for _ in range(rings):
        near[tets[near[tets].any(axis=1)].ravel()] = True
    return near


@kernel
def _shortfall(x: NDArray[np.float64], X: NDArray[np.float64], slot: NDArray[np.int64], tets: NDArray[np.int64],
               target: NDArray[np.float64], scale: float) -> tuple[float, NDArray[np.float64]]:
    """Knupp's squared untangling objective ``sum_t max(0, target_t - 6 V_t / scale)^2`` over
    ``tets`` and its gradient ``(F, 3)`` w.r.t. the free nodes: node ``i`` lies at
    ``x[slot[i]]`` where ``slot[i] >= 0`` (free), else at ``X[i]`` (mm; ``target`` in units of
    ``scale``, mm^3)."""
    grad = np.zeros(x.shape)
    P, G = np.empty((4, 3)), np.empty((4, 3))
    f = 0.0
    for t in range(len(tets)):
        for c in range(4):
            i = tets[t, c]
            s = slot[i]
            for k in range(3):
                P[c, k] = x[s, k] if s >= 0 else X[i, k]
        a0, a1, a2 = P[1, 0] - P[0, 0], P[1, 1] - P[0, 1], P[1, 2] - P[0, 2]
        b0, b1, b2 = P[2, 0] - P[0, 0], P[2, 1] - P[0, 1], P[2, 2] - P[0, 2]
        c0, c1, c2 = P[3, 0] - P[0, 0], P[3, 1] - P[0, 1], P[3, 2] - P[0, 2]
        G[3, 0], G[3, 1], G[3, 2] = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0   # a x b
        r = target[t] - (G[3, 0] * c0 + G[3, 1] * c1 + G[3, 2] * c2) / scale
        if r <= 0.0:
            continue
        f += r * r
        # d(6V)/d corner: b x c, c x a, a x b for corners 1-3, minus their sum for corner 0
        G[1, 0], G[1, 1], G[1, 2] = b1 * c2 - b2 * c1, b2 * c0 - b0 * c2, b0 * c1 - b1 * c0
        G[2, 0], G[2, 1], G[2, 2] = c1 * a2 - c2 * a1, c2 * a0 - c0 * a2, c0 * a1 - c1 * a0
        for k in range(3):
            G[0, k] = -(G[1, k] + G[2, k] + G[3, k])
        w = -2.0 * r / scale
        for c in range(4):
            s = slot[tets[t, c]]
            if s >= 0:
                for k in range(3):
                    grad[s, k] += w * G[c, k]
    return f, grad


#: L-BFGS iterations times free coordinates that an untangling round may spend beyond its
#: ``iterations`` once the rounds stall (:func:`map_pillow`): a fold in a plate 2.4 h thick on
#: the elk, 2 tetrahedra over ~1,000 coordinates, needed ~1,000 iterations; one costs ~0.3 us
#: per coordinate. Not from the start: on the bunny and the hand the longer runs slid surface
#: nodes further and cost coverage and worst quality (1.02 -> 1.34 h, 0.027 -> 0.006).
UNTANGLE_WORK = 3_000_000
#: ... up to this many iterations.
UNTANGLE_MAX_ITERATIONS = 3000


def _iterations(iterations: int, free: int, work: int) -> int:
    """L-BFGS iterations for ``free`` nodes: ``iterations``, or up to ``work / (3 free)`` (at
    most :data:`UNTANGLE_MAX_ITERATIONS`) where that is more."""
    extra = min(work // max(3 * free, 1), UNTANGLE_MAX_ITERATIONS)
    return int(max(iterations, extra))


def untangle(X: NDArray[np.float64], tets: NDArray[np.int64], movable: NDArray[np.bool_],
             reference_det: NDArray[np.float64], fraction: float = 0.1, rings: int = 2,
             iterations: int = 300, tangent: NDArray[np.float64] | None = None, floor: float = 0.0,
             work: int = 0) -> int:
    """Move ``movable`` nodes near inverted tetrahedra (in place) until every tetrahedron's
    ``6 V`` reaches ``fraction`` of its reference value where possible: L-BFGS on
    ``sum_t max(0, target_t - 6 V_t)^2`` (Knupp's untangling objective, squared), over the
    movable nodes within ``rings`` tetrahedron rings of an inverted one (only the tetrahedra
    touching those rings enter, :func:`_shortfall`). ``tangent`` ``(n, 3)`` (unit normals,
    zero rows for free nodes) keeps those nodes in their tangent planes: a penalty on the
    normal component of their move (surface nodes sliding on the mesh). ``work``: more
    iterations on small sub-problems (:func:`_iterations`). Returns how many
    tetrahedra were inverted before (``floor`` > 0: also those below ``floor`` of their
    target, which are then untangled too)."""
    target = _untangle_targets(reference_det, fraction)
    bad = _below_target(X, tets, target, floor)
    if not bad.any():
        return 0
    near = _near_nodes(len(X), tets, bad, rings)
    free = np.flatnonzero(near & movable)
    slot = np.full(len(X), -1, dtype=np.int64)
    slot[free] = np.arange(len(free))
    sel = np.flatnonzero(near[tets].any(axis=1))
    T = np.ascontiguousarray(tets[sel])
    x0 = X[free].copy()
    nf = None if tangent is None else tangent[free]
    # the penalty's scale: a normal move of a tenth of an edge costs as much as a tetrahedron
    # missing its whole target volume
    edge = float(np.median(np.abs(reference_det)) ** (1.0 / 3.0))
    tgt = target[sel]
    scale = max(float(np.median(tgt)), 1e-300)   # shortfalls in units of a typical target: L-BFGS-B's
    tgt = tgt / scale                            # stopping test is absolute below f = 1
    w = 100.0 / max(edge, 1e-300) ** 2

    def objective(v: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
        x = v.reshape(-1, 3)
        f, g = _shortfall(x, X, slot, T, tgt, scale)
        if nf is not None:
            off = np.einsum("ij,ij->i", x - x0, nf)
            f += w * float((off * off).sum())
            g += 2.0 * w * off[:, None] * nf
        return f, g.ravel()
    with blas_threads(1):   # L-BFGS-B's BLAS calls on long vectors: threads cost more than they do
        res = so.minimize(objective, x0.ravel(), jac=True, method="L-BFGS-B",
                          options={"maxiter": _iterations(iterations, len(free), work)})
    X[free] = res.x.reshape(-1, 3)
    return int(bad.sum())


def _project(mesh: Mesh, moved: NDArray[np.float64], features: Features, on_crease: NDArray[np.bool_]
             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Surface nodes moved off the mesh, projected back: the closest mesh points (and their
    normals), crease nodes onto the closest crease."""
    xs, _, _, nrm = closest_points(mesh, moved)
    if on_crease.any():
        xs[on_crease] = features.closest_on_creases(moved[on_crease])[0]
    return xs, nrm


def _reproject(mesh: Mesh, xs: NDArray[np.float64], before: NDArray[np.float64], nrm: NDArray[np.float64]) -> None:
    """The surface nodes ``xs`` (mm) that moved off ``before`` (on the mesh), back onto the mesh;
    their normals into ``nrm`` (both in place)."""
    moved = np.flatnonzero(np.any(xs != before, axis=1))
    if moved.size:
        xs[moved], _, _, nrm[moved] = closest_points(mesh, xs[moved])


def _spread(mesh: Mesh, xs: NDArray[np.float64], fixed: NDArray[np.bool_], smoother: sp.csr_matrix,
            features: Features, on_crease: NDArray[np.bool_], h: float, rounds: int, step: float = 0.7,
            smooth: float = 0.3) -> NDArray[np.float64]:
    """The coverage rounds (module docstring): each node moves ``step`` of the way to the
    centroid of the surface samples (spacing ``h / 3``) nearest to it, then ``smooth`` of the
    way to its neighbours' mean; re-projected onto the mesh (crease nodes onto the creases);
    ``fixed`` nodes stay."""
    samples = surface_samples(mesh, h / 3.0)
    S = len(xs)
    for _ in range(rounds):
        _, owner = cKDTree(xs).query(samples, workers=-1)
        count = np.bincount(owner, minlength=S)
        centroid = np.stack([np.bincount(owner, samples[:, k], minlength=S) for k in range(3)], axis=1)
        target = np.where(count[:, None] > 0, centroid / np.maximum(count, 1)[:, None], xs)
        moved = xs + step * (target - xs)
        moved += smooth * (smoother @ moved - moved)
        moved[fixed] = xs[fixed]
        xs = _project(mesh, moved, features, on_crease)[0]
        xs[fixed] = moved[fixed]
    return xs


#: Mesh vertices farther than this many spacings h from every surface node after the
#: coverage rounds get the nearest free node (:func:`_snap_tips`).
TIP_REACH = 1.25
#: Passes of the tip snapping (a moved node can uncover what it covered).
TIP_PASSES = 5
#: How far (in spacings h) the shape step may slide a surface node along the surface; nodes
#: nearest to a mesh vertex more than SHAPE_COVER h away do not slide.
SHAPE_SLIDE = 0.25
SHAPE_COVER = 1.0
#: Edges longer than this many spacings h are split at their midpoints after the mapping
#: (step 6; :mod:`glsldiff.grids.tetrahedral.split`). A mapped Kuhn lattice's own edges are h, sqrt(2) h
#: and sqrt(3) h long, so only stretched tetrahedra (thin parts, tips) are cut.
SPLIT_LENGTH = 2.0


def _snap_tips(mesh: Mesh, xs: NDArray[np.float64], fixed: NDArray[np.bool_], h: float
               ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Tips (ends of horns, tails, ears: mesh vertices the Lloyd rounds leave more than
    :data:`TIP_REACH` h from every surface node, since a centroid never reaches an extreme
    point): farthest first, the nearest surface node that is not ``fixed`` and not yet moved
    (a crease node too), within 3 h, moves onto the vertex and stays there as a corner node
    does. Returns the positions and the moved nodes."""
    xs = xs.copy()
    moved = np.zeros(len(xs), dtype=bool)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    for _ in range(TIP_PASSES):   # a move can uncover a vertex the moved node covered: passes
        gap, _ = cKDTree(xs).query(V)
        before = int(moved.sum())
        for v in np.argsort(-gap):
            if gap[v] <= TIP_REACH * h:
                break
            d = np.linalg.norm(xs - V[v], axis=1)
            if d.min() <= TIP_REACH * h:   # an earlier move covers it
                continue
            d[fixed | moved] = np.inf
            k = int(np.argmin(d))
            if d[k] <= 3.0 * h:
                xs[k] = V[v]
                moved[k] = True
        if moved.sum() == before:
            break
    return xs, moved


def map_pillow(cx: PillowComplex, mesh: Mesh, relax_iterations: int = 10, relax_step: float = 0.5,
               copy_weight: float = 2.0, untangle_fraction: float = 0.1, crease_deg: float = 45.0,
               cover_rounds: int = 10, split_length: float | None = SPLIT_LENGTH
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], MappingQuality, EdgeSplit | None]:
    """Positions of every node of ``cx`` in ``mesh`` (and of the split midpoints), the surface
    normals, the quality and the edge split (module docstring; ``split_length`` in lattice
    spacings h, None: no split).

    ``copy_weight``: weight of the outer-node-to-surface links in the harmonic placement
    (2: the outer layer settles about half a spacing under the surface, as in the reference
    geometry; measured on the sphere bench, 2 gave the smallest exitance error of 1, 2, 4)."""
    q = MappingQuality()
    t0 = time.perf_counter()
    N = cx.n_lattice
    ref = cx.reference_positions()
    X = ref.copy()
    features = mesh_features(mesh, crease_deg)
    S = len(cx.outer)
    xs, _, _, nrm = closest_points(mesh, X[N:])
    on_crease, on_corner = _feature_nodes(cx, mesh, xs, features)
    q.crease_nodes, q.corner_nodes = int(on_crease.sum()), int(on_corner.sum())
    M = _surface_smoother(cx.surface, N, S)
    for _ in range(relax_iterations):
        moved = xs + relax_step * (M @ xs - xs)
        moved[on_corner] = xs[on_corner]
        xs, nrm = _project(mesh, moved, features, on_crease)
    xs = _spread(mesh, xs, on_corner, M, features, on_crease, cx.lattice.h, cover_rounds)
    xs, tips = _snap_tips(mesh, xs, on_corner, cx.lattice.h)
    on_corner |= tips
    on_crease &= ~tips
    q.tip_nodes = int(tips.sum())
    nrm = closest_points(mesh, xs)[3]
    X[N:] = xs
    e = triangle_edges(cx.surface)
    L = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    q.surface_spacing, q.surface_spacing_cv = float(L.mean()), float(L.std() / L.mean())
    q.seconds["surface"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    X[: N] = _harmonic_interior(cx, X, copy_weight)
    q.seconds["interior"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    movable = np.zeros(len(X), dtype=bool)
    movable[cx.used] = True
    reference = 6.0 * signed_volumes(ref, cx.tets)
    q.untangled = untangle(X, cx.tets, movable, reference, fraction=untangle_fraction, floor=DEGENERATE)
    sliding = np.zeros(len(X), dtype=bool)
    sliding[N:] = ~(on_crease | on_corner)
    tangent = np.zeros_like(X)
    work, last = 0, -1
    for _release in range(RELEASE_ATTEMPTS + 1 if q.untangled else 0):
        for _ in range(UNTANGLE_ROUNDS):   # folds of the surface map: surface nodes slide too
            tangent[N:] = nrm
            before = X[N:].copy()
            count = untangle(X, cx.tets, movable | sliding, reference, fraction=untangle_fraction,
                             tangent=tangent, floor=DEGENERATE, work=work)
            if count == 0:
                break
            if count >= last >= 0:   # stalled: longer L-BFGS runs from now on (UNTANGLE_WORK)
                work = UNTANGLE_WORK
            last = count
            _reproject(mesh, X[N:], before, nrm)
            untangle(X, cx.tets, movable, reference, fraction=untangle_fraction, work=work)
        # what is left: flat or inverted tetrahedra at crease and corner nodes (three pinned
        # nodes on one crease line make a flat surface triangle): those nodes slide as well
        flat = _below_target(X, cx.tets, _untangle_targets(reference, untangle_fraction), DEGENERATE)
        pinned = _near_nodes(len(X), cx.tets, flat, rings=1)[N:] & ~sliding[N:]
        if not pinned.any():
            break
        sliding[N:] |= pinned
        q.released += int(pinned.sum())
    q.seconds["untangle"] = time.perf_counter() - t2

    # shapes: flat tetrahedra left by the mapping (ear tips, tips, released creases) get their
    # nodes moved; crease nodes that were not released slide along their creases
    crease = np.zeros(len(X), dtype=bool)
    crease[N:] = on_crease & ~sliding[N:]
    slide = sliding | crease
    gap, owner = cKDTree(X[N:]).query(mesh.vertices)   # nodes that cover far vertices stay:
    slide[N + owner[gap > SHAPE_COVER * cx.lattice.h]] = False   # coverage stays <= max(before, 1.25 h)
    before = X[N:].copy()
    edges = unique_tet_edges(cx.tets, len(X))   # the shape step's neighbours, the split's first edges
    shapes = improve_shapes(X, cx.tets, movable, slide, cx.surface,
                            lambda p, nodes: _project(mesh, p, features, crease[nodes])[0],
                            max_slide=SHAPE_SLIDE * cx.lattice.h, edges=edges[0])
    changed = np.flatnonzero(np.any(X[N:] != before, axis=1))
    if changed.size:
        nrm[changed] = closest_points(mesh, X[N:][changed])[3]
    q.poor_before, q.poor, q.reshaped = shapes.below_before, shapes.below_after, shapes.smoothed + shapes.searched
    q.seconds["shapes"] = shapes.seconds

    split, tets, surface_nodes = None, cx.tets, np.arange(N, cx.n_nodes)
    if split_length is not None:
        t3 = time.perf_counter()
        s = split_long_edges(X, cx.tets, cx.surface, split_length * cx.lattice.h, edges=edges)
        if len(s.parents):
            split, X, tets, new = s, s.positions, s.tets, s.surface_midpoints
            surface_nodes = np.concatenate([surface_nodes, new])
            nrm = np.concatenate([nrm, closest_points(mesh, X[new])[3]])
            q.split_edges, q.split_surface_nodes = len(s.parents), len(new)
            # the split's children can be flatter than their parents (a sliver cut along a
            # diagonal): the interior nodes, old and new, move again (surface nodes stay put)
            inner = np.ones(len(X), dtype=bool)
            inner[: len(movable)] = movable
            inner[new] = False
            again = improve_shapes(X, tets, inner, np.zeros(len(X), dtype=bool), s.surface, _unmoved)
            q.split_poor_before, q.split_poor = again.below_before, again.below_after
            q.reshaped += again.smoothed + again.searched
        q.seconds["split"] = time.perf_counter() - t3
    measure_quality(q, X, tets, X[surface_nodes], mesh, cx.lattice.h)
    q.seconds["total"] = time.perf_counter() - t0
    return X, nrm, q, split


def _unmoved(points: NDArray[np.float64], nodes: NDArray[np.int64]) -> NDArray[np.float64]:
    """The projection of a shape step with no sliding nodes (never called)."""
    return points


def measure_quality(q: MappingQuality, X: NDArray[np.float64], tets: NDArray[np.int64],
                   surface_X: NDArray[np.float64], mesh: Mesh, h: float) -> None:
    """Coverage and tetrahedron quality of the finished grid into ``q``."""
    gap, _ = cKDTree(surface_X).query(mesh.vertices)
    q.coverage_max, q.coverage_p99 = float(gap.max() / h), float(np.percentile(gap, 99) / h)
    qual = shape_quality(X, tets)
    q.tets = len(qual)
    q.inverted = int((qual <= 0).sum())
    q.worst_quality = float(qual.min())
    q.quality_p1 = float(np.percentile(qual, 1))


def build_fem_grid(mesh: Mesh, n: int = 4, cube_size: float | None = None, n_cubes: int | None = None,
                   threshold: float = 0.5, polycube: Polycube | None = None,
                   mapping: dict[str, Any] | None = None) -> FemGrid:
    """Polycube, pillowed lattice and mapping for a closed mesh (mm).

    ``cube_size`` (mm) or ``n_cubes`` with ``n`` set the lattice spacing h = cube / n. Cubes
    of more than :data:`FINE_CUBE_NODES` nodes whose polycube cannot carry the mesh (step 7
    of the module docstring) give way to cubes of :data:`FINE_CUBE_NODES` nodes at about the
    same h, and a grid that still misses the targets is built again with cubes a few percent
    larger or smaller (step 8); an explicit ``polycube`` is mapped as given."""
    if not isinstance(n, (int, np.integer)) or n < 2:
        raise InputError(f"n={n!r} nodes per cube edge must be an integer >= 2")
    budget = {"what": "tetrahedral grid", "limit": FEM_MAX_NODES, "bytes_per_node": FEM_BYTES_PER_NODE}
    if n_cubes is not None:
        check_node_budget(n_cubes, n, **budget)   # the target count: before the polycube search
    n = int(n)
    if polycube is not None:
        return _map_polycube(mesh, polycube, n, mapping, budget)
    grid = first = _build_searched(mesh, n, cube_size, n_cubes, threshold, mapping, budget)
    retries = 0
    for factor in RETRY_SIZES:
        if _meets_targets(grid.quality):
            break
        retries += 1
        try:
            other = _build_searched(mesh, first.complex.lattice.n, first.polycube.size * factor, None, threshold,
                                    mapping, budget, repairs=False)
        except InputError:       # no polycube of that size (topology), or over the budget: the next one
            continue
        other.quality.size_factor = factor
        if _rank(other.quality) < _rank(grid.quality):
            grid = other
    q = grid.quality
    q.retries, q.requested_n, q.fine_reason = retries, first.quality.requested_n, first.quality.fine_reason
    return grid


def _meets_targets(q: MappingQuality) -> bool:
    """No inverted tetrahedron and every mesh vertex within :data:`COVERAGE_TARGET` h of a surface node."""
    return q.inverted == 0 and q.coverage_max <= COVERAGE_TARGET


def _build_searched(mesh: Mesh, n: int, cube_size: float | None, n_cubes: int | None, threshold: float,
                    mapping: dict[str, Any] | None, budget: dict[str, Any], repairs: bool = True) -> FemGrid:
    """Steps 4 and 7 of the module docstring: the polycube searched for the request, mapped
    ungrown, grown if needed, and cubes of :data:`FINE_CUBE_NODES` nodes where cubes of ``n``
    cannot carry the mesh; with ``repairs``, the search's other repaired polycubes too
    (step 9)."""
    search = {"cube_size": cube_size, "n_cubes": n_cubes, "threshold": threshold}
    try:
        candidates = polycube_candidates(mesh, thin_parts=False, **search)
        coarse = next(candidates)
        reason = _too_coarse(mesh, coarse, n, n_cubes) if n > FINE_CUBE_NODES else None
    except InputError as exc:   # no polycube of that topology with cubes that large
        if n <= FINE_CUBE_NODES:
            raise
        why = str(exc)
        reason = f"no polycube was found ({why if len(why) <= 160 else why[:157] + '...'})"
    grid = None
    if reason is None:
        others = candidates if repairs else iter(())
        grid = _map_candidates(mesh, itertools.chain([coarse], others), search, n, mapping, budget)
        if n <= FINE_CUBE_NODES or _meets_targets(grid.quality):
            return grid
        q = grid.quality
        reason = (f"its grid had {q.inverted} inverted tetrahedra and left mesh vertices "
                  f"{q.coverage_max:.2f} h from every surface node")
    scale = n / FINE_CUBE_NODES   # about the same h: cubes `scale` times smaller, `scale^3` times as many
    fine = _build_searched(mesh, FINE_CUBE_NODES, None if cube_size is None else cube_size / scale,
                           None if n_cubes is None else max(1, round(n_cubes * scale ** 3)), threshold,
                           mapping, budget, repairs)
    fine.quality.requested_n, fine.quality.fine_reason = n, reason
    if grid is None or _rank(fine.quality) < _rank(grid.quality):
        return fine
    return grid


def _map_candidates(mesh: Mesh, polycubes: Iterator[Polycube], search: dict[str, Any], n: int,
                    mapping: dict[str, Any] | None, budget: dict[str, Any]) -> FemGrid:
    """Step 4 of the module docstring on each of ``polycubes`` (ungrown, from
    :func:`~glsldiff.grids.polycube.polycube_candidates` with ``search``) in turn, until a grid
    meets the targets: the best grid (:func:`_rank`)."""
    grid, grown_all = None, None
    for coarse in polycubes:
        tried = [_map_polycube(mesh, coarse, n, mapping, budget)]
        if not _meets_targets(tried[0].quality):
            grown_all = grown_all or polycube_candidates(mesh, **search)   # the same order, grown
            grown = next((g for g in grown_all if g.threshold == coarse.threshold), None)
            if grown is not None and grown.grown:
                tried.append(_map_polycube(mesh, grown, n, mapping, budget))
        for other in tried:
            if grid is None or _rank(other.quality) < _rank(grid.quality):
                grid = other
        if _meets_targets(grid.quality):
            break
    assert grid is not None
    return grid


def _too_coarse(mesh: Mesh, polycube: Polycube, n: int, n_cubes: int | None) -> str | None:
    """Why cubes of ``n`` nodes cannot carry ``mesh`` (step 7 of the module docstring), or None."""
    problem = node_budget_problem(polycube.count, n, FEM_MAX_NODES, FEM_BYTES_PER_NODE)
    if problem:
        return problem
    if n_cubes is not None and polycube.count > OVERSHOOT * n_cubes:
        return (f"the search fitted {polycube.count:,} cubes of {polycube.size:.3g} mm to the mesh's extents, "
                f"{polycube.count / n_cubes:.1f}x the {n_cubes:,} asked for")
    h = polycube.size / n
    gap = float(outside_distance(polycube, surface_samples(mesh, h)).max()) / h
    if gap > FINE_TRIGGER:
        return (f"the mesh surface lies up to {gap:.1f} h outside its {polycube.count:,} cubes of "
                f"{polycube.size:.3g} mm (more than {FINE_TRIGGER:g} h)")
    return None


def _rank(q: MappingQuality) -> tuple[int, bool, float]:
    """Order of preference between two grids of one mesh: fewer inverted tetrahedra, then
    coverage within :data:`COVERAGE_TARGET`, then the smaller coverage distance."""
    return q.inverted, q.coverage_max > COVERAGE_TARGET, q.coverage_max


def _map_polycube(mesh: Mesh, polycube: Polycube, n: int, mapping: dict[str, Any] | None,
                  budget: dict[str, Any]) -> FemGrid:
    check_node_budget(polycube.count, n, **budget)
    lattice = Lattice(polycube.cubes, n, polycube.size, np.asarray(polycube.origin, dtype=np.float64))
    cx = PillowComplex.build(lattice)
    X, nrm, q, split = map_pillow(cx, mesh, **(mapping or {}))
    q.thin_cubes = polycube.grown
    return FemGrid(cx, X, nrm, q, mesh, polycube, split)
