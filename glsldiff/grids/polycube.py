"""Polycubes: sets of equal axis-aligned cubes approximating a closed mesh.

Wang et al. (2008) build the polycube of each model by hand; :func:`polycube_from_mesh`
builds it automatically:

1. Lay a grid of cubes of edge ``size`` (mm) over the mesh's bounding box, centred on it.
2. Estimate each cube's inside-volume fraction from ``samples**3`` stratified points
   (stratum centres) tested with :func:`glsldiff.mesh.contains_grid`.
3. Keep the cubes whose fraction reaches ``threshold``.
4. Make the surface two-manifold: wherever two cubes share only an edge or a vertex (or two
   empty cells do, inside a block of cubes), add the missing cube with the largest inside
   fraction, until no such configuration remains.
5. Accept the result only if its topology equals the mesh's: one 6-connected component,
   no cavity, the same genus. Otherwise retry with other thresholds.

Cube coordinates are integer triples ``(ix, iy, iz)``; cube ``(i, j, k)`` spans
``origin + size * ([i, i+1] x [j, j+1] x [k, k+1])``. Cube lists are kept in scan-line
order: sorted by ``iz``, then ``iy``, then ``ix``.

(About 550 lines, over the usual 400: the cube-set topology (2x2x2 configurations,
:class:`Topology`) is the natural piece to move into its own grids module.)
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from glsldiff.core.checks import integer, real, vector3
from glsldiff.core.errors import InputError
from glsldiff.mesh import Mesh, contains_grid

log = logging.getLogger(__name__)

#: Thresholds tried, in this order after the requested one, when the topology does not match.
FALLBACK_THRESHOLDS = (0.5, 0.4, 0.6, 0.3, 0.7, 0.2)
#: Largest number of sample points (candidate cubes x samples^3) one build may test.
MAX_SAMPLE_POINTS = 50_000_000
_N_CUBES_TOL = 0.03  # relative count tolerance that ends the n_cubes search
_N_CUBES_ITER = 12


# ---------------------------------------------------------------------------------------
# Local configurations of 2x2x2 cells around a lattice vertex
# ---------------------------------------------------------------------------------------
_OFFSETS = np.array([(b & 1, (b >> 1) & 1, (b >> 2) & 1) for b in range(8)], dtype=np.int64)


def _connected(bits: list[int]) -> bool:
    """Whether cells (bit indices of a 2x2x2 block) are 6-connected inside the block."""
    if len(bits) <= 1:
        return True
    seen, todo = {bits[0]}, [bits[0]]
    while todo:
        b = todo.pop()
        for axis in range(3):
            n = b ^ (1 << axis)
            if n in bits and n not in seen:
                seen.add(n)
                todo.append(n)
    return len(seen) == len(bits)


def _manifold_table() -> NDArray[np.bool_]:
    """For each of the 256 block configurations: is the cube surface a disk at the vertex?

    It is iff the occupied cells and the empty cells of the block are each 6-connected
    (no two cubes, and no two holes, meeting only at an edge or at the vertex).
    """
    table = np.zeros(256, dtype=bool)
    for code in range(256):
        full = [b for b in range(8) if code >> b & 1]
        empty = [b for b in range(8) if not code >> b & 1]
        table[code] = _connected(full) and _connected(empty)
    return table


_MANIFOLD = _manifold_table()


def _block_codes(occ: NDArray[np.bool_]) -> NDArray[np.int64]:
    """Configuration code of the 2x2x2 block around every lattice vertex of ``occ``.

    ``occ`` must have an empty border; the result has shape ``occ.shape - 1``: vertex
    ``(i, j, k)`` is the corner shared by cells ``(i..i+1, j..j+1, k..k+1)``.
    """
    nx, ny, nz = occ.shape
    code = np.zeros((nx - 1, ny - 1, nz - 1), dtype=np.int64)
    for b, (dx, dy, dz) in enumerate(_OFFSETS):
        code |= occ[dx:nx - 1 + dx, dy:ny - 1 + dy, dz:nz - 1 + dz].astype(np.int64) << b
    return code


# ---------------------------------------------------------------------------------------
# Topology
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Topology:
    """Topology of a cube set and of its boundary quad surface.

    Attributes
    ----------
    components
        6-connected components of the cubes.
    cavities
        Enclosed (6-connected) empty regions.
    euler
        ``V - E + F`` of the boundary quad surface.
    surfaces
        Connected components of the boundary surface (quads joined through edges).
    genus
        ``(2 * surfaces - euler) / 2`` (sum over the surfaces; meaningful for a manifold
        surface).
    nonmanifold_edges
        Lattice edges shared by 4 boundary quads (cubes, or holes, meeting only at an edge).
    nonmanifold_vertices
        Lattice vertices whose surrounding surface is not a disk (includes the ends of
        non-manifold edges and vertex-only contacts).
    """

    components: int
    cavities: int
    euler: int
    surfaces: int
    genus: int
    nonmanifold_edges: int
    nonmanifold_vertices: int

    @property
    def manifold(self) -> bool:
        return self.nonmanifold_edges == 0 and self.nonmanifold_vertices == 0


def cube_coordinates(cubes: ArrayLike, what: str = "cubes", distinct: bool = False) -> NDArray[np.int64]:
    """Validated integer cube coordinates ``(k, 3)`` ``(ix, iy, iz)``, k >= 1, as int64 (integral
    floats are accepted); with ``distinct``, no cube may be listed twice."""
    a = np.asarray(cubes)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{what} must be an integer (k, 3) array of cube coordinates "
                         f"(ix, iy, iz), got shape {a.shape}")
    if a.shape[0] == 0:
        raise InputError(f"{what} is empty; a polycube needs at least one cube")
    if a.dtype == bool or not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{what} must hold integer cube coordinates, got dtype {a.dtype}")
    if not np.issubdtype(a.dtype, np.integer):
        if not np.isfinite(a).all() or (a != np.round(a)).any():
            raise InputError(f"{what} must hold integer cube coordinates (ix, iy, iz); found "
                             "non-integer values")
    a = a.astype(np.int64)
    if distinct:
        uniq, counts = np.unique(a, axis=0, return_counts=True)
        if (counts > 1).any():
            raise InputError(f"{what} has {int((counts - 1).sum())} duplicate entr(y/ies), e.g. "
                             f"{uniq[counts > 1][0].tolist()}; list every cube once")
    return a


def _occupancy(cubes: NDArray[np.int64], pad: int = 1
               ) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """Dense occupancy with ``pad`` empty layers; returns (occ, coordinate of cell [0,0,0])."""
    lo = cubes.min(axis=0) - pad
    shape = cubes.max(axis=0) - lo + 1 + pad
    occ = np.zeros(tuple(shape), dtype=bool)
    occ[tuple((cubes - lo).T)] = True
    return occ, lo


_SIX = np.array([[[0, 0, 0], [0, 1, 0], [0, 0, 0]],
                 [[0, 1, 0], [1, 1, 1], [0, 1, 0]],
                 [[0, 0, 0], [0, 1, 0], [0, 0, 0]]], dtype=bool)


def _topology_of(occ: NDArray[np.bool_]) -> Topology:
    """Topology of a dense occupancy grid with an empty border layer."""
    _, n_comp = ndimage.label(occ, structure=_SIX)
    _, n_empty = ndimage.label(~occ, structure=_SIX)
    shape = np.array(occ.shape)
    vshape = shape + 1  # lattice vertices
    quads, edges = [], []
    for axis in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        diff = occ[tuple(lo)] != occ[tuple(hi)]
        pos = np.argwhere(diff)
        pos[:, axis] += 1  # the face lies on lattice plane i + 1
        u, w = [a for a in range(3) if a != axis]
        eu, ew = np.eye(3, dtype=np.int64)[u], np.eye(3, dtype=np.int64)[w]
        corners = np.stack([pos, pos + eu, pos + eu + ew, pos + ew], axis=1)  # (n, 4, 3)
        vid = np.ravel_multi_index(tuple(np.moveaxis(corners, -1, 0)), tuple(vshape))
        quads.append(vid)
        # edges: (start vertex, direction): pos-u, pos-w, (pos+eu)-w, (pos+ew)-u
        starts = np.stack([pos, pos, pos + eu, pos + ew], axis=1)
        dirs = np.array([u, w, w, u])
        sid = np.ravel_multi_index(tuple(np.moveaxis(starts, -1, 0)), tuple(vshape))
        edges.append(sid * 3 + dirs)
    qv = np.concatenate(quads)
    qe = np.concatenate(edges)
    n_f = len(qv)
    if n_f == 0:
        return Topology(n_comp, max(n_empty - 1, 0), 0, 0, 0, 0, 0)
    uv = np.unique(qv)
    ue, e_inv, e_cnt = np.unique(qe, return_inverse=True, return_counts=True)
    euler = len(uv) - len(ue) + n_f
    e_inv = e_inv.reshape(n_f, 4)
    g = coo_matrix((np.ones(4 * n_f), (np.repeat(np.arange(n_f), 4), n_f + e_inv.ravel())),
                   shape=(n_f + len(ue),) * 2)
    _, lab = connected_components(g, directed=False)
    surfaces = int(np.unique(lab[:n_f]).size)
    codes = _block_codes(np.pad(occ, 1))
    bad_v = int((~_MANIFOLD[codes]).sum())
    return Topology(components=int(n_comp), cavities=max(int(n_empty) - 1, 0), euler=int(euler),
                    surfaces=surfaces, genus=int((2 * surfaces - euler) // 2),
                    nonmanifold_edges=int((e_cnt > 2).sum()), nonmanifold_vertices=bad_v)


def surface_topology(cubes: ArrayLike) -> Topology:
    """Topology of the cube set ``cubes`` (k, 3) and of its boundary quad surface.

    The surface is made of the cube faces not shared by two cubes; ``euler`` counts its
    unique vertices, edges and quads, and ``genus = (2 * surfaces - euler) / 2``.
    """
    c = cube_coordinates(cubes)
    return _topology_of(_occupancy(c)[0])


# ---------------------------------------------------------------------------------------
# Polycube
# ---------------------------------------------------------------------------------------
def _scanline(cubes: NDArray[np.int64]) -> NDArray[np.int64]:
    return np.lexsort((cubes[:, 0], cubes[:, 1], cubes[:, 2]))


@dataclass(frozen=True, eq=False)
class Polycube:
    """Equal axis-aligned cubes; cube ``(i, j, k)`` spans ``origin + size * [i, i+1] x ...``.

    Attributes
    ----------
    cubes
        ``(k, 3)`` int64 cube coordinates in scan-line order (by iz, then iy, then ix).
    size
        Cube edge, mm.
    origin
        ``(3,)`` position of the corner of cube ``(0, 0, 0)``, mm.
    fraction
        ``(k,)`` inside-volume fraction of each cube (NaN for explicit cube lists).
    threshold
        The inside-fraction threshold used (NaN for explicit cube lists).

    Build with :func:`polycube_from_mesh` or :func:`polycube_from_cubes` (which validate).
    """

    cubes: NDArray[np.int64]
    size: float
    origin: NDArray[np.float64]
    fraction: NDArray[np.float64]
    threshold: float = float("nan")

    def __post_init__(self) -> None:
        c = cube_coordinates(self.cubes)
        order = _scanline(c)
        c = np.ascontiguousarray(c[order])
        frac = np.asarray(self.fraction, dtype=np.float64)
        if frac.shape != (len(c),):
            raise InputError(f"polycube fraction must have shape ({len(c)},), got {frac.shape}")
        frac = frac[order].copy()
        origin = vector3(self.origin, "polycube origin (mm)").copy()
        size = real(self.size, "polycube size (cube edge, mm)", lo=0.0, lo_open=True)
        for a in (c, frac, origin):
            a.setflags(write=False)
        object.__setattr__(self, "cubes", c)
        object.__setattr__(self, "fraction", frac)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "threshold", float(self.threshold))

    def __repr__(self) -> str:
        return (f"Polycube(count={self.count}, size={self.size:.6g} mm, "
                f"origin={np.round(self.origin, 6).tolist()}, threshold={self.threshold:g}, "
                f"genus={self.genus})")

    @property
    def count(self) -> int:
        """Number of cubes."""
        return len(self.cubes)

    @cached_property
    def index_origin(self) -> NDArray[np.int64]:
        """``(3,)`` smallest cube coordinate per axis: the cube of ``index[0, 0, 0]``."""
        return self.cubes.min(axis=0)

    @cached_property
    def index(self) -> NDArray[np.int64]:
        """Dense ``[ix, iy, iz]`` array over the cubes' bounding box (offset by
        :attr:`index_origin`): the cube's position in :attr:`cubes`, or -1 where empty."""
        rel = self.cubes - self.index_origin
        idx = np.full(tuple(rel.max(axis=0) + 1), -1, dtype=np.int64)
        idx[tuple(rel.T)] = np.arange(self.count)
        idx.setflags(write=False)
        return idx

    def index_of(self, coords: ArrayLike) -> NDArray[np.int64]:
        """Position in :attr:`cubes` of each integer cube coordinate ``(m, 3)``; -1 if absent."""
        c = np.asarray(coords)
        if c.ndim == 1:
            c = c[None]
        if c.ndim != 2 or c.shape[1] != 3 or not np.issubdtype(c.dtype, np.integer):
            raise InputError(f"index_of: coords must be an integer (m, 3) array, got shape "
                             f"{c.shape} dtype {c.dtype}")
        rel = c.astype(np.int64) - self.index_origin
        ok = ((rel >= 0) & (rel < np.array(self.index.shape))).all(axis=1)
        out = np.full(len(c), -1, dtype=np.int64)
        out[ok] = self.index[tuple(rel[ok].T)]
        return out

    @cached_property
    def surface_topology(self) -> Topology:
        """:class:`Topology` of the cubes and their boundary surface."""
        return _topology_of(_occupancy(self.cubes)[0])

    @property
    def genus(self) -> int:
        """Genus of the boundary surface."""
        return self.surface_topology.genus

    @cached_property
    def bounds(self) -> NDArray[np.float64]:
        """``(2, 3)`` bounding box of the cubes, mm."""
        return np.stack([self.origin + self.size * self.cubes.min(axis=0),
                         self.origin + self.size * (self.cubes.max(axis=0) + 1)])

    @cached_property
    def centers(self) -> NDArray[np.float64]:
        """``(k, 3)`` cube centres, mm."""
        return self.origin + self.size * (self.cubes + 0.5)


