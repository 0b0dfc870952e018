"""Render targets and GL housekeeping: float textures, ping-pong pairs, the caller's
framebuffer kept bound around our passes, and resource lists released in reverse order."""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Iterator, TypeVar

import moderngl
import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import GlsldiffError

DTYPES = {"fp32": "f4", "fp16": "f2"}
FP16_MAX = 65504.0  # largest finite half float; llvmpipe clamps fp16 writes to it

T = TypeVar("T")


@contextmanager
def keep_framebuffer(ctx: moderngl.Context) -> Iterator[None]:
    """Leave the caller's framebuffer bound after our passes, never ours."""
    bound = ctx.fbo if ctx.fbo is not None else ctx.detect_framebuffer(0)
    try:
        yield
    finally:
        bound.use()


def quad_vertices(size: tuple[int, int]) -> NDArray[np.float32]:
    """Two triangles covering ``size = (w, h)`` texels, in texel-space corners (``quad.vert``)."""
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 0], [1, 1], [0, 1]], dtype="f4")
    return unit * np.array(size, dtype="f4")


class Resources:
    """GL objects owned by one module, released together in reverse order of creation."""

    def __init__(self) -> None:
        self._objects: list[Any] = []

    def add(self, obj: T) -> T:
        self._objects.append(obj)
        return obj

    def release(self) -> None:
        while self._objects:
            self._objects.pop().release()

    def __enter__(self) -> "Resources":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


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
