"""Shared pieces of the Hydra entry points: config location, error exit, console tables, a quiet console."""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from hybridqcm.config import CONFIG_DIR, check_experiment_overrides, check_schema_overrides, check_task_name
from hybridqcm.errors import ConfigError


def _register_resolvers() -> None:
    """${hybridqcm_pid:} in configs/hydra/default.yaml: run folders unique across processes;
    ${hybridqcm_groups:NAME}: the config groups app NAME takes, for its --help."""
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("hybridqcm_pid"):
        OmegaConf.register_new_resolver("hybridqcm_pid", lambda: os.getpid())
    if not OmegaConf.has_resolver("hybridqcm_groups"):
        OmegaConf.register_new_resolver("hybridqcm_groups", lambda name: app_groups_help(str(name)))


def app_groups_help(config_name: str, config_dir: Path | None = None) -> str:
    """One line per config group the app's defaults list names (not Hydra's own), with its options from
    the app's search path: configs/ and its own configs/apps/<app>/ (its experiments). Hydra's default --help
    listed every folder of configs/, the groups of the other apps included, which this app then refuses."""
    import yaml

    root = Path(config_dir or CONFIG_DIR)
    data = yaml.safe_load((root / f"{config_name}.yaml").read_text()) or {}
    lines = []
    for entry in data.get("defaults") or []:
        if not isinstance(entry, dict):
            continue
        group = str(next(iter(entry))).split("@")[0].removeprefix("override ").strip()
        folders = [f for f in (root / group, root / "apps" / config_name / group) if f.is_dir()]
        if group == "hydra" or not folders:
            continue
        lines.append(f"{group}: {', '.join(sorted({p.stem for f in folders for p in f.glob('*.yaml')}))}")
        lines += [
            f"{group}/{sub.name}: {', '.join(sorted(p.stem for p in sub.glob('*.yaml')))}"
            for folder in folders
            for sub in sorted(folder.iterdir())
            if sub.is_dir() and any(sub.glob("*.yaml"))
        ]
    return "\n".join(lines) or "(none)"


_register_resolvers()


def fail(error: BaseException | str, code: int = 2) -> NoReturn:
    """Print a one-line error (no traceback: the message names the file, key and value) and exit."""
    from rich.console import Console
    from rich.markup import escape

    # escape: messages quote shapes and install commands ("[batch, 2, N]", ".[tracking]") that rich would eat as markup
    Console(stderr=True).print(f"[bold red]error:[/] {escape(str(error))}", highlight=False, soft_wrap=True)
    sys.exit(code)


def install_signal_handlers() -> None:
    """Ctrl-C and SIGTERM raise hybridqcm.interrupt.Interrupted, kept pending until the app exits."""
    from hybridqcm import interrupt

    interrupt.install()


def interrupted_exit(error: KeyboardInterrupt) -> NoReturn:
    """Exit after Ctrl-C / SIGTERM with 128 + signal number (130 / 143) and one line."""
    import signal

    from hybridqcm.atomic import remove_temporaries

    remove_temporaries()  # what a writer stopped before its own cleanup left (atomic.new_temporary)
    signum = getattr(error, "signum", signal.SIGINT)
    name = signal.Signals(signum).name
    print(f"error: interrupted by {name}; temporary files removed, outputs left as they were", file=sys.stderr)
    sys.exit(128 + int(signum))


class _DropMessages(logging.Filter):
    """Drops log records whose message contains one of ``fragments``."""

    def __init__(self, *fragments: str):
        super().__init__()
        self.fragments = fragments

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        return not any(fragment in message for fragment in self.fragments)


# Third-party messages that say nothing actionable about a qcm run (matched on their text):
_NOISE_WARNINGS = (
    # lightning 2.6 calls a torch pytree API that torch deprecates; nothing of ours to change.
    r".*isinstance\(treespec, LeafSpec\)",
    # the worker count is a config choice (data.num_workers); 0 is right on a 2-core machine.
    r".*does not have many workers",
    # SimulatedStream shards its samples with get_worker_info(), so its __len__ is exact.
    r".*Your `IterableDataset` has `__len__` defined",
)
_NOISE_LOGS = (
    "litlogger",
    "Trainer already configured with model summary callbacks",
    # on a GPU, logged at every stage's setup (fit, then test): repeats what "GPU available" says
    "- CUDA_VISIBLE_DEVICES: [",
)
_LIGHTNING_LOGGERS = ("lightning", "lightning.pytorch", "lightning.fabric", "pytorch_lightning", "lightning_fabric")


