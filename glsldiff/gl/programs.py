"""Shader programs from the top-level ``shaders/`` folder, and uniform setting.

GLSL sources ship in the wheel as the ``glsldiff.shaders`` package. ``#include "name.glsl"``
lines are expanded from the same folder, and ``defines`` are inserted after the ``#version``
line.
"""
from __future__ import annotations

import importlib.resources
import re
from pathlib import Path
from typing import Any, Mapping

import moderngl
import numpy as np

from glsldiff.core.errors import GlsldiffError

def shader_dir() -> Path:
    """The folder holding the GLSL sources (installed package data or the checkout)."""
    try:
        path = Path(str(importlib.resources.files("glsldiff.shaders")))
        if path.is_dir():
            return path
    except ModuleNotFoundError:
        pass
    return Path(__file__).resolve().parents[2] / "shaders"


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


def set_uniforms(prog: moderngl.Program, values: Mapping[str, Any]) -> None:
    """Set the uniforms of ``prog`` that it uses (the GLSL compiler drops unused ones).

    numpy arrays of 9 or 16 values are written as column-major matrices (``A.T`` bytes); other
    values go through ``.value``.
    """
    for name, value in values.items():
        if name not in prog:
            continue
        if isinstance(value, np.ndarray) and value.ndim == 2:
            prog[name].write(np.ascontiguousarray(value.T, dtype="f4").tobytes())
        else:
            prog[name].value = value
