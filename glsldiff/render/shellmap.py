"""Material mapping onto objects through a shell layer (Wang et al. 2008, section 5;
Chen et al. 2004, "Shell texture functions").

An acquired block of heterogeneous material (kappa, mu on a regular ``(nz, ny, nx)`` grid
of voxel size ``h`` mm, ``z`` = depth below the captured surface, ``z = 0`` at it) is
wrapped around an object's polygrid as a **shell layer** over a homogeneous **inner core**
(Chen et al. 2004: heterogeneous shell from a small material sample, homogeneous core).
For every polygrid node :func:`map_shell` finds

``depth``
    the distance from the node to the object's surface, mm (section "Depth" below);
``(u, v)``
    surface coordinates from the polycube's own parameterization (section
    "Parameterization" below), mm;

and reads the block at ``(x, y, z) = (u, v, depth) / (h scale)`` voxels by trilinear
interpolation, tiled periodically in ``x-y`` (period ``nx h scale`` by ``ny h scale`` mm)
and clamped in ``z``. Nodes deeper than the shell thickness (default ``nz h scale``) take
the core material, blended linearly over the last voxel ``[thickness - h scale, thickness]``.

What is interpolated
--------------------
The optical coefficients: ``sigma_t = sigma_a + sigma_s' = 1 / (3 kappa)`` and
``mu = sigma_a`` are interpolated linearly (so ``sigma_a`` and ``sigma_s' = sigma_t - mu``
are too, for physical blocks), then converted back, ``kappa = 1 / (3 sigma_t)``. kappa is
thereby the harmonic mean of its neighbours, never the arithmetic one: the mixture of two
materials has the mean extinction, not the mean diffusion length. Every interpolated
value is a convex combination of voxel values, so kappa stays > 0, mu >= 0 and
``3 kappa mu <= 1`` wherever the block satisfies it (non-physical blocks, e.g. the
solver-test volumes of :func:`glsldiff.physics.procedural.random_volume`, are accepted as they are).
The core blend works in the same variables.

Depth
-----
``depth_from="nodes"``: distance to the nearest boundary node (the polygrid's surface
samples, where the boundary source ``q`` lives; depth 0 there). It is an upper bound of
the distance to the surface, exact on an axis-aligned box (:func:`box_polygrid`, whose
surface is the planes of its boundary nodes) and
within about a tenth of ``h`` rms (up to ~0.6 h on a sphere, ~2 h in the bunny's thin
parts, measured) on mapped meshes, because the surface between boundary nodes is not
sampled. ``depth_from="mesh"``: the exact distance to ``pg.mesh``
(:func:`glsldiff.mesh.closest_points`, ~0.2 ms per node, measured on the sphere and the
bunny), asked only for nodes that can lie inside the shell (nodes-depth minus the
boundary nodes' covering radius below the thickness); deeper nodes keep the nodes-depth
(they are core either way). ``"auto"`` (default) is ``"mesh"`` when the polygrid has a
mesh and at most :data:`AUTO_MESH_QUERIES` nodes need the query, else ``"nodes"``;
``info["depth_from"]`` says which ran.
Tangent planes of the nearest boundary nodes were tried as a cheap refinement and
rejected: within 0.03 h on the sphere, but up to 3.6 h too shallow in the bunny's concave
parts.

Parameterization and its seams
------------------------------
A node takes the polycube face of its nearest boundary node (object-space distance):
the face's outward axis ``+-x, +-y, +-z`` selects a fixed frame, and ``(u, v)`` are the
node's own polycube (lattice) coordinates, mm, along the frame's two in-face axes
(:data:`FACE_FRAMES`): ``v`` is ``z`` on the four side faces ("up") and ``y`` on the
``+-z`` faces; ``u`` is signed so that ``u x v`` is the outward axis, i.e. the block is
never mirrored seen from outside. Because the coordinates are global polycube
coordinates, not per-face charts:

* all faces of the same orientation share one planar map: coplanar faces of adjacent
  cubes join without a seam, and parallel faces at different heights (steps) continue
  each other's pattern;
* nodes in a lattice column below a face get that face's ``(u, v)``, so the pattern runs
  straight down into the shell (in polycube space; the polycube-to-mesh map bends it);
* **seams** remain where the nearest face changes orientation: along every polycube edge
  (convex or concave) on the surface, and inside along the surfaces equidistant from two
  faces (ties, e.g. on a box's diagonal planes, go to whichever nearest boundary node the
  k-d tree returns). There the pattern jumps to an unrelated place of the block (no attempt is made
  to match across; Chen et al. synthesise the shell with texture synthesis instead).
  ``info["seam_links"]`` counts the lattice links between active nodes of different faces;
* tiling seams: every ``nx h scale`` mm (``ny h scale``) the block restarts; with
  ``tiling="wrap"`` that shows unless the block is periodic, ``tiling="mirror"`` reflects
  every other tile (continuous, period doubled, mirror-symmetric pattern);
* distortion: ``(u, v)`` are polycube mm, so the pattern follows the polycube-to-mesh
  mapping's stretch; it is not corrected.

The simpler triplanar map by normal was not used: it blends three lookups (a blurred mix
of unrelated block places) and does not align with the lattice the solver runs on.

Units: mm, mm^-1. Inactive (removed) nodes take the core material.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from glsldiff.core.checks import choice, real, rgb
from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.fem_grid import FemGrid
from glsldiff.grids.graph import INACTIVE, NEIGHBOURS
from glsldiff.grids.lattice import STEPS
from glsldiff.grids.polygrid import Polygrid
from glsldiff.mesh import closest_points
from glsldiff.physics.material import Preset, preset

__all__ = ["AUTO_MESH_QUERIES", "FACE_FRAMES", "map_shell", "shell_coordinates"]

Array = NDArray[np.float64]
DepthFrom = Literal["auto", "mesh", "nodes"]
Tiling = Literal["wrap", "mirror"]
TILINGS = ("wrap", "mirror")

#: Per outward neighbour slot (``x-, x+, y-, y+, z-, z+``): ``(u axis, u sign, v axis)``
#: with axes 0, 1, 2 = x, y, z of the polycube; ``sign * e_u x e_v`` is the outward axis.
#: ``depth_from="auto"`` asks the mesh for at most this many nodes (measured ~0.2 ms per
#: node on the 100 mm bunny: ~40 s), else it uses the nodes-depth.
AUTO_MESH_QUERIES = 200_000

FACE_FRAMES = np.array([[1, -1, 2], [1, 1, 2], [0, 1, 2], [0, -1, 2], [0, -1, 1], [0, 1, 1]], dtype=np.int64)


# ---- validation ------------------------------------------------------------------------
def _block(name: str, values: ArrayLike) -> Array:
    """``(nz, ny, nx)`` grey or ``(nz, ny, nx, 1|3)`` block as a float64 ``(nz, ny, nx, 3)``."""
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric (nz, ny, nx, 3) array") from None
    if arr.ndim == 3:
        arr = arr[..., None]
    if arr.ndim != 4 or arr.shape[3] not in (1, 3) or min(arr.shape[:3]) < 1:
        raise InputError(f"{name} has shape {arr.shape}; the block must be (nz, ny, nx, 3) "
                         "(z = depth below the captured surface), or (nz, ny, nx) grey")
    bad = ~np.isfinite(arr)
    if bad.any():
        raise InputError(f"{name} has {int(bad.sum())} non-finite (NaN/inf) values, e.g. at voxel "
                         f"{tuple(int(i) for i in np.argwhere(bad)[0][:3])}")
    return np.array(np.broadcast_to(arr, arr.shape[:3] + (3,)))


def _core(core: Any, sigma_t: Array, mu: Array) -> tuple[Array, Array]:
    """Core ``(sigma_t, mu)``, each ``(3,)``."""
    if isinstance(core, str) and core.strip().lower() == "mean":
        return sigma_t[-1].mean(axis=(0, 1)), mu[-1].mean(axis=(0, 1))
    if isinstance(core, (str, Preset)):
        try:
            k, m = preset(core).coefficients()
        except InputError as exc:
            raise InputError(f"core: {exc} (or 'mean': the block's bottom-layer mean)") from None
        return 1.0 / (3.0 * np.asarray(k)), np.asarray(m, dtype=np.float64)
    if isinstance(core, (tuple, list)) and len(core) == 2:
        k, m = np.array(rgb(core[0], "core kappa", "mm")), np.array(rgb(core[1], "core mu", "mm^-1"))
        if np.any(k <= 0.0):
            raise InputError(f"core kappa={k.tolist()} must be > 0 mm")
        return 1.0 / (3.0 * k), m
    raise InputError(f"core={core!r}: give 'mean' (the block's bottom-layer mean), a preset name "
                     "or Preset, or a (kappa [mm], mu [mm^-1]) pair of scalars or RGB triples")


# ---- geometry ----------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class _Shell:
    """What the shell mapping needs of a grid, for the lattice polygrid and the tetrahedral
    (fem) grid alike: node positions (mm), which nodes are the surface samples and which are
    unknowns, each surface node's outward polycube face (slot of ``x-, x+, ... z+``) and every
    node's polycube (reference) coordinates, mm."""

    positions: Array          # (P, 3)
    boundary: NDArray[np.int64]
    active: NDArray[np.bool_]
    slot: NDArray[np.int64]   # (B,)
    reference: Array          # (P, 3)
    mesh: Any
    shape: tuple[int, ...]    # node-array shape of the grid's material arrays
    lattice: Any = None       # the lattice (seam links are counted on its links), or None

    @property
    def boundary_positions(self) -> Array:
        return self.positions[self.boundary]