def polycube_from_cubes(cubes: ArrayLike, size: float,
                        origin: ArrayLike = (0.0, 0.0, 0.0)) -> Polycube:
    """Validated polycube from an explicit cube list (k, 3), cube edge ``size`` mm.

    The cubes must be distinct, form one 6-connected component without enclosed cavities,
    and have a two-manifold surface (no two cubes meeting only at an edge or a vertex).
    """
    c = cube_coordinates(cubes, distinct=True)
    s = real(size, "polycube size (cube edge, mm)", lo=0.0, lo_open=True)
    topo = _topology_of(_occupancy(c)[0])
    _check_explicit(topo)
    return Polycube(c, s, np.asarray(origin, dtype=np.float64), np.full(len(c), np.nan),
                    float("nan"))


def _check_explicit(topo: Topology) -> None:
    if topo.components != 1:
        raise InputError(f"cubes form {topo.components} separate (6-connected) components; a "
                         "polycube must be one piece of face-connected cubes: add cubes that "
                         "join them or drop the extra pieces")
    if not topo.manifold:
        raise InputError(f"cubes surface is not two-manifold: {topo.nonmanifold_edges} edge(s) "
                         f"and {topo.nonmanifold_vertices} vertex(es) where cubes (or holes) meet "
                         "only at an edge or a corner; add a cube next to each such contact")
    if topo.cavities:
        raise InputError(f"cubes enclose {topo.cavities} cavit(y/ies) (empty cells with no path "
                         "to the outside); fill them")


