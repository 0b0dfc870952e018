"""glsldiff: heterogeneous translucent materials with the diffusion equation on the GPU.

Reimplements Wang et al., "Modeling and Rendering of Heterogeneous Translucent
Materials Using the Diffusion Equation" (ACM TOG 27(1), 2008) in Python + GLSL.
Units throughout: lengths in mm, coefficients (mu, sigma_a, sigma_s') in mm^-1,
diffusion coefficient kappa in mm.
"""
from __future__ import annotations

from glsldiff.core.errors import BackendError, GlsldiffError, InputError, SolverError

__version__ = "0.1.0"

__all__ = ["GlsldiffError", "InputError", "BackendError", "SolverError", "__version__"]
