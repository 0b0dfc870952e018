"""The command-line reference as Markdown, generated from the argument parsers (the docs'
``reference/cli.md``; docs/hooks.py inserts it at build time), so it cannot drift from the
commands."""
from __future__ import annotations

import argparse
import re

from glsldiff.commands.cli import build_parser


def _escape(text: str) -> str:
    """Help text as a Markdown table cell: no pipes, stars or newlines break the table."""
    text = re.sub(r"\s+", " ", text).strip()
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("*", "\\*").replace("<", "&lt;")


def _option_rows(parser: argparse.ArgumentParser) -> list[str]:
    fmt = parser._get_formatter()
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if action.help == argparse.SUPPRESS:
            continue
        if action.option_strings:
            name = ", ".join(action.option_strings)
            if action.nargs != 0:
                name += " " + fmt._format_args(action, fmt._get_default_metavar_for_optional(action))
        else:
            name = fmt._format_args(action, fmt._get_default_metavar_for_positional(action))
        helptext = fmt._expand_help(action) if action.help else ""
        default = action.default
        hidden = default is None or default is False or default == argparse.SUPPRESS
        shown = "" if hidden or action.nargs == 0 else f"`{default}`"
        rows.append(f"| `{name}` | {shown} | {_escape(helptext)} |")
    return rows


def _subparsers(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of each sub-command, in the order they were added."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            for name, sub in action.choices.items():
                out.append((name, helps.get(name, ""), sub))
    return out


def _command(parser: argparse.ArgumentParser, path: str, helptext: str, level: int) -> list[str]:
    lines = [f"{'#' * level} `{path}`", ""]
    if helptext:
        lines += [_escape(helptext)[:1].upper() + _escape(helptext)[1:] + ".", ""]
    usage = re.sub(r"\s+", " ", parser.format_usage()).strip().removeprefix("usage: ")
    lines += [f"Usage: `{usage}`", ""]
    rows = _option_rows(parser)
    if rows:
        lines += ["| argument | default | meaning |", "| --- | --- | --- |", *rows, ""]
    for name, sub_help, sub in _subparsers(parser):
        lines += _command(sub, f"{path} {name}", sub_help, min(level + 1, 4))
    return lines


def cli_markdown() -> str:
    """Every ``glsldiff`` command and sub-command with its usage line and an options table."""
    parser = build_parser()
    lines = []
    for name, sub_help, sub in _subparsers(parser):
        lines += _command(sub, f"glsldiff {name}", sub_help, 2)
    return "\n".join(lines)
