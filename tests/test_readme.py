"""The README's Python examples run verbatim (each ```python block, in order, in a fresh
namespace), so the first thing a user copies works."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_readme_has_examples():
    assert len(BLOCKS) >= 2


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_example_runs(ctx, index, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)          # files an example writes (edited.npz) land here
    namespace: dict = {"__name__": f"readme_example_{index}"}
    exec(compile(BLOCKS[index], f"README.md python block {index + 1}", "exec"), namespace)
    out = capsys.readouterr().out
    assert "converged" in out and "NOT converged" not in out   # each example prints its solve report
