"""Printed tables: every command and benchmark prints its rows through :func:`print_table`."""
from __future__ import annotations

import math
from typing import Sequence

from rich.console import Console
from rich.table import Table

__all__ = ["print_table", "format_cell"]


def format_cell(v: object) -> str:
    """A table cell: floats to 3 significant digits (``-`` for NaN), everything else ``str``."""
    if isinstance(v, float):
        if math.isnan(v):
            return "-"
        return f"{v:.3g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.2e}"
    return str(v)


def print_table(title: str, rows: Sequence[dict[str, object]]) -> None:
    """Print dict rows as a rich table; the columns are the union of the rows' keys."""
    table = Table(title=title)
    keys = list(dict.fromkeys(k for row in rows for k in row))
    cells = [[format_cell(row[k]) if k in row else "" for k in keys] for row in rows]
    for key in keys:
        table.add_column(key, justify="right")
    for line in cells:
        table.add_row(*line)
    console = Console()
    if not console.is_terminal:  # a file or pipe: wide enough that no cell is cut or wrapped
        widths = [max([len(str(k))] + [len(c[i]) for c in cells]) for i, k in enumerate(keys)]
        console = Console(width=max(80, sum(w + 3 for w in widths) + 1))
    console.print(table)
