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
5. **Thin parts** (:func:`_grow_thin_parts`): where the mesh surface lies more than
   :data:`THIN_SEED` cube edges outside the cubes (ears, horns, tails thinner than a cube,
   which no threshold keeps; a smooth surface never does), add the empty cubes that hold
   surface points of that region farther than :data:`THIN_REACH` edges outside, are
   face-adjacent to the set and at least :data:`THIN_MIN_FRACTION` inside, one at a time
   and only where that keeps the topology and the manifold surface
   (:func:`glsldiff.grids.cubeset.addable`); repeat while cubes are added.
6. Accept the result only if its topology equals the mesh's: one 6-connected component,
   no cavity, the same genus. Otherwise retry with other thresholds.
7. **Bridges** (only where no threshold gave the mesh's topology): parts closer than a cube
   (a camel's tail and rump, its legs) are joined by cubes into handles the mesh does not
   have. At each threshold tried, the cubes of steps 3-4 are repaired by a
   topology-preserving growth that leaves out the cubes closing such handles
   (:func:`glsldiff.grids.bridges.repair_bridges`); the repair that leaves out the least
   inside volume is kept, grown into thin parts (step 5), and said in one warning
   (:attr:`Polycube.repair`). CGAL's camel at 15,000 cubes: genus 1-2 at every threshold;
   repaired by leaving out 4-26 cubes. :func:`polycube_candidates` offers the other thresholds'
   repairs as well, by the inside volume they leave out: which one maps best turns on where
   the near-contacts and thin parts fall (the camel's 15,000 cubes: coverage 1.22-2.28 h and
   0-9 inverted tetrahedra over its six thresholds' repairs, grown or not), so the tetrahedral
   grid build maps them in turn (:mod:`glsldiff.grids.tetrahedral.fem_grid`, step 9).

Cube coordinates are integer triples ``(ix, iy, iz)``; cube ``(i, j, k)`` spans
``origin + size * ([i, i+1] x [j, j+1] x [k, k+1])``. Cube lists are kept in scan-line
order: sorted by ``iz``, then ``iy``, then ``ix``.

The cube-set topology (2x2x2 configurations, manifold test, genus) is in
:mod:`glsldiff.grids.cubeset`.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.spatial import cKDTree

from glsldiff.core.checks import integer, real, vector3
from glsldiff.core.errors import InputError
from glsldiff.grids.bridges import BridgeRepair, repair_bridges
from glsldiff.grids.cubeset import (MANIFOLD, OFFSETS, Topology, addable, block_codes, cube_coordinates, occupancy,
                                    topology_of)
from glsldiff.mesh import Mesh, contains_grid, surface_samples

log = logging.getLogger(__name__)

#: Thresholds tried, in this order after the requested one, when the topology does not match.
FALLBACK_THRESHOLDS = (0.5, 0.4, 0.6, 0.3, 0.7, 0.2)
#: Largest number of sample points (candidate cubes x samples^3) one build may test.
MAX_SAMPLE_POINTS = 50_000_000
#: Thin parts (module docstring, step 5): where the surface lies farther than THIN_SEED cube
#: edges outside the cubes (a smooth surface leaves at most ~0.47: spheres of 2-32 cubes per
#: radius; the bunny's ears 0.80, the cow's ears and horns 2.7), the surface within
#: THIN_REGION cube edges of it that is farther than THIN_REACH gets cubes ...
THIN_SEED = 0.6
THIN_REGION = 2.0
THIN_REACH = 0.3
#: ... that are at least this much inside (thinner slivers squeeze the tetrahedral grid's
#: lattice flat: with 0.15, one tetrahedron stayed inverted on the cow, with 0.3 none).
THIN_MIN_FRACTION = 0.3
_THIN_ROUNDS = 50
_N_CUBES_TOL = 0.03  # relative count tolerance that ends the n_cubes search
_N_CUBES_ITER = 12


# ---------------------------------------------------------------------------------------
# Polycube
# ---------------------------------------------------------------------------------------
def _scanline(cubes: NDArray[np.int64]) -> NDArray[np.int64]:
    return np.lexsort((cubes[:, 0], cubes[:, 1], cubes[:, 2]))


class PolycubeNotFound(InputError):
    """No set of cubes at any threshold has the mesh's topology (one component, no cavity, its
    genus); ``failures``: one line per threshold tried (what the cubes had instead)."""

    def __init__(self, message: str, failures: list[str] | None = None) -> None:
        super().__init__(message)
        self.failures = list(failures or [])


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
    grown
        Cubes added in thin parts (module docstring, step 5).
    bridged
        Cubes left out because they bridged near-contacts into handles (step 7).
    repair
        One line on that repair (what and why; empty where none was needed).

    Build with :func:`polycube_from_mesh` or :func:`polycube_from_cubes` (which validate).
    """

    cubes: NDArray[np.int64]
    size: float
    origin: NDArray[np.float64]
    fraction: NDArray[np.float64]
    threshold: float = float("nan")
    grown: int = 0
    bridged: int = 0
    repair: str = ""

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
        return topology_of(occupancy(self.cubes)[0])

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
    topo = topology_of(occupancy(c)[0])
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
            f"samples exceeds {MAX_SAMPLE_POINTS}; use larger cubes (glsldiff polygrid --cube-size or fewer --cubes; a scene's [polygrid].cubes)")
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
        codes = block_codes(occ)
        bad = np.argwhere(~MANIFOLD[codes])
        if len(bad) == 0:
            return occ, frac, offset
        cells = bad[:, None, :] + OFFSETS[None]  # (b, 8, 3)
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


def _outside_distance(points: NDArray[np.float64], occ: NDArray[np.bool_], corner: NDArray[np.float64],
                      size: float) -> NDArray[np.float64]:
    """Distance (mm) from each point to the union of the occupied cubes (exact for the eight
    nearest cube centres); cell ``p`` of ``occ`` spans ``corner + size * [p, p + 1]``."""
    return _distance_to_cubes(points, corner + size * (np.argwhere(occ) + 0.5), size)


def outside_distance(polycube: Polycube, points: ArrayLike) -> NDArray[np.float64]:
    """Distance (mm) from each point to the union of the polycube's cubes (0 inside)."""
    return _distance_to_cubes(np.asarray(points, dtype=np.float64), polycube.centers, polycube.size)


def _distance_to_cubes(points: NDArray[np.float64], centres: NDArray[np.float64], size: float
                       ) -> NDArray[np.float64]:
    _, j = cKDTree(centres).query(points, k=min(8, len(centres)))
    j = j.reshape(len(points), -1)
    gap = np.maximum(np.abs(points[:, None] - centres[j]) - 0.5 * size, 0.0)
    return np.linalg.norm(gap, axis=2).min(axis=1)


def _grow_thin_parts(samples: NDArray[np.float64], occ: NDArray[np.bool_], frac: NDArray[np.float64],
                     corner: NDArray[np.float64], size: float) -> tuple[NDArray[np.bool_], int]:
    """Step 5 of the module docstring on a manifold occupancy ``occ`` (with its ``frac``; cell
    ``p`` spans ``corner + size * [p, p + 1]``, at least two empty border layers). Returns the
    new occupancy and the number of cubes added."""
    occ = occ.copy()
    added = 0
    d = _outside_distance(samples, occ, corner, size)
    seeds = samples[d > THIN_SEED * size]
    if len(seeds) == 0:
        return occ, 0
    near, _ = cKDTree(seeds).query(samples, distance_upper_bound=THIN_REGION * size)
    region = samples[np.isfinite(near)]
    for _ in range(_THIN_ROUNDS):
        far = region[_outside_distance(region, occ, corner, size) > THIN_REACH * size]
        cells = np.floor((far - corner) / size).astype(np.int64)
        inside = ((cells >= 1) & (cells < np.array(occ.shape) - 1)).all(axis=1)
        want = np.zeros_like(occ)
        want[tuple(cells[inside].T)] = True
        want &= ~occ & ndimage.binary_dilation(occ) & (frac >= THIN_MIN_FRACTION)
        before = added
        for cell in np.argwhere(want):
            if addable(occ, cell):
                occ[tuple(cell)] = True
                added += 1
        if added == before:
            break
    return occ, added


def _base(fr: _Fractions, threshold: float) -> tuple[NDArray[np.bool_], NDArray[np.float64], int] | None:
    """Steps 3-4 of the module docstring: the manifold occupancy of the cubes at least ``threshold``
    inside, their fractions and the offset of fraction cell ``[0, 0, 0]`` in them (None: no cube)."""
    occ0 = fr.frac >= threshold
    if not occ0.any():
        return None
    return _make_manifold(occ0, fr.frac)


def _finish(fr: _Fractions, occ: NDArray[np.bool_], frac: NDArray[np.float64], off: int,
            samples: NDArray[np.float64] | None) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_], int]:
    """Step 5 on a manifold occupancy (with surface ``samples``; none: no growth): cubes (k, 3),
    their fractions, the padded occupancy and the number of cubes grown into thin parts."""
    added = 0
    if samples is not None:   # fraction cells outside the grid are empty (0 inside): pad
        occ, frac, off = np.pad(occ, 1), np.pad(frac, 1), off + 1
        occ, added = _grow_thin_parts(samples, occ, frac, fr.origin - off * fr.size, fr.size)
    cubes = np.argwhere(occ) - off
    return cubes, frac[occ], occ, added


def _build(mesh: Mesh, fr: _Fractions, threshold: float, samples: NDArray[np.float64] | None = None
           ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_], int]:
    """Cubes (k,3), their fractions, the padded occupancy for one threshold and the number of
    cubes grown into thin parts (with surface ``samples``; module docstring, step 5)."""
    base = _base(fr, threshold)
    if base is None:
        return np.zeros((0, 3), np.int64), np.zeros(0), np.zeros((1, 1, 1), bool), 0
    return _finish(fr, *base, samples)


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