# ---------------------------------------------------------------------------------------
# From a mesh
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Fractions:
    size: float
    origin: NDArray[np.float64]
    frac: NDArray[np.float64]  # (nx, ny, nz)


def _fractions(mesh: Mesh, size: float, samples: int,
               cache: dict[float, _Fractions]) -> _Fractions:
    """Inside-volume fraction of every cube of the grid of edge ``size`` centred on the mesh."""
    if size in cache:
        return cache[size]
    lo, hi = mesh.bounds
    ext = hi - lo
    n = np.maximum(np.ceil(ext / size - 1e-9), 1).astype(np.int64)
    total = int(np.prod(n)) * samples ** 3
    if total > MAX_SAMPLE_POINTS:
        raise InputError(
            f"cube size {size:.4g} mm is too small for mesh {mesh.name!r} (extents "
            f"{np.round(ext, 4).tolist()} mm): {int(np.prod(n))} candidate cubes x {samples}^3 "
            f"samples exceeds {MAX_SAMPLE_POINTS}; use a larger cube size or fewer samples")
    origin = (lo + hi) / 2 - n * size / 2
    axes = [origin[a] + size * (np.arange(n[a] * samples) + 0.5) / samples for a in range(3)]
    inside = contains_grid(mesh, *axes)
    frac = inside.reshape(n[0], samples, n[1], samples, n[2], samples).mean(axis=(1, 3, 5))
    out = _Fractions(float(size), origin, frac)
    cache[size] = out
    return out


