"""Loading closed meshes through pymeshlab: read (any format pymeshlab reads, or a built-in
sample), optionally repair (duplicate vertices and faces, degenerate faces, unreferenced
vertices, non-manifold edges and vertices, incoherent orientation, small holes), check the
topology and orient the faces outward. What the repair changed is counted in
:attr:`glsldiff.mesh.types.Mesh.repairs`. Coordinates are taken as mm.

pymeshlab is a core dependency but a heavy import (~96 MB resident, kept until the process ends):
it is imported only where a mesh is read or checked (:mod:`glsldiff.mesh.meshlab`), and
:func:`cached_load_mesh` (the renderer's) runs it in a child interpreter.
"""
from __future__ import annotations

import importlib.metadata
import importlib.util
import logging
import os
import re
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from glsldiff.core import cache
from glsldiff.core.checks import choice, real
from glsldiff.core.errors import InputError
from glsldiff.core.io import not_a_file
from glsldiff.mesh.meshlab import MAX_HOLE_EDGES, ChildMeshLab, ChildUnavailable, MeshLab
from glsldiff.mesh.types import (Mesh, check_face_indices, n_directed_edges, signed_volume, unique_edges,
                                 vertex_labels)

log = logging.getLogger(__name__)

#: Built-in sample meshes (shipped with pymeshlab's tests).
SAMPLE_MESHES: dict[str, str] = {
    "bunny": "bunny.obj",
    "cow": "cow.obj",
    "bone": "bone.ply",
    "airplane": "airplane.obj",
}
COMPONENT_MODES = ("error", "largest")


def sample_mesh_path(name: str) -> Path:
    """Path of a built-in sample mesh: ``'bunny'``, ``'cow'``, ``'bone'`` or ``'airplane'``."""
    if name not in SAMPLE_MESHES:
        raise InputError(f"unknown sample mesh {name!r}; valid names: {', '.join(SAMPLE_MESHES)} "
                         "(or pass the path of a mesh file)")
    spec = importlib.util.find_spec("pymeshlab")     # found, not imported (a heavy import)
    if spec is None or not spec.submodule_search_locations:  # pragma: no cover - depends on the environment
        raise InputError(f"sample mesh {name!r} ships with pymeshlab, which is not installed; "
                         "install it with: pip install pymeshlab")
    path = Path(list(spec.submodule_search_locations)[0]) / "tests" / "sample_meshes" / SAMPLE_MESHES[name]
    if not path.is_file():  # pragma: no cover - broken install
        raise InputError(f"sample mesh {name!r}: {path} is missing from the pymeshlab install; "
                         "reinstall pymeshlab or pass a mesh file path")
    return path


#: Object sizes glsldiff takes (mm): below 0.1 mm no material is many mean free paths across
#: (the diffusion model does not hold) and the solver stiffens; above 100 m the float32 textures
#: lose the node spacing.
MIN_SIZE_MM, MAX_SIZE_MM = 0.1, 1e5


def load_mesh(source: str | os.PathLike, size_mm: float | None = None, repair: bool = True,
              component: str = "error") -> Mesh:
    """Load, repair and validate a closed mesh file (any format pymeshlab reads).

    Parameters
    ----------
    source
        File path, or a sample name (see :func:`sample_mesh_path`).
    size_mm
        If given, scale uniformly (about the origin) so that the longest bounding-box
        extent is ``size_mm`` mm; ``None`` keeps the file's units, taken as mm.
    repair
        Remove duplicate/degenerate/unreferenced elements, fix non-manifold edges and
        vertices and incoherent orientation, and close holes of up to
        :data:`MAX_HOLE_EDGES` edges (see :func:`mesh_from_arrays`).
    component
        ``'error'``: several connected components raise InputError; ``'largest'``: keep
        the component of largest volume (counted as ``removed_components``).
    """
    return _load(source, size_mm, repair, component, child=False)


def _load(source: str | os.PathLike, size_mm: float | None, repair: bool, component: str, child: bool) -> Mesh:
    """:func:`load_mesh`, pymeshlab in a child interpreter with ``child`` (:func:`_meshset`)."""
    path, name = _mesh_file(source)
    ms = _read(path, child)
    try:
        return _finish(ms, name, size_mm, repair, component, file_units=True)
    finally:
        ms.close()


