"""Public meshes the project was not developed with, for ``glsldiff bench meshes``: CGAL's data
set (the meshes of its examples and tests, shipped by Debian's ``libcgal-demo`` package as
``/usr/share/doc/libcgal-dev/data.tar.gz``).

:func:`public_mesh` returns the path of one of :data:`PUBLIC_MESHES`, extracted once into the
glsldiff cache (``meshes/`` in :func:`glsldiff.core.cache.cache_dir`); the package is read from
the system when installed, else fetched with ``apt-get download`` (about 24 MB, once).
"""
from __future__ import annotations

import shutil
import subprocess
import tarfile
import tempfile
from pathlib import Path

from glsldiff.core import cache
from glsldiff.core.errors import GlsldiffError

__all__ = ["PUBLIC_MESHES", "public_mesh"]

#: name -> what it tests (CGAL's data/meshes/<name>.off).
PUBLIC_MESHES = {
    "hand": "thin limbs: fingers, a wrist crease (scan)",
    "camel": "thin limbs: four long legs (scan)",
    "elk": "thin legs and spiky antlers, genus 1 (scan)",
    "triceratops": "spikes: horns, a frill, thin legs",
    "fandisk": "CAD part: sharp edges and flat faces",
    "couplingdown": "CAD part: sharp edges, genus 9",
}
PACKAGE = "libcgal-demo"
ARCHIVE = Path("usr/share/doc/libcgal-dev/data.tar.gz")


def _folder() -> Path:
    base = cache.cache_dir()
    return (base if base is not None else Path(tempfile.gettempdir()) / "glsldiff-meshes") / "meshes"


def _archive(work: Path) -> Path:
    """CGAL's data archive: the installed package's, or the package downloaded into ``work``."""
    installed = Path("/") / ARCHIVE
    if installed.is_file():
        return installed
    if shutil.which("apt-get") is None or shutil.which("dpkg-deb") is None:
        raise GlsldiffError(f"the public meshes come from Debian's {PACKAGE} package: install it "
                            f"(apt-get install {PACKAGE}) or run on a Debian machine")
    got = subprocess.run(["apt-get", "download", PACKAGE], cwd=work, capture_output=True, text=True)
    debs = sorted(work.glob(f"{PACKAGE}_*.deb"))
    if got.returncode != 0 or not debs:
        raise GlsldiffError(f"apt-get download {PACKAGE} failed ({(got.stderr or got.stdout).strip()[-200:]}); "
                            f"install it (apt-get install {PACKAGE}) and run again")
    subprocess.run(["dpkg-deb", "-x", str(debs[0]), str(work / "deb")], check=True, capture_output=True)
    return work / "deb" / ARCHIVE


def public_mesh(name: str) -> Path:
    """The path of the public mesh ``name`` (:data:`PUBLIC_MESHES`), extracted on first use."""
    if name not in PUBLIC_MESHES:
        raise GlsldiffError(f"unknown public mesh {name!r}; choose one of {', '.join(PUBLIC_MESHES)}")
    folder = _folder()
    path = folder / f"{name}.off"
    if path.is_file():
        return path
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(_archive(Path(tmp))) as tar:
            for n in PUBLIC_MESHES:
                member = tar.extractfile(f"data/meshes/{n}.off")
                if member is None:
                    raise GlsldiffError(f"{PACKAGE}'s data has no meshes/{n}.off")
                part = folder / f".{n}.off.part"
                part.write_bytes(member.read())
                part.replace(folder / f"{n}.off")
    return path
