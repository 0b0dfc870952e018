"""Settings and helpers shared by the calibration and capture tests (test_calibration_geometry.py,
test_capture_layout.py, test_calibration_radiometric.py, test_capture.py): the synthetic rig's
sizes and board, ``glsldiff capture`` in this process, and the one-line CLI error check."""
from __future__ import annotations

from typing import Sequence

from glsldiff.calibration.camera import BoardSpec
from glsldiff.commands.cli import main as glsldiff_main

CAM, PROJ = (640, 512), (512, 384)
BOARD = BoardSpec(9, 7, 20.0)
BOARD_ARGS = ["--board", "9x7", "--square", "20"]


def rel_err(a: float, b: float) -> float:
    return abs(a / b - 1.0)


#: How ``glsldiff`` starts the line of an error a user caused (exit status 2).
ERR = "glsldiff: error: "


def capture(argv: Sequence[str]) -> int:
    """``glsldiff capture ARGV...`` run in this process (``capture(["camera", ...])``): its exit
    status."""
    return glsldiff_main(["capture", *map(str, argv)])


def error_lines(err: str) -> list[str]:
    """The lines of a command's stderr, without the heartbeat's progress lines ("glsldiff: still
    working", printed when a step is quiet for 10 s on a slow machine)."""
    return [line for line in err.strip().splitlines() if not line.startswith("glsldiff: still working")]


def check_cli_error(capsys, rc: int, *needles: str) -> str:
    """The command returned 2 and printed one error line containing every ``needle``."""
    lines = error_lines(capsys.readouterr().err)
    assert rc == 2
    assert len(lines) == 1 and lines[0].startswith(ERR), lines
    err = lines[0]
    for n in needles:
        assert n in err, err
    return err
