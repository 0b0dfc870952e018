"""GLSL sources of glsldiff (package data; see glsldiff.gl.shader_dir)."""
