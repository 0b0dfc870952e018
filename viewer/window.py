"""The interactive viewer and material editor: a pyglet window whose GL context moderngl shares,
the three-pass renderer drawing into it, and the section-5.4 editing operations under the mouse.

Why pyglet and not pyrender's viewer: pyrender's ``Viewer`` draws pyrender scenes with its own
shaders, so it cannot show the renderer's pass 3 (per-vertex multiple scattering from the
polygrid, Ward specular, single scattering, unscattered light) without re-implementing it; and
its PyOpenGL pin breaks on OSMesa. Its window layer is pyglet, which is used here directly:
``moderngl.create_context()`` attaches to the window's GL context, and the
:class:`~glsldiff.render.renderer.Renderer`, the solver and the GPU editor all run in it.

Controls (also in the overlay, H hides it):

=====================  ==========================================================
left drag              orbit the camera (trackball about the target)
right drag             turn the first directional light
scroll                 zoom
E                      edit mode on/off: the left button paints with the tool
K / O / V / D          tool: property (kappa, mu) / operation / value / depth window
M                      use the pattern mask (``--mask``) inside the brush
[ / ]                  brush radius
Ctrl+Z / Ctrl+Y        undo / redo (one step per stroke)
Ctrl+S                 save the edited material (``[material].nodes`` file)
F12 or P               screenshot (PNG)
Tab                    next scene preset
X                      re-expose (the exposure is otherwise fixed, so edits show)
Esc / Q                close
=====================  ==========================================================
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff import gl
from glsldiff.core import io
from glsldiff.core.errors import BackendError, GlsldiffError, InputError
from glsldiff.render.output import auto_exposure
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import Scene
from glsldiff.viewer.controls import Orbit, Tool, scene_orbit, turn_light, with_size
from glsldiff.viewer.overlay import draw_overlay, status_frame

#: Sweeps per frame while a warm-started pass 2 converges (frame coherence, section 5.3).
FRAME_SWEEPS = 10
INSTALL_HINT = ("the viewer needs an X display with OpenGL 3.3: on a desktop run it there; headless, install "
                "Xvfb and Mesa (apt-get install xvfb libgl1-mesa-dri libglx-mesa0) and run "
                "`xvfb-run -s '-screen 0 1280x1024x24' glsldiff view`; pyglet comes with pip install glsldiff[viewer]")


def open_window(width: int, height: int, caption: str) -> tuple[Any, Any]:
    """A visible pyglet window and the moderngl context on its GL context; a failed start is a
    :class:`BackendError` naming what to install."""
    try:
        import pyglet
    except ImportError as exc:
        raise BackendError(f"pyglet is not installed ({exc}); {INSTALL_HINT}") from None
    pyglet.options["debug_gl"] = False         # moderngl leaves GL errors pyglet would raise on
    pyglet.options["shadow_window"] = False
    import moderngl
    try:
        config = pyglet.gl.Config(major_version=3, minor_version=3, forward_compatible=True,
                                  double_buffer=True, depth_size=24)
        window = pyglet.window.Window(width, height, caption=caption, config=config, resizable=True, vsync=False)
    except Exception as exc:   # NoSuchDisplayException, NoSuchConfigException, ImportError of libGL/X11
        raise BackendError(f"cannot open a window ({type(exc).__name__}: {' '.join(str(exc).split())}); "
                           f"{INSTALL_HINT}") from None
    try:
        ctx = moderngl.create_context(require=330)
    except Exception as exc:
        window.close()
        raise BackendError(f"the window has no OpenGL 3.3 context ({exc}); {INSTALL_HINT}") from None
    ctx.glsldiff_backend = "window"
    return window, ctx


class Viewer:
    """A window showing ``presets`` (name, scene) rendered live, with the editing tools.

    Drive it with :meth:`run` (the event loop), or from a script or test with the window's
    events (``viewer.window.dispatch_event(...)``) and :meth:`step`.
    """

    def __init__(self, presets: Sequence[tuple[str, Scene]], width: int = 640, height: int = 480,
                 mask: NDArray[np.float32] | None = None, save_path: str | Path = "edited.npz",
                 shots: str | Path = ".", frame_sweeps: int = FRAME_SWEEPS,
                 log: Callable[[str], None] | None = None) -> None:
        if not presets:
            raise InputError("the viewer needs at least one scene")
        self.presets = list(presets)
        self.save_path, self.shots = Path(save_path), Path(shots)
        self.log = log or (lambda line: None)
        self.window, self.ctx = open_window(width, height, f"glsldiff: {self.presets[0][0]}")
        import moderngl
        self._gpu = gl.Resources()
        self.prog = self._gpu.add(gl.program(self.ctx, "quad.vert", "copy.frag"))
        self._quad_size: tuple[int, int] | None = None
        self._vao: Any = None
        self._tex: moderngl.Texture | None = None
        self.tool = Tool(mask=mask)
        self.renderer = Renderer(self.ctx, status=self._progress, frame_sweeps=frame_sweeps, allow_unconverged=True)
        self.closed, self.edit_mode, self.show_overlay = False, False, True
        self.dirty = True
        self.exposure: float | None = None
        self.message = ""
        self.error: GlsldiffError | None = None      # the last render's error, if it failed
        self.frame_times: list[float] = []
        self.last_report: Any = None
        self._stroke_started = False
        self._image8: NDArray[np.uint8] | None = None
        self.shown: NDArray[np.uint8] | None = None   # the last frame as the window shows it
        self._connect()
        self.select(0)

    # ---- scenes ---------------------------------------------------------------------------
    def select(self, index: int) -> None:
        """Show preset ``index`` (its camera as the orbit's start)."""
        self.preset = index % len(self.presets)
        name, scene = self.presets[self.preset]
        self.window.set_caption(f"glsldiff: {name}")
        self.scene = scene
        self.orbit: Orbit | None = None
        self.exposure = None
        self.dirty = True
        self.message = f"preset {self.preset + 1}/{len(self.presets)}: {name}"

    def current_scene(self) -> Scene:
        """The scene as drawn now: the preset with the orbit camera, at the framebuffer size."""
        w, h = self.window.get_framebuffer_size()
        s = with_size(self.scene, w, h)
        if self.orbit is not None:
            orbit = self.orbit.camera(s.camera.fov_deg)   # the scene's camera type and view width stay
            s = replace(s, camera=replace(s.camera, position=orbit.position, target=orbit.target, up=orbit.up))
        return s

    # ---- frames ---------------------------------------------------------------------------
    def _progress(self, line: str) -> None:
        """A status line from the renderer (polygrid build, solves): shown at once."""
        self.log(line)
        if self.closed:
            return
        w, h = self.window.get_framebuffer_size()
        self._show(status_frame(line, w, h, self._image8))
        self._clear_gl_errors()
        self.window.dispatch_events()

    def render(self) -> None:
        """Render the current scene and show it with the overlay."""
        scene = self.current_scene()
        t0 = time.perf_counter()
        try:
            img, rep = self.renderer.render(scene)
        except GlsldiffError as exc:
            self.message = f"error: {exc}"
            self.log(self.message)
            self.error = exc
            self.dirty = False
            self._show(status_frame(self.message, scene.output.width, scene.output.height, None))
            return
        if self.orbit is None:
            self.orbit = scene_orbit(scene, self.renderer.mesh_framing)
        if self.exposure is None:
            self.exposure = auto_exposure(img)
        dt = time.perf_counter() - t0
        self.frame_times.append(dt)
        self.last_report = rep
        self.radiance = img
        self._image8 = io.tonemap(img, self.exposure)
        self.dirty = not self.renderer.converged          # keep sweeping until pass 2 meets tol
        self._show(draw_overlay(self._image8, self.overlay_lines(rep, dt)) if self.show_overlay else self._image8)

    def overlay_lines(self, rep: Any, seconds: float) -> list[str]:
        fps = 1.0 / max(np.mean(self.frame_times[-10:]), 1e-9)
        s = rep.seconds
        lines = [f"{self.presets[self.preset][0]}   {fps:.1f} fps   frame {seconds * 1e3:.0f} ms",
                 "t1/t2/t3 " + "/".join(f"{s.get(k, 0.0) * 1e3:.0f}" for k in ("t1", "t2", "t3")) + " ms"
                 + (f"   pass 2: {rep.solver.sweeps} sweeps"
                    + ("" if np.isnan(rep.solver.residual) else f", residual {rep.solver.residual:.1e}")
                    if rep.ran("pass2") and rep.solver is not None else "")
                 + ("" if self.renderer.converged else "  (converging)"),
                 f"{rep.nodes:,} nodes   undo {self.renderer.edit_counts[0]} redo {self.renderer.edit_counts[1]}"]
        lines.append(("EDIT: " if self.edit_mode else "view (E: edit): ") + self.tool.describe())
        if self.message:
            lines.append(self.message)
        return lines

    def _show(self, image8: NDArray[np.uint8]) -> None:
        """Draw an ``(h, w, 3)`` 8-bit image (row 0 = top) over the window and flip."""
        gl.make_current(self.ctx)
        self.window.switch_to()
        h, w = image8.shape[:2]
        if self._tex is None or self._tex.size != (w, h):
            if self._tex is not None:
                self._tex.release()
            self._tex = self.ctx.texture((w, h), 3, dtype="f1")
        self._tex.write(np.ascontiguousarray(image8[::-1]).tobytes(), alignment=1)
        if self._quad_size != (w, h):
            if self._vao is not None:
                self._vao.release()
                self._vbo.release()
            self._vbo = self.ctx.buffer(gl.quad_vertices((w, h)).tobytes())
            self._vao = self.ctx.vertex_array(self.prog, [(self._vbo, "2f", "in_pos")])
            self._quad_size = (w, h)
        self.ctx.screen.use()
        self.ctx.viewport = (0, 0, w, h)
        self.ctx.clear(0.0, 0.0, 0.0)
        self._tex.use(0)
        self.prog["u_src"].value = 0
        self.prog["u_size"].value = (float(w), float(h))
        self._vao.render()
        self.shown = self.read_screen()   # before the flip: the back buffer is undefined after it
        self._clear_gl_errors()
        self.window.flip()

    def read_screen(self) -> NDArray[np.uint8]:
        """``(h, w, 3)`` of what is in the window's back buffer now (row 0 = top); what the window
        shows is :attr:`shown`, read this way just before each flip."""
        w, h = self.window.get_framebuffer_size()
        raw = self.ctx.screen.read(viewport=(0, 0, w, h), components=3, alignment=1)
        return np.frombuffer(raw, np.uint8).reshape(h, w, 3)[::-1].copy()

    def screenshot(self, path: str | Path | None = None) -> Path:
        """Write what the window shows to a PNG (default: ``shots/glsldiff-view-<n>.png``)."""
        if path is None:
            k = len(list(self.shots.glob("glsldiff-view-*.png")))
            path = self.shots / f"glsldiff-view-{k:03d}.png"
        out = io.write_png(path, self.shown)
        self.message = f"screenshot {out}"
        self.log(self.message)
        return out

    def _clear_gl_errors(self) -> None:
        """Read GL's error flags empty: pyglet checks glGetError after its own calls (when its
        debug_gl option was on at import) and would blame it on a flag moderngl left."""
        for _ in range(16):
            if self.ctx.error == "GL_NO_ERROR":
                break

    def step(self) -> bool:
        """Handle pending events and render when something changed; False once closed."""
        if self.closed:
            return False
        self._clear_gl_errors()
        self.window.dispatch_events()
        if self.closed:
            return False
        if self.dirty:
            self.render()
        return not self.closed

    def run(self, seconds: float | None = None, screenshot: str | Path | None = None) -> Path | None:
        """The event loop: until the window closes, or for ``seconds`` counted from the first
        frame shown (the grid build before it does not count). With ``screenshot``, the first
        converged frame (pass 2 within tolerance) is written there as PNG, without the overlay,
        and the window closes then unless ``seconds`` keeps it open; a scene that fails to
        render raises its error instead. Returns the screenshot's path."""
        t_end: float | None = None
        shot: Path | None = None
        if screenshot is not None:
            self.show_overlay = False
        while self.step():
            if seconds is not None and t_end is None and self.frame_times:
                t_end = time.perf_counter() + seconds
            if screenshot is not None and shot is None:
                if self.error is not None:
                    raise self.error
                if self.frame_times and not self.dirty:
                    shot = self.screenshot(screenshot)
                    if seconds is None:
                        break
            if t_end is not None and time.perf_counter() > t_end:
                break
            if not self.dirty:
                time.sleep(1.0 / 120.0)
        self.close()
        return shot

    def close(self) -> None:
        """Release the renderer and the GL objects, then close the window."""
        if getattr(self, "_released", False):
            return
        self._released = True
        self.closed = True
        gl.make_current(self.ctx)
        self.renderer.release()
        for obj in (self._vao, getattr(self, "_vbo", None), self._tex):
            if obj is not None:
                obj.release()
        self._gpu.release()
        self._clear_gl_errors()
        self.window.close()

    # ---- editing --------------------------------------------------------------------------
    def paint(self, x: float, y: float) -> None:
        """One brush dab at window point ``(x, y)`` (pyglet: y up)."""
        scene = self.current_scene()
        h = scene.output.height
        try:
            view = self.renderer.edit_view(scene)
            res = self.renderer.edit(self.tool.dab(x, h - y), view, history=not self._stroke_started)
        except GlsldiffError as exc:
            self.message = f"edit refused: {exc}"
            return
        self._stroke_started = True
        self.message = f"edit: {res.describe()}"
        self.dirty = True

    def undo(self, redo: bool = False) -> None:
        ok = self.renderer.redo() if redo else self.renderer.undo()
        self.message = f"{'redo' if redo else 'undo'}{'' if ok else ': nothing to ' + ('redo' if redo else 'undo')}"
        self.dirty = self.dirty or ok

    def save(self) -> Path | None:
        try:
            out = self.renderer.save_material(self.save_path)
        except (GlsldiffError, RuntimeError) as exc:
            self.message = f"not saved: {exc}"
            return None
        self.message = f"saved the material to {out} ([material] nodes = \"{out.name}\")"
        self.log(self.message)
        return out

    # ---- events ---------------------------------------------------------------------------
    def _connect(self) -> None:
        from pyglet.window import key, mouse
        win = self.window

        @win.event
        def on_close() -> bool:
            self.closed = True
            return True

        @win.event
        def on_draw() -> None:
            pass

        @win.event
        def on_resize(w: int, h: int) -> bool:
            self.dirty = True
            return True

        @win.event
        def on_mouse_press(x: int, y: int, button: int, modifiers: int) -> None:
            if button == mouse.LEFT and self.edit_mode:
                self._stroke_started = False
                self.paint(x, y)

        @win.event
        def on_mouse_release(x: int, y: int, button: int, modifiers: int) -> None:
            self._stroke_started = False

        @win.event
        def on_mouse_drag(x: int, y: int, dx: int, dy: int, buttons: int, modifiers: int) -> None:
            if buttons & mouse.LEFT and self.edit_mode:
                self.paint(x, y)
            elif buttons & mouse.LEFT and self.orbit is not None:
                self.orbit = self.orbit.dragged(dx, dy)
                self.dirty = True
            elif buttons & mouse.RIGHT:
                self.scene, ok = turn_light(self.scene, dx, dy)
                self.message = "light turned" if ok else "this scene has no directional light to turn"
                self.dirty = self.dirty or ok

        @win.event
        def on_mouse_scroll(x: int, y: int, sx: float, sy: float) -> None:
            if self.orbit is not None:
                self.orbit = self.orbit.zoomed(sy)
                self.dirty = True

        @win.event
        def on_key_press(symbol: int, modifiers: int) -> bool:
            ctrl = bool(modifiers & (key.MOD_CTRL | key.MOD_COMMAND))
            cycle = {key.K: "prop", key.O: "op", key.V: "value", key.D: "depth"}
            if symbol in (key.ESCAPE, key.Q):
                self.closed = True
            elif ctrl and symbol == key.Z:
                self.undo()
            elif ctrl and symbol == key.Y:
                self.undo(redo=True)
            elif ctrl and symbol == key.S:
                self.save()
            elif symbol in (key.F12, key.P):
                self.screenshot()
            elif symbol == key.E:
                self.edit_mode = not self.edit_mode
            elif symbol in cycle:
                self.tool = self.tool.cycled(cycle[symbol])
            elif symbol == key.M:
                self.tool = replace(self.tool, use_mask=not self.tool.use_mask)
                if self.tool.mask is None:
                    self.message = "no mask image: start with --mask IMAGE"
            elif symbol == key.BRACKETLEFT:
                self.tool = replace(self.tool, radius=max(2.0, self.tool.radius / 1.25))
            elif symbol == key.BRACKETRIGHT:
                self.tool = replace(self.tool, radius=min(1000.0, self.tool.radius * 1.25))
            elif symbol == key.TAB:
                self.select(self.preset + 1)
            elif symbol == key.X:
                self.exposure = None
            elif symbol == key.H:
                self.show_overlay = not self.show_overlay
            else:
                return False
            self.dirty = True
            return True