def _shell(pg: Any) -> _Shell:
    """The :class:`_Shell` of a :class:`Polygrid` or a :class:`FemGrid`. A fem surface node at a
    polycube edge or corner takes the one of its outer faces closest to its mesh normal (a
    :class:`_Shell` is returned as it is)."""
    if isinstance(pg, _Shell):
        return pg
    if isinstance(pg, Polygrid):
        lat = pg.lattice
        return _Shell(pg.positions, lat.boundary, lat.kind != INACTIVE, lat.outward_slot[lat.boundary],
                      lat.lattice_positions, pg.mesh, pg.shape, lat)
    if isinstance(pg, FemGrid):
        axes = pg.outward_axes                                           # (S, 3) of +-1 / 0
        fits = np.where((STEPS[None] * axes[:, None]).sum(axis=2) > 0,   # the node's own faces
                        pg.normals @ STEPS.T.astype(np.float64), -np.inf)
        return _Shell(pg.positions, pg.surface_nodes, pg.active, np.argmax(fits, axis=1),
                      pg.reference_positions(), pg.mesh, (len(pg.positions),))
    raise InputError(f"the shell mapping needs a Polygrid or a FemGrid, got {type(pg).__name__}")


def _cover_radius(sh: _Shell, tree: cKDTree) -> float:
    """Largest distance from a mesh vertex or face centroid to its nearest boundary node, mm."""
    mesh = sh.mesh
    pts = np.concatenate([mesh.vertices, mesh.triangles.mean(axis=1)])
    d, _ = tree.query(pts)
    return float(d.max())


