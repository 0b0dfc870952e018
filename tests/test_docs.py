"""Every code block of the README and of docs/ runs in a test, so what a user copies works.

* ```python blocks are executed (each in a fresh namespace, in a scratch folder);
* ```toml blocks are parsed as scenes (on top of a lit 20 mm sphere),
  with the image and volume files they name made in the scratch folder;
* ```bash blocks: every ``glsldiff`` command line is parsed by the real argument parser in the
  default run (an option that no longer exists, a misspelt sub-command or a bad value fails
  here), and executed for real, in order, in the slow run (``pytest -m slow``); the README's
  set-up commands are checked against ``.ci/run``, which runs them;
* ```text blocks are diagrams and printed output, not code.
"""
from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
try:
    import tomllib
except ModuleNotFoundError:        # Python 3.10
    import tomli as tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
LANGUAGES = ("python", "toml", "bash", "text")


@dataclass(frozen=True)
class Block:
    page: Path
    line: int
    lang: str
    text: str

    @property
    def id(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def _blocks() -> list[Block]:
    out = []
    for page in PAGES:
        lines = page.read_text().splitlines()
        i = 0
        while i < len(lines):
            m = re.match(r"^```(\S*)\s*$", lines[i])
            if m:
                j = i + 1
                while not lines[j].startswith("```"):
                    j += 1
                out.append(Block(page, i + 1, m.group(1), "\n".join(lines[i + 1:j]) + "\n"))
                i = j
            i += 1
    return out


BLOCKS = _blocks()


def _of(lang: str) -> list:
    return [pytest.param(b, id=b.id) for b in BLOCKS if b.lang == lang]


def test_every_block_names_its_language():
    """A fence without a language (or an unknown one) would escape every test below."""
    bad = [f"{b.id} ({b.lang or 'none'})" for b in BLOCKS if b.lang not in LANGUAGES]
    assert not bad, f"code blocks need one of {LANGUAGES}: {bad}"
    assert sum(b.lang == "bash" for b in BLOCKS) >= 5 and sum(b.lang == "python" for b in BLOCKS) >= 2


def test_readme_is_a_quick_start():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150


# --- shell blocks -------------------------------------------------------------------------------

def _commands(text: str) -> list[str]:
    """The command lines of a shell block: comments and continuation lines dropped, ``&&``
    chains split."""
    out = []
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        code = line.split("  #", 1)[0].strip()
        out += [c.strip() for c in code.split("&&") if c.strip()]
    return out


def _glsldiff_argv(command: str) -> list[str] | None:
    """The glsldiff arguments of ``command`` (after ``xvfb-run ...``, ``.venv/bin/``, env
    assignments), or None when it runs something else."""
    words = shlex.split(command)
    for k, w in enumerate(words):
        if w == "glsldiff" or w.endswith("/glsldiff"):
            return words[k + 1:]
    return None


SETUP = {"bash .ci/install", "GLSLDIFF_GL=osmesa .venv/bin/python -m pytest"}


def _other_command_ok(command: str) -> None:
    """Commands that are not glsldiff: the set-up ones must be what .ci/run runs; the docs build
    must be the one .ci/run runs (strict)."""
    ci = (ROOT / ".ci" / "run").read_text()
    if command in SETUP:
        assert command in ci, f"{command!r} is in the docs but not in .ci/run"
    elif command.startswith(".venv/bin/mkdocs build --strict"):
        assert ".venv/bin/mkdocs build --strict" in ci
    else:
        raise AssertionError(f"don't know how to test {command!r}: add it to tests/test_docs.py")


@pytest.mark.parametrize("block", _of("bash"))
def test_shell_block_parses(block: Block):
    from glsldiff.commands.cli import build_parser
    commands = _commands(block.text)
    assert commands, "an empty shell block"
    for command in commands:
        argv = _glsldiff_argv(command)
        if argv is None:
            _other_command_ok(command)
            continue
        try:
            build_parser().parse_args(argv)
        except SystemExit as exc:   # argparse printed the reason to stderr
            raise AssertionError(f"{block.id}: {command!r} does not parse (exit {exc.code})") from None


# The files the docs' commands and scenes name, made small in the scratch folder.
SCENE = """[mesh]
source = "sphere"
size_mm = 20.0

[output]
width = 96
height = 96

[[lights]]
type = "directional"
direction = [0.3, 1.0, 0.6]
"""


def _fixtures(folder: Path) -> None:
    from glsldiff.core.io import write_exr, write_npz, write_png
    (folder / "scene.toml").write_text(SCENE)
    yy, xx = np.mgrid[0:48, 0:64]
    stripes = ((xx // 8) % 2 * 255).astype(np.uint8)
    write_png(folder / "pattern.png", np.repeat(stripes[..., None], 3, axis=2))
    write_exr(folder / "sky.exr", np.ones((16, 32, 3), np.float32))
    kappa = np.full((6, 8, 8, 3), 0.3)
    write_npz(folder / "block.npz", kappa=kappa, mu=np.full_like(kappa, 0.01), h_mm=np.array(0.5))
    write_npz(folder / "material.npz", kappa=kappa, mu=np.full_like(kappa, 0.01), h=np.array(0.5))
    pts = np.random.default_rng(0).uniform(-10, 10, (64, 3))
    write_npz(folder / "edited.npz", kappa=np.full((64, 3), 0.3), mu=np.full((64, 3), 0.01),
              positions_mm=pts)


@pytest.mark.slow
@pytest.mark.parametrize("block", _of("bash"))
def test_shell_block_runs(block: Block, tmp_path: Path):
    """Each command of the block, in order, in one scratch folder (with the fixtures), exits 0."""
    _fixtures(tmp_path)
    env = dict(os.environ, GLSLDIFF_GL=os.environ.get("GLSLDIFF_GL", "osmesa"),
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    for command in _commands(block.text):
        if _glsldiff_argv(command) is None:
            _other_command_ok(command)     # the set-up and docs build: .ci/run runs them
            continue
        command = _headless(_from_path(command))
        if command.startswith("xvfb-run") and not shutil.which("xvfb-run"):
            pytest.skip("xvfb-run is not installed")
        done = subprocess.run(command, shell=True, cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=3600)
        assert done.returncode == 0, f"{block.id}: {command!r} exit {done.returncode}:\n{done.stderr[-2000:]}"
        assert "Traceback" not in done.stderr


def _from_path(command: str) -> str:
    """``.venv/bin/glsldiff ...`` (the README's, relative to the checkout) as ``glsldiff ...``: the
    scratch folder has no ``.venv``, and PATH starts with this interpreter's own bin folder."""
    return re.sub(r"(^|\s)\.venv/bin/glsldiff\b", r"\1glsldiff", command)


def _headless(command: str) -> str:
    """A ``glsldiff view`` line as a test can run it: closed 5 s after its first frame when the
    line itself does not close it (a user closes the window), under Xvfb when there is no display."""
    argv = _glsldiff_argv(command)
    if not argv or argv[0] != "view":
        return command
    if not {"--seconds", "--screenshot"} & set(argv):
        command += " --seconds 5"
    if not command.startswith("xvfb-run") and not os.environ.get("DISPLAY"):
        command = 'xvfb-run -a -s "-screen 0 1280x1024x24" ' + command
    return command


# --- python and toml blocks ---------------------------------------------------------------------

@pytest.mark.parametrize("block", _of("python"))
def test_python_block_runs(ctx, block: Block, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)          # files an example writes (edited.npz) land here
    namespace: dict = {"__name__": f"docs_example_{block.line}"}
    exec(compile(block.text, block.id, "exec"), namespace)
    out = capsys.readouterr().out
    assert "converged" in out and "NOT converged" not in out   # each example prints its solve report


@pytest.mark.parametrize("block", _of("toml"))
def test_toml_block_is_a_valid_scene(block: Block, tmp_path):
    from glsldiff.render.scene import parse_scene
    _fixtures(tmp_path)
    data = tomllib.loads(block.text)
    data = {**tomllib.loads(SCENE), **data}     # the sphere, its light and its output size
    parse_scene(data, block.id, tmp_path)


def test_cli_reference_covers_every_command_and_option():
    """The generated command-line reference (docs/reference/cli.md) has a section for every
    command and sub-command, and every option says what it does."""
    from glsldiff.commands.cli import build_parser
    from glsldiff.commands.reference import _subparsers, cli_markdown
    text = cli_markdown()

    def paths(parser, prefix):
        for name, _, sub in _subparsers(parser):
            yield f"{prefix} {name}"
            yield from paths(sub, f"{prefix} {name}")
    missing = [p for p in paths(build_parser(), "glsldiff") if f"`{p}`" not in text]
    assert not missing and "glsldiff capture calibrate" in text
    silent = [line for line in text.splitlines() if line.startswith("| `") and line.rstrip().endswith("|  |")]
    assert not silent, silent
