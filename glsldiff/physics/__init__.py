"""Physics: interface optics (Fresnel, C, the dipole), material coefficients and presets,
procedural volumes, exitance/source conventions and single scattering. No GL, no grids.
"""