def shell_coordinates(pg: Polygrid | FemGrid | _Shell, *, depth_from: DepthFrom = "auto",
                      max_depth_mm: float = np.inf) -> dict[str, Any]:
    """Depth below the surface and polycube surface coordinates of every node (flat order).

    Parameters
    ----------
    pg
        A lattice :class:`Polygrid` or a tetrahedral :class:`FemGrid` (whose surface nodes
        and polycube reference positions play the boundary nodes' and lattice positions' part).
    depth_from
        ``"nodes"``, ``"mesh"`` or ``"auto"`` (module docstring, "Depth").
    max_depth_mm
        With ``"mesh"``, nodes surely deeper than this keep the nodes-depth (no mesh query).

    Returns
    -------
    dict with ``depth`` ``(N,)`` mm (0 at boundary nodes), ``u``, ``v`` ``(N,)`` mm,
    ``face`` ``(N,)`` outward slot (index into :data:`FACE_FRAMES`) of the nearest
    boundary node, ``depth_from`` (the mode used) and ``mesh_queries`` (nodes asked).
    """
    sh = _shell(pg)
    choice(depth_from, "depth_from", ("auto", "mesh", "nodes"))
    if depth_from == "mesh" and sh.mesh is None:
        raise InputError("depth_from='mesh' needs a polygrid built from a mesh (pg.mesh is None)")
    b = sh.boundary
    tree = cKDTree(sh.boundary_positions)
    depth, nearest = tree.query(sh.positions)
    depth[b], nearest[b] = 0.0, np.arange(b.size)
    queries, mode = 0, "nodes"
    if depth_from != "nodes" and sh.mesh is not None:
        alive = sh.active.copy()
        alive[b] = False
        need = np.flatnonzero(alive & (depth - _cover_radius(sh, tree) < max_depth_mm))
        if depth_from == "mesh" or need.size <= AUTO_MESH_QUERIES:
            mode = "mesh"
    if mode == "mesh":
        if need.size:
            _, d, _, _ = closest_points(sh.mesh, sh.positions[need])
            depth[need] = np.minimum(d, depth[need])
        queries = int(need.size)
    face = sh.slot[nearest]
    ua, us, va = FACE_FRAMES[face].T
    lp = sh.reference
    rows = np.arange(lp.shape[0])
    return {"depth": depth, "u": us * lp[rows, ua], "v": lp[rows, va], "face": face,
            "depth_from": mode, "mesh_queries": queries}


