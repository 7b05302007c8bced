"""qcm-train: train and/or test one network of the project (Hydra app, lightning-hydra-template style).

    qcm-train experiment=exp1_labelled                     # CPU recipe (streamed samples), ~10 min on 2 cores
    qcm-train experiment=exp1_labelled_reference data.path=data/reference.h5   # source scale
    qcm-train experiment=exp1_labelled train=false ckpt_path=CKPT data.path=FILE data.noise_sigma=0.05 [denoiser_ckpt=CKPT]
    qcm-train -m experiment=exp2_physics data.noise_sigma=0,0.01,0.05,0.1     # one run folder per job + summary.csv
    qcm-train experiment=exp2_physics train=false ckpt_path=CKPT data.path=FILE sensor=additive sensor.sigma=0.05
    qcm-train experiment=exp1_labelled debug=fdr            # fast_dev_run
    qcm-train summarize SWEEP_DIR                           # summary.{csv,md} of a sweep folder

Run folder (hydra.run.dir): checkpoints/{best-*.ckpt,last.ckpt}, tensorboard/, test_metrics.json and,
for the parameter CNNs, predictions.csv, error_distribution.{csv,md}, sorted_predictions_<p>.png;
for the CAE / U-Net, per_sample_mse.csv, mse_summary.{csv,md}, mse_hist_<channel>.png, examples.png.
The work itself: hybridqcm/training.py (prepare, train) and reports/train.py (the artefacts).
"""

from __future__ import annotations

import logging
import sys

from hybridqcm.apps import common
from hybridqcm.errors import ConfigError, HybridQCMError

log = logging.getLogger("qcm-train")


def run(cfg) -> float | None:
    """Hydra task function: train/test, return `optimized_metric` (for sweepers)."""
    from hybridqcm.errors import CheckpointError, DatasetError
    from hybridqcm.training import train

    try:
        # Every input is validated in prepare(), which train() runs before any training step;
        # such errors print as one line. Anything raised later keeps its traceback.
        metrics = train(cfg)
    except (HybridQCMError, ConfigError, DatasetError, CheckpointError) as error:
        common.fail(error)
    metric = cfg.get("optimized_metric")
    if metric and metric in metrics:
        return float(metrics[metric])
    if metric and cfg.get("train", True):
        log.warning("optimized_metric %s not among the metrics %s", metric, sorted(metrics))
    return None


def main() -> None:
    if len(sys.argv) >= 3 and sys.argv[1] == "summarize":  # qcm-train summarize SWEEP_DIR
        from hybridqcm.reports.train import summarize_multirun

        path = summarize_multirun(sys.argv[2])
        print(path or f"no error_distribution.csv / mse_summary.csv under {sys.argv[2]}")
        return
    common.run_hydra_app("train", "train", run)


if __name__ == "__main__":
    main()
