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


#: The widest printed table, characters: wider ones show their first columns and name the rest.
MAX_WIDTH = 100


def print_table(title: str, rows: Sequence[dict[str, object]], first: Sequence[str] = (),
                rest: str = "") -> None:
    """Print dict rows as a rich table; the columns are the union of the rows' keys, those named in
    ``first`` leading. A table wider than :data:`MAX_WIDTH` (or the terminal) shows the columns
    that fit and names the others on a line of their own, with ``rest`` saying where they are
    (e.g. "all in validation.csv")."""
    keys = list(dict.fromkeys(k for row in rows for k in row))
    keys = [k for k in first if k in keys] + [k for k in keys if k not in first]
    cells = [[format_cell(row[k]) if k in row else "" for k in keys] for row in rows]
    widths = [max([len(str(k))] + [len(c[i]) for c in cells]) + 3 for i, k in enumerate(keys)]
    console = Console()
    limit = min(MAX_WIDTH, console.width) if console.is_terminal else MAX_WIDTH
    shown, used = 0, 1
    while shown < len(keys) and (shown == 0 or used + widths[shown] <= limit):
        used += widths[shown]
        shown += 1
    table = Table(title=title)
    for key in keys[:shown]:
        table.add_column(key, justify="right")
    for line in cells:
        table.add_row(*line[:shown])
    Console(width=max(used, 40), soft_wrap=False).print(table)
    if shown < len(keys):
        print(f"not shown ({len(keys) - shown} columns, to keep the table within {limit} characters): "
              f"{', '.join(keys[shown:])}" + (f"; {rest}" if rest else ""))
