"""Headless OpenGL for glsldiff: contexts, shader programs, float textures, ping-pong pairs.

``create_context()`` is the only place a context is made. The backend comes from the
argument or the environment variable ``GLSLDIFF_GL``:

``egl`` (default)
    moderngl's standalone EGL context (Mesa llvmpipe on a CPU machine, the GPU on an
    NVIDIA machine with its driver).
``osmesa``
    Mesa's off-screen renderer through ctypes (moderngl has no OSMesa backend):
    ``OSMesaCreateContextAttribs`` for a 3.3 core profile, then
    ``moderngl.init_context`` with ``OSMesaGetProcAddress`` as the loader.
``auto``
    EGL, then OSMesa.

GLSL sources live in the top-level ``shaders/`` folder (shipped in the wheel as the
``glsldiff.shaders`` package). ``#include "name.glsl"`` lines are expanded from the
same folder, and ``defines`` are inserted after the ``#version`` line.
"""
from __future__ import annotations

import ctypes
import importlib.resources
import logging
import os
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff.errors import BackendError, GlsldiffError

logger = logging.getLogger(__name__)

BACKENDS = ("egl", "osmesa", "auto")
INSTALL_HINT = ("install Mesa's headless GL libraries, e.g. on Debian/Ubuntu: "
                "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 "
                "(on an NVIDIA machine the driver's libEGL_nvidia provides EGL)")
DTYPES = {"fp32": "f4", "fp16": "f2"}
FP16_MAX = 65504.0  # largest finite half float; llvmpipe clamps fp16 writes to it

# OSMesa constants (GL/osmesa.h)
_OSMESA_FORMAT, _OSMESA_RGBA, _OSMESA_DEPTH_BITS = 0x22, 0x1908, 0x30
_OSMESA_PROFILE, _OSMESA_CORE_PROFILE = 0x33, 0x34
_OSMESA_MAJOR, _OSMESA_MINOR = 0x36, 0x37
_GL_UNSIGNED_BYTE = 0x1401


class _OSMesaLoader:
    """Owns an OSMesa context and its 1x1 colour buffer; loads GL entry points."""

    def __init__(self) -> None:
        try:
            lib = ctypes.CDLL("libOSMesa.so.8")
        except OSError:
            try:
                lib = ctypes.CDLL("libOSMesa.so")
            except OSError as exc:
                raise BackendError(f"OSMesa library not found ({exc}); {INSTALL_HINT}") from exc
        lib.OSMesaCreateContextAttribs.restype = ctypes.c_void_p
        lib.OSMesaCreateContextAttribs.argtypes = [ctypes.POINTER(ctypes.c_int), ctypes.c_void_p]
        lib.OSMesaMakeCurrent.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint,
                                          ctypes.c_int, ctypes.c_int]
        lib.OSMesaGetProcAddress.restype = ctypes.c_void_p
        lib.OSMesaGetProcAddress.argtypes = [ctypes.c_char_p]
        lib.OSMesaDestroyContext.argtypes = [ctypes.c_void_p]
        attrs = [_OSMESA_FORMAT, _OSMESA_RGBA, _OSMESA_DEPTH_BITS, 24,
                 _OSMESA_PROFILE, _OSMESA_CORE_PROFILE, _OSMESA_MAJOR, 3, _OSMESA_MINOR, 3, 0]
        handle = lib.OSMesaCreateContextAttribs((ctypes.c_int * len(attrs))(*attrs), None)
        if not handle:
            raise BackendError(f"OSMesaCreateContextAttribs failed (no GL 3.3 core); {INSTALL_HINT}")
        self._lib, self._handle = lib, handle
        self._buffer = (ctypes.c_ubyte * 4)()
        if not lib.OSMesaMakeCurrent(handle, self._buffer, _GL_UNSIGNED_BYTE, 1, 1):
            raise BackendError("OSMesaMakeCurrent failed")

    def __enter__(self) -> "_OSMesaLoader":
        """Make this context current (moderngl's ``with ctx:`` and :func:`make_current`)."""
        if not self._lib.OSMesaMakeCurrent(self._handle, self._buffer, _GL_UNSIGNED_BYTE, 1, 1):
            raise BackendError("OSMesaMakeCurrent failed")
        return self

    def __exit__(self, *exc: object) -> None:
        """Leave the context current (OSMesa cannot restore another context's buffer)."""

    def load_opengl_function(self, name: str) -> int:
        return self._lib.OSMesaGetProcAddress(name.encode()) or 0

    def release(self) -> None:
        if self._handle:
            self._lib.OSMesaDestroyContext(self._handle)
            self._handle = None


