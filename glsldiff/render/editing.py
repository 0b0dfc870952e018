"""Material editing on the GPU (Wang et al. 2008, section 5.4): one pass of ``shaders/edit.frag``
over a lattice solver level's packed T_kappa / T_mu.

The pass reads T_kappa, T_mu and the node positions T_p, writes the edited material into this
module's T'_kappa / T'_mu (two render targets), and blits them into the solver's textures (a
GPU copy: the next sweep reads the edited material, nothing crosses to the CPU). The formulas
are those of :mod:`glsldiff.physics.editing` (its oracle); :meth:`GpuMaterialEditor.read`
brings the edited material back for the CPU side of the solver (residual checks) and for undo.

GPU objects (T_p, T', the mask and surface textures, framebuffers, the program) belong to the
editor; the solver's textures stay the solver's.
"""
from __future__ import annotations

import time
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff import gl
from glsldiff.core.errors import InputError
from glsldiff.physics.editing import KAPPA_MIN, NO_SURFACE, OPS, PROPERTIES, Edit, EditView


class GpuMaterialEditor:
    """Edits the material textures of ``level`` (a :class:`glsldiff.solve.jacobi.GlslDiffusion`
    with fp32 material) in place on the GPU.

    Parameters
    ----------
    level
        The solver level whose T_kappa / T_mu are edited (the finest level of a polygrid).
    positions
        ``(N, 3)`` node positions, mm, in the level's flat node order.
    """

    def __init__(self, level: Any, positions: NDArray) -> None:
        if level.material_bits != 32:
            raise InputError("editing needs fp32 material textures: use [options] precision = \"fp32\" or "
                             "\"fp16\" (\"paper\" stores kappa and mu in 8 bits)")
        self.level, self.ctx = level, level.ctx
        g = level.problem.grid
        pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        if len(pos) != g.size:
            raise InputError(f"{len(pos)} node positions for a grid of {g.size} nodes")
        self.size: tuple[int, int] = level.size
        self._gpu = gl.Resources()
        self._mask: tuple[Any, moderngl.Texture] | None = None
        self._surface: tuple[Any, moderngl.Texture] | None = None
        gl.make_current(self.ctx)
        try:
            p4 = np.concatenate([pos, np.asarray(g.active, dtype=np.float64).reshape(-1, 1)], axis=1)
            self.t_pos = self._gpu.add(gl.float_texture(self.ctx, self.size, g.pack(p4.reshape(tuple(g.shape) + (4,)))))
            self.t_new = [self._gpu.add(gl.float_texture(self.ctx, self.size)) for _ in PROPERTIES]
            self.fbo_new = self._gpu.add(self.ctx.framebuffer(color_attachments=self.t_new))
            self.fbo_from = [self._gpu.add(self.ctx.framebuffer(color_attachments=[t])) for t in self.t_new]
            self.fbo_to = [self._gpu.add(self.ctx.framebuffer(color_attachments=[level.textures[f"u_{name}"]]))
                           for name in PROPERTIES]
            self.prog = self._gpu.add(gl.program(self.ctx, "quad.vert", "edit.frag"))
            vbo = self._gpu.add(self.ctx.buffer(gl.quad_vertices(self.size).tobytes()))
            self.vao = self._gpu.add(self.ctx.vertex_array(self.prog, [(vbo, "2f", "in_pos")]))
            self.blank = self._gpu.add(gl.float_texture(self.ctx, (1, 1), np.zeros((1, 1, 4)), components=4))
            gl.set_uniforms(self.prog, {"u_size": tuple(float(s) for s in self.size), "u_kappa": 0, "u_mu": 1,
                                        "u_pos": 2, "u_mask": 3, "u_surface": 4, "u_kappa_min": KAPPA_MIN,
                                        "u_no_surface": NO_SURFACE})
        except Exception:
            self._gpu.release()
            raise
        self.seconds = 0.0   # GPU time of the edits so far (finished), s

    def _image_texture(self, slot: str, key: Any, image: NDArray | None) -> moderngl.Texture:
        """The R32F texture of ``image`` (row 0 = top), uploaded when ``key`` changes."""
        held = getattr(self, slot)
        if image is None:
            return self.blank
        if held is not None and held[0] is key:
            return held[1]
        if held is not None:
            held[1].release()
        img = np.ascontiguousarray(image, dtype=np.float32)
        tex = gl.float_texture(self.ctx, (img.shape[1], img.shape[0]), img[..., None], components=1)
        setattr(self, slot, (key, tex))
        return tex

    def apply(self, edit: Edit, view: EditView | None = None) -> float:
        """Run ``edit`` seen in ``view`` on the level's material textures; returns the GPU
        seconds (the pass and the blit, finished)."""
        if edit.restricted and view is None:
            raise InputError("a brush, mask or depth range needs a view to project the nodes into")
        gl.make_current(self.ctx)
        t0 = time.perf_counter()
        W, H = view.size if view is not None else (1, 1)
        b = edit.brush
        u: dict[str, Any] = {
            "u_prop": PROPERTIES.index(edit.prop), "u_op": OPS.index(edit.op), "u_value": edit.value,
            "u_strength": float(edit.strength), "u_restricted": int(edit.restricted),
            "u_view": (float(W), float(H)), "u_brush": int(b is not None),
            "u_has_mask": int(edit.mask is not None), "u_has_depth": int(edit.depth is not None),
            "u_has_surface": int(view is not None and view.surface is not None)}
        if view is not None:
            u.update({"u_mvp": view.matrix, "u_eye": tuple(float(x) for x in view.eye),
                      "u_ortho": int(view.axis is not None),
                      "u_axis": tuple(float(x) for x in (view.axis if view.axis is not None else (0, 0, 1)))})
        if b is not None:
            u.update({"u_centre": tuple(float(x) for x in b.centre), "u_radius": float(b.radius),
                      "u_inner": float(b.inner)})
        if edit.mask is not None:
            u["u_mask_size"] = (float(edit.mask.shape[1]), float(edit.mask.shape[0]))
        if edit.depth is not None:
            u["u_depth"] = tuple(float(np.float32(d)) for d in edit.depth)
        gl.set_uniforms(self.prog, u)
        mask = self._image_texture("_mask", edit.mask, edit.mask)
        surf = self._image_texture("_surface", view, view.surface if view is not None else None)
        tex = self.level.textures
        with gl.keep_framebuffer(self.ctx):
            for unit, t in enumerate((tex["u_kappa"], tex["u_mu"], self.t_pos, mask, surf)):
                t.use(unit)
            self.fbo_new.use()
            self.ctx.viewport = (0, 0, *self.size)
            self.vao.render(moderngl.TRIANGLES)
            for src, dst in zip(self.fbo_from, self.fbo_to):
                self.ctx.copy_framebuffer(dst, src)
            self.ctx.finish()
        dt = time.perf_counter() - t0
        self.seconds += dt
        return dt

    def read(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The level's current kappa and mu as node arrays ``shape + (3,)`` (float64)."""
        gl.make_current(self.ctx)
        g = self.level.problem.grid
        out = []
        for name in PROPERTIES:
            t = self.level.textures[f"u_{name}"]
            raw = np.frombuffer(t.read(alignment=1), dtype=np.float32).reshape(self.size[1], self.size[0], 4)
            out.append(g.unpack(raw).astype(np.float64))
        return out[0], out[1]

    def release(self) -> None:
        for held in (self._mask, self._surface):
            if held is not None:
                held[1].release()
        self._mask = self._surface = None
        self._gpu.release()

    def __enter__(self) -> "GpuMaterialEditor":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class MaterialHistory:
    """Undo and redo of node materials: the ``(kappa, mu)`` before each edit, at most
    ``depth`` kept (the oldest dropped first; 125 k nodes take 6 MB per step)."""

    def __init__(self, depth: int = 32) -> None:
        self.depth = depth
        self._undo: list[tuple[NDArray, NDArray]] = []
        self._redo: list[tuple[NDArray, NDArray]] = []

    def push(self, kappa: NDArray, mu: NDArray) -> None:
        """Remember the material before an edit (clears the redo stack)."""
        self._undo.append((kappa, mu))
        del self._undo[:-self.depth]
        self._redo.clear()

    def undo(self, current: tuple[NDArray, NDArray]) -> tuple[NDArray, NDArray] | None:
        """The material before the last edit (``current`` goes to redo), or None."""
        if not self._undo:
            return None
        self._redo.append(current)
        return self._undo.pop()

    def redo(self, current: tuple[NDArray, NDArray]) -> tuple[NDArray, NDArray] | None:
        """The material of the last undone edit (``current`` goes to undo), or None."""
        if not self._redo:
            return None
        self._undo.append(current)
        return self._redo.pop()

    @property
    def counts(self) -> tuple[int, int]:
        """(undo steps, redo steps) available."""
        return len(self._undo), len(self._redo)
