"""Malformed input and unavailable backends: each raises the specific GlsldiffError subclass with a
message that names the offending field (and, for backends, says what to install).

Reference: the validation rules documented in glsldiff.grids.regular, glsldiff.system.problem, glsldiff.physics.material,
glsldiff.solve.jacobi and glsldiff.gl.
"""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff import gl
from glsldiff.gl import context as glctx
from glsldiff.solve.jacobi import GlslDiffusion
from glsldiff.core.errors import BackendError, GlsldiffError, InputError
from glsldiff.grids.regular import RegularGrid
from glsldiff.system.problem import DiffusionProblem

G = RegularGrid(6, 5, 4, 0.5)
S = G.shape  # (nz, ny, nx) = (4, 5, 6)


def _with(arr: np.ndarray, index: tuple, value: float) -> np.ndarray:
    out = np.array(arr, dtype=float)
    out[index] = value
    return out


# ---------------------------------------------------------------- problem fields
BAD_PROBLEMS = [
    ("nan-kappa", dict(kappa=_with(np.full(S, 0.3), (1, 2, 3), np.nan)), r"kappa has \d+ NaN value\(s\) at e\.g\. index \(1, 2, 3"),
    ("inf-kappa", dict(kappa=_with(np.full(S + (3,), 0.3), (0, 1, 1, 2), np.inf)), r"kappa has 1 inf value\(s\)"),
    ("zero-kappa", dict(kappa=_with(np.full(S, 0.3), (2, 2, 2), 0.0)), r"kappa must be > 0 but has \d+ value\(s\) violating it \(e\.g\. 0\)"),
    ("negative-kappa", dict(kappa=-0.3), r"kappa must be > 0"),
    ("negative-mu", dict(mu=_with(np.full(S, 0.1), (3, 1, 1), -1e-3)), r"mu must be >= 0 .*e\.g\. -0\.001"),
    ("nan-mu", dict(mu=[0.1, np.nan, 0.1]), r"mu has \d+ NaN value\(s\)"),
    ("mu-shape", dict(mu=np.zeros((4, 5, 7))), r"mu has shape \(4, 5, 7\); the grid needs"),
    ("kappa-shape", dict(kappa=np.ones((5, 4, 6))), r"kappa has shape \(5, 4, 6\); the grid needs"),
    ("kappa-channels", dict(kappa=np.ones(S + (2,))), r"kappa has shape \(4, 5, 6, 2\)"),
    ("inf-q-face", dict(q={"z-": _with(np.ones(G.face_shape("z-")), (1, 1), np.inf)}), r"q has 3 non-finite values"),
    ("nan-q-volume", dict(q=_with(np.zeros(S), (0, 2, 2), np.nan)), r"q has 3 non-finite values \(e\.g\. x=2, y=2, z=0"),
    ("q-face-shape", dict(q={"x+": np.ones((3, 3))}), r"face 'x\+' array has shape \(3, 3\), expected \(2, 3\)"),
    ("q-unknown-face", dict(q={"w+": 1.0}), r"unknown face 'w\+'; valid faces: x-, x\+, y-, y\+, z-, z\+"),
    ("q-interior", dict(q=_with(np.zeros(S), (1, 2, 2), 1.0)), r"q is non-zero at 1 nodes that are not boundary nodes \(e\.g\. x=2, y=2, z=1\)"),
    ("q-edge", dict(q=_with(np.zeros(S), (0, 0, 3), 1.0)), r"q is non-zero at 1 nodes that are not boundary nodes \(e\.g\. x=3, y=0, z=0\)"),
    ("q-volume-shape", dict(q=np.zeros((4, 5))), r"q has shape \(4, 5\); expected \(4, 5, 6\)"),
    ("stencil", dict(stencil="fem"), r"stencil='fem'; choose one of \('paper', 'conservative'\)"),
    ("face-mean", dict(stencil="conservative", face_mean="geometric"), r"face_mean='geometric'; choose one of"),
    ("eta", dict(eta=0.0), r"eta=0\.0 must be a finite relative index > 0"),
    ("C", dict(C=-1.0), r"C=-1\.0 must be finite and > 0"),
    ("grid-type", dict(grid=(6, 5, 4)), r"grid must be a RegularGrid or a Polygrid, got tuple"),
]


@pytest.mark.parametrize("overrides, match", [p[1:] for p in BAD_PROBLEMS], ids=[p[0] for p in BAD_PROBLEMS])
def test_bad_problem_is_input_error(overrides, match):
    """DiffusionProblem rejects the field with an InputError (a ValueError) naming it."""
    kwargs = dict(grid=G, kappa=0.3, mu=0.1, q={"z-": 1.0})
    kwargs.update(overrides)
    with pytest.raises(InputError, match=match) as info:
        DiffusionProblem(**kwargs)
    assert isinstance(info.value, GlsldiffError) and isinstance(info.value, ValueError)


# ---------------------------------------------------------------- grid fields
BAD_GRIDS = [
    ("nz=2", dict(nx=6, ny=5, nz=2), r"grid nz=2: a block needs at least 3 nodes per axis .*empty"),
    ("nx=0", dict(nx=0, ny=5, nz=4), r"grid nx=0"),
    ("ny-float", dict(nx=6, ny=5.0, nz=4), r"grid ny must be an integer, got 5\.0"),
    ("nx-bool", dict(nx=True, ny=5, nz=4), r"grid nx must be an integer, got True"),
    ("h=0", dict(nx=6, ny=5, nz=4, h=0.0), r"grid spacing h=0\.0 mm must be a finite number > 0"),
    ("h<0", dict(nx=6, ny=5, nz=4, h=-0.1), r"grid spacing h=-0\.1 mm"),
    ("h=nan", dict(nx=6, ny=5, nz=4, h=float("nan")), r"grid spacing h=nan mm"),
    ("h=inf", dict(nx=6, ny=5, nz=4, h=float("inf")), r"grid spacing h=inf mm"),
    ("h-str", dict(nx=6, ny=5, nz=4, h="1"), r"grid spacing h='1' mm"),
]


