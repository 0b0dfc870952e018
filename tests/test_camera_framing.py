"""The automatic camera (glsldiff.render.camera.Framing): it looks along the axis showing the
largest silhouette, from the front side, up +y where +y lies across the image, else the
object's longest axis; a sphere and the default bunny keep the front view (+z, up +y)."""
from __future__ import annotations

import numpy as np
import pytest

from glsldiff.mesh import box_mesh, cached_load_mesh, sphere_mesh
from glsldiff.render.camera import Framing, frame_camera, silhouette_area
from glsldiff.render.scene import CameraSpec, default_scene


def test_silhouette_area_of_a_box_and_a_sphere():
    box = box_mesh((40.0, 20.0, 10.0), origin=(-20.0, -10.0, -5.0))
    assert silhouette_area(box, np.array([0.0, 0.0, 1.0])) == pytest.approx(800.0, rel=0.03)
    assert silhouette_area(box, np.array([1.0, 0.0, 0.0])) == pytest.approx(200.0, rel=0.03)
    ball = sphere_mesh(10.0, 4)
    assert silhouette_area(ball, np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)) == pytest.approx(np.pi * 100.0, rel=0.03)


@pytest.mark.parametrize("extents, view, up", [
    ((10.0, 60.0, 40.0), (1, 0, 0), (0, 1, 0)),     # thin along x: seen from +x, +y across the image: up
    ((60.0, 10.0, 40.0), (0, 1, 0), (1, 0, 0)),     # thin along y (the view): up the longest axis, x
    ((40.0, 10.0, 60.0), (0, 1, 0), (0, 0, 1)),     # ... z
    ((60.0, 40.0, 10.0), (0, 0, 1), (0, 1, 0)),     # thin along z: the front view
])
def test_a_box_is_seen_along_its_thin_axis(extents, view, up):
    e = np.asarray(extents)
    f = Framing.of_mesh(box_mesh(e, origin=tuple(-0.5 * e)))
    np.testing.assert_allclose(f.view, view, atol=1e-9)
    np.testing.assert_allclose(f.up, up, atol=1e-9)


def test_a_tilted_slab_is_seen_along_its_normal():
    """A flat box turned 40 degrees about z: its principal axis shows 1.3x the silhouette of any
    coordinate axis, so the camera looks along it."""
    box = box_mesh((60.0, 8.0, 40.0), origin=(-30.0, -4.0, -20.0))
    a = np.radians(40.0)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    from glsldiff.mesh import Mesh
    f = Framing.of_mesh(Mesh(np.asarray(box.vertices) @ R.T, np.asarray(box.faces)))
    assert abs(f.view @ (R @ np.array([0.0, 1.0, 0.0]))) > 0.999
    assert abs(f.up @ f.view) < 1e-9


def test_sphere_and_default_bunny_keep_the_front_view():
    scene = default_scene()
    for mesh in (sphere_mesh(20.0, 4), cached_load_mesh(scene.mesh.source, size_mm=scene.mesh.size_mm)):
        f = Framing.of_mesh(mesh)
        np.testing.assert_allclose(f.view, (0, 0, 1), atol=1e-9)
        np.testing.assert_allclose(f.up, (0, 1, 0), atol=1e-9)
        eye, target, up = frame_camera(scene, f)
        old, _, _ = frame_camera(scene, np.asarray(mesh.vertices))      # vertices alone: the box from +z
        np.testing.assert_allclose(eye, old, atol=1e-9)


def test_a_scene_position_overrides_the_framing():
    f = Framing.of_mesh(box_mesh((10.0, 60.0, 40.0), origin=(-5.0, -30.0, -20.0)))
    scene = default_scene()
    cam = CameraSpec(position=(0.0, 0.0, 300.0), up=(0.0, 0.0, 1.0))
    eye, target, up = frame_camera(type(scene)(**{**scene.__dict__, "camera": cam}), f)
    np.testing.assert_allclose(eye, (0, 0, 300))
    np.testing.assert_allclose(up, (0, 0, 1))
