"""A mesh with no tetrahedral polygrid (no set of cubes with its topology) renders on the
lattice polygrid instead, said in one warning with the reason and the way back; a mesh with no
polygrid at all is one InputError naming the scene key to change."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.core.errors import InputError
from glsldiff.grids.polycube import PolycubeNotFound
import glsldiff.render.backends as backends
from glsldiff.render.grid_check import discretisation_error
from glsldiff.render.renderer import Renderer
from glsldiff.render.scene import PolygridSpec, parse_scene

SMALL = PolygridSpec(6, 27, 2, "conservative", adapt=False)     # the fallback lattice, small for the test

pytestmark = pytest.mark.usefixtures("ctx")


def _scene():
    return parse_scene({"mesh": {"source": "sphere", "size_mm": 20.0},
                        "lights": [{"type": "directional", "direction": [0.3, 0.4, 1.0]}],
                        "output": {"width": 48, "height": 48}})


def _no_polycube(*args, **kwargs):
    raise PolycubeNotFound("no polycube (test)", ["threshold 0.5 (12 cubes of 4 mm): 2 component(s), 0 cavities"])


def test_no_tetrahedral_polycube_falls_back_to_the_lattice(monkeypatch):
    import glsldiff.render.backends.tetrahedral as tet
    monkeypatch.setattr(tet, "cached_fem_grid", _no_polycube)
    monkeypatch.setattr(backends, "FALLBACK_POLYGRID", SMALL)
    scene = _scene()
    assert scene.polygrid.discretisation == "fem"
    with Renderer() as r:
        img, rep = r.render(scene)
        assert np.isfinite(img).all() and img.max() > 0
        assert r.polygrid.__class__.__name__ == "Polygrid"               # the lattice's
        warning = rep.warnings[0]
        assert "no tetrahedral polygrid of sphere" in warning and "2 component(s)" in warning
        assert "lattice polygrid" in warning and "[polygrid] cubes" in warning
        assert "cube_size" not in warning and "n_cubes" not in warning   # scene keys, not arguments
        _, rep2 = r.render(scene)                                        # kept: no second search
        assert not rep2.ran("setup") and rep2.warnings[0] == warning
        with pytest.raises(InputError, match="needs a tetrahedral grid"):   # --check-grid: one line
            discretisation_error(r, scene)
    with Renderer() as r:                                                # the same as asking for it
        direct, _ = r.render(parse_scene({**_raw(), "polygrid": {"discretisation": SMALL.discretisation, "n": SMALL.n,
                                                                   "cubes": SMALL.cubes, "levels": SMALL.levels}}))
    np.testing.assert_allclose(img, direct, rtol=1e-3, atol=1e-6 * float(direct.max()))   # both to the solve's tol


def _raw():
    return {"mesh": {"source": "sphere", "size_mm": 20.0},
            "lights": [{"type": "directional", "direction": [0.3, 0.4, 1.0]}],
            "output": {"width": 48, "height": 48}}


def test_no_polycube_at_all_is_one_input_error(monkeypatch):
    import glsldiff.render.backends.lattice as lat
    import glsldiff.render.backends.tetrahedral as tet
    monkeypatch.setattr(tet, "cached_fem_grid", _no_polycube)
    monkeypatch.setattr(lat, "cached_polygrid", _no_polycube)
    monkeypatch.setattr(backends, "FALLBACK_POLYGRID", SMALL)
    with Renderer() as r, pytest.raises(InputError, match=r"\[polygrid\] cubes = 30000") as info:
        r.render(_scene())
    assert "lattice fallback" in str(info.value) and "cube_size" not in str(info.value)