def _make_manifold(occ: NDArray[np.bool_], frac: NDArray[np.float64]
                   ) -> tuple[NDArray[np.bool_], NDArray[np.float64], int]:
    """Add cubes until no two cubes (or holes) meet only at an edge or vertex.

    ``occ``/``frac`` are padded by one empty layer (the result may grow by a layer where
    needed). Returns the padded occupancy, matching fractions and the offset of the
    original cell ``[0, 0, 0]`` in them.
    """
    occ = np.pad(occ, 1)
    frac = np.pad(frac, 1)
    offset = 1
    limit = occ.size + 1
    for _ in range(limit):
        codes = _block_codes(occ)
        bad = np.argwhere(~_MANIFOLD[codes])
        if len(bad) == 0:
            return occ, frac, offset
        cells = bad[:, None, :] + _OFFSETS[None]  # (b, 8, 3)
        ci = tuple(np.moveaxis(cells, -1, 0))
        score = np.where(occ[ci], -np.inf, frac[ci])
        pick = cells[np.arange(len(bad)), np.argmax(score, axis=1)]
        occ[tuple(pick.T)] = True
        border = (pick == 0).any() or (pick == np.array(occ.shape) - 1).any()
        if border:  # keep an empty border layer
            occ = np.pad(occ, 1)
            frac = np.pad(frac, 1)
            offset += 1
    raise InputError("polycube manifold repair did not converge")  # pragma: no cover