def quiet_third_party() -> None:
    """The console of our entry points: each log line once, without third-party chatter.

    Call it inside the Hydra job, after Hydra has configured logging (root: console + run-folder
    file). `import lightning` attaches its own console handler to the "lightning" logger (and, if
    imported before Hydra configured the root logger, to "lightning.pytorch"/"lightning.fabric"
    with propagation off), so each Lightning INFO line printed twice, or never reached the run's
    log file. Here those handlers go and the records propagate to Hydra's handlers: printed once,
    and kept in `<run>/<task>.log`. Only our console scripts call this; importing the library
    changes no logging or warning state."""
    import lightning  # noqa: F401  (attach its handlers now, so they can be removed before any run logs)

    root = logging.getLogger()
    if root.handlers:  # Hydra (or the caller) configured logging: route Lightning's records there
        for name in _LIGHTNING_LOGGERS:
            logger = logging.getLogger(name)
            for handler in list(logger.handlers):
                if type(handler) is logging.StreamHandler and handler.stream in (sys.stderr, sys.stdout):
                    logger.removeHandler(handler)
            logger.propagate = True
    noise = _DropMessages(*_NOISE_LOGS)
    for name in (
        "lightning.pytorch.utilities.rank_zero",
        "lightning.fabric.utilities.rank_zero",
        "lightning.pytorch.accelerators.cuda",
    ):
        logger = logging.getLogger(name)
        if not any(isinstance(f, _DropMessages) for f in logger.filters):
            logger.addFilter(noise)
    for pattern in _NOISE_WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)


def run_hydra_app(config_name: str, task: str, entry) -> None:
    """Console-script body: reject unknown / other-app experiments and settings its schema refuses (a
    structured config registered as ``schema/<config_name>``) in one line, then hand over to Hydra.

    The Hydra job quiets third-party output (`quiet_third_party`) before it calls ``entry(cfg)``."""
    import hydra

    install_signal_handlers()
    try:
        check_experiment_overrides(sys.argv[1:], task)
        check_schema_overrides(sys.argv[1:], config_name)
        check_task_name_overrides(sys.argv[1:])
    except ConfigError as error:
        fail(error)

    @functools.wraps(entry)
    def job(cfg):
        quiet_third_party()
        with run_folder(f"qcm-{config_name}"), disk_full_is_one_line():
            return entry(cfg)

    try:
        hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name=config_name)(job)()
    except KeyboardInterrupt as error:
        interrupted_exit(error)


def check_task_name_overrides(args: Sequence[str]) -> None:
    """Refuse task_name=../x, and a hydra.run.dir another live run holds, before Hydra builds (and
    writes into) a run folder."""
    from hybridqcm import runfiles

    for arg in args:
        key, sep, value = arg.partition("=")
        if sep and key.lstrip("+~") == "task_name":
            check_task_name(value)
        if sep and key.lstrip("+~") == "hydra.run.dir" and value:
            runfiles.check_free(value)


@contextlib.contextmanager
def disk_full_is_one_line():
    """A write that failed for want of room (ENOSPC, EDQUOT, EFBIG of `ulimit -f`) ends the app with one
    line naming the file; outputs are written atomically, so none is left half-written."""
    from hydra.core.hydra_config import HydraConfig

    from hybridqcm.data.h5file import DISK_FULL, disk_error_message

    try:
        yield
    except OSError as error:
        if error.errno not in DISK_FULL:
            raise
        run_dir = HydraConfig.get().runtime.output_dir if HydraConfig.initialized() else "."
        where = error.filename or f"an output in hydra.run.dir={run_dir}"
        after = "the run is incomplete (no summary or completion marker): rerun it"
        fail(disk_error_message(where, error, after, folder=run_dir))


def _process_rank() -> int:
    """This process's global rank as launchers set it (Lightning's order of variables); 0 when alone."""
    for key in ("RANK", "LOCAL_RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK"):
        value = os.environ.get(key)
        if value is not None and value.strip().isdigit():
            return int(value)
    return 0


@contextlib.contextmanager
def run_folder(app: str):
    """The Hydra job's run folder held for this job: locked against a second run (one line naming
    the holder), its file manifest frozen on the way out (hybridqcm/runfiles.py). Only the process
    of global rank zero holds it (the ranks of one job share the folder)."""
    from hydra.core.hydra_config import HydraConfig

    from hybridqcm import runfiles

    if not HydraConfig.initialized() or _process_rank() != 0:
        yield None
        return
    run_dir = HydraConfig.get().runtime.output_dir
    try:
        runfiles.lock(run_dir, app)
    except ConfigError as error:
        fail(error)
    try:
        yield run_dir
    finally:
        runfiles.release(run_dir)