def _read(path: Path, child: bool) -> MeshLab | ChildMeshLab:
    """A MeshSet holding the mesh file ``path``, checked first (:func:`_check_file_numbers`,
    while a child starts); in this process where the child cannot serve (:func:`_meshset`)."""
    ms = _meshset(child=child)
    try:
        _check_file_numbers(path)
        ms.read(str(path))
        return ms
    except ChildUnavailable as exc:
        ms.close()
        log.debug("no pymeshlab child process (%s): loading in this process", exc)
        return _read(path, child=False)
    except InputError:
        ms.close()
        raise
    except Exception as exc:  # pymeshlab.PyMeshLabException and friends
        ms.close()
        raise InputError(f"mesh file {str(path)!r} could not be read by pymeshlab ({exc}); "
                         "check the file format (obj, ply, stl, off, ...)") from exc


def _mesh_file(source: str | os.PathLike) -> tuple[Path, str]:
    """The file and the name of a :func:`load_mesh` source (a path or a sample name)."""
    if isinstance(source, str) and source in SAMPLE_MESHES and not Path(source).exists():
        return sample_mesh_path(source), source
    path = Path(source)
    if not path.is_file():
        raise InputError(f"mesh file {str(path)!r} {not_a_file(path)}; pass an existing file "
                         f"or one of the sample names {', '.join(SAMPLE_MESHES)}")
    return path, path.name


#: Part of every cached mesh's key: bump it when reading, repairing or checking a mesh changes.
LOAD_CACHE_VERSION = 1


def cached_load_mesh(source: str | os.PathLike, size_mm: float | None = None, repair: bool = True,
                     component: str = "error") -> Mesh:
    """:func:`load_mesh` through the on-disk cache (:mod:`glsldiff.core.cache`), keyed by the
    file's bytes, name and suffix, the arguments and pymeshlab's version (0.5 s of reading,
    checks and repair for the bunny). pymeshlab runs in a child interpreter
    (:class:`~glsldiff.mesh.meshlab.ChildMeshLab`; here where none starts): its ~96 MB of
    libraries stay out of the renderer. A file that does not load raises every time (nothing
    is cached for it)."""
    path, name = _mesh_file(source)
    try:
        reader = importlib.metadata.version("pymeshlab")
    except importlib.metadata.PackageNotFoundError:
        return load_mesh(source, size_mm, repair, component)     # which says what to install
    key = cache.digest(f"mesh v{LOAD_CACHE_VERSION}", path.read_bytes(), name, path.suffix.lower(), size_mm,
                       repair, component, reader)
    return cache.memo("mesh", key, Mesh, lambda: _load(source, size_mm, repair, component, child=True))


