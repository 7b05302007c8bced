"""The console of our entry points with stdout in a file: each line once, tables whole, no third-party chatter."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from hybridqcm.metrics import error_distribution_rows, write_error_distribution

# Rule lines of rich or markdown tables repeat legitimately (two tables with equal column widths).
_RULE = re.compile(r"^[\s|:\-─━┏┓┗┛┃│┡┩┠┨╇┳┻┼╋└┘┌┐├┤┬┴╭╮╰╯═]*$")
# The same log record through two handlers differs only in its prefix: compare the message.
_PREFIX = re.compile(r"^(\[[^\]]*\]\[[^\]]*\]\[[A-Z]+\] - |[A-Z]+: )")


def _run_to_file(command: list[str], log: Path) -> str:
    """Run with stdout and stderr redirected to a file (not a terminal, as in `make demo > demo.log`)."""
    with open(log, "w") as out:
        result = subprocess.run(
            command, stdout=out, stderr=subprocess.STDOUT, timeout=400, cwd=Path(__file__).resolve().parents[1]
        )
    text = log.read_text()
    assert result.returncode == 0, text[-3000:]
    return text


def _repeated_lines(text: str) -> list[str]:
    messages = [_PREFIX.sub("", line).strip() for line in text.splitlines()]
    counts = Counter(m for m in messages if m and not _RULE.match(m))
    return [m for m, n in counts.items() if n > 1]


def test_repeated_line_detector_catches_a_record_printed_by_two_handlers():
    twice = (
        "INFO: GPU available: False, used: False\n"
        "[2026-01-01 00:00:00,000][lightning.pytorch.utilities.rank_zero][INFO] - GPU available: False, used: False\n"
        "┏━━┳━━┓\n\n┏━━┳━━┓\n|---|---|\n|---|---|\n"
    )
    assert _repeated_lines(twice) == ["GPU available: False, used: False"]


def test_simulate_and_train_print_each_line_once_and_tables_whole(tmp_path):
    # A long output path is a long table title: in a log file it must stay on one line.
    dataset = tmp_path / ("a_long_folder_name_that_does_not_fit_in_eighty_columns_" * 2) / "tiny.h5"
    simulate = _run_to_file(
        [
            sys.executable,
            "-m",
            "hybridqcm.apps.simulate",
            "preset=tiny",
            f"output={dataset}",
            f"hydra.run.dir={tmp_path / 'sim'}",
        ],
        tmp_path / "simulate.log",
    )
    assert str(dataset) in simulate.splitlines()
    assert "prior acceptance" in simulate and "peak \\|a\\| (a3 a2 a1) m/s²" in simulate
    run_dir = tmp_path / "train"
    train = _run_to_file(
        [
            sys.executable,
            "-m",
            "hybridqcm.apps.train",
            "experiment=exp2_physics",
            f"data.path={dataset}",
            "debug=fdr",
            "model.net.channels=[8,8]",
            "model.net.hidden=[16,8]",
            f"hydra.run.dir={run_dir}",
        ],
        tmp_path / "train.log",
    )
    for log in (simulate, train):
        assert _repeated_lines(log) == []
    assert "GPU available" in train  # Lightning's INFO lines are kept, once ...
    assert "GPU available" in (run_dir / "debug.log").read_text()  # ... and reach the run's own log file
    for noise in ("litlogger", "LeafSpec", "does not have many workers", "Trainer already configured"):
        assert noise not in train, noise


def test_comparison_tables_keep_every_column_in_a_log_file(tmp_path):
    """qcm-pipeline's closing tables: the last (`beat`) column survives when stdout is a file."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(1, 2, size=(200, 10))
    run_dir = tmp_path / "bad"
    write_error_distribution(error_distribution_rows(truth * 1000.0, truth, [f"p{i + 1}" for i in range(10)]), run_dir)
    manifest = tmp_path / "manifest.json"
    manifest.write_text(
        json.dumps(
            {
                "pipeline": "test",
                "dataset": "x.h5",
                "stages": [
                    {
                        "name": "exp5_bad",
                        "app": "qcm-estimate",
                        "run_dir": str(run_dir),
                        "table": "5.11",
                        "setting": "s",
                        "command": "qcm-estimate ...",
                        "seconds": 1.0,
                    }
                ],
            }
        )
    )
    code = f"from hybridqcm.reports.results import print_summary; print_summary({str(manifest)!r})"
    text = _run_to_file([sys.executable, "-c", code], tmp_path / "summary.log")
    rows = [line for line in text.splitlines() if re.match(r"\| p\d+ ", line)]
    assert len(rows) == 10
    # every estimate is 1000x too large: each row loses on all four criteria, and says so in full
    assert all(row.rstrip(" |").endswith("✗ mean,≤10 %,>25 %,max") for row in rows), rows


