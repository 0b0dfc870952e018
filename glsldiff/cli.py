"""The ``glsldiff`` command: ``demo`` (default job), ``bench forward``, ``info``.

Errors a user can cause are printed as one line without a traceback (exit code 2).
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from pathlib import Path
from typing import Sequence

from glsldiff.errors import GlsldiffError


def _fmt(v: object) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "-"
        return f"{v:.3g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.2e}"
    return str(v)


def print_table(title: str, rows: Sequence[dict[str, object]]) -> None:
    """Print dict rows as a rich table."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    for key in rows[0]:
        table.add_column(key, justify="right")
    for row in rows:
        table.add_row(*(_fmt(v) for v in row.values()))
    console = Console()
    if not console.is_terminal:
        console = Console(width=200)
    console.print(table)


def _add_gl(p: argparse.ArgumentParser) -> None:
    p.add_argument("--gl", choices=("egl", "osmesa", "auto"),
                   help="GL backend (default: $GLSLDIFF_GL or egl)")


def cmd_demo(args: argparse.Namespace) -> int:
    from glsldiff import demo, gl

    cfg = demo.DemoConfig(nx=args.size[0], ny=args.size[1], nz=args.size[2], h=args.h,
                          tol=args.tol, precision=args.precision, out=Path(args.out), seed=args.seed)
    rows = demo.run(cfg, progress=not args.quiet)
    print_table(f"Back-lit marble slab {cfg.nx}x{cfg.ny}x{cfg.nz}, h = {cfg.h} mm, "
                f"{gl.describe(gl.get_context())}", rows)
    print("error_phi: relative L2 of the GPU fluence vs the scipy direct solve of the same system; "
          "error_image: same for the front-face radiance image; est_error: the solver's own estimate.")
    print(f"wrote {cfg.regions ** 2} EXR images, contact_sheet.png and report.csv to {cfg.out}/")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from glsldiff import bench

    rows = bench.forward(sizes=args.sizes, out=Path(args.out), max_direct_nodes=args.max_direct_nodes,
                         seconds=args.seconds, precisions=args.precision)
    print_table("glsldiff bench forward", rows)
    print(f"wrote forward.csv, forward_curves.csv and forward.png to {args.out}/")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from glsldiff import gl

    for backend in ("egl", "osmesa"):
        try:
            ctx = gl.create_context(backend)
            print(f"{backend}: {gl.describe(ctx)}; max texture {ctx.info['GL_MAX_TEXTURE_SIZE']}")
            ctx.release()
        except GlsldiffError as exc:
            print(f"{backend}: unavailable ({exc})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="glsldiff", description=__doc__)
    sub = parser.add_subparsers(dest="command")

    p = sub.add_parser("demo", help="back-lit marble slab, 4x4 projector regions (default job)")
    p.add_argument("--size", type=int, nargs=3, default=(64, 64, 12), metavar=("NX", "NY", "NZ"))
    p.add_argument("--h", type=float, default=0.5, help="node spacing, mm")
    p.add_argument("--tol", type=float, default=5e-7, help="Jacobi residual tolerance")
    p.add_argument("--precision", choices=("fp32", "fp16"), default="fp32")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="glsldiff-out")
    p.add_argument("--quiet", action="store_true")
    _add_gl(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("bench", help="benchmarks")
    bsub = p.add_subparsers(dest="bench", required=True)
    b = bsub.add_parser("forward", help="GLSL Jacobi vs numpy Jacobi vs scipy direct / pyamg, 1e4..1e6 nodes")
    b.add_argument("--sizes", nargs="+", default=["32x32x10", "80x80x16", "200x200x25"],
                   help="grids as NXxNYxNZ")
    b.add_argument("--seconds", type=float, default=20.0, help="time budget per iterative run")
    b.add_argument("--max-direct-nodes", type=int, default=200_000,
                   help="largest grid for the scipy direct (SuperLU) solve; above it the "
                        "pyamg solution is the reference")
    b.add_argument("--precision", nargs="+", default=["fp32", "fp16"], choices=("fp32", "fp16"))
    b.add_argument("--out", default="bench-out")
    _add_gl(b)
    b.set_defaults(func=cmd_bench)

    p = sub.add_parser("info", help="report the available GL backends and renderers")
    p.set_defaults(func=cmd_info)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not getattr(args, "command", None):
        args = build_parser().parse_args(["demo", *(argv or [])])
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if getattr(args, "gl", None):
        os.environ["GLSLDIFF_GL"] = args.gl
    try:
        return args.func(args)
    except GlsldiffError as exc:
        print(f"glsldiff: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
