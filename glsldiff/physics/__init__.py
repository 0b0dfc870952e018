"""Physics: interface optics (Fresnel, C, the dipole), material coefficients and presets,
procedural volumes, exitance/source conventions, light types (:mod:`.lights`), spherical
harmonics of environment light (:mod:`.sh`) and single scattering. No GL, no grids.
"""
