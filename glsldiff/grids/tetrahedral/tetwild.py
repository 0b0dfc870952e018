"""Tetrahedral meshes that follow the surface exactly, by fTetWild (pytetwild): TransCut's
discretisation (Li et al. 2012, section 3) and the high-accuracy peer of the polygrids.

:func:`tetrahedralize` checks that the triangle mesh is closed, runs fTetWild in a temporary
working directory (it writes ``__tracked_surface.stl`` into the current one) at a target edge
length ``edge_mm``, orients every tetrahedron positively, extracts the boundary triangles
(outward) and reports the quality (:class:`TetQuality`): dihedral angles, radius ratios,
slivers, the volume against the input mesh's and how far the boundary strays from the input
surface. fTetWild runs in a child process, so that Ctrl-C reaches the program (the C++ code
would otherwise end it with no word) and its scratch folder is removed.
:func:`cached_tetrahedralize` keeps the result in the on-disk cache (:mod:`glsldiff.core.cache`)
keyed by the mesh's arrays and the parameters: the bunny at 2.5 mm (127k tetrahedra) took 490 s
on one core of this machine.

A :class:`TetMesh` answers the attributes the tetrahedral system uses
(:class:`glsldiff.system.tet_problem.TetProblem`, :func:`glsldiff.oracle.fem.tet_geometry`):
``positions``, ``tets``, ``surface``, ``surface_nodes``, ``boundary_positions``, ``normals``,
``surface_triangles``, ``active``, ``h``. Lengths in mm.
"""
from __future__ import annotations

import importlib.util
import math
import multiprocessing
import os
import signal
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from glsldiff.core import cache
from glsldiff.core.errors import InputError
from glsldiff.grids.tetrahedral.pillow import TET_EDGES, signed_volumes, subdivide_tets
from glsldiff.mesh import Mesh, closest_points
from glsldiff.mesh.types import unique_edges

__all__ = ["TetMesh", "TetQuality", "tetrahedralize", "cached_tetrahedralize", "tet_quality", "dihedral_cos_sin",
           "refine", "boundary_faces", "min_dihedral_deg", "SLIVER_DEG", "INERT_DIHEDRAL_DEG"]

#: A tetrahedron with a dihedral angle below this (degrees) counts as a sliver.
SLIVER_DEG = 5.0
#: Below this dihedral angle (degrees; TransCut's bound for cut relaxation, section 7) a
#: tetrahedron is inert: it carries no stiffness (:attr:`TetMesh.inert`; its lumped absorption
#: stays). fTetWild can leave such slivers (a 54 mm torus at 1.5 mm: 574 below 5 deg, the worst
#: 4e-14 deg, with cotangents up to 1e10 that made the GPU multigrid diverge); their vertices stay
#: coupled through their other tetrahedra (a Delaunay test ball: fluence within 2.8 % of the maximum of keeping them).
INERT_DIHEDRAL_DEG = 0.5
#: Part of every cache key: bump it when the construction changes.
CACHE_VERSION = 2   # 2: the module moved to grids.tetrahedral (pickled class paths)
_FACES = np.array([(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)])     # outward for a positive tetrahedron


@dataclass(frozen=True)
class TetQuality:
    """Quality of a tetrahedral mesh: dihedral angles in degrees, radius ratio ``3 r_in /
    r_circ`` (1 for the regular tetrahedron), volumes in mm^3, distances in mm."""

    tets: int
    nodes: int
    boundary_triangles: int
    min_dihedral_deg: float
    dihedral_p01_deg: float           # 1st percentile of the per-tetrahedron minimum
    max_dihedral_deg: float
    min_radius_ratio: float
    mean_radius_ratio: float
    slivers: int                      # tetrahedra with a dihedral angle below SLIVER_DEG
    inverted: int
    volume_mm3: float
    mesh_volume_mm3: float
    surface_distance_max: float       # boundary nodes to the input surface
    seconds: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(eq=False)
