"""Topology repair of cube sets that bridge near-contacts (glsldiff.grids.bridges) and its use
by the polycube search (step 7 of glsldiff.grids.polycube).

Reference: a square frame cut through by a slit narrower than a cube (genus 0) whose cubes
bridge the slit into a ring (genus 1); the compiled simple-cell test against
:func:`glsldiff.grids.cubeset.addable`.
"""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pymeshlab")
pytest.importorskip("trimesh")

from glsldiff import mesh as M  # noqa: E402
from glsldiff.grids import bridges as B  # noqa: E402
from glsldiff.grids import cubeset as C  # noqa: E402
from glsldiff.grids import polycube as P  # noqa: E402


def _box_union_mesh(occ: np.ndarray, xs, ys, zs) -> M.Mesh:
    """Closed mesh of the boundary of the cells ``occ`` of the rectilinear grid with cell edges
    at ``xs``, ``ys``, ``zs`` (mm)."""
    axes = [np.asarray(a, float) for a in (xs, ys, zs)]
    shape = tuple(len(a) for a in axes)
    pad = np.pad(occ, 1)
    tris = []
    for axis in range(3):
        u, w = [a for a in range(3) if a != axis]
        diff = pad[tuple(slice(1, None) if a == axis else slice(1, -1) for a in range(3))].astype(int) - \
            pad[tuple(slice(0, -1) if a == axis else slice(1, -1) for a in range(3))].astype(int)
        for p in np.argwhere(diff != 0):
            eu, ew = np.eye(3, dtype=int)[u], np.eye(3, dtype=int)[w]
            quad = [p, p + eu, p + eu + ew, p + ew]
            ids = [np.ravel_multi_index(tuple(q), shape) for q in quad]
            a, b, c, d = ids if diff[tuple(p)] < 0 else ids[::-1]
            tris += [(a, b, c), (a, c, d)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return M.mesh_from_arrays(grid, np.array(tris), name="slit frame")


def _slit_frame() -> M.Mesh:
    """A 12 x 12 x 3 mm square frame (bars 3 mm wide) cut through by a 0.4 mm slit: genus 0."""
    xs = [0, 3, 5.8, 6.2, 9, 12]
    ys = [0, 3, 9, 12]
    occ = np.ones((5, 3, 1), bool)
    occ[1:4, 1, 0] = False        # the hole
    occ[2, 2, 0] = False          # the slit through the top bar
    return _box_union_mesh(occ, xs, ys, [0, 3])


def test_slit_frame_search_bridges_then_repairs(caplog):
    mesh = _slit_frame()
    assert mesh.genus == 0
    fr = P._fractions(mesh, 1.5, 4, {})
    for t in P.FALLBACK_THRESHOLDS:   # every threshold's cubes close the slit into a ring
        assert C.topology_of(P._build(mesh, fr, t)[2]).genus == 1
    with caplog.at_level("WARNING", logger="glsldiff.grids.polycube"):
        pc = P.polycube_from_mesh(mesh, cube_size=1.5)
    topo = pc.surface_topology
    assert (topo.components, topo.cavities, topo.genus, topo.manifold) == (1, 0, 0, True)
    assert 0 < pc.bridged <= 8
    # the cubes left out lie next to the slit (x = 6 mm), in the top bar
    full = {tuple(c) for c in P._build(mesh, fr, pc.threshold)[0].tolist()}
    gone = np.array(sorted(full - {tuple(c) for c in pc.cubes.tolist()}))
    centres = pc.origin + pc.size * (gone + 0.5)
    assert (np.abs(centres[:, 0] - 6.0) < 1.5).all() and (centres[:, 1] > 9.0).all()
    lines = [r.getMessage() for r in caplog.records if "bridged" in r.getMessage()]
    assert len(lines) == 1 and "\n" not in lines[0] and f"left out {pc.bridged} cube(s) that bridged" in lines[0]
    assert pc.repair in lines[0]


def test_slit_frame_with_thin_parts_off_has_the_same_cubes():
    mesh = _slit_frame()
    a = P.polycube_from_mesh(mesh, cube_size=1.5, thin_parts=False)
    b = P.polycube_from_mesh(mesh, cube_size=1.5)
    assert a.bridged == b.bridged and b.grown == 0
    np.testing.assert_array_equal(a.cubes, b.cubes)


def test_candidates_offer_each_thresholds_repair_once():
    """At 1.2 mm cubes the slit frame's thresholds repair into four different cube sets: the
    search offers each once, least inside volume left out first (the one polycube_from_mesh
    returns), each with the mesh's topology; grown or not, in the same order."""
    mesh = _slit_frame()
    plain = list(P.polycube_candidates(mesh, cube_size=1.2, thin_parts=False))
    grown = list(P.polycube_candidates(mesh, cube_size=1.2))
    assert [pc.threshold for pc in plain] == [pc.threshold for pc in grown] == [0.6, 0.5, 0.3, 0.2]
    first = P.polycube_from_mesh(mesh, cube_size=1.2, thin_parts=False)
    np.testing.assert_array_equal(plain[0].cubes, first.cubes)
    assert plain[0].threshold == first.threshold and plain[0].repair == first.repair
    lost = [float(pc.repair.split(" cubes of inside volume")[0].rsplit("(", 1)[1]) for pc in plain]
    assert lost == sorted(lost)
    assert len({pc.cubes.tobytes() for pc in plain}) == len(plain)
    for pc in plain:
        topo = pc.surface_topology
        assert (topo.components, topo.cavities, topo.genus, topo.manifold) == (1, 0, 0, True) and pc.bridged > 0


def test_meshes_that_build_never_reach_the_repair(monkeypatch):
    """Cube sets with the mesh's topology are returned as before: the repair is not called."""
    def boom(*args, **kwargs):
        raise AssertionError("repair_bridges called")
    monkeypatch.setattr(P, "repair_bridges", boom)
    for mesh, size in ((M.sphere_mesh(1.0, 3), 0.4), (M.torus_mesh(2.0, 0.8), 0.5)):
        pc = P.polycube_from_mesh(mesh, cube_size=size)
        assert pc.bridged == 0 and pc.repair == ""


def test_no_repair_adds_a_handle():
    """A torus whose cubes are too coarse to keep its hole stays an error (the repair only
    leaves cubes out), with the scene key in the message."""
    with pytest.raises(P.PolycubeNotFound, match=r"bridge near-contacts did not give it.*\[polygrid\] cubes"):
        P.polycube_from_mesh(M.torus_mesh(2.0, 0.8), cube_size=1.4)


def test_simple_cell_equals_addable():
    rng = np.random.default_rng(1)
    agree = positives = 0
    for _ in range(4000):
        occ = np.zeros((5, 5, 5), bool)
        occ[1:4, 1:4, 1:4] = rng.random((3, 3, 3)) < rng.uniform(0.1, 0.9)
        occ[2, 2, 2] = False
        want = C.addable(occ, (2, 2, 2))
        positives += want
        agree += B.simple_cell(occ, 2, 2, 2, C.MANIFOLD) == want
    assert agree == 4000 and positives > 20
    # structured cases: a face neighbour (simple), two opposite ones (would join two parts)
    occ = np.zeros((5, 5, 5), bool)
    occ[1, 2, 2] = True
    assert B.simple_cell(occ, 2, 2, 2, C.MANIFOLD)
    occ[3, 2, 2] = True
    assert not B.simple_cell(occ, 2, 2, 2, C.MANIFOLD)


def test_grow_simple_opens_a_ring_and_keeps_a_ball():
    ring = np.zeros((8, 8, 3), bool)
    ring[1:7, 1:7, 1] = True
    ring[3:5, 3:5, 1] = False
    frac = np.where(ring, 1.0, 0.0)
    frac[5:7, 3, 1] = 0.6        # the weakest cross-section (two cubes): where the fronts meet
    kept = B.grow_simple(ring, frac)
    topo = C.topology_of(kept)
    assert (topo.components, topo.cavities, topo.genus, topo.manifold) == (1, 0, 0, True)
    assert (kept <= ring).all() and not kept[5:7, 3, 1].any() and ring.sum() - kept.sum() == 2
    block = np.zeros((6, 6, 6), bool)
    block[1:5, 1:5, 1:5] = True
    np.testing.assert_array_equal(B.grow_simple(block, block * 1.0), block)
    rep = B.repair_bridges(ring, frac, genus=1)   # the mesh's own handle is closed again
    assert rep.matches(1) and rep.removed == rep.detached == 0
