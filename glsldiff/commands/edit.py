"""``glsldiff edit``: scripted material edits of a volume file, without a window (Wang et al.
2008, section 5.4), with the same implementation the GPU pass is tested against
(:mod:`glsldiff.physics.editing`).

Volumes: a block (``kappa``, ``mu`` of shape ``(nz, ny, nx, 3)``, voxel size ``h_mm`` or
``h``: ``glsldiff fit -o``, ``glsldiff synth``'s truth, a scene's ``[material].volume``), edited
in the orthographic view of its captured face (voxel = pixel, depth = z); or a node material
(``kappa``, ``mu``, ``positions_mm`` of shape ``(N, 3)``: the viewer's save, a scene's
``[material].nodes``), which has no face: only whole-volume edits there.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from glsldiff.core import arguments as A
from glsldiff.core.errors import InputError
from glsldiff.core.io import check_output, read_mask, read_npz, write_npz
from glsldiff.physics.editing import PROPERTIES, Brush, Edit, apply_edit, block_positions, block_view
from glsldiff.render.scene import block_arrays, node_arrays


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("edit", help="edit kappa or mu of a volume file (block or node material): set, multiply or "
                                    "add, inside a brush, a mask image and a depth range")
    p.add_argument("volume", help="block volume .npz (kappa, mu (nz, ny, nx, 3), h_mm or h) or node material .npz "
                                  "(kappa, mu, positions_mm)")
    op = p.add_mutually_exclusive_group(required=True)
    for name, what in (("set", "paint VALUE"), ("multiply", "multiply by VALUE"), ("add", "add VALUE")):
        op.add_argument(f"--{name}", nargs="+", metavar=("PROP", "VALUE"),
                        help=f"{what} (1 or 3 numbers) into PROP = kappa (mm) or mu (mm^-1)")
    p.add_argument("--mask", default=None, help="pattern image stretched over the block's face (PNG grey/255, or EXR)")
    p.add_argument("--depth", default=None, metavar="D0:D1", help="depth range below the face, mm (e.g. 0.5:1.5; "
                                                                  "an empty end is open)")
    p.add_argument("--brush", type=float, nargs=3, default=None, metavar=("X", "Y", "R"),
                   help="a disc on the face: centre x, y and radius, mm (voxel (i, j) at x = i h, y = j h)")
    p.add_argument("--feather", type=A.number(0.0, 1.0), default=0.25, help="soft share of the brush radius")
    p.add_argument("--strength", type=A.number(0.0, 1.0), default=1.0, help="edit weight in [0, 1]")
    p.add_argument("-o", "--out", required=True, help="edited volume (.npz; the input's other arrays are kept)")
    p.set_defaults(func=cmd_edit)


def _op(args: argparse.Namespace) -> tuple[str, str, tuple[float, ...]]:
    for name in ("set", "multiply", "add"):
        given = getattr(args, name)
        if given is None:
            continue
        prop, values = given[0], given[1:]
        if prop not in PROPERTIES:
            raise InputError(f"--{name} {prop}: the property is kappa or mu (e.g. --{name} mu 2)")
        if len(values) not in (1, 3):
            raise InputError(f"--{name} {prop}: give 1 or 3 values (RGB), got {len(values)}")
        try:
            return name, prop, tuple(float(v) for v in values)
        except ValueError:
            raise InputError(f"--{name} {prop}: values must be numbers, got {' '.join(values)}") from None
    raise InputError("give one of --set, --multiply, --add")


def _depth(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    lo, sep, hi = text.partition(":")
    try:
        if not sep:
            raise ValueError
        return (float(lo) if lo.strip() else -np.inf, float(hi) if hi.strip() else np.inf)
    except ValueError:
        raise InputError(f"--depth {text!r}: give D0:D1 in mm below the surface, e.g. 0.5:1.5") from None


def cmd_edit(args: argparse.Namespace) -> int:
    out = check_output(args.out, (".npz",))
    src = Path(args.volume)
    if out.resolve() == src.resolve():
        raise InputError(f"-o {args.out}: write the edit to a new file (the input is kept as it is)")
    what = "volume file"
    arrays = read_npz(src, what, ("kappa", "mu"))
    name, prop, value = _op(args)
    if "positions_mm" in arrays:
        kappa, mu, pos = node_arrays(arrays, src, what)
        if args.mask or args.depth or args.brush:
            raise InputError(f"{src}: a node material has no face to place --mask, --depth or --brush on; restrict "
                             "edits in the viewer (glsldiff view), or edit a block volume here")
        view, shape = None, (len(pos),)
    else:
        kappa, mu, h = block_arrays(arrays, src, what)
        shape = kappa.shape[:3]
        pos, view = block_positions(shape, h), block_view(shape, h)   # (block_arrays added h_mm to a fit's h)
    brush = None
    if args.brush is not None:
        x, y, r = args.brush
        if not (np.isfinite([x, y, r]).all() and r > 0):
            raise InputError(f"--brush {x} {y} {r}: give a finite centre and a positive radius, mm")
        brush = Brush((x / h + 0.5, y / h + 0.5), r / h, args.feather)
    edit = Edit(prop, name, value, brush=brush, mask=read_mask(args.mask) if args.mask else None,
                depth=_depth(args.depth), strength=args.strength)
    k2, m2, res = apply_edit(edit, kappa.reshape(-1, 3), mu.reshape(-1, 3), pos, view)
    arrays["kappa"], arrays["mu"] = k2.reshape(kappa.shape), m2.reshape(mu.shape)
    log = [str(x) for x in np.atleast_1d(arrays.get("edit_log", np.array([], dtype=str)))]
    arrays["edit_log"] = np.array(log + [edit.describe()])
    write_npz(out, **arrays)
    total = int(np.prod(shape))
    print(f"{edit.describe()}: {res.describe()} of {total:,} {'voxels' if view is not None else 'nodes'}; "
          f"wrote {out}")
    if res.edited == 0:
        print("note: the edit reached no voxel (check --brush, --mask and --depth against the volume's size)")
    return 0


# ---------------------------------------------------------------- glsldiff view
def add_view_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="interactive viewer and material editor (a window; pip install glsldiff[viewer])")
    p.add_argument("scene", nargs="?", help="scene file (TOML) shown first; the built-in presets follow (Tab)")
    p.add_argument("--example", metavar="NAME", help="a shipped example scene shown first")
    p.add_argument("--size", type=A.integer(64, 8192), nargs=2, default=(640, 480), metavar=("W", "H"),
                   help="window size, pixels")
    p.add_argument("--mask", default=None, help="pattern mask image for the brush (M toggles it)")
    p.add_argument("--save", "--save-material", dest="save", default="edited.npz",
                   help="where Ctrl+S saves the edited material (.npz; a screenshot is --screenshot)")
    p.add_argument("--shots", default=".", help="folder for screenshots (F12 / P)")
    p.add_argument("--screenshot", metavar="PATH", default=None,
                   help="write the first converged frame (no overlay) to this PNG, then close (with "
                        "--seconds: stay open that long)")
    p.add_argument("--frame-sweeps", type=A.integer(1, 100000), default=10,
                   help="pass-2 sweeps per frame while a warm start converges (frame coherence)")
    p.add_argument("--seconds", type=A.number(0.0, lo_open=True), default=None,
                   help="close this many seconds after the first frame is shown (demos, smoke tests)")
    p.set_defaults(func=cmd_view)


def cmd_view(args: argparse.Namespace) -> int:
    from glsldiff.render.scene import example_scene, load_scene
    from glsldiff.viewer.presets import presets
    from glsldiff.viewer.window import Viewer
    if args.scene and args.example:
        raise InputError("give a scene file or --example NAME, not both")
    check_output(args.save, (".npz",), "--save is the edited material; a screenshot is --screenshot PATH.png")
    shot = check_output(args.screenshot, (".png",)) if args.screenshot else None
    first = ((Path(args.scene).name, load_scene(args.scene)) if args.scene
             else (f"example {args.example}", example_scene(args.example)) if args.example else None)
    mask = read_mask(args.mask) if args.mask else None
    v = Viewer(presets(first), *args.size, mask=mask, save_path=args.save, shots=args.shots,
               frame_sweeps=args.frame_sweeps, log=lambda line: print(line, flush=True))
    try:
        v.run(args.seconds, shot)      # the screenshot, when written, is logged ("screenshot PATH")
    finally:
        v.close()
    times = v.frame_times
    if times:
        print(f"viewer closed: {len(times)} frames, median {1e3 * float(np.median(times)):.0f} ms")
    return 0