class TetMesh:
    """A tetrahedral mesh of a closed surface (module docstring)."""

    positions: NDArray[np.float64]     # (n, 3) mm
    tets: NDArray[np.int64]            # (T, 4), positive volume
    surface: NDArray[np.int64]         # (F, 3) boundary triangles, outward, node indices
    normals: NDArray[np.float64]       # (S, 3) outward unit normals at the surface nodes
    quality: TetQuality
    edge_mm: float
    origin: NDArray[np.int64] | None = None     # (T,) index of each tetrahedron in the uncut mesh (after a cut)
    cut_faces: NDArray[np.bool_] | None = None  # (F,) boundary triangles made by a cut (after a cut)

    @property
    def inert(self) -> NDArray[np.bool_]:
        """``(T,)`` tetrahedra with a dihedral angle below :data:`INERT_DIHEDRAL_DEG`: no stiffness
        in the P1 and TransCut systems (a documented repair of fTetWild's slivers)."""
        return min_dihedral_deg(self.positions, self.tets) < INERT_DIHEDRAL_DEG

    @property
    def surface_nodes(self) -> NDArray[np.int64]:
        """``(S,)`` node indices of the boundary nodes (sorted)."""
        return np.unique(self.surface)

    @property
    def boundary_positions(self) -> NDArray[np.float64]:
        return self.positions[self.surface_nodes]

    @property
    def surface_triangles(self) -> NDArray[np.int64]:
        """``(F, 3)`` boundary triangles as indices into :attr:`surface_nodes`."""
        return np.searchsorted(self.surface_nodes, self.surface)

    @property
    def active(self) -> NDArray[np.bool_]:
        a = np.zeros(len(self.positions), dtype=bool)
        a[self.tets.ravel()] = True
        return a

    @property
    def n_active(self) -> int:
        return int(self.active.sum())

    @property
    def h(self) -> float:
        """The target edge length, mm."""
        return self.edge_mm


def _check_closed(mesh: Mesh) -> None:
    _, counts = unique_edges(mesh.faces)
    if np.any(counts != 2):
        open_edges, multi = int(np.sum(counts == 1)), int(np.sum(counts > 2))
        raise InputError(f"mesh {mesh.name!r} is not a closed manifold surface ({open_edges} boundary edges, {multi} "
                         "edges shared by more than two faces); a tetrahedral mesh needs a closed surface: repair "
                         "it first (e.g. pymeshlab's meshing_close_holes and meshing_repair_non_manifold_edges)")


def _tetwild_child(conn: Any, v: NDArray, f: NDArray, edge_mm: float, epsilon: float, threads: int,
                   workdir: str) -> None:
    """fTetWild in a child process (:func:`_run_tetwild`): its result or its error down ``conn``.
    It ignores Ctrl-C: the parent is interrupted and ends this process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.chdir(workdir)           # fTetWild writes __tracked_surface.stl into the working directory
    try:
        import pytetwild
        X, T = pytetwild.tetrahedralize(v, f, edge_length_abs=edge_mm, epsilon=epsilon, num_threads=threads,
                                        quiet=True)
        conn.send(("ok", np.asarray(X, dtype=np.float64), np.asarray(T, dtype=np.int64)))
    except Exception as exc:    # reported by the parent as the input error it is
        conn.send(("error", type(exc).__name__, str(exc)))
    finally:
        conn.close()


def _run_tetwild(v: NDArray, f: NDArray, edge_mm: float, epsilon: float, threads: int) -> tuple[NDArray, NDArray]:
    """``pytetwild.tetrahedralize`` in a child process, in a temporary working directory removed
    afterwards: a Ctrl-C (which the C++ code would otherwise take, ending the whole program with
    no word and leaving its files) reaches this process within 0.2 s, ends the child and
    raises KeyboardInterrupt here (the command's heartbeat, :mod:`glsldiff.core.heartbeat`, keeps
    the user informed meanwhile)."""
    mp = multiprocessing.get_context("spawn")
    receive, send = mp.Pipe(duplex=False)
    with tempfile.TemporaryDirectory(prefix="glsldiff-tetwild-") as tmp:
        main = threading.current_thread() is threading.main_thread()
        # Ctrl-C blocked (held, not lost) while the child starts: it inherits the block and ignores
        # the signal; here it is delivered once the block lifts
        if main:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            child = mp.Process(target=_tetwild_child, args=(send, v, f, float(edge_mm), float(epsilon), int(threads),
                                                            tmp), daemon=True)
            child.start()
        finally:
            if main:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        send.close()
        try:
            while not receive.poll(0.2):
                if not child.is_alive():
                    raise InputError(f"fTetWild stopped without a result (exit code {child.exitcode}); repair the "
                                     "mesh (pymeshlab) or change the edge length")
            message = receive.recv()
        finally:
            if child.is_alive():
                child.terminate()
                child.join(2.0)
                if child.is_alive():
                    child.kill()
            child.join()
            receive.close()
    if message[0] == "error":
        raise InputError(f"fTetWild failed: {message[2]}; repair the mesh (pymeshlab) or change the edge length")
    return message[1], message[2]


def dihedral_cos_sin(P: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(T, 6)`` each of tetrahedra ``P`` ``(T, 4, 3)``: the interior dihedral angle at the
    edges of :data:`glsldiff.grids.tetrahedral.pillow.TET_EDGES` as ``(c, s)``, cosine and sine times one
    common positive factor per entry (``|n1| |n2|``, the two faces' edge-normal lengths), so
    ``c / s`` is its cotangent and ``arctan2(s, c)`` the angle."""
    c = np.empty((len(P), 6))
    s = np.empty((len(P), 6))
    for k, (a, b) in enumerate(TET_EDGES):
        o, d = [i for i in range(4) if i not in (a, b)]
        e = P[:, b] - P[:, a]
        n1 = np.cross(e, P[:, o] - P[:, a])                 # normals of faces {a, b, o} and {a, b, d}
        n2 = np.cross(e, P[:, d] - P[:, a])
        c[:, k] = np.einsum("ij,ij->i", n1, n2)
        s[:, k] = np.linalg.norm(np.cross(n1, n2), axis=1)
    return c, s