def _create(backend: str) -> moderngl.Context:
    if backend == "egl":
        return moderngl.create_context(standalone=True, backend="egl", require=330)
    loader = _OSMesaLoader()
    moderngl.init_context(loader=loader)
    ctx = moderngl.get_context()
    ctx.extra = {"osmesa": loader}  # keep the OSMesa handle alive with the context
    return ctx


def create_context(backend: str | None = None) -> moderngl.Context:
    """A new headless moderngl context (GL >= 3.3 core).

    Parameters
    ----------
    backend
        ``"egl"``, ``"osmesa"`` or ``"auto"``; default: ``$GLSLDIFF_GL`` or ``"egl"``.

    Raises
    ------
    BackendError
        The backend name is unknown, or no context could be created; the message says
        which libraries to install.
    """
    name = (backend or os.environ.get("GLSLDIFF_GL") or "egl").strip().lower()
    if name not in BACKENDS:
        raise BackendError(f"unknown GL backend {name!r} (GLSLDIFF_GL); choose one of {BACKENDS}")
    tries = ("egl", "osmesa") if name == "auto" else (name,)
    errors = []
    for b in tries:
        try:
            ctx = _create(b)
        except BackendError as exc:
            errors.append(f"{b}: {exc}")
            continue
        except Exception as exc:  # moderngl/glcontext raise plain Exceptions
            errors.append(f"{b}: {exc}")
            continue
        if ctx.version_code < 330:
            errors.append(f"{b}: OpenGL {ctx.version_code} < 3.3")
            ctx.release()
            continue
        ctx.glsldiff_backend = b
        logger.info("GL context: %s via %s", renderer(ctx), b)
        return ctx
    raise BackendError("no headless OpenGL context could be created (" + "; ".join(errors)
                       + f"); {INSTALL_HINT}")


@lru_cache(maxsize=None)
def _shared(backend: str) -> moderngl.Context:
    return create_context(backend)


def get_context(backend: str | None = None) -> moderngl.Context:
    """The process-wide shared context for ``backend`` (created on first use)."""
    return _shared((backend or os.environ.get("GLSLDIFF_GL") or "egl").strip().lower())


def make_current(ctx: moderngl.Context) -> None:
    """Make ``ctx`` the current GL context of this thread (several may coexist)."""
    ctx.mglo.__enter__()


def renderer(ctx: moderngl.Context) -> str:
    """Renderer string, e.g. ``"llvmpipe (LLVM 15.0.6, 256 bits)"``."""
    return str(ctx.info.get("GL_RENDERER", "unknown"))


def describe(ctx: moderngl.Context) -> str:
    """``"<renderer> (GL <version>, <backend>)"`` for reports."""
    return f"{renderer(ctx)} (GL {ctx.version_code}, {getattr(ctx, 'glsldiff_backend', '?')})"


# ---- shaders --------------------------------------------------------------------
def shader_dir() -> Path:
    """The folder holding the GLSL sources (installed package data or the checkout)."""
    try:
        path = Path(str(importlib.resources.files("glsldiff.shaders")))
        if path.is_dir():
            return path
    except ModuleNotFoundError:
        pass
    return Path(__file__).resolve().parent.parent / "shaders"


_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.M)


