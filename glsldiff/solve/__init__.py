"""GPU solvers (Wang et al. 2008, sections 5.2-5.3), one GLSL stack for regular grids and
polygrids: what the passes draw and read, built from a grid's node graph and texture mosaic
(:mod:`.stencil`); the Jacobi relaxation on ping-pong float textures (:mod:`.jacobi`); the level
stack of a grid hierarchy with its transfer passes (:mod:`.levels`); the single / hierarchical /
adaptive / multigrid schedules (:mod:`.schedules`) behind :class:`~.multilevel.MultilevelDiffusion`;
and the paper's reduced material precision (:mod:`.quantize`). Every solver takes the uniform
arguments of :mod:`glsldiff.system.report` and returns (solution, SolveReport).
"""
