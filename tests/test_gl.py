"""Tests for glsldiff.gl: headless contexts (EGL, OSMesa, auto), shader sources, float textures,
ping-pong buffers, and the real GL rasterisation of a regular grid's pass primitives.

References: the glsldiff.gl module docstring (backends, ``#include`` and ``defines`` rules),
the OpenGL 3.3 core rasterisation rules (pixel centres, exact float32/float16 storage).
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import moderngl
import numpy as np
import pytest

from glsldiff import gl
from glsldiff.core.errors import BackendError, GlsldiffError
from glsldiff.grids.regular import RegularGrid
from glsldiff.packing import primitive_vertices
from glsldiff.solve.stencil import PASSES, pass_primitives

REPO = Path(__file__).resolve().parents[1]


def _run_python(code: str, env_gl: str | None) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (a new GL context there cannot disturb this process's)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH")) if p)
    env.pop("GLSLDIFF_GL", None)
    if env_gl is not None:
        env["GLSLDIFF_GL"] = env_gl
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=120)


# ---------------------------------------------------------------- contexts
def test_backend_context(bctx, backend):
    """Each backend gives a GL >= 3.3 context with a renderer string; get_context shares it."""
    assert bctx.version_code >= 330
    assert gl.renderer(bctx).strip() not in ("", "unknown")
    assert bctx.glsldiff_backend == backend
    assert backend in gl.describe(bctx) and str(bctx.version_code) in gl.describe(bctx)
    assert gl.get_context(backend) is bctx


def test_default_context_follows_env(ctx):
    """get_context() with no argument is the $GLSLDIFF_GL (default egl) shared context."""
    want = (os.environ.get("GLSLDIFF_GL") or "egl").strip().lower()
    assert gl.get_context() is ctx is gl.get_context(want)
    if want != "auto":
        assert ctx.glsldiff_backend == want


_PROBE = ("from glsldiff import gl, BackendError\n"
          "try:\n"
          "    c = gl.create_context({arg})\n"
          "except BackendError as e:\n"
          "    print('UNAVAILABLE', e)\n"
          "else:\n"
          "    print('OK', c.glsldiff_backend, c.version_code, c.error, gl.renderer(c))\n")


@pytest.mark.parametrize("env_gl, arg, allowed", [
    ("auto", "", {"egl", "osmesa"}),       # EGL, then OSMesa
    (None, "", {"egl"}),                    # default: egl
    (" OSMesa ", "", {"osmesa"}),          # env value is stripped and lower-cased
    ("bogus", "'osmesa'", {"osmesa"}),     # an explicit argument wins over the env var
    (None, "'AUTO'", {"egl", "osmesa"}),
], ids=["env-auto", "env-unset", "env-OSMesa", "arg-over-env", "arg-AUTO"])
def test_backend_selection_in_fresh_process(env_gl, arg, allowed):
    """Backend choice from the argument / $GLSLDIFF_GL, checked in a fresh interpreter."""
    out = _run_python(_PROBE.format(arg=arg), env_gl)
    assert out.returncode == 0, out.stderr
    line = out.stdout.strip().splitlines()[-1]
    if line.startswith("UNAVAILABLE"):
        pytest.skip(line)
    tag, name, version, err, *renderer = line.split()
    assert tag == "OK" and name in allowed and int(version) >= 330 and err == "GL_NO_ERROR"
    assert renderer, "empty renderer string"


@pytest.mark.parametrize("arg, named", [("vulkan", "vulkan"), ("GLX", "glx"), ("egl2", "egl2"),
                                        (None, "bogus")])
def test_unknown_backend_is_backend_error(arg, named, monkeypatch):
    """An unknown backend name (argument, else $GLSLDIFF_GL=bogus) is a BackendError naming it and
    listing the valid ones; no context is made."""
    monkeypatch.setenv("GLSLDIFF_GL", "bogus")
    with pytest.raises(BackendError, match=rf"unknown GL backend '{named}' \(GLSLDIFF_GL\); "
                                           r"choose one of \('egl', 'osmesa', 'auto'\)"):
        gl.create_context(arg)


_TWO_CONTEXTS = """
import logging
import numpy as np
from glsldiff import gl, BackendError
from glsldiff.grids.regular import RegularGrid
from glsldiff.system.problem import DiffusionProblem, relative_l2
from glsldiff.solve.jacobi import solve_glsl
from glsldiff.oracle.solvers import solve_direct

