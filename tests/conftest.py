"""Shared fixtures for the glsldiff tests: GL contexts, GL error checks, the ``slow`` marker.

GL contexts
-----------
``ctx``
    The process-wide context of ``$GLSLDIFF_GL`` (``glsldiff.gl.get_context()``).
``bctx``
    The context of one named backend, parametrized over ``BACKENDS`` (tests that use it run
    once per backend; a backend that cannot be created is skipped).

Both are checked around every test that uses them: the fixture makes the context current
(``gl.make_current``; several contexts coexist in one process) and ``ctx.error`` must be
``GL_NO_ERROR`` when the test starts (fixture setup) and when its body has finished. The second
check runs inside the call phase (``pytest_runtest_call`` below) and raises :class:`GLStateError`
(not an ``AssertionError``, so a GL-state failure is told apart from a numerical one); so does
a test that leaves a released framebuffer as moderngl's bound one (``ctx.fbo``).

Tests are grouped per backend: all tests of the ``$GLSLDIFF_GL`` backend run first and the
other backend's tests run last, as one group (one context switch). Contexts are the shared
``gl.get_context(name)`` ones, never re-created per module. No framebuffer is bound by the
fixtures: ``GlslDiffusion.sweep()`` restores the caller's framebuffer, so a released solver
leaves nothing bound that a later test could trip over (test_diffusion.py checks this).
"""
from __future__ import annotations

import os

import moderngl
import numpy as np
import pytest

from glsldiff import gl
from glsldiff.core.errors import BackendError
from glsldiff.grids.polygrid import build_polygrid
from glsldiff.mesh import sphere_mesh

BACKENDS = ("egl", "osmesa")

# Tests never read or write the user's cache, even with $GLSLDIFF_CACHE set (test_hardening.py
# and test_fem_render.py test the cache in a tmp folder).
os.environ["GLSLDIFF_CACHE"] = "off"


class GLStateError(Exception):
    """The GL error flag was set after a test body (not an AssertionError on purpose)."""


def default_backend() -> str:
    return (os.environ.get("GLSLDIFF_GL") or "egl").strip().lower()


# ---- markers and ordering ---------------------------------------------------------------
def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "slow: long-running test (deselect with -m 'not slow')")


def _backend_of(item: pytest.Item) -> str | None:
    callspec = getattr(item, "callspec", None)
    return None if callspec is None else callspec.params.get("backend")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Run the tests of the non-default GL backend last, grouped per backend (see module doc)."""
    default = default_backend()

    def key(item: pytest.Item) -> int:
        b = _backend_of(item)
        return 0 if b is None or b == default else 1 + BACKENDS.index(b)

    items.sort(key=key)  # stable: keeps pytest's order inside each group


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item):
    """After the test body: the GL error flag of the context it used must be clear."""
    try:
        result = yield
    except BaseException:
        c = getattr(item, "_glsldiff_ctx", None)
        if c is not None:
            gl.make_current(c)
            c.error  # read (and so clear) the flag: a failing test must not break the next one
        raise
    c = getattr(item, "_glsldiff_ctx", None)
    if c is not None:
        gl.make_current(c)  # read the flag of the test's context, whichever is current now
        err = c.error
        if err != "GL_NO_ERROR":
            raise GLStateError(f"{err} after the test body ({gl.describe(c)})")
        if c.fbo is not None and isinstance(c.fbo.mglo, moderngl.InvalidObject):
            raise GLStateError("a released framebuffer is still moderngl's bound framebuffer "
                               "(ctx.fbo) after the test body; the next ctx.framebuffer() or "
                               "GlslDiffusion.sweep() would use it")
    return result


# ---- contexts ---------------------------------------------------------------------------
def _open(name: str):
    try:
        c = gl.get_context(name)
    except BackendError as exc:
        pytest.skip(f"GL backend {name!r} unavailable: {exc}")
    gl.make_current(c)
    assert c.error == "GL_NO_ERROR", f"the shared {name} context reports a GL error before any test"
    return c


def _checked(c, request: pytest.FixtureRequest):
    gl.make_current(c)
    assert c.error == "GL_NO_ERROR", "GL error flag set before the test started"
    request.node._glsldiff_ctx = c
    return c


@pytest.fixture(scope="session")
def _default_context():
    return _open(default_backend())


@pytest.fixture
def ctx(_default_context, request: pytest.FixtureRequest):
    """The ``$GLSLDIFF_GL`` context, made current, GL error flag checked before and after the test."""
    return _checked(_default_context, request)


@pytest.fixture(scope="session", params=BACKENDS)
def backend(request: pytest.FixtureRequest) -> str:
    """A GL backend name (tests using it run once per backend)."""
    return request.param


@pytest.fixture(scope="session")
def _backend_context(backend: str):
    return _open(backend)


@pytest.fixture
def bctx(_backend_context, request: pytest.FixtureRequest):
    """The shared context of ``backend``, made current, GL error flag checked before and after
    the test."""
    return _checked(_backend_context, request)


# ---- helpers shared by several test files ------------------------------------------------
def _smooth_kappa(shape: tuple[int, int, int], seed: int, k0: float = 0.01,
                  contrast: float = 100.0, sigma: float = 2.5) -> np.ndarray:
    """Smooth random kappa ``shape + (3,)``: ``k0 * contrast**f``, f = Gaussian-filtered white
    noise (``sigma`` nodes) rescaled to [0, 1] per channel, so max/min = ``contrast`` exactly."""
    from scipy import ndimage

    noise = np.random.default_rng(seed).standard_normal(tuple(shape) + (3,))
    f = ndimage.gaussian_filter(noise, (sigma, sigma, sigma, 0))
    lo, hi = f.min(axis=(0, 1, 2)), f.max(axis=(0, 1, 2))
    return k0 * contrast ** ((f - lo) / (hi - lo))


@pytest.fixture(scope="session")
def smooth_kappa():
    """The :func:`_smooth_kappa` generator (smooth log-normal-ish kappa with exact contrast)."""
    return _smooth_kappa


# ---- built grids shared by several test files (session scope: built once per run) ----------
@pytest.fixture(scope="session")
def sphere_polygrid():
    """The polygrid of a 10 mm icosphere (subdivisions 4): n = 6 nodes per cube edge, 5 mm cubes."""
    return build_polygrid(sphere_mesh(10.0, subdivisions=4), n=6, cube_size=5.0)


@pytest.fixture(scope="session")
def fem_system():
    """The gather-solver tests' P1 system (tests/gather_systems.py): a 10 mm sphere, subdivisions
    3, n = 3 nodes per 5 mm cube edge (1376 unknowns), kappa and mu different per channel."""
    from gather_systems import p1_system
    return p1_system(3, 3)
