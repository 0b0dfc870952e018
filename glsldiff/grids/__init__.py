"""Grids: the node graphs a diffusion equation is discretised on (CPU only, never GL).

The regular block grid (acquisition samples), and the polygrid of Wang et al. 2008 section 5.1:
polycube, lattice, mapping into the mesh, Laplacian weights, and the multiresolution hierarchy;
the tetrahedral grids built on the same polycube in :mod:`glsldiff.grids.tetrahedral`; the disk
cache of both in :mod:`glsldiff.grids.cache`.
"""
