"""The split's pass-3 terms (glsldiff.render.split_frame): a frame that only changes the
fluence reuses the fluence-independent terms and gives the same radiance as a full evaluation."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from glsldiff.mesh import sphere_mesh
from glsldiff.render.split_frame import SplitInputs, split_again, split_radiance, split_repaint


def _inputs(seed: int) -> SplitInputs:
    m = sphere_mesh(10.0, subdivisions=2)
    v, n = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.vertex_normals, dtype=np.float64)
    S = len(v)
    rng = np.random.default_rng(seed)
    kappa = rng.uniform(0.2, 0.4, (S, 3))
    mu = rng.uniform(0.001, 0.05, (S, 3))
    lit = np.clip(n @ np.array([0.0, 0.0, 1.0]), 0.0, None)
    E = lit[:, None] * np.array([1.0, 0.9, 0.8])
    return SplitInputs(far="surface", march=False, eta=1.3, C=2.0, interp=sp.identity(S, format="csr"),
                       vertices=v, normals=n, beams=[(E, np.full(S, 0.9))], kappa=kappa, mu=mu,
                       phi=rng.uniform(0.5, 2.0, (S, 3)), q=E)


def test_a_new_fluence_reuses_the_static_terms_exactly():
    inp = _inputs(1)
    eye = np.array([5.0, 20.0, 60.0])
    first = split_radiance(inp, eye)
    assert first.static is not None and first.radiance.max() > 0
    inp2 = replace(inp, phi=inp.phi * np.random.default_rng(2).uniform(0.5, 1.5, inp.phi.shape))
    again = split_again(first.static, inp2.interp, inp2.phi)
    full = split_radiance(inp2, eye)
    np.testing.assert_allclose(again.radiance, full.radiance, rtol=1e-12, atol=1e-15)
    assert not np.allclose(again.radiance, first.radiance)      # the fluence's change shows
    assert again.info == full.info


def test_a_local_material_change_repaints_only_its_vertices():
    """A brush's change of kappa and mu at a few nodes (same light and camera): split_repaint
    recomputes the half-space terms at those vertices only and equals a full evaluation; a
    change of most nodes, or the 3-D march, is left to split_radiance."""
    inp = _inputs(3)
    eye = np.array([5.0, 20.0, 60.0])
    first = split_radiance(inp, eye)
    kappa, mu = inp.kappa.copy(), inp.mu.copy()
    near = np.argsort(np.linalg.norm(inp.vertices - inp.vertices[0], axis=1))[:12]
    kappa[near] *= 0.7
    mu[near, 1] *= 5.0
    inp2 = replace(inp, kappa=kappa, mu=mu)
    again = split_repaint(first.static, inp2)
    full = split_radiance(inp2, eye)
    assert again is not None
    np.testing.assert_allclose(again.radiance, full.radiance, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(again.static.w, full.static.w, rtol=1e-12, atol=1e-15)
    assert not np.allclose(again.radiance, first.radiance)
    assert split_repaint(first.static, replace(inp, kappa=inp.kappa * 0.5)) is None      # everywhere: no
    assert split_repaint(first.static, replace(inp2, march=True)) is None


def test_the_split_counts_the_fluence_it_clamps():
    """fluence_clamped: vertices facing the eye whose interpolated fluence is negative, how deep
    (over the largest) and how many below -1 %; vertices facing away do not count."""
    from glsldiff.render.split_frame import fluence_clamped
    phi = np.array([[1.0, 1.0, 1.0], [-0.005, 0.2, 0.2], [0.3, -0.05, 0.3], [-0.5, -0.5, -0.5]])
    facing = np.array([True, True, True, False])
    assert fluence_clamped(sp.identity(4, format="csr"), phi, facing) == (2, 0.05, 1)
    assert fluence_clamped(sp.identity(4, format="csr"), np.abs(phi), facing) == (0, 0.0, 0)
