"""matplotlib for the benches' and the fit's PNG figures, headless (Agg backend)."""
from __future__ import annotations

from typing import Any


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (no display needed)."""
    import matplotlib  # heavy import (~0.3 s), loaded only when a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg"): never opens a window

    return plt
