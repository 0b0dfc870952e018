"""Scene presets the viewer's Tab key cycles through: the scene given on the command line (if
any), the default scene as ``glsldiff render`` draws it (tetrahedral; edits update its P1 system
in place), the same bunny on the lattice polygrid (GPU editing of its material textures), a
torus (the paper's "Hole", Table III) on a tetrahedral grid and on the lattice, and the shipped
examples."""
from __future__ import annotations

from dataclasses import replace

from glsldiff.render.scene import (EDIT_LATTICE, HOLE_CUBES, MeshSpec, PolygridSpec, Scene, default_cubes,
                                   default_scene, example_names, example_scene, tetrahedral)

def lattice(scene: Scene, n: int = 8, cubes: int | None = None, levels: int = 3) -> Scene:
    """``scene`` on the conservative lattice polygrid (GPU editing of its material textures);
    ``levels`` needs n divisible by 2^(levels - 1) with at least 2 nodes left."""
    return replace(scene, polygrid=PolygridSpec(n, cubes or default_cubes("conservative", n), levels, "conservative"))


def interactive(scene: Scene) -> Scene:
    """``scene`` with a grid that does not follow its lights (``[polygrid] adapt = false``):
    the refinement under sharp light re-runs the setup whenever a light moves, and the viewer
    turns the light with the mouse."""
    return replace(scene, polygrid=replace(scene.polygrid, adapt=False))


def presets(first: tuple[str, Scene] | None = None, examples: bool = True) -> list[tuple[str, Scene]]:
    """(name, scene) pairs, ``first`` first, each :func:`interactive`."""
    return [(name, interactive(scene)) for name, scene in _presets(first, examples)]


def _presets(first: tuple[str, Scene] | None, examples: bool) -> list[tuple[str, Scene]]:
    base = default_scene()
    out = [] if first is None else [first]
    torus = replace(base, mesh=MeshSpec("torus", 100.0))
    out += [("bunny, veined marble (tetrahedral, as glsldiff render)", base),
            ("bunny, veined marble (lattice polygrid: GPU editing)", replace(base, polygrid=EDIT_LATTICE)),
            (f"torus 'Hole', veined marble (tetrahedral, about {HOLE_CUBES:,} cubes)", tetrahedral(torus, HOLE_CUBES)),
            ("torus 'Hole', veined marble (lattice, 36 cubes x 12^3)", lattice(torus, n=12, cubes=36))]
    if examples:
        out += [(f"example {name}", example_scene(name)) for name in example_names()]
    return out