logging.disable(logging.WARNING)
try:
    a = gl.create_context({a!r})
    b = gl.create_context({b!r})   # now the current context
except BackendError as e:
    print("UNAVAILABLE", e)
    raise SystemExit(0)
p = DiffusionProblem(RegularGrid(7, 6, 5, 0.5), 0.3, 0.5, {{"z-": 1.0}})
ref, _ = solve_direct(p)
if {use_with!r}:
    with a:                        # moderngl: make `a` current for this block
        phi, rep = solve_glsl(p, a, tol=1e-7)
else:                              # GlslDiffusion makes its own context current
    phi, rep = solve_glsl(p, a, tol=1e-7)
gl.make_current(a)
err = a.error
gl.make_current(b)
print("OK", relative_l2(phi, ref), err, b.error, rep.status)
"""


@pytest.mark.parametrize("use_with", [True, False], ids=["with-ctx", "solver-makes-current"])
@pytest.mark.parametrize("first, second", [("egl", "osmesa"), ("osmesa", "egl")],
                         ids=["egl-then-osmesa", "osmesa-then-egl"])
def test_older_context_can_be_made_current_again(first, second, use_with):
    """With two contexts in one process, ``with ctx:`` (also for OSMesa, whose loader now has
    ``__enter__``) or GlslDiffusion itself (gl.make_current) makes the older one current again, and
    a solve on it matches the direct solve with no GL error on either context (fresh interpreter).
    Measured: rel L2 ~1e-7, status converged or stalled at the fp32 floor."""
    out = _run_python(_TWO_CONTEXTS.format(a=first, b=second, use_with=use_with), None)
    assert out.returncode == 0, out.stderr[-2000:]
    line = out.stdout.strip().splitlines()[-1]
    if line.startswith("UNAVAILABLE"):
        pytest.skip(line)
    tag, err_l2, gl_err_a, gl_err_b, status = line.split()
    print(f"{first} then {second}, with={use_with}: {status}, rel L2 {float(err_l2):.1e}")
    assert tag == "OK" and float(err_l2) < 1e-5 and gl_err_a == gl_err_b == "GL_NO_ERROR"
    assert status in ("converged", "stalled")


# ---------------------------------------------------------------- shader sources
@pytest.mark.parametrize("name", ["stencil.frag", "transfer.frag", "stencil.vert"])
def test_shader_source_expands_includes_and_defines(name):
    """``#include`` lines are replaced by the file; defines follow the ``#version`` line."""
    src = gl.shader_source(name, {"STENCIL_PAPER": 1, "FACE_HARMONIC": 0})
    lines = src.splitlines()
    assert lines[0] == "#version 330 core"
    assert lines[1:3] == ["#define STENCIL_PAPER 1", "#define FACE_HARMONIC 0"]
    assert "#include" not in src
    assert src.count("#version") == 1
    if name.endswith(".frag"):
        common = (gl.shader_dir() / "diffusion.glsl").read_text()
        assert common.strip() in src
        assert "uniform sampler2D u_state;" in src


