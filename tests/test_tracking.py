"""Run tracking and callbacks: HPARAMS with test metrics, csv / mlflow loggers, estimation results in
TensorBoard, early stopping, rich progress bar, logger=none with the LR monitor."""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hydra.utils import instantiate

from hybridqcm.errors import ConfigError
from hybridqcm.tracking import log_estimation_to_tensorboard
from hybridqcm.training import prepare, train
from test_app_train import BIN, SMALL, SMALL_NET, _cfg, data  # noqa: F401 - the tiny-dataset fixture of the train tests

EXP2 = ["experiment=exp2_physics", *SMALL, *SMALL_NET["exp2_physics"]]


def _events(log_dir):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(log_dir), size_guidance={"images": 0, "tensors": 0, "scalars": 0})
    accumulator.Reload()
    return accumulator


def test_test_metrics_reach_hparams_and_csv(data, tmp_path):
    out = tmp_path / "run"
    train(_cfg([*EXP2, f"data.path={data['tiny']}", "logger=[tensorboard,csv]"], out))
    summary = json.loads((out / "test_metrics.json").read_text())["metrics"]
    assert "test/mean_rel_err" in summary

    from tensorboard.plugins.hparams import plugin_data_pb2

    events = _events(out / "tensorboard")
    content = events.PluginTagToContent("hparams")
    experiment = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/experiment"]).experiment
    session = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/session_start_info"]).session_start_info
    metric_tags = {m.name.tag for m in experiment.metric_infos}
    assert set(summary) <= metric_tags and "hp_metric" not in metric_tags
    assert session.hparams["model/window"].number_value == 500 and session.hparams["seed"].number_value == 1
    assert session.hparams["data/path"].string_value == str(data["tiny"])
    # HPARAMS shows each metric's scalar; its value is the one test_metrics.json holds.
    last = events.Scalars("test/mean_rel_err")[-1].value
    assert last == pytest.approx(summary["test/mean_rel_err"], rel=1e-6)

    with open(out / "csv" / "metrics.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    test_rows = [r for r in rows if r.get("test/mean_rel_err")]
    assert len(test_rows) == 1 and float(test_rows[0]["test/mean_rel_err"]) == pytest.approx(
        summary["test/mean_rel_err"], rel=1e-6
    )
    assert any(r.get("val/mean_rel_err") for r in rows) and (out / "csv" / "hparams.yaml").exists()


def test_early_stopping_stops_and_logger_none_keeps_lr_monitor_quiet(data, tmp_path):
    """6 epochs without early stopping; with min_delta larger than any change, it stops after the 2nd validation."""
    common = [*EXP2, f"data.path={data['tiny']}", "trainer.max_epochs=6", "logger=none"]
    train(_cfg(common, tmp_path / "full"))  # callbacks=default: lr_monitor would raise here
    train(
        _cfg(
            [
                *common,
                "callbacks=early_stopping",
                "callbacks.early_stopping.min_delta=1e9",
                "callbacks.early_stopping.patience=1",
            ],
            tmp_path / "stopped",
        )
    )
    full = json.loads((tmp_path / "full" / "test_metrics.json").read_text())["steps"]
    stopped = json.loads((tmp_path / "stopped" / "test_metrics.json").read_text())["steps"]
    assert full > 0 and stopped * 3 == full, (stopped, full)


def test_callback_and_logger_configs_compose(tmp_path):
    from lightning.pytorch.callbacks import EarlyStopping, RichProgressBar

    cfg = _cfg(["experiment=exp1_labelled", "callbacks=[early_stopping,rich]", "logger=csv"], tmp_path)
    callbacks = [instantiate(c) for c in cfg.callbacks.values() if c is not None]
    stopper = next(c for c in callbacks if isinstance(c, EarlyStopping))
    assert stopper.monitor == cfg.optimized_metric == "val/mean_rel_err"
    assert any(isinstance(c, RichProgressBar) for c in callbacks)
    assert Path(instantiate(cfg.logger.csv).log_dir) == tmp_path / "csv"
    none = _cfg(["experiment=exp1_labelled", "logger=none"], tmp_path)
    assert dict(none.logger) == {} and none.callbacks.lr_monitor is None and none.callbacks.model_checkpoint is not None
    mlflow = _cfg(["experiment=exp1_labelled", "logger=mlflow"], tmp_path)
    assert mlflow.logger.mlflow._target_.endswith("MLFlowLogger")
    assert mlflow.logger.mlflow.tracking_uri == f"file:{tmp_path}/mlruns"


@pytest.mark.parametrize(
    "choice, bar",
    [
        ("default", "RichProgressBar"),
        ("rich", "RichProgressBar"),
        ("tqdm", "TQDMProgressBar"),
        ("[early_stopping,tqdm]", "TQDMProgressBar"),
    ],
)
def test_progress_bar_switch(tmp_path, choice, bar):
    cfg = _cfg(["experiment=exp1_labelled", f"callbacks={choice}"], tmp_path)
    callbacks = [instantiate(c) for c in cfg.callbacks.values() if c is not None]
    trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=False)
    assert type(trainer.progress_bar_callback).__name__ == bar


