"""Console tables for the apps and reports: rich on a terminal, markdown in a log file or a pipe."""

from __future__ import annotations

import sys
from collections.abc import Iterable, Sequence


def _markdown_cell(value) -> str:
    return str(value).replace("|", "\\|").replace("\n", " ")


def print_table(title: str, header: Sequence[str], rows: Iterable[Sequence], markdown: bool | None = None) -> None:
    """A console table: rich on a terminal, a markdown table when stdout is not one (a log file, a pipe).

    markdown=None picks by `sys.stdout.isatty()`. A rich table in a file is cut at the console's
    width (80 columns when there is no terminal); the markdown form is never cut, and pastes into docs."""
    rows = [[str(x) for x in row] for row in rows]
    if markdown is None:
        markdown = not sys.stdout.isatty()
    if markdown:
        cells = [[_markdown_cell(c) for c in header]] + [[_markdown_cell(c) for c in row] for row in rows]
        widths = [max(len(row[i]) for row in cells if i < len(row)) for i in range(len(header))]
        lines = ["| " + " | ".join(c.ljust(w) for c, w in zip(row, widths)) + " |" for row in cells]
        lines.insert(1, "|" + "|".join("-" * (w + 2) for w in widths) + "|")
        print("\n".join(["", f"{title}", "", *lines, ""]), flush=True)
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, title_justify="left")
    for column in header:
        table.add_column(str(column))
    for row in rows:
        table.add_row(*row)
    Console().print(table)