def snap_to_extents(size: float, extents: NDArray[np.float64], band: float = 0.25, tol: float = 0.01) -> float:
    """A cube edge within ``(1 +- band)`` of ``size`` that divides all three bounding-box
    extents into whole numbers of cubes, if there is one (the closest to ``size``); else
    ``size``. With the grid centred on the bounding box, a box-shaped mesh then gets the exact
    polycube (its faces on cube faces, its edges on cube edges) instead of a bevelled one. A
    box thinner than ``size`` may take its thickness as the edge (a 100 x 100 x 2 mm tile:
    2 mm), so that it is one whole cube thick rather than a partial one."""
    ext = np.asarray(extents, dtype=np.float64)
    best = None
    thin = float(ext.min())
    for e in ext:
        for k in range(max(1, math.floor(e / size / (1 + band))), math.ceil(e / size / (1 - band)) + 1):
            c = e / k
            # a box thinner than the cube: its thickness (whole) is also a candidate
            if abs(c / size - 1) > band and not (size > thin and math.isclose(c, thin)):
                continue
            r = ext / c
            if np.all((np.abs(r - np.round(r)) <= tol) & (np.round(r) >= 1)):
                if best is None or abs(c - size) < abs(best - size):
                    best = c
    return float(size if best is None else best)


def polycube_from_mesh(mesh: Mesh, cube_size: float | None = None, n_cubes: int | None = None,
                       threshold: float = 0.5, samples: int = 4, thin_parts: bool = True) -> Polycube:
    """Polycube approximating a closed mesh, with the mesh's topology: the first of
    :func:`polycube_candidates` (same parameters)."""
    return next(polycube_candidates(mesh, cube_size, n_cubes, threshold, samples, thin_parts))