def _build(mesh: Mesh, fr: _Fractions, threshold: float
           ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]:
    """Cubes (k,3), their fractions and the padded occupancy for one threshold."""
    occ0 = fr.frac >= threshold
    if not occ0.any():
        return np.zeros((0, 3), np.int64), np.zeros(0), np.zeros((1, 1, 1), bool)
    occ, frac, off = _make_manifold(occ0, fr.frac)
    cubes = np.argwhere(occ) - off
    return cubes, frac[occ], occ


def _count(mesh: Mesh, size: float, threshold: float, samples: int,
           cache: dict[float, _Fractions]) -> int:
    return len(_build(mesh, _fractions(mesh, size, samples, cache), threshold)[0])


def _search_size(mesh: Mesh, n_cubes: int, threshold: float, samples: int,
                 cache: dict[float, _Fractions]) -> float:
    """Cube size whose polycube (after the manifold repair) has about ``n_cubes`` cubes."""
    s = (abs(mesh.volume) / n_cubes) ** (1 / 3)
    s = min(s, float(mesh.extents.max()))
    lo = hi = None  # sizes giving too many / too few cubes
    best = (math.inf, s)
    for _ in range(_N_CUBES_ITER):
        c = _count(mesh, s, threshold, samples, cache)
        err = abs(c - n_cubes)
        best = min(best, (err, s))
        if err <= max(1, _N_CUBES_TOL * n_cubes):
            break
        if c > n_cubes:
            lo = s if lo is None else max(lo, s)
        else:
            hi = s if hi is None else min(hi, s)
        guess = s * (max(c, 1) / n_cubes) ** (1 / 3)
        if lo is not None and hi is not None and not lo < guess < hi:
            guess = math.sqrt(lo * hi)
        if guess == s:
            break
        s = guess
    log.debug("n_cubes=%d threshold=%g: cube size %.6g mm (count off by %d)", n_cubes,
              threshold, best[1], best[0])
    return best[1]