# ---- block lookup ----------------------------------------------------------------------
def _tile(i: NDArray[np.int64], n: int, tiling: str) -> NDArray[np.int64]:
    """Integer voxel index -> index in ``[0, n)``: periodic, or reflected (period ``2n``)."""
    if tiling == "wrap":
        return np.mod(i, n)
    j = np.mod(i, 2 * n)
    return np.where(j >= n, 2 * n - 1 - j, j)


def _trilinear(vol: Array, x: Array, y: Array, z: Array, tiling: str) -> Array:
    """``vol[z, y, x, c]`` at fractional voxel coordinates: tiled in x-y, clamped in z."""
    nz, ny, nx = vol.shape[:3]
    z = np.clip(z, 0.0, nz - 1.0)
    z0 = np.minimum(np.floor(z).astype(np.int64), max(nz - 2, 0))
    z1 = np.minimum(z0 + 1, nz - 1)
    fz = z - z0
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    xs = (_tile(x0, nx, tiling), _tile(x0 + 1, nx, tiling))
    ys = (_tile(y0, ny, tiling), _tile(y0 + 1, ny, tiling))
    out = np.zeros((x.size, vol.shape[3]))
    for zi, wz in ((z0, 1.0 - fz), (z1, fz)):
        for yi, wy in ((ys[0], 1.0 - fy), (ys[1], fy)):
            for xi, wx in ((xs[0], 1.0 - fx), (xs[1], fx)):
                out += (wz * wy * wx)[:, None] * vol[zi, yi, xi]
    return out


def _seam_links(lat: Any, face: NDArray[np.int64]) -> int:
    """Lattice links between two active nodes whose faces differ (each link once)."""
    act = lat.kind != INACTIVE
    nb = lat.lattice_neighbours
    total = 0
    for s in (1, 3, 5):  # +x, +y, +z
        j = nb[:, s]
        ok = act & (j >= 0)
        ok[ok] &= act[j[ok]]
        total += int(np.count_nonzero(face[ok] != face[j[ok]]))
    return total


