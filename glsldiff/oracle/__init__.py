"""The CPU oracle: the same discrete system assembled with scipy.sparse, solved directly
(SuperLU), by algebraic multigrid (pyamg) or by Jacobi; and closed-form solutions of the continuous
problem. Every GLSL operator is tested against it. Never imports GL.
"""
