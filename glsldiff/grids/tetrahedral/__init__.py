"""The tetrahedral grids (the default discretisation): P1 finite elements on the pillowed polycube
or on an fTetWild mesh of the surface (CPU only, never GL).

``fem_grid``
    :func:`~glsldiff.grids.tetrahedral.fem_grid.build_fem_grid`: the polycube's lattice pillowed
    (``pillow``), mapped into the mesh and untangled, its tetrahedra reshaped (``shapes``) and
    long edges split (``split``).
``adapt``
    Refinement under the lights' sharp edges.
``tetwild``, ``tetcut``
    fTetWild meshes of the surface (TransCut) and their cutting.

They build on the lattice family's polycube, cube sets and lattice (:mod:`glsldiff.grids`), never
the other way round (an import contract); the P1 systems they are solved with live in
:mod:`glsldiff.system` and :mod:`glsldiff.oracle`.
"""
