"""The discrete system every solver shares: :class:`~glsldiff.system.problem.DiffusionProblem`
(a grid, kappa, mu, the source q, eta, stencil) and the :class:`~glsldiff.system.report.SolveReport`
each solver returns next to its solution, with the convergence monitor and error estimates.
"""
