"""Every shipped example scene (glsldiff/render/examples/*.toml) parses and renders through
``glsldiff render --example NAME``: a finite, non-black image and its PNG."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.commands.cli import main
from glsldiff.core import io
from glsldiff.core.errors import InputError
from glsldiff.render.scene import example_names, example_scene


def test_examples_are_listed():
    assert set(example_names()) >= {"backlit_bunny", "spot_sphere", "layered_cow"}
    with pytest.raises(InputError, match="no example scene 'nope'; the examples are: backlit_bunny"):
        example_scene("nope")


@pytest.mark.parametrize("name", example_names())
def test_example_renders(ctx, tmp_path, name):
    out = tmp_path / f"{name}.exr"
    assert main(["render", "--example", name, "-o", str(out)]) == 0
    img = io.read_exr(out)
    assert np.all(np.isfinite(img)) and img.max() > 0 and (img.sum(axis=2) > 0).mean() > 0.02
    assert out.with_suffix(".png").stat().st_size > 0
