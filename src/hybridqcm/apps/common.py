"""Shared pieces of the Hydra entry points: config location, error exit, console tables."""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Iterable, NoReturn, Sequence

def _register_resolvers() -> None:
    """${hybridqcm_pid:} in configs/hydra/default.yaml: run folders unique across processes."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("hybridqcm_pid"):
        OmegaConf.register_new_resolver("hybridqcm_pid", lambda: os.getpid())


_register_resolvers()

# The configs live at the repository root (configs/); HYBRIDQCM_CONFIG_DIR points elsewhere.
CONFIG_DIR = Path(os.environ.get("HYBRIDQCM_CONFIG_DIR", Path(__file__).resolve().parents[3] / "configs"))


def fail(error: BaseException | str, code: int = 2) -> NoReturn:
    """Print a one-line error (no traceback: the message names the file, key and value) and exit."""
    from rich.console import Console

    Console(stderr=True).print(f"[bold red]error:[/] {error}", highlight=False, soft_wrap=True)
    sys.exit(code)


def install_signal_handlers() -> None:
    """Ctrl-C and SIGTERM raise hybridqcm.interrupt.Interrupted, kept pending until the app exits."""
    from hybridqcm import interrupt

    interrupt.install()


def interrupted_exit(error: KeyboardInterrupt) -> NoReturn:
    """Exit after Ctrl-C / SIGTERM with 128 + signal number (130 / 143) and one line."""
    import signal

    signum = getattr(error, "signum", signal.SIGINT)
    name = signal.Signals(signum).name
    print(f"error: interrupted by {name}; temporary files removed, outputs left as they were", file=sys.stderr)
    sys.exit(128 + int(signum))


def check_writable_dir(path: str | Path, key: str = "hydra.run.dir") -> Path:
    """Create `path` if needed and prove it writable (a probe file), before any work; ConfigError otherwise."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".write-probe-{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as error:
        raise ConfigError(f"{key}={path}: run folder is not writable ({error.strerror or error})") from None
    return path


def check_task_name(name) -> None:
    """task_name names a folder under outputs/: one plain path component, no separators or '..'."""
    text = str(name)
    if not text or text in (".", "..") or "/" in text or "\\" in text or "\0" in text:
        raise ConfigError(f"task_name={text!r} must be a plain folder name (no '/', '..' or empty)")


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


from hybridqcm.errors import ConfigError  # noqa: E402 - kept importable here (apps.common.ConfigError)


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

    install_signal_handlers()
    try:
        check_experiment_overrides(sys.argv[1:], task)
        check_task_name_overrides(sys.argv[1:])
    except ConfigError as error:
        fail(error)
    try:
        hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=config_name)(entry)()
    except KeyboardInterrupt as error:
        interrupted_exit(error)


def check_task_name_overrides(args: Sequence[str]) -> None:
    """Refuse task_name=../x before Hydra builds (and creates) a run folder from it."""
    for arg in args:
        key, sep, value = arg.partition("=")
        if sep and key.lstrip("+~") == "task_name":
            check_task_name(value)