def dihedral_deg(P: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(T, 6)`` the dihedral angles of tetrahedra ``P`` ``(T, 4, 3)`` in degrees."""
    c, s = dihedral_cos_sin(P)
    return np.degrees(np.arctan2(s, c))


def min_dihedral_deg(positions: NDArray[np.float64], tets: NDArray[np.int64]) -> NDArray[np.float64]:
    """``(T,)`` each tetrahedron's smallest dihedral angle, degrees."""
    return dihedral_deg(positions[tets]).min(axis=1)


def _radius_ratio(P: NDArray[np.float64], vol: NDArray[np.float64]) -> NDArray[np.float64]:
    """``3 r_in / r_circ`` per tetrahedron."""
    areas = np.stack([0.5 * np.linalg.norm(np.cross(P[:, j] - P[:, i], P[:, k] - P[:, i]), axis=1)
                      for i, j, k in _FACES], axis=1).sum(axis=1)
    r_in = 3.0 * np.abs(vol) / np.maximum(areas, 1e-300)
    a, b, c = P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], P[:, 3] - P[:, 0]
    num = (np.einsum("ij,ij->i", a, a)[:, None] * np.cross(b, c) + np.einsum("ij,ij->i", b, b)[:, None] * np.cross(c, a)
           + np.einsum("ij,ij->i", c, c)[:, None] * np.cross(a, b))
    r_circ = np.linalg.norm(num, axis=1) / np.maximum(12.0 * np.abs(vol), 1e-300)
    return 3.0 * r_in / np.maximum(r_circ, 1e-300)


def tet_quality(positions: NDArray[np.float64], tets: NDArray[np.int64], surface: NDArray[np.int64],
                mesh_volume: float = math.nan, surface_distance: float = math.nan,
                seconds: dict[str, float] | None = None) -> TetQuality:
    """The :class:`TetQuality` of a tetrahedral mesh; ``mesh_volume`` (mm^3) and
    ``surface_distance`` (mm) of the input surface it should fill are the caller's figures."""
    P = positions[tets]
    vol = signed_volumes(positions, tets)
    dih = dihedral_deg(P)
    rr = _radius_ratio(P, vol)
    return TetQuality(len(tets), int(len(np.unique(tets))), len(surface), float(dih.min()),
                      float(np.percentile(dih.min(axis=1), 1)), float(dih.max()), float(rr.min()), float(rr.mean()),
                      int(np.sum(dih.min(axis=1) < SLIVER_DEG)), int(np.sum(vol <= 0.0)), float(np.abs(vol).sum()),
                      float(mesh_volume), float(surface_distance), dict(seconds or {}))


