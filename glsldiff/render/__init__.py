"""Rendering (Wang et al. 2008, section 5): TOML scenes, shadow maps and pass 1 (incident
light at the boundary nodes), per-node materials and the shell-layer mapping, pass 2 through
:mod:`glsldiff.solve` by one backend per grid family (:mod:`glsldiff.render.backends`), and
pass 3 (surface shading) into an HDR image.
"""
