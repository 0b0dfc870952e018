"""pymeshlab's part of loading a mesh (:mod:`glsldiff.mesh.load`): read a file, run the repair
filters, give the arrays and the topological measures, in this process (:class:`MeshLab`) or in
a child interpreter (:class:`ChildMeshLab`, the same methods).

pymeshlab's libraries and plugins are ~96 MB of resident memory once imported, kept until the
process ends: a renderer that loads its mesh in a child never maps them (the first render of a
147k-node grid then stays under 1 GB). The child runs this file by its path with only numpy and
pymeshlab imported (no ``glsldiff`` package: its imports would cost the child ~0.3 s), so this
module imports nothing from ``glsldiff``; requests and answers are pickles over the child's
stdin and stdout.
"""
from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import pickle
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger("glsldiff.mesh.load")

#: Largest hole (in boundary edges) that :meth:`MeshLab.repair` closes.
MAX_HOLE_EDGES = 30


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Send what native code writes to stdout/stderr (pymeshlab warnings) to the log."""
    try:
        fds = (sys.__stdout__.fileno(), sys.__stderr__.fileno())  # type: ignore[union-attr]
    except (AttributeError, ValueError, OSError):  # no real file descriptors: do nothing
        yield
        return
    try:
        libc: Any = ctypes.CDLL(None)
    except OSError:  # pragma: no cover - no C library handle (Windows)
        libc = None
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved = [os.dup(fd) for fd in fds]
    with tempfile.TemporaryFile() as tmp:
        try:
            for fd in fds:
                os.dup2(tmp.fileno(), fd)
            yield
        finally:
            if libc is not None:
                with contextlib.suppress(Exception):
                    libc.fflush(None)
            for fd, s in zip(fds, saved):
                os.dup2(s, fd)
                os.close(s)
            tmp.seek(0)
            text = tmp.read().decode(errors="replace").strip()
            if text:
                log.debug("pymeshlab output: %s", text)


class MeshLab:
    """One pymeshlab MeshSet in this process, empty or holding the mesh ``(v, f)`` (vertices mm,
    ``(V, 3)``; faces ``(F, 3)``). Raises ImportError without pymeshlab."""

    def __init__(self, v: NDArray[np.float64] | None = None, f: NDArray[np.int64] | None = None,
                 name: str = "") -> None:
        import pymeshlab  # heavy import, loaded only to read or repair a mesh
        self.ms = pymeshlab.MeshSet(verbose=False)
        if v is not None and f is not None:
            self.ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=np.asarray(f, dtype=np.int32)), name)

    def read(self, path: str) -> None:
        """Load the mesh file ``path`` (any format pymeshlab reads)."""
        with quiet():
            self.ms.load_new_mesh(path)

    def counts(self) -> tuple[int, int]:
        m = self.ms.current_mesh()
        return m.vertex_number(), m.face_number()

    def arrays(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """The current mesh's vertices ``(V, 3)`` and faces ``(F, 3)``."""
        m = self.ms.current_mesh()
        return (np.array(m.vertex_matrix(), dtype=np.float64),
                np.array(m.face_matrix(), dtype=np.int64).reshape(-1, 3))

    def topology(self, v: NDArray[np.float64] | None = None, f: NDArray[np.int64] | None = None) -> dict[str, int]:
        """pymeshlab's topological measures (boundary edges, holes, non-manifold edges and
        vertices, ...) of the mesh ``(v, f)`` where given (the current mesh stays), else of the current mesh."""
        ms = self.ms if v is None or f is None else MeshLab(v, f).ms
        with quiet():
            return dict(ms.get_topological_measures())

    def repair(self) -> dict[str, int]:
        """Run the repair filters; return the non-zero change counts."""
        ms, rep = self.ms, {}

        def add(key: str, n: int) -> None:
            rep[key] = rep.get(key, 0) + abs(int(n))

        def step(filt: str, v_key: str | None, f_key: str | None, **kw: Any) -> None:
            v0, f0 = self.counts()
            getattr(ms, filt)(**kw)
            v1, f1 = self.counts()
            if v_key:
                add(v_key, v0 - v1)
            if f_key:
                add(f_key, f0 - f1)

        with quiet():
            # merging duplicates also drops faces that then repeat a vertex (degenerate)
            step("meshing_remove_duplicate_vertices", "duplicate_vertices", "degenerate_faces")
            step("meshing_remove_duplicate_faces", None, "duplicate_faces")
            step("meshing_remove_null_faces", None, "degenerate_faces")
            step("meshing_remove_unreferenced_vertices", "unreferenced_vertices", None)
            step("meshing_repair_non_manifold_edges", None, "nonmanifold_edge_faces")
            step("meshing_repair_non_manifold_vertices", "split_nonmanifold_vertices", None)
            step("meshing_remove_unreferenced_vertices", "unreferenced_vertices", None)
            f_before = self.arrays()[1]
            ms.meshing_re_orient_faces_coherently()
            f_after = self.arrays()[1]
            if f_before.shape == f_after.shape:
                changed = int((f_before != f_after).any(axis=1).sum())
                # pymeshlab may flip the majority; the outward flip below undoes that globally
                add("reoriented_faces", min(changed, len(f_after) - changed))
            holes0 = int(ms.get_topological_measures()["number_holes"])
            step("meshing_close_holes", None, "hole_faces_added", maxholesize=MAX_HOLE_EDGES)
            if rep["hole_faces_added"]:
                add("closed_holes", max(holes0 - int(ms.get_topological_measures()["number_holes"]), 0))
                step("meshing_remove_null_faces", None, "degenerate_faces")
        return {k: n for k, n in rep.items() if n}

    def close(self) -> None:
        """Nothing to release in this process (:class:`ChildMeshLab` ends its child)."""