def shader_source(name: str, defines: Mapping[str, Any] | None = None) -> str:
    """Read ``shaders/<name>`` with includes expanded and ``defines`` after ``#version``."""
    root = shader_dir()

    def read(fname: str, stack: tuple[str, ...]) -> str:
        if fname in stack:
            raise GlsldiffError(f"shader include cycle: {' -> '.join(stack + (fname,))}")
        path = root / fname
        if not path.is_file():
            raise GlsldiffError(f"shader {fname!r} not found in {root}")
        return _INCLUDE.sub(lambda m: read(m.group(1), stack + (fname,)), path.read_text())

    src = read(name, ())
    lines = src.splitlines()
    head = [f"#define {k} {v}" for k, v in (defines or {}).items()]
    if lines and lines[0].startswith("#version"):
        return "\n".join([lines[0], *head, *lines[1:]]) + "\n"
    return "\n".join(head + lines) + "\n"


def program(ctx: moderngl.Context, vertex: str, fragment: str,
            defines: Mapping[str, Any] | None = None) -> moderngl.Program:
    """Compile and link ``shaders/<vertex>`` + ``shaders/<fragment>``."""
    try:
        return ctx.program(vertex_shader=shader_source(vertex, defines),
                           fragment_shader=shader_source(fragment, defines))
    except moderngl.Error as exc:
        raise GlsldiffError(f"compiling {vertex}/{fragment} failed: {exc}") from exc


# ---- textures and framebuffers --------------------------------------------------
def float_texture(ctx: moderngl.Context, size: tuple[int, int], data: NDArray | None = None,
                  components: int = 4, precision: str = "fp32") -> moderngl.Texture:
    """A nearest-filtered float texture (``precision`` ``"fp32"`` or ``"fp16"``)."""
    if precision not in DTYPES:
        raise GlsldiffError(f"precision={precision!r}; choose one of {tuple(DTYPES)}")
    dtype = DTYPES[precision]
    raw = None if data is None else np.ascontiguousarray(data, dtype=np.dtype(dtype)).tobytes()
    tex = ctx.texture(size, components, raw, dtype=dtype, alignment=1)
    tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
    tex.repeat_x = tex.repeat_y = False
    return tex


@dataclass
class PingPong:
    """Two same-sized float render targets; a pass reads ``src`` and writes ``dst``."""

    textures: tuple[moderngl.Texture, moderngl.Texture]
    framebuffers: tuple[moderngl.Framebuffer, moderngl.Framebuffer]
    index: int = 0

    @classmethod
    def create(cls, ctx: moderngl.Context, size: tuple[int, int], precision: str = "fp32",
               components: int = 4) -> "PingPong":
        texs = tuple(float_texture(ctx, size, components=components, precision=precision)
                     for _ in range(2))
        fbos = tuple(ctx.framebuffer(color_attachments=[t]) for t in texs)
        for f in fbos:
            f.clear(0.0, 0.0, 0.0, 0.0)
        return cls(texs, fbos)  # type: ignore[arg-type]

    @property
    def src(self) -> moderngl.Texture:
        return self.textures[self.index]

    @property
    def dst(self) -> moderngl.Framebuffer:
        return self.framebuffers[1 - self.index]

    @property
    def size(self) -> tuple[int, int]:
        return self.textures[0].size

    @property
    def dtype(self) -> str:
        return self.textures[0].dtype

    def swap(self) -> None:
        self.index = 1 - self.index

    def read(self, which: str = "src", size: tuple[int, int] | None = None) -> NDArray[np.float32]:
        """``(height, width, components)`` float32 copy of ``src`` or ``dst`` (the lower-left
        ``size`` texels only when given: a level of a shared buffer)."""
        tex = self.src if which == "src" else self.textures[1 - self.index]
        w, h = tex.size
        dtype = tex.dtype
        arr = np.frombuffer(tex.read(alignment=1), dtype=np.dtype(dtype)).reshape(h, w, tex.components)
        if size is not None:
            arr = arr[:size[1], :size[0]]
        return arr.astype(np.float32)

    def write(self, data: NDArray, which: str = "src") -> None:
        """Write ``(height, width, components)`` data at texel (0, 0) (a sub-region when smaller)."""
        tex = self.src if which == "src" else self.textures[1 - self.index]
        arr = np.ascontiguousarray(data, dtype=np.dtype(tex.dtype))
        tex.write(arr.tobytes(), viewport=(0, 0, arr.shape[1], arr.shape[0]), alignment=1)

    def release(self) -> None:
        for obj in (*self.framebuffers, *self.textures):
            obj.release()
