"""Headless OpenGL for glsldiff (moderngl): contexts (:mod:`.context`), shader programs and
uniforms (:mod:`.programs`), float textures, ping-pong pairs and GL housekeeping
(:mod:`.targets`). Only solve, render, figures, bench, viewer and the command layer import it
(the contract in pyproject.toml).
"""
from glsldiff.gl.context import (BACKENDS, INSTALL_HINT, create_context, describe, get_context,
                                 make_current, renderer)
from glsldiff.gl.programs import program, set_uniforms, shader_dir, shader_source
from glsldiff.gl.targets import DTYPES, FP16_MAX, PingPong, Resources, float_texture, keep_framebuffer, quad_vertices

__all__ = ["BACKENDS", "INSTALL_HINT", "create_context", "describe", "get_context", "make_current",
           "renderer", "program", "set_uniforms", "shader_dir", "shader_source", "DTYPES", "FP16_MAX",
           "PingPong", "Resources", "float_texture", "keep_framebuffer", "quad_vertices"]
