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
    for key in keys:
        table.add_column(key, justify="right")
    for row in rows:
        table.add_row(*(format_cell(row[k]) if k in row else "" for k in keys))
    console = Console()
    if not console.is_terminal:
        console = Console(width=200)
    console.print(table)