def test_shader_include_rules(tmp_path, monkeypatch):
    """Nested includes expand recursively; a cycle or a missing file is a GlsldiffError;
    without ``#version`` the defines are prepended."""
    (tmp_path / "a.glsl").write_text('#version 330 core\n#include "b.glsl"\nvoid main() {}\n')
    (tmp_path / "b.glsl").write_text('  #include "c.glsl"  \nfloat b;\n')
    (tmp_path / "c.glsl").write_text("float c;\n")
    (tmp_path / "plain.glsl").write_text("float p;\n")
    (tmp_path / "loop1.glsl").write_text('#include "loop2.glsl"\n')
    (tmp_path / "loop2.glsl").write_text('#include "loop1.glsl"\n')
    (tmp_path / "missing.glsl").write_text('#include "nope.glsl"\n')
    monkeypatch.setattr(gl.programs, "shader_dir", lambda: tmp_path)
    lines = gl.shader_source("a.glsl", {"X": 2}).splitlines()
    assert [ln for ln in lines if ln.strip()] == [
        "#version 330 core", "#define X 2", "float c;", "float b;", "void main() {}"]
    assert gl.shader_source("plain.glsl", {"Y": "1.5"}) == "#define Y 1.5\nfloat p;\n"
    with pytest.raises(GlsldiffError, match=r"include cycle: loop1.glsl -> loop2.glsl -> loop1.glsl"):
        gl.shader_source("loop1.glsl")
    with pytest.raises(GlsldiffError, match=r"shader 'nope.glsl' not found"):
        gl.shader_source("missing.glsl")


@pytest.mark.parametrize("paper", [0, 1])
@pytest.mark.parametrize("harmonic", [0, 1])
@pytest.mark.parametrize("uniform", [0, 1])
def test_programs_compile_for_every_variant(bctx, paper, harmonic, uniform):
    """The interior and boundary rows, as sweep and as residual, compile and link for each
    stencil / face-mean / weight define and expose their uniforms."""
    progs = {(row, res): gl.program(bctx, "stencil.vert", "stencil.frag",
                                    {"STENCIL_PAPER": paper, "FACE_HARMONIC": harmonic, "UNIFORM_WEIGHTS": uniform,
                                     "ROW_BOUNDARY": row, "RESIDUAL": res})
             for row in (0, 1) for res in (0, 1)}
    try:
        for prog in progs.values():
            for u in ("u_state", "u_kappa", "u_size"):
                assert u in prog
        for res in (0, 1):
            assert "u_mu" in progs[0, res] and ("u_w1" in progs[0, res]) == (not uniform)
            assert ("u_scale" in progs[0, res]) == bool(uniform)
            assert "u_C" in progs[1, res] and ("u_d" in progs[1, res]) == bool(uniform)
        assert "u_q" in progs[1, 0] and "u_q" in progs[1, 1]
    finally:
        for prog in progs.values():
            prog.release()


def test_program_compile_error_is_glsldiff_error(bctx, tmp_path, monkeypatch):
    """A shader that does not compile raises GlsldiffError naming the files."""
    (tmp_path / "v.vert").write_text("#version 330 core\nvoid main() { gl_Position = vec4(0.0); }\n")
    (tmp_path / "bad.frag").write_text("#version 330 core\nout vec4 f;\nvoid main() { f = nonsense; }\n")
    monkeypatch.setattr(gl.programs, "shader_dir", lambda: tmp_path)
    with pytest.raises(GlsldiffError, match=r"compiling v.vert/bad.frag failed"):
        gl.program(bctx, "v.vert", "bad.frag")


# ---------------------------------------------------------------- textures and ping-pong
@pytest.mark.parametrize("precision, np_dtype", [("fp32", np.float32), ("fp16", np.float16)])
def test_pingpong_write_read_round_trip(bctx, precision, np_dtype):
    """PingPong stores exactly what is written (after rounding to the buffer precision);
    swap() exchanges src and dst."""
    size = (7, 5)  # odd width: rows are not 4-byte aligned in fp16
    rng = np.random.default_rng(3)
    a = rng.uniform(-100, 100, (5, 7, 4)).astype(np.float32)
    b = rng.uniform(-1, 1, (5, 7, 4)).astype(np.float32)
    pp = gl.PingPong.create(bctx, size, precision)
    try:
        assert pp.src.dtype == gl.DTYPES[precision]
        np.testing.assert_array_equal(pp.read(), 0.0)  # cleared on creation
        np.testing.assert_array_equal(pp.read("dst"), 0.0)
        pp.write(a)
        pp.write(b, "dst")
        want_a = a.astype(np_dtype).astype(np.float32)
        want_b = b.astype(np_dtype).astype(np.float32)
        np.testing.assert_array_equal(pp.read(), want_a)
        np.testing.assert_array_equal(pp.read("dst"), want_b)
        src_before, dst_before = pp.src, pp.dst
        pp.swap()
        np.testing.assert_array_equal(pp.read(), want_b)
        assert pp.dst.color_attachments[0] is src_before
        assert pp.src is dst_before.color_attachments[0]
    finally:
        pp.release()


