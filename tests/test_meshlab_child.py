"""pymeshlab in a child interpreter (glsldiff.mesh.meshlab.ChildMeshLab): what
cached_load_mesh gives equals an in-process load_mesh, its errors are load_mesh's, it loads
in this process where no child starts, and the parent never imports pymeshlab.

Reference: load_mesh in this process (the same pymeshlab calls).
"""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("pymeshlab")

from glsldiff.core.errors import InputError  # noqa: E402
from glsldiff.mesh import load as L  # noqa: E402
from glsldiff.mesh.meshlab import ChildMeshLab, ChildUnavailable  # noqa: E402


def _same(a, b) -> None:
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert a.repairs == b.repairs and a.name == b.name


@pytest.mark.parametrize("size_mm", [None, 100.0])
def test_child_load_equals_in_process(size_mm):
    _same(L._load("bunny", size_mm, True, "error", child=True), L.load_mesh("bunny", size_mm))


def test_child_repairs_equal_in_process(tmp_path):
    # an OBJ of the sample cow with one face doubled: the repair counts come back from the child
    src = L.sample_mesh_path("cow").read_text().splitlines()
    face = next(line for line in src if line.startswith("f "))
    p = tmp_path / "cow2.obj"
    p.write_text("\n".join(src + [face]) + "\n")
    child = L._load(p, None, True, "error", child=True)
    _same(child, L.load_mesh(p))
    assert child.repairs.get("duplicate_faces") == 1


def test_child_errors_are_load_mesh_errors(tmp_path):
    p = tmp_path / "junk.xyz_unknown"
    p.write_text("not a mesh")
    with pytest.raises(InputError, match=r"could not be read by pymeshlab"):
        L._load(p, None, True, "error", child=True)


def test_no_child_loads_here(monkeypatch):
    monkeypatch.setattr(sys, "executable", "/nonexistent/python")
    _same(L._load("bunny", 100.0, True, "error", child=True), L.load_mesh("bunny", 100.0))


def test_ended_child_is_unavailable():
    lab = ChildMeshLab()
    lab.proc.kill()
    lab.proc.wait()
    with pytest.raises(ChildUnavailable):
        lab.arrays()
    lab.close()


def test_cached_load_keeps_pymeshlab_out(tmp_path):
    code = ("import sys; from glsldiff.mesh import cached_load_mesh; m = cached_load_mesh('bunny', 100.0); "
            "print(len(m.faces), 'pymeshlab' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**__import__("os").environ, "GLSLDIFF_CACHE": str(tmp_path)}).stdout.split()
    assert out == [str(len(L.load_mesh("bunny").faces)), "False"]