def boundary_faces(tets: NDArray[np.int64]) -> NDArray[np.int64]:
    """``(F, 3)`` faces that belong to one tetrahedron only, outward."""
    faces = tets[:, _FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    return faces[first[counts == 1]]


def _closest_surface(mesh: Mesh, points: NDArray[np.float64]) -> tuple[NDArray[np.float64], float]:
    """Outward unit normals of the input surface at its closest points to ``points``, and the
    largest distance to it (mm)."""
    _, d, tri, _ = closest_points(mesh, points)
    return mesh.face_normals[tri], float(np.max(d, initial=0.0))


def tetrahedralize(mesh: Mesh, edge_mm: float, epsilon: float = 1e-3, threads: int = 0,
                   status: Callable[[str], None] | None = None) -> TetMesh:
    """A :class:`TetMesh` of the closed surface ``mesh`` with target edge length ``edge_mm``
    (mm); ``epsilon``: fTetWild's envelope, relative to the bounding-box diagonal; ``threads``:
    0 for all cores. ``status`` receives a line before the slow step."""
    if not (isinstance(edge_mm, (int, float)) and math.isfinite(edge_mm) and edge_mm > 0):
        raise InputError(f"tetrahedral edge length {edge_mm!r} mm must be a positive number")
    _check_closed(mesh)
    v = np.array(mesh.vertices, dtype=np.float64)          # writable copies: the binding rejects read-only arrays
    f = np.array(mesh.faces, dtype=np.uint32)
    extent = float(np.ptp(v, axis=0).max())
    if edge_mm > extent:
        raise InputError(f"tetrahedral edge length {edge_mm:g} mm exceeds the mesh's extent ({extent:.3g} mm); "
                         "choose an edge length a tenth of the thinnest part or less")
    if importlib.util.find_spec("pytetwild") is None:       # it runs in a child process (_run_tetwild)
        raise InputError("tetrahedral meshing needs pytetwild; pip install 'glsldiff[tet]'")
    if status is not None:
        status(f"tetwild: meshing {mesh.name} ({len(f):,} triangles) at edge {edge_mm:g} mm: seconds to minutes")
    t0 = time.perf_counter()
    try:
        X, T = _run_tetwild(v, f, edge_mm, epsilon, threads)
    except InputError as exc:
        raise InputError(f"mesh {mesh.name!r}: {exc}") from None
    t_mesh = time.perf_counter() - t0
    if len(T) == 0:
        raise InputError(f"fTetWild produced no tetrahedra for mesh {mesh.name!r} at edge {edge_mm:g} mm; the mesh "
                         "may be thinner than the edge length: choose a smaller edge")
    used = np.unique(T)                                      # drop nodes of no tetrahedron
    remap = np.full(len(X), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    X, T = X[used], remap[T]
    neg = signed_volumes(X, T) < 0.0
    T[neg] = T[neg][:, [0, 2, 1, 3]]
    surface = boundary_faces(T)
    t1 = time.perf_counter()
    nodes = np.unique(surface)
    normals, distance = _closest_surface(mesh, X[nodes])
    quality = tet_quality(X, T, surface, abs(mesh.volume), distance,
                          {"tetwild": t_mesh, "report": time.perf_counter() - t1})
    if quality.volume_mm3 < 0.5 * quality.mesh_volume_mm3:
        raise InputError(f"the tetrahedral mesh of {mesh.name!r} holds {quality.volume_mm3:.4g} mm^3 of the surface's "
                         f"{quality.mesh_volume_mm3:.4g} mm^3: parts thinner than the edge length {edge_mm:g} mm were "
                         "lost; choose a smaller edge")
    return TetMesh(X, T, surface, normals, quality, float(edge_mm))


def cached_tetrahedralize(mesh: Mesh, edge_mm: float, epsilon: float = 1e-3, threads: int = 0,
                          status: Callable[[str], None] | None = None) -> tuple[TetMesh, bool]:
    """:func:`tetrahedralize` through the on-disk cache; returns the mesh and whether it came
    from the cache."""
    key = cache.digest(f"tetwild v{CACHE_VERSION}", np.asarray(mesh.vertices, dtype=np.float64),
                       np.asarray(mesh.faces, dtype=np.int64), float(edge_mm), float(epsilon))
    tm = cache.load("tetwild", key, TetMesh)
    if tm is not None:
        return tm, True
    tm = tetrahedralize(mesh, edge_mm, epsilon, threads, status)
    cache.store("tetwild", key, tm)
    return tm, False


def refine(tm: TetMesh) -> TetMesh:
    """Regular 1:8 subdivision of every tetrahedron (:func:`glsldiff.grids.tetrahedral.pillow.subdivide_tets`):
    8x the tetrahedra at half the edge length, for timing solvers at scale. The new boundary nodes lie on
    the old boundary triangles (not on the input surface); their normals are the normalised
    mean of the edge ends'."""
    X, T8, edges = subdivide_tets(tm.positions, tm.tets)
    n = len(tm.positions)
    surface = boundary_faces(T8)
    nodes = np.unique(surface)
    normal = np.zeros((len(X), 3))
    normal[tm.surface_nodes] = tm.normals
    mid = normal[edges[:, 0]] + normal[edges[:, 1]]
    normal[n:] = mid / np.maximum(np.linalg.norm(mid, axis=1, keepdims=True), 1e-300)
    q = tm.quality
    quality = tet_quality(X, T8, surface, q.mesh_volume_mm3, q.surface_distance_max, dict(q.seconds))
    return TetMesh(X, T8, surface, normal[nodes], quality, tm.edge_mm / 2.0)