def polycube_from_mesh(mesh: Mesh, cube_size: float | None = None, n_cubes: int | None = None,
                       threshold: float = 0.5, samples: int = 4) -> Polycube:
    """Polycube approximating a closed mesh, with the mesh's topology.

    Parameters
    ----------
    mesh
        A validated :class:`glsldiff.mesh.Mesh`.
    cube_size
        Cube edge, mm. Give exactly one of ``cube_size`` and ``n_cubes``.
    n_cubes
        Target cube count (the paper's bunny: 253); the cube size is searched so the
        result has about this many cubes.
    threshold
        Keep cubes whose inside-volume fraction is at least this (0 < threshold <= 1).
        If the result's topology differs from the mesh's, the thresholds of
        :data:`FALLBACK_THRESHOLDS` are tried in turn; :attr:`Polycube.threshold` tells
        which one was used.
    samples
        ``samples**3`` stratified points estimate each cube's inside fraction.
    """
    name = f"mesh {mesh.name!r}" if mesh.name else "mesh"
    if (cube_size is None) == (n_cubes is None):
        raise InputError("polycube_from_mesh: give exactly one of cube_size (cube edge, mm) and "
                         f"n_cubes (target cube count); got cube_size={cube_size!r}, "
                         f"n_cubes={n_cubes!r}")
    integer(samples, "samples (samples^3 points per cube)", 1, 16)
    real(threshold, "threshold (inside-volume fraction)", 0.0, 1.0, lo_open=True)
    ext = mesh.extents
    ext_txt = f"{np.round(ext, 4).tolist()} mm"
    if cube_size is not None:
        s = real(cube_size, "cube_size (cube edge, mm)", lo=0.0, lo_open=True)
        if s > ext.max():
            raise InputError(f"cube_size={s:g} mm is larger than {name} (extents {ext_txt}); "
                             f"use a cube size below its smallest extent {ext.min():.4g} mm")
        if s > ext.min():
            log.warning("%s: cube_size=%g mm exceeds the smallest mesh extent %.4g mm; the "
                        "polycube will be one cube thick there", name, s, ext.min())
    else:
        if not isinstance(n_cubes, (int, np.integer)) or isinstance(n_cubes, bool) or n_cubes < 1:
            raise InputError(f"n_cubes={n_cubes!r} must be an integer >= 1")

    cache: dict[float, _Fractions] = {}
    tried = [float(threshold)] + [t for t in FALLBACK_THRESHOLDS if not math.isclose(t, threshold)]
    want = (1, 0, mesh.genus)
    failures = []
    for t in tried:
        s = float(cube_size) if cube_size is not None else _search_size(mesh, int(n_cubes), t,
                                                                         samples, cache)
        fr = _fractions(mesh, s, samples, cache)
        cubes, frac, occ = _build(mesh, fr, t)
        if len(cubes) == 0:
            failures.append(f"threshold {t:g}: no cube is {t:.0%} inside")
            continue
        topo = _topology_of(occ)
        got = (topo.components, topo.cavities, topo.genus)
        if got == want:
            pc = Polycube(cubes, s, fr.origin, frac, t)
            log.info("%s: polycube of %d cubes, size %.6g mm, threshold %g (genus %d)",
                     name, pc.count, s, t, topo.genus)
            return pc
        failures.append(f"threshold {t:g} ({len(cubes)} cubes of {s:.4g} mm): {topo.components} "
                        f"component(s), {topo.cavities} cavit(y/ies), genus {topo.genus}")
    raise InputError(
        f"no polycube of {name} (extents {ext_txt}, genus {mesh.genus}) with one component, "
        f"no cavity and genus {mesh.genus} was found: " + "; ".join(failures) +
        ". Use a smaller cube_size (or a larger n_cubes), or pass an explicit cube list to "
        "polycube_from_cubes")
