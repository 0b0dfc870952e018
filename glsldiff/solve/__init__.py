"""GPU solvers: GLSL Jacobi relaxation on ping-pong float textures, the level stack and the
hierarchical / adaptive / multigrid schedules (Wang et al. 2008, sections 5.2-5.3), and the paper's
reduced precision modes. Every solver returns (solution, SolveReport).
"""
