#!/usr/bin/env python3
"""Re-run the bad-input probes of the hardening issue against the installed ``glsldiff``
and print one row per probe: exit code, stderr line count, seconds, files left behind, and
the first stderr line. Run from the repository root: ``.venv/bin/python .ci/probes.py``
(``--only capture``: only the probes whose name contains "capture", the ``glsldiff capture``
steps). Each probe runs in a fresh temporary folder with GLSLDIFF_GL=osmesa and the cache off."""
from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

GL = str(Path(sys.executable).with_name("glsldiff"))
ENV = dict(os.environ, GLSLDIFF_GL="osmesa", GLSLDIFF_CACHE="off")

SCENE = """[mesh]
source = "sphere"
size_mm = {size}
[polygrid]
n = {n}
cubes = 20
levels = 1
[material]
sigma_s_prime = {sp}
sigma_a = 0.002
{extra}
[[lights]]
type = "directional"
direction = [0, 0, 1]
irradiance = [{e}, {e}, {e}]
[output]
width = 32
height = 32
"""


def scene(d: Path, size: float = 20, n: int = 4, sp: float = 1.0, e: float = 1.0, extra: str = "") -> str:
    p = d / "s.toml"
    p.write_text(SCENE.format(size=size, n=n, sp=sp, e=e, extra=extra))
    return str(p)


def files(d: Path) -> set[str]:
    return {str(p.relative_to(d)) for p in d.rglob("*")}


