"""GL contexts: ``create_context()`` is the only place a context is made.

The backend comes from the argument or the environment variable ``GLSLDIFF_GL``:

``egl`` (default)
    moderngl's standalone EGL context (Mesa llvmpipe on a CPU machine, the GPU on an
    NVIDIA machine with its driver).
``osmesa``
    Mesa's off-screen renderer through ctypes (moderngl has no OSMesa backend):
    ``OSMesaCreateContextAttribs`` for a 3.3 core profile, then
    ``moderngl.init_context`` with ``OSMesaGetProcAddress`` as the loader.
``auto``
    EGL, then OSMesa.
"""
from __future__ import annotations

import ctypes
import logging
import os
from functools import lru_cache

import moderngl

from glsldiff.core.errors import BackendError

logger = logging.getLogger(__name__)

BACKENDS = ("egl", "osmesa", "auto")
INSTALL_HINT = ("install Mesa's headless GL libraries, e.g. on Debian/Ubuntu: "
                "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 "
                "(on an NVIDIA machine the driver's libEGL_nvidia provides EGL)")

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