@pytest.mark.parametrize("kwargs, match", [p[1:] for p in BAD_GRIDS], ids=[p[0] for p in BAD_GRIDS])
def test_bad_grid_is_input_error(kwargs, match):
    """RegularGrid rejects empty grids, non-integer sizes and non-positive / non-finite spacing."""
    with pytest.raises(InputError, match=match):
        RegularGrid(**kwargs)


# ---------------------------------------------------------------- solver options
def test_unknown_precision_is_input_error(ctx):
    """GlslDiffusion(precision='fp64') is an InputError listing fp32, fp16 and paper."""
    p = DiffusionProblem(G, 0.3, 0.1, {"z-": 1.0})
    with pytest.raises(InputError, match=r"precision='fp64'; choose one of \('fp32', 'fp16', 'paper'\)"):
        GlslDiffusion(p, ctx, precision="fp64")


@pytest.mark.parametrize("kwargs, match", [
    (dict(check_every=0), r"check_every must be >= 1"),
    (dict(maxiter=-1), r"maxiter >= 0"),
])
def test_bad_solve_options_are_input_errors(ctx, kwargs, match):
    """solve(check_every=0) / solve(maxiter=-1) are InputErrors."""
    p = DiffusionProblem(G, 0.3, 0.1, {"z-": 1.0})
    with GlslDiffusion(p, ctx) as solver:
        with pytest.raises(InputError, match=match):
            solver.solve(**kwargs)


# ---------------------------------------------------------------- GL backends
@pytest.mark.parametrize("call", ["create_context", "get_context"])
def test_bogus_env_backend_is_backend_error(monkeypatch, call):
    """GLSLDIFF_GL=bogus: create_context() / get_context() raise BackendError naming the variable."""
    monkeypatch.setenv("GLSLDIFF_GL", "bogus")
    with pytest.raises(BackendError, match=r"unknown GL backend 'bogus' \(GLSLDIFF_GL\); choose one of "
                                           r"\('egl', 'osmesa', 'auto'\)"):
        getattr(gl, call)()


def _no_osmesa(name, *args, **kwargs):
    raise OSError(f"{name}: cannot open shared object file: No such file or directory")


def _no_egl(*args, **kwargs):
    raise Exception("libEGL.so: cannot open shared object file")  # what glcontext raises


def test_missing_osmesa_library_is_backend_error(monkeypatch):
    """No libOSMesa: BackendError saying which library is missing and the apt-get line."""
    monkeypatch.setattr(glctx.ctypes, "CDLL", _no_osmesa)
    with pytest.raises(BackendError, match=r"osmesa: OSMesa library not found .*libOSMesa\.so.*"
                                           r"apt-get install .*libosmesa6") as info:
        gl.create_context("osmesa")
    assert str(info.value).count("apt-get install") >= 1


def test_missing_egl_is_backend_error(monkeypatch):
    """moderngl/glcontext cannot open EGL: BackendError with the cause and the apt-get line."""
    monkeypatch.setattr(glctx.moderngl, "create_context", _no_egl)
    with pytest.raises(BackendError, match=r"egl: libEGL\.so: cannot open.*apt-get install .*libegl1"):
        gl.create_context("egl")


def test_auto_without_any_backend_lists_both(monkeypatch):
    """auto with neither EGL nor OSMesa: one BackendError listing both failures and the install hint."""
    monkeypatch.setattr(glctx.moderngl, "create_context", _no_egl)
    monkeypatch.setattr(glctx.ctypes, "CDLL", _no_osmesa)
    with pytest.raises(BackendError, match=r"no headless OpenGL context could be created \(egl: .*; "
                                           r"osmesa: OSMesa library not found.*apt-get install"):
        gl.create_context("auto")


class _FakeOSMesa:
    """A libOSMesa whose OSMesaCreateContextAttribs returns NULL (no GL 3.3 core profile)."""

    def __init__(self, *args, **kwargs):
        for name in ("OSMesaCreateContextAttribs", "OSMesaMakeCurrent", "OSMesaGetProcAddress",
                     "OSMesaDestroyContext"):
            fn = (lambda *a: 0)
            setattr(self, name, fn)


def test_osmesa_without_core_profile_is_backend_error(monkeypatch):
    """OSMesaCreateContextAttribs returning NULL is a BackendError with the install hint."""
    monkeypatch.setattr(glctx.ctypes, "CDLL", _FakeOSMesa)
    with pytest.raises(BackendError, match=r"OSMesaCreateContextAttribs failed \(no GL 3\.3 core\).*apt-get install"):
        gl.create_context("osmesa")


def test_old_gl_version_is_backend_error(monkeypatch):
    """A context below GL 3.3 is released and reported as a BackendError."""
    released = []

    class _OldContext:
        version_code = 210

        def release(self):
            released.append(True)

    monkeypatch.setattr(glctx.moderngl, "create_context", lambda *a, **k: _OldContext())
    with pytest.raises(BackendError, match=r"egl: OpenGL 210 < 3\.3.*apt-get install"):
        gl.create_context("egl")
    assert released == [True]
