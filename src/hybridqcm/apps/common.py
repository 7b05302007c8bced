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
    from rich.markup import escape

    # escape: messages quote shapes and install commands ("[batch, 2, N]", ".[tracking]") that rich would eat as markup
    Console(stderr=True).print(f"[bold red]error:[/] {escape(str(error))}", highlight=False, soft_wrap=True)
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


class ConfigError(ValueError):
    """An invalid setting or combination of settings, reported before any work; names key and value."""


def experiment_task(path: Path) -> str | None:
    """The `task:` an experiment config declares (train or estimate), None if unreadable or absent."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except yaml.YAMLError:
        return None
    return data.get("task") if isinstance(data, dict) else None


def experiments_for(task: str, config_dir: Path = CONFIG_DIR) -> list[str]:
    return sorted(p.stem for p in (Path(config_dir) / "experiment").glob("*.yaml") if experiment_task(p) == task)


def check_experiment_overrides(args: Sequence[str], task: str, config_dir: Path = CONFIG_DIR) -> None:
    """Fail early, before Hydra composes anything, on an unknown experiment or one of the other app's task.

    Experiments of both apps share configs/experiment/; each declares `task: train` or `task: estimate`."""
    app, other = {"train": ("qcm-train", "qcm-estimate"), "estimate": ("qcm-estimate", "qcm-train")}[task]
    for arg in args:
        key, _, value = arg.partition("=")
        if key.lstrip("+~") != "experiment" or not value or value == "null":
            continue
        for name in (n.strip() for n in value.split(",")):
            path = Path(config_dir) / "experiment" / f"{name}.yaml"
            if not path.is_file():
                raise ConfigError(f"unknown experiment {name!r} (no {path}); {app} experiments: "
                                  f"{', '.join(experiments_for(task, config_dir))}")
            declared = experiment_task(path)
            if declared != task:
                raise ConfigError(f"experiment {name!r} is not a{'n' if task == 'estimate' else ''} "
                                  f"{'estimation' if task == 'estimate' else 'training'} experiment (its config says "
                                  f"task: {declared}); {app} runs {', '.join(experiments_for(task, config_dir))}, "
                                  f"the others run with {other}")


def run_hydra_app(config_name: str, task: str, entry) -> None:
    """Console-script body: reject unknown / other-app experiments in one line, then hand over to Hydra."""
    import hydra

    try:
        check_experiment_overrides(sys.argv[1:], task)
    except ConfigError as error:
        fail(error)
    hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=config_name)(entry)()