def map_shell(pg: Polygrid | FemGrid, kappa_block: ArrayLike, mu_block: ArrayLike, h_mm: float,
              core: str | Preset | tuple[ArrayLike, ArrayLike] = "mean",
              thickness_mm: float | None = None, scale: float = 1.0, *,
              depth_from: DepthFrom = "auto", tiling: Tiling = "wrap") -> tuple[Array, Array, dict[str, Any]]:
    """Per-node kappa and mu of an acquired block mapped onto a polygrid's shell.

    Parameters
    ----------
    pg
        The polygrid (finest level; coarser levels get the material by averaging,
        :meth:`glsldiff.grids.hierarchy.Hierarchy.problems`), or a tetrahedral
        :class:`FemGrid` (its node order; ``seam_links`` is then -1).
    kappa_block, mu_block
        ``(nz, ny, nx, 3)`` (or grey ``(nz, ny, nx)``) kappa [mm] > 0 and mu [mm^-1] >= 0
        of the block; index ``[z, y, x]``, ``z = 0`` at the captured surface.
    h_mm
        Voxel size of the block, mm.
    core
        Inner core material: ``"mean"`` (the block's bottom layer averaged in
        ``sigma_t`` and ``mu``), a preset name or :class:`~glsldiff.physics.material.Preset`, or a
        ``(kappa, mu)`` pair of scalars / RGB triples.
    thickness_mm
        Shell thickness, mm (default ``nz h_mm scale``: the whole block). Beyond the
        block's depth the bottom layer repeats.
    scale
        Magnification of the block on the object: its voxels become ``h_mm * scale`` mm
        in all three directions (the coefficients per mm are unchanged).
    depth_from
        How depth is measured (module docstring): ``"auto"``, ``"mesh"``, ``"nodes"``.
    tiling
        ``"wrap"`` (periodic, period ``n h scale``) or ``"mirror"`` (reflected tiles).

    Returns
    -------
    kappa, mu
        Node arrays ``pg.shape + (3,)`` for :class:`glsldiff.system.problem.DiffusionProblem`
        (removed nodes hold the core); ``(P, 3)`` for a :class:`FemGrid`.
    info
        ``depth`` (node array, mm), ``face`` (node array of outward slots, -1 at removed
        nodes), ``depth_min_mm`` / ``depth_mean_mm`` / ``depth_max_mm`` (active nodes),
        ``n_active``, ``n_shell`` (depth < thickness, blend zone included), ``n_blend``,
        ``n_core``, ``faces`` (active nodes per face), ``seam_links``, ``thickness_mm``,
        ``voxel_mm``, ``period_mm``, ``core_kappa``, ``core_mu``, ``depth_from``,
        ``mesh_queries``, ``tiling``, ``seconds``.
    """
    t0 = time.perf_counter()
    sh = _shell(pg)
    kb, mb = _block("kappa_block", kappa_block), _block("mu_block", mu_block)
    if kb.shape != mb.shape:
        raise InputError(f"kappa_block {np.shape(kappa_block)} and mu_block {np.shape(mu_block)} "
                         "must have the same (nz, ny, nx) shape")
    if np.any(kb <= 0.0):
        raise InputError(f"kappa_block has {int((kb <= 0).sum())} values <= 0; kappa = 1/(3 (sigma_a + "
                         "sigma_s')) is a positive length in mm")
    if np.any(mb < 0.0):
        raise InputError(f"mu_block has {int((mb < 0).sum())} negative values; mu = sigma_a >= 0 mm^-1")
    h = real(h_mm, "h_mm (block voxel size, mm)", 0.0, lo_open=True)
    scale = real(scale, "scale (block magnification on the object)", 0.0, lo_open=True)
    choice(tiling, "tiling", TILINGS)
    nz, ny, nx = kb.shape[:3]
    voxel = h * scale
    thickness = nz * voxel if thickness_mm is None else real(thickness_mm, "thickness_mm (mm)", 0.0, lo_open=True)
    sigma_t = 1.0 / (3.0 * kb)
    core_st, core_mu = _core(core, sigma_t, mb)

    geo = shell_coordinates(sh, depth_from=depth_from, max_depth_mm=thickness)
    depth, face = geo["depth"], geo["face"]
    act = np.flatnonzero(sh.active)
    width = min(voxel, thickness)
    t = np.clip((depth[act] - (thickness - width)) / width, 0.0, 1.0)[:, None]

    vals = np.full((len(sh.positions), 6), np.concatenate([core_st, core_mu]))
    shell = np.flatnonzero(t[:, 0] < 1.0)
    inner = act[shell]
    vals[inner] = _trilinear(np.concatenate([sigma_t, mb], axis=3), geo["u"][inner] / voxel,
                             geo["v"][inner] / voxel, depth[inner] / voxel, tiling)
    ts = t[shell]
    vals[inner] = (1.0 - ts) * vals[inner] + ts * np.concatenate([core_st, core_mu])
    kappa = (1.0 / (3.0 * vals[:, :3])).reshape(sh.shape + (3,))
    mu = vals[:, 3:].reshape(sh.shape + (3,))

    d_act = depth[act]
    face_out = np.where(sh.active, face, -1)
    n_core = int(np.count_nonzero(t >= 1.0))
    info: dict[str, Any] = {
        "depth": depth.reshape(sh.shape), "face": face_out.reshape(sh.shape),
        "depth_min_mm": float(d_act.min()), "depth_mean_mm": float(d_act.mean()),
        "depth_max_mm": float(d_act.max()),
        "n_active": int(act.size), "n_shell": int(act.size - n_core),
        "n_blend": int(np.count_nonzero((t > 0.0) & (t < 1.0))), "n_core": n_core,
        "faces": {NEIGHBOURS[s]: int(np.count_nonzero(face[act] == s)) for s in range(6)},
        "seam_links": _seam_links(sh.lattice, face) if sh.lattice is not None else -1,
        "thickness_mm": thickness, "voxel_mm": voxel, "period_mm": (nx * voxel, ny * voxel),
        "core_kappa": (1.0 / (3.0 * core_st)).tolist(), "core_mu": core_mu.tolist(),
        "depth_from": geo["depth_from"], "mesh_queries": geo["mesh_queries"], "tiling": tiling,
        "seconds": time.perf_counter() - t0,
    }
    return kappa, mu, info


def map_surface(pg: Polygrid | FemGrid, image: ArrayLike, period_mm: tuple[float, float],
                tiling: Tiling = "wrap") -> Array:
    """A map over the block's captured face (e.g. the measured diffuse reflectance,
    :mod:`glsldiff.inverse.reflectance`), ``(H, W, C)`` covering ``period_mm`` = (x, y)
    extent in mm, read at the boundary nodes, ``(n_boundary, C)``, with the same surface
    coordinates and tiling as :func:`map_shell` (bilinear, pixel centres at integer
    coordinates like the block's voxels)."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or not np.all(np.isfinite(img)):
        raise InputError(f"a surface map must be a finite (H, W, C) array, got shape {img.shape}")
    px, py = (real(p, "period_mm (map extent, mm)", 0.0, lo_open=True) for p in period_mm)
    choice(tiling, "tiling", TILINGS)
    sh = _shell(pg)
    geo = shell_coordinates(sh, depth_from="nodes")
    b = sh.boundary
    h, w = img.shape[:2]
    return _trilinear(img[None], geo["u"][b] / (px / w), geo["v"][b] / (py / h), np.zeros(b.size), tiling)
