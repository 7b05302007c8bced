"""Run tracking: hyper-parameters with the final metrics, logger packages, estimation results in TensorBoard.

- `log_test_hparams`: after the test, each TensorBoard logger gets the run's hyper-parameters
  together with its test metrics (`log_hyperparams(params, metrics)`), which is what fills
  TensorBoard's HPARAMS tab: point `tensorboard --logdir` at a sweep folder and every job is one
  row with its metrics. (`default_hp_metric: false` keeps Lightning from logging a placeholder
  hp_metric at fit start; this is the one hparams record of a run.)
- `check_logger_packages`: a logger whose package is an optional extra (MLflow) fails before any
  work, in one line naming the extra to install.
- `log_estimation_to_tensorboard`: the estimation error-distribution table (markdown text) and
  the sorted-prediction plots (images) into a TensorBoard event file, beside the GN losses.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

# logger class name -> (module it imports, pyproject extra that installs it)
OPTIONAL_LOGGER_PACKAGES = {
    "MLFlowLogger": ("mlflow", "tracking"),
    "WandbLogger": ("wandb", None),
    "CometLogger": ("comet_ml", None),
    "NeptuneLogger": ("neptune", None),
}
# top-level config keys recorded as hyper-parameters (the rest is paths and bookkeeping)
HPARAM_KEYS = ("task_name", "seed", "model", "data", "trainer", "ckpt_path", "denoiser_ckpt", "optimized_metric")


class TrackingError(ValueError):
    """A logger that cannot run here (its package is missing); the message names the install command."""


def check_logger_packages(logger_cfg: Mapping | None) -> None:
    """Raise TrackingError for a configured logger whose optional package is not installed."""
    for key, entry in (logger_cfg or {}).items():
        target = (entry or {}).get("_target_") if hasattr(entry, "get") else None
        if not target:
            continue
        module, extra = OPTIONAL_LOGGER_PACKAGES.get(str(target).rsplit(".", 1)[-1], (None, None))
        if module and importlib.util.find_spec(module) is None:
            how = f"pip install -e '.[{extra}]'" if extra else f"pip install {module}"
            raise TrackingError(f"logger.{key} ({target}) needs the package {module!r}, which is not installed: {how}")


def hparams_of(cfg) -> dict[str, Any]:
    """The run's hyper-parameters: resolved HPARAM_KEYS of the config, plus the Hydra group choices when run by Hydra."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    params: dict[str, Any] = {}
    for key in HPARAM_KEYS:
        if key not in cfg:
            continue
        value = cfg[key]
        try:
            params[key] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
        except OmegaConfBaseException:  # an interpolation only Hydra's runtime resolves; keep it unresolved
            params[key] = OmegaConf.to_container(value, resolve=False)
    try:
        from hydra.core.hydra_config import HydraConfig

        choices = OmegaConf.to_container(HydraConfig.get().runtime.choices)
        params["choices"] = {
            k: ",".join(map(str, v)) if isinstance(v, list) else v
            for k, v in choices.items()
            if k != "hydra" and not k.startswith("hydra/") and v is not None
        }  # callbacks=[a,b] -> "a,b"
    except (ImportError, ValueError):  # composed outside a Hydra run (tests, API use)
        pass
    return params


def log_test_hparams(loggers: Iterable, params: Mapping[str, Any], metrics: Mapping[str, float]) -> int:
    """Log `params` with the final `metrics` to every TensorBoard logger; returns how many got them.

    Other loggers (CSV, MLflow) already hold the metrics from the test and their hyper-parameters
    from fit start; TensorBoard's HPARAMS tab is the one view that needs them linked."""
    from lightning.pytorch.loggers import TensorBoardLogger

    count = 0
    finite = {k: float(v) for k, v in metrics.items() if v == v and abs(float(v)) != float("inf")}
    for logger in loggers or []:
        if isinstance(logger, TensorBoardLogger) and finite:
            logger.log_hyperparams(dict(params), metrics=finite)
            logger.experiment.flush()
            count += 1
    return count


def _markdown(rows: Sequence[Mapping[str, Any]], title: str | None) -> str:
    from hybridqcm.metrics import rows_to_markdown

    if rows and all({"param", "max_err", "within_1pct"} <= set(r) for r in rows):
        return rows_to_markdown(rows, title)
    fields: list[str] = []
    for row in rows:
        fields += [k for k in row if k not in fields]
    lines = ([f"**{title}**", ""] if title else []) + ["| " + " | ".join(fields) + " |", "|" + "---|" * len(fields)]
    lines += [
        "| "
        + " | ".join(f"{r.get(f, ''):.4g}" if isinstance(r.get(f), float) else str(r.get(f, "")) for f in fields)
        + " |"
        for r in rows
    ]
    return "\n".join(lines) + "\n"


def log_estimation_to_tensorboard(
    log_dir: str | Path,
    table_rows: Sequence[Mapping[str, Any]],
    plot_paths: Iterable[str | Path],
    step: int = 0,
    title: str | None = None,
    prefix: str = "estimation",
) -> Path:
    """Write the error-distribution table and the plots (PNG files) to a TensorBoard event file in `log_dir`.

    table_rows: metrics.error_distribution_rows output (rendered as in error_distribution.md) or any
    list of flat dicts (a generic markdown table); tag `<prefix>/error_distribution` (TEXT tab).
    plot_paths: PNG files, each logged as image `<prefix>/<file stem>` (IMAGES tab), RGB [H, W, 3].
    Returns log_dir. Use the GN loss log_dir to see both in one TensorBoard run."""
    import matplotlib.image as mpimg
    from torch.utils.tensorboard import SummaryWriter

    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    writer = SummaryWriter(log_dir=str(log_dir))
    try:
        if table_rows:
            writer.add_text(f"{prefix}/error_distribution", _markdown(table_rows, title), global_step=step)
        for path in plot_paths:
            path = Path(path)
            if not path.is_file():
                raise FileNotFoundError(f"{path}: plot file does not exist")
            image = mpimg.imread(path)  # PNG -> float [H, W, 3|4] in [0, 1]
            if image.ndim == 2:
                image = image[..., None].repeat(3, -1)
            writer.add_image(f"{prefix}/{path.stem}", image[..., :3], global_step=step, dataformats="HWC")
    finally:
        writer.close()
    return log_dir


__all__ = ["TrackingError", "check_logger_packages", "hparams_of", "log_test_hparams", "log_estimation_to_tensorboard"]
