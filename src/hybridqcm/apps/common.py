"""Shared pieces of the Hydra entry points: config location, error exit, console tables."""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Iterable, NoReturn, Sequence

# The configs live at the repository root (configs/); HYBRIDQCM_CONFIG_DIR points elsewhere.
CONFIG_DIR = Path(os.environ.get("HYBRIDQCM_CONFIG_DIR", Path(__file__).resolve().parents[3] / "configs"))


def fail(error: BaseException | str, code: int = 2) -> NoReturn:
    """Print a one-line error (no traceback: the message names the file, key and value) and exit."""
    from rich.console import Console

    Console(stderr=True).print(f"[bold red]error:[/] {error}", highlight=False, soft_wrap=True)
    sys.exit(code)


def print_table(title: str, header: Sequence[str], rows: Iterable[Sequence], markdown: bool = False) -> None:
    """A console table (rich)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, title_justify="left")
    for column in header:
        table.add_column(str(column))
    for row in rows:
        table.add_row(*[str(x) for x in row])
    Console(width=max(120, Console().width)).print(table)