def run(name: str, make, interrupt_after: float | None = None, env: dict[str, str] | None = None) -> dict:
    env = {**ENV, **(env or {})}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        argv = make(d)
        before = files(d)
        t0 = time.perf_counter()
        if interrupt_after is None:
            p = subprocess.run([GL, *argv], cwd=d, env=env, capture_output=True, text=True, timeout=900)
            code, err, out = p.returncode, p.stderr, p.stdout
        else:
            p = subprocess.Popen([GL, *argv], cwd=d, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            time.sleep(interrupt_after)
            p.send_signal(signal.SIGINT)
            out, err = p.communicate(timeout=300)
            code = p.returncode
        dt = time.perf_counter() - t0
        lines = [l for l in err.splitlines() if l.strip() and not l.startswith(("setup:", "pass ", "fit:", "lightings"))]
        if not lines and code != 0:   # a command that reports its interruption on stdout
            lines = [l for l in out.splitlines() if l.strip()][-1:]
        left = sorted(files(d) - before)
        return {"probe": name, "exit": code, "err_lines": len(lines), "seconds": round(dt, 1),
                "left": ",".join(left)[:60] or "-", "message": (lines[-1] if lines else "")[:150]}


def npz_bad(d: Path, kind: str) -> str:
    p = d / f"{kind}.npz"
    if kind == "empty":
        p.write_bytes(b"")
    elif kind == "truncated":
        np.savez(p, kappa=np.ones((4, 4, 4)))
        p.write_bytes(p.read_bytes()[:100])
    elif kind == "text":
        p.write_text("this is not an archive\n")
    elif kind == "pickle":
        np.savez(p, kappa=np.array([object()], dtype=object))
    elif kind == "missing-array":
        np.savez(p, other=np.ones(3))
    return str(p)


def synth(d: Path, nx: str, ny: str, nz: str, n: str, *extra: str) -> str:
    """Synthetic measurements ``d/m.npz`` (``glsldiff synth``) for a probe that needs good ones."""
    subprocess.run([GL, "synth", str(d / "m.npz"), "--size", nx, ny, nz, "--n", n, *extra], env=ENV, capture_output=True)
    return str(d / "m.npz")


PROBES = [
    # bad npz of each kind, each reader
    *[(f"scene volume npz: {k}", (lambda k: lambda d: ["render", scene(d, extra=f'volume = "{npz_bad(d, k)}"'), "-o", "r.exr"])(k))
      for k in ("empty", "truncated", "text", "pickle", "missing-array")],
    *[(f"fit measurements npz: {k}", (lambda k: lambda d: ["fit", npz_bad(d, k), "-o", "m.npz"])(k)) for k in ("empty", "text")],
    ("fit --truth npz: truncated", lambda d: ["fit", synth(d, "8", "8", "4", "2"), "--truth", npz_bad(d, "truncated"),
                                              "-o", str(d / "f.npz")]),
    ("reflectance material npz: text", lambda d: ["reflectance", synth(d, "8", "8", "4", "2", "--setup", "front"),
                                                  npz_bad(d, "text")]),
    # unwritable outputs
    ("polygrid --out names a file", lambda d: (d.joinpath("f").write_text("x"), ["polygrid", "cow", "--n", "4", "--out", "f"])[1]),
    ("polygrid --out unwritable", lambda d: ["polygrid", "cow", "--n", "4", "--out", "/proc/pg"]),
    ("demo --out names a file", lambda d: (d.joinpath("f").write_text("x"), ["demo", "--out", "f"])[1]),
    ("render -o /proc/x.exr", lambda d: ["render", scene(d), "-o", "/proc/x.exr"]),
    # argument ranges
    ("synth --seed -1", lambda d: ["synth", "m.npz", "--seed", "-1"]),
    ("synth --size -4 8 8", lambda d: ["synth", "m.npz", "--size", "-4", "8", "8"]),
    ("synth --noise nan", lambda d: ["synth", "m.npz", "--noise", "nan"]),
    ("fit --max-seconds 0", lambda d: ["fit", "m.npz", "--max-seconds", "0"]),
    ("polygrid --cube-size 0", lambda d: ["polygrid", "cow", "--cube-size", "0"]),
    ("[polygrid] n = 512", lambda d: ["render", scene(d, n=512), "-o", "r.exr"]),
    ("mesh at 1e-30 scale", lambda d: (d.joinpath("t.obj").write_text(
        "v 0 0 0\nv 1e-30 0 0\nv 0 1e-30 0\nv 0 0 1e-30\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"), ["polygrid", "t.obj"])[1]),
    ("mesh with a NaN vertex", lambda d: (d.joinpath("t.obj").write_text(
        "v 0 0 0\nv 10 0 0\nv 0 10 0\nv 0 0 nan\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"), ["polygrid", "t.obj"])[1]),
    ("render size_mm = 1e-9", lambda d: ["render", scene(d, size=1e-9), "-o", "r.exr"]),
    # silent wrong output
    ("kappa ~ 3e5 mm (sigma_s' = 1e-6/mm)", lambda d: ["render", scene(d, sp=1e-6), "-o", "r.exr"]),
    ("irradiance 1e38", lambda d: ["render", scene(d, e=1e38), "-o", "r.exr"]),
    ("zero source", lambda d: ["render", scene(d, e=0.0), "-o", "r.exr"]),
    # issue 44: tracebacks
    ("render -o r.exr, r.png a folder", lambda d: (d.joinpath("r.png").mkdir(), ["render", scene(d), "-o", "r.exr"])[1]),
    ("fit --max-seconds 1e-9", lambda d: ["fit", synth(d, "8", "8", "4", "2"), "-o", "f.npz", "--max-seconds", "1e-9"]),
    # issue 44: misleading or silent
    ("demo --size 3 3 3", lambda d: ["demo", "--size", "3", "3", "3"]),
    ("tet --light 0 0 0", lambda d: ["tet", "sphere", "--light", "0", "0", "0"]),
    ("scene path is a folder", lambda d: (d.joinpath("sc").mkdir(), ["render", "sc", "-o", "r.exr"])[1]),
    ("preset plus sigma_s_prime", lambda d: ["render", scene(d, extra='preset = "marble"'), "-o", "r.exr"]),
    ("light inside the object", lambda d: (d.joinpath("s.toml").write_text(SCENE.format(
        size=20, n=4, sp=1.0, e=1.0, extra="").replace('type = "directional"\ndirection = [0, 0, 1]\nirradiance = [1.0, 1.0, 1.0]',
                                                     'type = "point"\nposition = [0, 0, 0]')), ["render", "s.toml", "-o", "r.exr"])[1]),
    ("point light with a direction", lambda d: (d.joinpath("s.toml").write_text(SCENE.format(
        size=20, n=4, sp=1.0, e=1.0, extra="").replace('type = "directional"', 'type = "point"\nposition = [0, 0, 50]')),
        ["render", "s.toml", "-o", "r.exr"])[1]),
    ("OBJ face names vertex 99 of 4", lambda d: (d.joinpath("t.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 99\n"), ["tet", "t.obj"])[1]),
    ("block volume h_mm = 1e6", lambda d: (np.savez(d / "v.npz", kappa=np.full((2, 2, 2, 3), 0.3),
        mu=np.full((2, 2, 2, 3), 0.01), h_mm=1e6), ["render", scene(d, extra='volume = "v.npz"'), "-o", "r.exr"])[1]),
    ("edit --set mu -1", lambda d: (synth(d, "8", "8", "4", "2"), ["edit", str(d / "m_truth.npz"), "--set", "mu", "-1",
                                                                  "-o", "e.npz"])[1]),
    ("cut --stroke -500,-500", lambda d: ["cut", "--stroke", "-500,-500", "-o", "c.exr"]),
    # the capture pipeline (glsldiff capture STEP): bad input is one line and exit 2
    ("capture merge: no such bracket folder", lambda d: ["capture", "merge", "nowhere", "-o", "m.exr"]),
    ("capture camera: folder without images", lambda d: (d.joinpath("e").mkdir(), ["capture", "camera", "e",
                                                         "--board", "9x7", "--square", "20"])[1]),
    ("capture calibrate --board 9by7", lambda d: ["capture", "calibrate", "x", "--board", "9by7", "--square", "20",
                                                  "--projector", "512x384"]),
    ("capture patterns -o /proc/pat", lambda d: ["capture", "patterns", "--projector", "37x21", "-o", "/proc/pat"]),
    ("capture plan --face-corners 1,2 3 4,5 6,7", lambda d: ["capture", "plan", "p", "--shape", "6", "14", "14", "--h",
                                                             "0.5", "--face-corners", "1,2", "3", "4,5", "6,7"]),
    ("capture measure: no plan.json", lambda d: (d.joinpath("c").mkdir(), ["capture", "measure", "c", "--corners",
                                                 "1,1", "9,1", "9,9", "1,9", "-o", "m.npz"])[1]),
    ("capture white-balance: broken EXR", lambda d: (d.joinpath("w.exr").write_bytes(b"garbage"),
                                                     ["capture", "white-balance", "w.exr", "-o", "wb.json"])[1]),
    ("capture virtual: output folder not empty", lambda d: (d.joinpath("v").mkdir(),
                                                            d.joinpath("v", "x").write_text("x"),
                                                            ["capture", "virtual", "v"])[2]),
    ("capture without a step", lambda d: ["capture"]),
    # first run
    ("bare glsldiff", lambda d: []),
    ("validate without Mitsuba (if absent)", lambda d: ["validate", "--out", "v"]),
]

#: Probes that need an environment variable of their own: (name, variables, argv maker).
ENV_PROBES = [
    ("GLSLDIFF_GL=bogus glsldiff info", {"GLSLDIFF_GL": "bogus"}, lambda d: ["info"]),
]

INTERRUPTS = [
    ("Ctrl-C during render", lambda d: ["render", "-o", "r.exr"], 8.0),
    ("Ctrl-C during fit", lambda d: ["fit", synth(d, "12", "12", "6", "3"), "-o", "f.npz", "--no-png"], 20.0),
    ("Ctrl-C inside fTetWild (tet)", lambda d: ["tet", "bunny", "--edge", "1.5", "--out", "o"], 8.0),
    ("Ctrl-C inside SuperLU (demo 96x96x24)", lambda d: ["demo", "--size", "96", "96", "24"], 5.0),
    ("Ctrl-C inside fTetWild (cut)", lambda d: ["cut", "--plane", "0", "0", "1", "52", "--edge", "1.5", "-o", "c.exr"],
     8.0),
    ("Ctrl-C during bench fit", lambda d: ["bench", "fit", "--size", "24", "24", "8", "--out", "o"], 8.0),
    ("Ctrl-C during bench convergence", lambda d: ["bench", "convergence", "--out", "o"], 8.0),
]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Re-run the bad-input probes against the installed glsldiff and "
                                                 "print a Markdown table.")
    parser.add_argument("--only", metavar="TEXT", action="append",
                        help="run only the probes whose name contains TEXT (repeatable; e.g. --only capture)")
    args = parser.parse_args(argv)

    def chosen(name: str) -> bool:
        return not args.only or any(text in name for text in args.only)

    rows = [run(name, make) for name, make in PROBES if chosen(name)]
    rows += [run(name, make, env=env) for name, env, make in ENV_PROBES if chosen(name)]
    rows += [run(name, make, after) for name, make, after in INTERRUPTS if chosen(name)]
    print("| probe | exit | stderr lines | s | files left | message |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['probe']} | {r['exit']} | {r['err_lines']} | {r['seconds']} | {r['left']} | {r['message']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