def test_quiet_third_party_acts_only_when_an_entry_point_calls_it():
    """Importing the library changes no warning filter or log handler; quiet_third_party() does, once called."""
    code = """
import logging, sys, warnings
import hybridqcm.apps.common as common, hybridqcm.apps.pipeline, hybridqcm.apps.train, hybridqcm.apps.estimate
import lightning

ours = lambda: [f for f in warnings.filters if f[1] is not None and "LeafSpec" in f[1].pattern]
lightning_console = lambda: [h for h in logging.getLogger("lightning").handlers if type(h) is logging.StreamHandler]
assert ours() == [] and len(lightning_console()) == 1, (ours(), lightning_console())
logging.basicConfig(stream=sys.stdout, format="%(name)s | %(message)s")  # stands in for Hydra's job logging
common.quiet_third_party()
assert len(ours()) == 1 and lightning_console() == [], (ours(), lightning_console())
from lightning.pytorch.utilities.rank_zero import rank_zero_info
rank_zero_info("kept: GPU available")
rank_zero_info("Tip: try installing litlogger")
logging.getLogger("lightning.pytorch.accelerators.cuda").info("LOCAL_RANK: 0 - CUDA_VISIBLE_DEVICES: [0]")
"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.splitlines() == ["lightning.pytorch.utilities.rank_zero | kept: GPU available"]
    assert "kept" not in result.stderr


def test_help_lists_only_the_groups_and_experiments_the_app_takes():
    """Before: every app's --help listed every folder of configs/ (qcm-estimate: model, logger, callbacks,
    launcher, ... and the training experiments), which the app then refused."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import ConfigCompositionException, MissingConfigException

    from hybridqcm.config import CONFIG_DIR, app_experiments

    bin_dir = Path(sys.executable).parent
    from hybridqcm.apps.common import app_groups_help

    assert app_groups_help("simulate") == "paths: default\npreset: small, tiny"
    for app, config in (("qcm-estimate", "estimate"), ("qcm-train", "train")):
        result = subprocess.run([str(bin_dir / app), "--help"], capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, result.stderr[-2000:]
        section = result.stdout.split("== Configuration groups (group=option) ==\n", 1)[1].split("\n\n", 1)[0]
        listed = {line.split(": ", 1)[0]: line.split(": ", 1)[1].split(", ") for line in section.splitlines()}
        assert result.stdout.startswith(f"{app}: key=value overrides")
        with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
            for group, options in listed.items():
                if group == "experiment":  # this app's own folder, configs/<app>/experiment/, and each composes
                    assert options == app_experiments(config) and options, (app, options)
                    for option in options:
                        compose(config, overrides=[f"experiment={option}"])
                    other = app_experiments("train" if config == "estimate" else "estimate")[0]
                    with pytest.raises(ConfigCompositionException, match=f"experiment/{other}"):
                        compose(config, overrides=[f"experiment={other}"])  # not on this app's search path
                    continue
                try:  # the group is in the app's defaults list: an option of it composes
                    compose(config, overrides=[f"{group}={options[-1]}"])
                except MissingConfigException as error:  # a launcher whose optional plugin is not installed
                    assert group == "launcher" and "hydra/launcher" in str(error), error
        if app == "qcm-estimate":
            assert set(listed) == {"paths", "solver", "sensor", "trainer", "experiment"}
            assert "occupant_roadfree" in listed["experiment"] and "exp1_labelled" not in listed["experiment"]
        if app == "qcm-train":
            assert "solver" not in listed and "exp5_random_init" not in listed["experiment"]
