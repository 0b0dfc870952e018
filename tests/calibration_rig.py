"""Settings and helpers shared by the geometric calibration tests (test_calibration_geometry.py,
test_capture_layout.py): the synthetic rig's sizes and board, and the one-line CLI error check."""
from __future__ import annotations

from glsldiff.calibration.camera import BoardSpec

CAM, PROJ = (640, 512), (512, 384)
BOARD = BoardSpec(9, 7, 20.0)
BOARD_ARGS = ["--board", "9x7", "--square", "20"]


def rel_err(a: float, b: float) -> float:
    return abs(a / b - 1.0)


def check_cli_error(capsys, rc: int, *needles: str) -> str:
    """The command returned 2 and printed one error line containing every ``needle``."""
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert err.startswith("glsldiff-calibration: error: ") and "\n" not in err, err
    for n in needles:
        assert n in err, err
    return err