class ChildMeshError(RuntimeError):
    """pymeshlab raised in the child; the message is its exception's."""


class ChildUnavailable(OSError):
    """The child interpreter did not start, could not make a MeshSet, or ended."""


class ChildMeshLab:
    """:class:`MeshLab` in a child interpreter: the same methods, each a request to the child
    (which imports only numpy and pymeshlab). The child is started here and makes its MeshSet
    while the caller goes on (its ~0.3 s of imports overlap the caller's work until the first
    request). :meth:`close` ends it (also a context manager). Requests raise
    :class:`ChildUnavailable` where the child cannot serve them, :class:`ChildMeshError` where
    pymeshlab raised."""

    def __init__(self, v: NDArray[np.float64] | None = None, f: NDArray[np.int64] | None = None,
                 name: str = "") -> None:
        code = ("import sys; del sys.path[0]; p = sys.argv[1]; "
                "exec(compile(open(p).read(), p, 'exec'), {'__name__': '__main__', '__file__': p})")
        self.proc = subprocess.Popen([sys.executable, "-c", code, os.path.abspath(__file__)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self._made = False            # the answer to the MeshSet's making not read yet
        try:
            self._send("__init__", v, f, name)
        except BaseException:
            self.close()
            raise

    def _send(self, method: str, *args: Any) -> None:
        assert self.proc.stdin is not None
        try:
            pickle.dump((method, args), self.proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self.proc.stdin.flush()
        except OSError as exc:
            raise ChildUnavailable(f"the pymeshlab child process ended (exit status {self.proc.poll()})") from exc

    def _receive(self) -> Any:
        assert self.proc.stdout is not None
        try:
            ok, value = pickle.load(self.proc.stdout)
        except (EOFError, OSError, pickle.UnpicklingError) as exc:
            raise ChildUnavailable(f"the pymeshlab child process ended (exit status {self.proc.poll()})") from exc
        if not ok:
            raise (ChildMeshError if self._made else ChildUnavailable)(value)
        return value

    def _call(self, method: str, *args: Any) -> Any:
        self._send(method, *args)
        if not self._made:
            self._receive()
            self._made = True
        return self._receive()

    def read(self, path: str) -> None:
        self._call("read", path)

    def arrays(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        return self._call("arrays")

    def topology(self, v: NDArray[np.float64] | None = None, f: NDArray[np.int64] | None = None) -> dict[str, int]:
        return self._call("topology", v, f)

    def repair(self) -> dict[str, int]:
        return self._call("repair")

    def close(self) -> None:
        """End the child (its stdin closed: it exits)."""
        for stream in (self.proc.stdin, self.proc.stdout):
            with contextlib.suppress(OSError):
                if stream is not None:
                    stream.close()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:  # pragma: no cover - a hung child
            self.proc.kill()
            self.proc.wait()

    def __enter__(self) -> "ChildMeshLab":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _serve(requests: BinaryIO, answers: BinaryIO) -> None:
    """The child's loop: ``(method, args)`` pickles in, ``(ok, value or message)`` pickles out,
    until ``requests`` ends. ``"__init__"`` makes the MeshSet."""
    lab: MeshLab | None = None
    while True:
        try:
            method, args = pickle.load(requests)
        except EOFError:
            return
        try:
            if method == "__init__":
                lab, value = MeshLab(*args), None
            else:
                assert lab is not None
                value = getattr(lab, method)(*args)
            out: tuple[bool, Any] = (True, value)
        except Exception as exc:  # pymeshlab.PyMeshLabException, ImportError and friends go back to the parent
            out = (False, str(exc))
        pickle.dump(out, answers, protocol=pickle.HIGHEST_PROTOCOL)
        answers.flush()


if __name__ == "__main__":
    # answers on a private copy of stdout; what native code prints goes to stderr, not into them
    _answers = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    _serve(sys.stdin.buffer, _answers)
