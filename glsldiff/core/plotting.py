"""matplotlib for the benches' and the fit's PNG figures, headless (Agg backend)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from glsldiff.core.io import atomic_path


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (no display needed)."""
    import matplotlib  # heavy import (~0.3 s), loaded only when a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg"): never opens a window

    return plt


def save_figure(fig: Any, path: str | Path, dpi: int = 110) -> None:
    """Lay ``fig`` out, write it to ``path`` as PNG (atomically: no half-written file) and
    close it."""
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    pyplot().close(fig)
