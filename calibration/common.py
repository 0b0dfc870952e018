"""Helpers shared by the calibration commands: one-line errors (their parser is
:class:`glsldiff.core.arguments.CommandParser`), JSON and folder outputs that appear only when
complete, ``WxH`` arguments."""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from glsldiff.core.errors import GlsldiffError, InputError
from glsldiff.core.io import atomic_path

PROG = "glsldiff-calibration"


def run_command(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> int:
    """Parse ``argv`` and run ``args.func(args)``; a user error, or a file that cannot be
    written, prints one line ``glsldiff-calibration: error: ...`` to stderr and returns 2."""
    try:
        args = parser.parse_args(argv)
        return int(args.func(args) or 0)
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 2
    except (GlsldiffError, OSError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2


def save_json(path: str | os.PathLike, data: dict) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_path(path, ".json") as tmp:
        tmp.write_text(json.dumps(data, indent=1))
    return Path(path)


@contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``path`` (which must not exist or be empty); it is
    renamed to ``path`` when the block succeeds and removed when it fails."""
    dest = Path(path)
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())):
        raise InputError(f"output folder {str(dest)!r} exists and is not empty")
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    try:
        yield tmp
        if dest.exists():
            dest.rmdir()
        os.replace(tmp, dest)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def parse_size(text: str) -> tuple[int, int]:
    """``"1024x768"`` -> ``(1024, 768)`` (argparse type)."""
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected WxH, e.g. 9x7 or 1024x768") from None
    if a <= 0 or b <= 0:
        raise argparse.ArgumentTypeError(f"{text!r}: both numbers must be > 0")
    return a, b


def parse_points(text: Sequence[str] | None, option: str, count: int = 4) -> np.ndarray | None:
    """``["X,Y", ...]`` -> ``(count, 2)`` float pixels (None when not given)."""
    if not text:
        return None
    try:
        pts = np.array([[float(v) for v in p.split(",")] for p in text])
    except ValueError:
        pts = np.zeros(0)
    if pts.shape != (count, 2):
        raise InputError(f"{option} {' '.join(text)}: expected {count} points X,Y (pixels)")
    return pts
