"""The benchmarks' honesty (``glsldiff bench ...``): repeated timings give the median and the
minimum (``t_median_s``, ``t_min_s``, ``repeats`` in every CSV), and every peer row names the
solver and the tolerance the code passed to it, taken from the same constant the call uses.
Tiny sizes: each bench runs in about a second."""
from __future__ import annotations

import csv
import math

import pytest

from glsldiff.bench import peers
from glsldiff.bench.peers import tol_text
from glsldiff.bench.timing import TIME_COLUMNS, median_min, repeat, runs_note, timing_columns


def _timed_ok(row: dict, prefix: str = "") -> None:
    """The row has the repeated-timing columns, min <= median, and as many runs as asked."""
    lo, med = float(row[f"{prefix}t_min_s"]), float(row[f"{prefix}t_median_s"])
    assert 0 <= lo <= med, row
    assert int(row["repeats"]) >= 1


def _csv(path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_repeat_keeps_every_run_and_the_last_result():
    calls = iter([3.0, 1.0, 2.0, 5.0])
    tim = repeat(lambda: next(calls), 4, seconds=lambda r: r)      # a run that times itself
    assert tim.times == [3.0, 1.0, 2.0, 5.0] and tim.result == 5.0 and tim.repeats == 4
    assert tim.min == 1.0 and tim.median == 2.5 and tim.first == 3.0
    assert tim.columns(first=True) == {"t_median_s": 2.5, "t_min_s": 1.0, "repeats": 4, "t_first_s": 3.0}
    assert tuple(timing_columns([1.0])) == TIME_COLUMNS
    wall = repeat(lambda: "x", 3)                                       # wall clock around the call
    assert wall.result == "x" and len(wall.times) == 3 and 0 <= wall.min <= wall.median
    with pytest.raises(ValueError):
        repeat(lambda: None, 0)
    assert all(math.isnan(v) for v in median_min([1.0, math.nan]))   # a run that never got there
    assert runs_note(1) == "1 run" and runs_note(3) == "median of 3 runs"


def test_peer_labels_carry_the_tolerance_passed():
    assert "direct" in peers.direct_label()
    assert peers.amg_label("gmres", 1e-12) == "pyamg SA + GMRES, rtol 1e-12"
    assert peers.relax_label("GLSL Jacobi fp32", 5e-7).endswith("tol 5e-07")
    label, rtol = peers.reference_label(peers.REFERENCE_MAX_DIRECT)      # pyamg from the switch on
    assert rtol == peers.REFERENCE_AMG_RTOL and f"rtol {tol_text(peers.REFERENCE_AMG_RTOL)}" in label
    label, rtol = peers.reference_label(peers.REFERENCE_MAX_DIRECT - 1)
    assert label == peers.direct_label() and math.isnan(rtol)
    label, rtol = peers.fem_reference_label(10, max_direct=5)
    from glsldiff.system.report import REFERENCE_TOL
    assert rtol == REFERENCE_TOL and "pyamg SA + CG" in label and tol_text(REFERENCE_TOL) in label


def test_bench_forward_rows_name_the_peers_and_time_them_repeatedly(ctx, tmp_path):
    from glsldiff.bench import forward as fb
    tol = 2e-6
    # the budget also stops the multigrid run: 0.05 s was too short for it to reach 1e-3 while a
    # full test run loaded the 2 cores (t(err<1e-3) NaN, seen once)
    rows = fb.forward(["17x17x9"], tmp_path, seconds=0.5, precisions=("fp32",), schemes=("multigrid",),
                      levels=2, tol=tol, repeats=2)
    by = {r["method"]: r for r in _csv(tmp_path / "forward.csv")}
    assert len(by) == len(rows) == 5
    for r in by.values():
        _timed_ok(r)
        assert int(r["repeats"]) == 2 and "tol" in r and "residual" in r
    amg = by[peers.amg_label("gmres", fb.AMG_RTOL)]
    assert f"rtol {tol_text(fb.AMG_RTOL)}" in amg["method"] and float(amg["tol"]) == fb.AMG_RTOL
    assert float(amg["residual"]) < 1e-9
    assert peers.direct_label() in by and "direct" in peers.direct_label()
    mg = next(m for m in by if "multigrid" in m)
    assert f"tol {tol_text(tol)}" in mg and float(by[mg]["tol"]) == tol
    assert all("no tol" in m for m in by if "Jacobi" in m)            # the budget runs pass no tolerance
    assert 0 < float(by[mg]["t(err<1e-3) min"]) <= float(by[mg]["t(err<1e-3)"]) <= float(by[mg]["t_median_s"])


def test_bench_throughput_median_and_min(ctx):
    from glsldiff.bench.throughput import sweep_throughput
    rows = sweep_throughput(polygrids=(("torus", 4, 8),), sweeps=5, packings=("texels",), repeats=3)
    assert len(rows) == 2
    for r in rows:
        _timed_ok(r)
        assert r["repeats"] == 3 and r["ms/sweep min"] <= r["ms/sweep"] and r["setup_s"] > 0


def test_bench_convergence_peer_is_the_solver_that_ran(ctx, monkeypatch):
    """The figure-15 peer row names SuperLU or pyamg with the rtol it got (it was labelled
    'scipy-direct' whatever ran); with the switch at 0 nodes the tiny model takes pyamg."""
    from glsldiff.bench.convergence import SCHEME_TOL, hole_polygrid, study
    pg = hole_polygrid(n=4, cubes=36)
    summary, _, _ = study("hole", pg, levels=2, schemes=("single",), precisions=(), repeats=2)
    assert summary[0]["method"].startswith(peers.direct_label())
    monkeypatch.setattr(peers, "REFERENCE_MAX_DIRECT", 0)
    summary, _, _ = study("hole", pg, levels=2, schemes=("single", "multigrid"), precisions=(), repeats=2)
    peer = summary[0]
    assert f"pyamg SA + GMRES, rtol {tol_text(peers.REFERENCE_AMG_RTOL)}" in peer["method"]
    assert peer["tol"] == peers.REFERENCE_AMG_RTOL and peer["residual"] < 1e-8
    for r in summary:
        _timed_ok(r)
        assert r["repeats"] == 2
    for r in summary[1:]:
        assert f"tol {tol_text(SCHEME_TOL)}" in r["method"] and r["tol"] == SCHEME_TOL
        assert r["t_median_s"] >= r["seconds_to_target"] and r["setup_s"] > 0     # set-up included


def test_bench_fit_backends_time_each_path_repeatedly(ctx):
    from glsldiff.bench.fit import Case, backend_study
    from glsldiff.inverse.glsl import GlslForwardModel
    rows = backend_study(Case((8, 8, 4), 0.5, "veins"), 1, 0.01, repeats=2)
    superlu, glsl = rows
    assert superlu["path"] == peers.direct_label()
    assert glsl["path"].endswith(f"tol {tol_text(GlslForwardModel.tol)}") and glsl["tol"] == GlslForwardModel.tol
    for r in rows:
        _timed_ok(r)
        assert r["repeats"] == 2 and r["seconds_per_gradient"] == r["t_median_s"] and r["warmup_s"] > 0


def test_demo_reports_the_setup_apart_and_names_its_solvers(ctx, tmp_path):
    from glsldiff.bench import demo
    cfg = demo.DemoConfig(nx=8, ny=8, nz=4, tol=1e-6, out=tmp_path)
    rows = demo.run(cfg, progress=False)
    assert len(rows) == cfg.regions ** 2 + 2 and rows[-1]["image"].startswith("set-up")
    assert rows[-1]["gpu_s"] > 0 and rows[-1]["direct_s"] > 0
    for r in rows:
        assert r["gpu"] == f"GLSL Jacobi fp32, tol {tol_text(cfg.tol)}" and r["direct"] == peers.direct_label()


def test_polygrid_check_solve_labels(ctx, sphere_polygrid):
    from glsldiff.bench.polygrid import check_solve
    tol = 1e-6
    ref, gpu = check_solve(sphere_polygrid, tol)
    assert ref["solver"] == peers.reference_label(sphere_polygrid.n_active)[0]
    assert gpu["solver"] == f"GLSL Jacobi fp32, tol {tol_text(tol)}" and gpu["tol"] == tol