def test_float_texture_rejects_unknown_precision(bctx):
    """float_texture(precision='fp64') is a GlsldiffError listing the choices."""
    with pytest.raises(GlsldiffError, match=r"precision='fp64'; choose one of \('fp32', 'fp16'\)"):
        gl.float_texture(bctx, (2, 2), precision="fp64")


_COUNT_FS = """#version 330 core
flat in ivec2 v_off0;
flat in ivec2 v_off4;
layout(location = 0) out vec4 f_color;
void main() { f_color = vec4(1.0, float(v_off0.x), float(v_off0.y), float(4096 * v_off4.x + v_off4.y)); }
"""


@pytest.mark.parametrize("shape", [(5, 7, 11), (3, 3, 3), (40, 3, 17)], ids=lambda s: "x".join(map(str, s)))
def test_gl_rasterises_grid_primitives_once_per_texel(bctx, shape):
    """With additive blending, stencil.vert + the quads, lines and points of pass_primitives hit
    every interior texel exactly once (interior pass) and every boundary texel exactly once
    (boundary pass), with that node's own offsets (x- and z- neighbour; interior partner);
    inactive texels and padding get nothing."""
    g = RegularGrid(*shape)
    w, h = g.texture_size
    graph, mosaic = g.graph, g.mosaic
    prog = bctx.program(vertex_shader=gl.shader_source("stencil.vert"), fragment_shader=_COUNT_FS)
    prog["u_size"] = (float(w), float(h))
    tex = gl.float_texture(bctx, (w, h))
    fbo = bctx.framebuffer(color_attachments=[tex])
    objs = [prog, fbo, tex]
    attrs = ("in_pos", "in_off0", "in_off1", "in_off2", "in_off3", "in_off4", "in_off5")
    fmt = " ".join(f if a in prog else "8x" for a, f in zip(attrs, ("2f",) + ("2i",) * 6))
    modes = {"triangles": moderngl.TRIANGLES, "lines": moderngl.LINES, "points": moderngl.POINTS}
    before = bctx.fbo  # rebound before fbo is released (never leave a deleted framebuffer bound)
    try:
        for name, prims in zip(PASSES, pass_primitives(g).values()):
            fbo.clear(0.0, 0.0, 0.0, 0.0)
            fbo.use()
            bctx.enable(moderngl.BLEND)
            bctx.blend_func = moderngl.ONE, moderngl.ONE
            try:
                for mode, verts in primitive_vertices(prims).items():
                    if len(verts):
                        vbo = bctx.buffer(verts.tobytes())
                        vao = bctx.vertex_array(prog, [(vbo, fmt, *(a for a in attrs if a in prog))])
                        objs += [vao, vbo]
                        vao.render(modes[mode])
            finally:
                bctx.disable(moderngl.BLEND)
                bctx.blend_func = moderngl.DEFAULT_BLENDING
            out = np.frombuffer(tex.read(), dtype=np.float32).reshape(h, w, 4)
            nodes = graph.interior if name == "interior" else graph.boundary
            t = mosaic.texel(nodes)
            want = np.zeros((h, w, 4), np.float32)
            if name == "interior":
                off0 = mosaic.texel(graph.neighbours[:, 0]) - t
                off4 = mosaic.texel(graph.neighbours[:, 4]) - t
            else:
                off0, off4 = mosaic.texel(graph.link) - t, np.zeros_like(t)
            want[t[:, 1], t[:, 0]] = np.column_stack([np.ones(len(t)), off0, 4096 * off4[:, 0] + off4[:, 1]])
            np.testing.assert_array_equal(out, want)
    finally:
        (before if before is not None else bctx.detect_framebuffer(0)).use()
        for o in reversed(objs):
            o.release()