def polycube_candidates(mesh: Mesh, cube_size: float | None = None, n_cubes: int | None = None,
                        threshold: float = 0.5, samples: int = 4, thin_parts: bool = True) -> Iterator[Polycube]:
    """Polycubes approximating a closed mesh, with the mesh's topology, best first (computed
    as they are asked for): the first threshold's cubes that have it (one), else the
    repaired cube sets of every threshold whose repair gives it, by the inside volume they
    leave out (module docstring, step 7). Raises :class:`PolycubeNotFound` on the first
    ``next`` where there is none.

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
    thin_parts
        Grow the cubes into parts of the mesh thinner than a cube (module docstring, step 5).
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
    failures, missed = [], []
    for t in tried:
        s = float(cube_size) if cube_size is not None else snap_to_extents(
            _search_size(mesh, int(n_cubes), t, samples, cache), ext)
        fr = _fractions(mesh, s, samples, cache)
        cubes, frac, occ, grown = _build(mesh, fr, t, surface_samples(mesh, s / 3.0) if thin_parts else None)
        if len(cubes) == 0:
            failures.append(f"threshold {t:g}: no cube is {t:.0%} inside")
            continue
        topo = topology_of(occ)
        got = (topo.components, topo.cavities, topo.genus)
        if got == want:
            pc = Polycube(cubes, s, fr.origin, frac, t, grown)
            log.info("%s: polycube of %d cubes (%d in thin parts), size %.6g mm, threshold %g (genus %d)",
                     name, pc.count, grown, s, t, topo.genus)
            yield pc
            return
        failures.append(f"threshold {t:g} ({len(cubes)} cubes of {s:.4g} mm): {topo.components} "
                        f"component(s), {topo.cavities} cavit(y/ies), genus {topo.genus}")
        missed.append((t, fr, topo))
    found = False
    for pc in _without_bridges(mesh, missed, thin_parts):
        if found:
            log.info("%s: another repair: %s", name, pc.repair)
        else:
            log.warning("%s: %s", name, pc.repair)
        found = True
        yield pc
    if found:
        return
    raise PolycubeNotFound(
        f"no polycube of {name} (extents {ext_txt}, genus {mesh.genus}) with one component, "
        f"no cavity and genus {mesh.genus} was found: " + "; ".join(failures) +
        " (leaving out the cubes that bridge near-contacts did not give it either). Use smaller cubes "
        "(more [polygrid] cubes), or give the cubes (polycube_from_cubes)", failures)


def _without_bridges(mesh: Mesh, missed: list[tuple[float, _Fractions, Topology]], thin_parts: bool
                     ) -> Iterator[Polycube]:
    """Step 7 of the module docstring over the thresholds whose cubes ``missed`` the mesh's
    topology (threshold, fractions, the topology they had): the repaired polycubes that have
    it, the least inside volume left out first (each finished as it is asked for; a cube set
    that an earlier threshold's repair gave too, once)."""
    repairs, seen = [], set()
    for t, fr, _ in missed:
        base = _base(fr, t)
        if base is None:
            continue
        rep = repair_bridges(base[0], base[1], mesh.genus)
        key = (fr.size, (np.argwhere(rep.occ) - base[2]).tobytes())   # thresholds of the same cubes: once
        if rep.matches(mesh.genus) and key not in seen:
            seen.add(key)
            repairs.append((rep, t, fr, base))
    repairs.sort(key=lambda r: r[0].removed_volume)   # stable: ties in the thresholds' order
    for rep, t, fr, (_, frac, off) in repairs:
        pc = _finish_repair(mesh, missed, rep, t, fr, frac, off, thin_parts)
        if pc is not None:
            yield pc


def _finish_repair(mesh: Mesh, missed: list[tuple[float, _Fractions, Topology]], rep: BridgeRepair, t: float,
                   fr: _Fractions, frac: NDArray[np.float64], off: int, thin_parts: bool) -> Polycube | None:
    """The repaired cubes ``rep`` of threshold ``t`` grown into thin parts (step 5) as a
    polycube with its note (:attr:`Polycube.repair`), or None where they lost the mesh's topology."""
    samples = surface_samples(mesh, fr.size / 3.0) if thin_parts else None
    cubes, kept, occ, grown = _finish(fr, rep.occ, frac, off, samples)
    got = topology_of(occ)
    if (got.components, got.cavities, got.genus) != (1, 0, mesh.genus):   # pragma: no cover (growth keeps it)
        return None
    had = [m[2] for m in missed]
    b = rep.before
    note = (f"no threshold's cubes had its topology (one component, genus {mesh.genus}; thresholds "
            f"{_span([m[0] for m in missed])} gave {_span([h.components for h in had])} component(s), genus "
            f"{_span([h.genus for h in had])}): left out {rep.removed - rep.detached} cube(s) that bridged parts "
            f"closer than a cube into handles{_detached(rep.detached)} ({rep.removed_volume:.1f} cubes of inside "
            f"volume), at threshold {t:g} ({b.components} component(s) of genus {b.genus} -> one of genus "
            f"{mesh.genus}): {len(cubes):,} cubes of {fr.size:.4g} mm, {grown} in thin parts")
    return Polycube(cubes, fr.size, fr.origin, kept, t, grown, rep.removed, note)


def _detached(count: int) -> str:
    """The note's words for ``count`` cubes left out in pieces apart from the fullest cube's."""
    return f" and {count} cube(s) in pieces apart from the rest" if count else ""


def _span(values: list[float]) -> str:
    """``'a'`` or ``'a-b'``: the range of ``values``."""
    lo, hi = min(values), max(values)
    return f"{lo:g}" if lo == hi else f"{lo:g}-{hi:g}"
