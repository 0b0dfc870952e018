"""MkDocs hooks (mkdocs.yml `hooks:`): the command-line reference is generated from the
argument parsers when the site is built (glsldiff.commands.reference)."""
from __future__ import annotations

MARKER = "<!-- cli-reference -->"


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ANN001 (MkDocs API)
    if MARKER not in markdown:
        return markdown
    from glsldiff.commands.reference import cli_markdown
    return markdown.replace(MARKER, cli_markdown())