def mesh_from_arrays(vertices: ArrayLike, faces: ArrayLike, size_mm: float | None = None,
                     repair: bool = True, component: str = "error", name: str = "") -> Mesh:
    """Build a validated :class:`Mesh` from vertex ``(V, 3)`` mm and face ``(F, 3)`` arrays.

    Same pipeline as :func:`load_mesh`. With ``repair=True`` pymeshlab removes duplicate
    vertices, duplicate faces, degenerate (zero-area) faces and unreferenced vertices,
    repairs non-manifold edges (removing faces) and vertices (splitting them), makes the
    orientation coherent and closes holes of at most :data:`MAX_HOLE_EDGES` edges. The
    result must then be closed, two-manifold and (unless ``component='largest'``) one
    connected component with non-zero volume; its faces are flipped if they point inward.
    """
    label = name or "mesh"
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or not np.issubdtype(v.dtype, np.number):
        raise InputError(f"{label}: vertices must be a numeric (V, 3) array, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not (np.issubdtype(f.dtype, np.integer) or f.size == 0):
        raise InputError(f"{label}: faces must be an integer (F, 3) array of vertex indices, "
                         f"got shape {f.shape} dtype {f.dtype}")
    if len(f) == 0 or len(v) == 0:
        raise InputError(f"{label}: the mesh is empty ({len(v)} vertices, {len(f)} faces); "
                         "pass a closed triangle surface")
    v = np.asarray(v, dtype=np.float64)
    _check_finite(v, label)
    check_face_indices(f, len(v), label)
    ms = _meshset(v, f, label)
    try:
        return _finish(ms, name, size_mm, repair, component)
    finally:
        ms.close()


def _meshset(v: NDArray[np.float64] | None = None, f: NDArray[np.int64] | None = None, name: str = "",
             child: bool = False) -> MeshLab | ChildMeshLab:
    """An empty pymeshlab MeshSet, or one holding the mesh ``(v, f)``: in a child interpreter
    with ``child`` (:class:`~glsldiff.mesh.meshlab.ChildMeshLab`; in this process where none starts),
    else here. The caller closes it."""
    if child:
        try:
            return ChildMeshLab(v, f, name)
        except OSError as exc:
            log.debug("no pymeshlab child process (%s): loading in this process", exc)
    try:
        return MeshLab(v, f, name)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise InputError("loading meshes needs pymeshlab; install it with: "
                         "pip install pymeshlab") from exc


#: A NaN or infinite number as C's strtod spells it, as a whole token.
_NON_FINITE = re.compile(rb"(?<![\w.+-])[+-]?(nan|inf(inity)?)(?![\w.])", re.IGNORECASE)
#: Comment lines of the text formats (obj/off ``#``, ply ``comment``/``obj_info``).
_COMMENT = re.compile(rb"^\s*(#|comment\b|obj_info\b)")


def _check_file_numbers(path: Path) -> None:
    """Refuse a mesh file with a NaN or infinite vertex coordinate. pymeshlab drops such
    vertices and the faces using them without a word, which would leave a different (often
    open) mesh; text formats are scanned line by line, binary STL as float32 records (binary
    PLY is checked after loading only)."""
    data = path.read_bytes()
    if data[:5].lower() != b"solid" and path.suffix.lower() == ".stl" and len(data) >= 84:
        n = int(np.frombuffer(data, "<u4", 1, 80)[0])
        if len(data) >= 84 + 50 * n:
            rec = np.frombuffer(data, np.dtype([("f", "<f4", 12), ("a", "<u2")]), n, 84)
            bad = ~np.isfinite(rec["f"][:, 3:]).all(axis=1)
            if bad.any():
                raise InputError(f"mesh file {str(path)!r}: {int(bad.sum())} triangles have NaN or infinite "
                                 f"vertex coordinates (e.g. triangle {int(np.flatnonzero(bad)[0])}); fix or "
                                 "remove them")
        return
    head = data[:4096]
    if (head[:3] == b"ply" and b"format ascii" not in head) or (head[:3] != b"ply" and b"\0" in head):
        return                                   # binary: nothing to scan as text
    if path.suffix.lower() == ".obj":
        _check_obj_faces(path, data)
    lower = data.lower()
    if b"nan" not in lower and b"inf" not in lower:
        return                                   # the usual case: no line can match (7 ms, not 89 ms)
    for number, line in enumerate(data.splitlines(), 1):
        if _NON_FINITE.search(line) and not _COMMENT.match(line):
            raise InputError(f"mesh file {str(path)!r} line {number}: a NaN or infinite number "
                             f"({line.decode(errors='replace').strip()[:60]!r}); fix or remove that vertex")


def _check_obj_faces(path: Path, data: bytes) -> None:
    """Refuse an OBJ face that names a vertex the file does not have (pymeshlab drops such
    faces without a word, leaving a hole): 1-based indices up to the vertex count, negative ones
    counted back from the end."""
    nv = len(re.findall(rb"(?m)^[ \t]*v[ \t]", data))
    for number, line in enumerate(data.splitlines(), 1):
        if not line.lstrip().startswith((b"f ", b"f\t")):
            continue
        try:
            idx = [int(tok.split(b"/")[0]) for tok in line.split()[1:]]
        except ValueError:
            raise InputError(f"mesh file {str(path)!r} line {number}: a face with a non-integer vertex index "
                             f"({line.decode(errors='replace').strip()[:60]!r})") from None
        bad = [i for i in idx if i == 0 or i > nv or i < -nv]
        if bad:
            raise InputError(f"mesh file {str(path)!r} line {number}: face names vertex {bad[0]} but the file has "
                             f"{nv} vertices (OBJ indices run 1..{nv}); fix or remove that face")


def _check_finite(v: NDArray[np.float64], label: str) -> None:
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise InputError(f"{label}: {int(bad.sum())} vertices have non-finite coordinates "
                         f"(e.g. vertex {int(np.flatnonzero(bad)[0])}); fix or remove them")


def _finish(ms: MeshLab | ChildMeshLab, name: str, size_mm: float | None, repair: bool, component: str,
            file_units: bool = False) -> Mesh:
    """Validate, repair and scale the meshset's mesh. ``file_units``: a file read without
    ``size_mm`` keeps its units, taken as mm, which must then make a physical size."""
    label = f"mesh {name!r}" if name else "mesh"
    choice(component, f"{label}: component", COMPONENT_MODES)
    if size_mm is not None:
        real(size_mm, f"{label}: size_mm (mm; None keeps the file's units)", lo=MIN_SIZE_MM, hi=MAX_SIZE_MM)
    v, f = ms.arrays()
    if len(f) == 0:
        raise InputError(f"{label} has no faces ({len(v)} vertices); pass a closed triangle "
                         "surface")
    _check_finite(v, label)
    if size_mm is None and file_units and not MIN_SIZE_MM <= (longest := float(np.ptp(v, axis=0).max())) <= MAX_SIZE_MM:
        raise InputError(f"mesh {name!r} is {longest:.3g} mm across in its file's units (taken as mm), "
                         f"outside {MIN_SIZE_MM:g} .. {MAX_SIZE_MM:g} mm; scale it to a physical size with "
                         "--size-mm (polygrid) or [mesh].size_mm (scenes)")
    repairs = ms.repair() if repair else {}
    v, f = ms.arrays()
    if len(f) == 0:
        raise InputError(f"{label}: no faces left after removing degenerate/duplicate ones")

    # components
    _, labels = vertex_labels(f, len(v))
    face_comp = labels[f[:, 0]]
    comps = np.unique(face_comp)
    if len(comps) > 1 and component == "largest":
        vols = np.array([abs(signed_volume(v, f[face_comp == c])) for c in comps])
        sizes = np.array([np.count_nonzero(face_comp == c) for c in comps])
        best = comps[np.lexsort((-sizes, -vols))[0]]
        f = f[face_comp == best]
        used = np.unique(f)
        remap = np.full(len(v), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        v, f = v[used], remap[f]
        repairs["removed_components"] = len(comps) - 1
        log.info("%s: kept the largest of %d components (%d faces)", label, len(comps), len(f))

    _check_topology(ms, v, f, label, repair, n_components=len(comps) if component == "error" else 1)
    vol = signed_volume(v, f)
    ext = v.max(axis=0) - v.min(axis=0)
    if not abs(vol) > 1e-9 * float(ext.max()) ** 3:
        raise InputError(f"{label} encloses zero volume ({vol:.3g} mm^3 for extents "
                         f"{np.round(ext, 6).tolist()} mm); pass a solid, not a flat or "
                         "double-sided sheet")
    if vol < 0:
        f = f[:, ::-1].copy()
        repairs["flipped_orientation"] = 1
    if size_mm is not None:
        v = v * (float(size_mm) / float(ext.max()))
    if repairs:
        log.info("%s: repairs %s", label, repairs)
    return Mesh(v, f, name=name, repairs=repairs)


def _check_topology(ms: MeshLab | ChildMeshLab, v: NDArray[np.float64], f: NDArray[np.int64], label: str,
                    repair: bool, n_components: int = 1) -> None:
    """Raise one InputError listing every problem of the mesh ``(v, f)`` (measured by ``ms``'s
    pymeshlab): open, non-manifold, incoherent, several components."""
    topo = ms.topology(v, f)
    problems = []
    if topo["boundary_edges"] > 0:
        problems.append(f"it is open: {topo['boundary_edges']} boundary edges in "
                        f"{max(topo['number_holes'], 1)} hole(s)")
    if topo["non_two_manifold_edges"] > 0 or topo["non_two_manifold_vertices"] > 0:
        problems.append(f"it is not two-manifold: {topo['non_two_manifold_edges']} non-manifold "
                        f"edges, {topo['non_two_manifold_vertices']} non-manifold vertices")
    _, counts = unique_edges(f)
    if not problems and n_directed_edges(f) != 2 * len(counts):
        problems.append("its faces are not coherently oriented")
    fixes = []
    if problems and repair:
        fixes.append(f"repair=True could not fix it (it closes only holes of up to "
                     f"{MAX_HOLE_EDGES} edges); repair the surface in a mesh editor "
                     "(e.g. MeshLab: close holes, remove non-manifold edges)")
    elif problems:
        fixes.append(f"pass repair=True (closes holes of up to {MAX_HOLE_EDGES} edges, "
                     "repairs non-manifold elements and face orientation)")
    if n_components > 1:
        problems.append(f"it has {n_components} connected components")
        fixes.append("keep the largest one (glsldiff polygrid --component largest; in Python "
                     "load_mesh(..., component='largest')), or split the file")
    if problems:
        raise InputError(f"{label}: {'; '.join(problems)}; glsldiff needs one closed "
                         f"two-manifold surface: {'; '.join(fixes)}")