def test_rich_progress_bar_run(data, tmp_path):
    metrics = train(_cfg([*EXP2, f"data.path={data['tiny']}", "debug=fdr", "callbacks=rich"], tmp_path))
    assert "test/mean_rel_err" in metrics


@pytest.mark.skipif(importlib.util.find_spec("mlflow") is not None, reason="mlflow is installed here")
def test_mlflow_without_package_is_one_line_naming_the_extra(data, tmp_path):
    with pytest.raises(ConfigError, match=r"logger\.mlflow .*'mlflow'.*pip install -e '\.\[tracking\]'"):
        prepare(_cfg(["experiment=exp2_physics", f"data.path={data['tiny']}", "logger=mlflow"], tmp_path))
    result = subprocess.run(
        [
            str(BIN / "qcm-train"),
            "experiment=exp2_physics",
            f"data.path={data['tiny']}",
            "logger=mlflow",
            f"hydra.run.dir={tmp_path}/cli",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2 and "[tracking]" in result.stderr and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1].startswith("error: logger.mlflow"), result.stderr


def test_estimation_table_and_plots_in_event_file(tmp_path):
    import matplotlib.image as mpimg

    from hybridqcm.metrics import error_distribution_rows
    from hybridqcm.plots import close, plot_sorted_predictions

    rng = np.random.default_rng(0)
    true = rng.uniform(1, 2, size=(50, 2))
    pred = true * (1 + rng.normal(0, 0.02, size=true.shape))
    rows = error_distribution_rows(pred, true, ["p1", "p4"])
    paths = []
    for j, name in enumerate(["p1", "p4"]):
        paths.append(tmp_path / f"sorted_{name}.png")
        close(plot_sorted_predictions(pred[:, j], true[:, j], name, paths[-1]))
    log_dir = log_estimation_to_tensorboard(tmp_path / "tb", rows, paths, title="exp10: test")

    events = _events(log_dir)
    (tag,) = [t for t in events.Tags()["tensors"] if t.startswith("estimation/error_distribution")]  # + /text_summary
    (text,) = events.Tensors(tag)
    assert events.SummaryMetadata(tag).plugin_data.plugin_name == "text"
    table = text.tensor_proto.string_val[0].decode()
    assert "**exp10: test**" in table and "| p1 |" in table and "| p4 |" in table
    assert f"{100 * rows[0]['max_err']:.3g} %" in table
    assert set(events.Tags()["images"]) == {"estimation/sorted_p1", "estimation/sorted_p4"}
    for path in paths:
        (logged,) = events.Images(f"estimation/{path.stem}")
        original = np.round(mpimg.imread(path)[..., :3] * 255).astype(np.uint8)
        from io import BytesIO

        decoded = np.round(mpimg.imread(BytesIO(logged.encoded_image_string), format="png")[..., :3] * 255).astype(
            np.uint8
        )
        assert (logged.height, logged.width) == original.shape[:2]
        assert np.array_equal(decoded, original)
    with pytest.raises(FileNotFoundError, match="missing.png"):
        log_estimation_to_tensorboard(tmp_path / "tb2", rows, [tmp_path / "missing.png"])
