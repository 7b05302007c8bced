"""qcm-pipeline: plans, resumes (finished stages are skipped) and records a manifest."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hybridqcm.apps import pipeline
from hybridqcm.pipelines import catalog, runner
from hybridqcm.reports import manifest


def test_demo_plan_lists_every_stage_with_its_command(tmp_path, capsys):
    assert pipeline.main(["demo", "--plan", "--root", str(tmp_path / "r"), "--dataset", str(tmp_path / "d.h5")]) == 0
    out = capsys.readouterr().out
    for name in ("simulate", "exp2_physics", "exp9_unet", "exp5_random_init", "exp10_hybrid"):
        assert name in out
    assert f"cnn_ckpt={tmp_path}/r/exp2_physics/checkpoints/last.ckpt" in out


def test_reproduce_covers_every_source_table():
    tables = {s.table for s in catalog.reproduce_stages() if s.table}
    from hybridqcm.reports.results import load_thesis_tables

    assert tables == {r["table"] for r in load_thesis_tables()}


def test_finished_stages_are_skipped_and_recorded(tmp_path, monkeypatch):
    root, dataset = tmp_path / "r", tmp_path / "d.h5"
    dataset.write_bytes(b"")  # the simulate stage's output exists -> done
    calls = []
    monkeypatch.setattr(
        runner.subprocess, "run", lambda cmd, **kw: calls.append(cmd) or subprocess.CompletedProcess(cmd, 0)
    )
    assert runner.run_pipeline("demo", str(root), str(dataset), only=["simulate"]) == 0
    assert calls == []
    manifest = json.loads((root / "manifest.json").read_text())
    assert [s["name"] for s in manifest["stages"]] == ["simulate"]


def test_stage_with_unfinished_dependency_is_not_run(tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(
        runner.subprocess, "run", lambda cmd, **kw: calls.append(cmd) or subprocess.CompletedProcess(cmd, 0)
    )
    runner.run_pipeline("demo", str(tmp_path / "r"), str(tmp_path / "d.h5"), only=["exp10_hybrid"])
    assert calls == []
    assert "needs ['exp2_physics', 'exp9_unet']" in capsys.readouterr().out


def test_failed_stage_stops_the_pipeline(tmp_path, monkeypatch):
    monkeypatch.setattr(runner.subprocess, "run", lambda cmd, **kw: subprocess.CompletedProcess(cmd, 3))
    assert runner.run_pipeline("demo", str(tmp_path / "r"), str(tmp_path / "d.h5"), only=["simulate"]) == 3


def test_unknown_stage_is_an_error(tmp_path):
    with pytest.raises(SystemExit, match="unknown stage"):
        runner.run_pipeline("demo", str(tmp_path), only=["nope"], plan=True)


@pytest.mark.slow
def test_demo_end_to_end_on_a_tiny_scale(tmp_path):
    """The whole demo (simulate, train CNN and U-Net briefly, GN exps 5 and 10, tables) on tiny data."""
    root, dataset = tmp_path / "demo", tmp_path / "tiny.h5"
    command = [
        sys.executable,
        "-m",
        "hybridqcm.apps.pipeline",
        "demo",
        "--root",
        str(root),
        "--dataset",
        str(dataset),
        "--preset",
        "tiny",
        "--train-time",
        "00:00:00:30",
    ]
    result = subprocess.run(command, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    for stage in ("exp5_random_init", "exp10_hybrid"):
        assert (root / stage / "estimates.csv").exists()
        assert (root / stage / "error_distribution.csv").exists()
    assert "vs source table 5.11" in result.stdout
    # A second run finds every stage done and runs nothing.
    again = subprocess.run(command, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1])
    stages = catalog.demo_stages(str(root), str(dataset), preset="tiny")
    assert again.returncode == 0 and again.stdout.count("done already") == len(stages) == 6


def test_dependency_outside_the_selected_stages_is_honoured(tmp_path, monkeypatch):
    """--only runs a stage whose prerequisite finished earlier, even though that one is not selected."""
    root = tmp_path / "r"
    checkpoint = root / "exp2_physics" / "checkpoints" / "last.ckpt"
    checkpoint.parent.mkdir(parents=True)
    checkpoint.write_bytes(b"")
    (root / "exp2_physics" / "test_metrics.json").write_text("{}")
    for name in ("exp9_unet",):
        (root / name / "checkpoints").mkdir(parents=True)
        (root / name / "checkpoints" / "last.ckpt").write_bytes(b"")
        (root / name / "test_metrics.json").write_text("{}")
    from hybridqcm.runfolder import write_completion_marker

    by_name = {s.name: s for s in catalog.demo_stages(str(root), str(tmp_path / "d.h5"))}
    for name in ("exp2_physics", "exp9_unet"):  # finished runs leave their marker last
        write_completion_marker(root / name, "qcm-train", by_name[name].task_overrides())
    calls = []
    monkeypatch.setattr(
        runner.subprocess, "run", lambda cmd, **kw: calls.append(cmd) or subprocess.CompletedProcess(cmd, 0)
    )
    monkeypatch.setattr(runner, "print_summary", lambda path: None)
    runner.run_pipeline("demo", str(root), str(tmp_path / "d.h5"), only=["exp10_hybrid"])
    assert len(calls) == 1 and "experiment=exp10_hybrid" in calls[0]


def test_manifest_records_merge_across_runs(tmp_path):
    """Two pipelines recording different stages of one root keep both records; a re-run updates in place."""
    root = str(tmp_path)
    manifest.record_stage(root, "demo", "d.h5", {"name": "a", "seconds": 1.0})
    manifest.record_stage(root, "demo", "d.h5", {"name": "b", "seconds": 2.0})
    # a skip keeps the timing
    manifest.record_stage(root, "demo", "d.h5", {"name": "a", "seconds": None}, replace=False)
    manifest.record_stage(root, "demo", "d.h5", {"name": "b", "seconds": 3.0})
    records = manifest.load_manifest(tmp_path / "manifest.json")["stages"]
    assert {s["name"]: s["seconds"] for s in records} == {"a": 1.0, "b": 3.0}


def test_noise_pipeline_needs_the_demo_networks_and_plans_every_level(tmp_path, monkeypatch, capsys):
    """Without the demo's checkpoints the noise sweep stops before any work, naming the files; with
    them it runs exp 10, the road-free model and the CNN alone at every noise level, against those checkpoints."""
    root, networks, dataset = tmp_path / "r", tmp_path / "demo", tmp_path / "d.h5"
    calls = []
    monkeypatch.setattr(
        runner.subprocess, "run", lambda cmd, **kw: calls.append(cmd) or subprocess.CompletedProcess(cmd, 0)
    )
    monkeypatch.setattr(runner, "print_summary", lambda path: None)
    with pytest.raises(SystemExit, match="exp2_physics/checkpoints/last.ckpt.*make demo"):
        runner.run_pipeline("noise", str(root), str(dataset), networks=str(networks))
    assert calls == [] and not (root / "manifest.json").exists()
    dataset.write_bytes(b"")
    for name in ("exp2_physics", "exp9_unet"):
        (networks / name / "checkpoints").mkdir(parents=True)
        (networks / name / "checkpoints" / "last.ckpt").write_bytes(b"")
    assert runner.run_pipeline("noise", str(root), str(dataset), networks=str(networks)) == 0
    assert len(calls) == 3 * len(catalog.NOISE_LEVELS)
    for sigma in catalog.NOISE_LEVELS:
        exp10 = next(c for c in calls if f"hydra.run.dir={root}/exp10_noise{sigma:g}" in c)
        assert f"sensor.sigma={sigma:g}" in exp10 and f"cnn_ckpt={networks}/exp2_physics/checkpoints/last.ckpt" in exp10
        roadfree = next(c for c in calls if f"hydra.run.dir={root}/occupant_noise{sigma:g}" in c)
        assert "experiment=occupant_roadfree" in roadfree and "sensor=additive" in roadfree
        cnn = next(c for c in calls if f"hydra.run.dir={root}/cnn_noise{sigma:g}" in c)
        assert "train=false" in cnn and f"ckpt_path={networks}/exp2_physics/checkpoints/last.ckpt" in cnn
        assert f"sensor.sigma={sigma:g}" in cnn
    with pytest.raises(SystemExit):  # --networks belongs to the noise pipeline
        pipeline.main(["demo", "--networks", "x", "--plan"])


def test_estimation_stage_rejects_an_unknown_network(tmp_path):
    """A stage may use the cnn, unet and cae checkpoints only: any other key would be dropped silently."""
    from hybridqcm.pipelines.stage import estimate_stage

    stage = estimate_stage("e", "exp10_hybrid", "d.h5", "r", 1, networks={"unet": "u", "cnn": "c"})
    # qcm-estimate gets the checkpoints in a fixed key order, and the stage needs both training stages
    assert stage.overrides[-2:] == ["cnn_ckpt=r/c/checkpoints/last.ckpt", "unet_ckpt=r/u/checkpoints/last.ckpt"]
    assert stage.needs == ["c", "u"]
    with pytest.raises(ValueError, match="stage e: networks \\['gan'\\]"):
        estimate_stage("e", "exp10_hybrid", "d.h5", "r", 1, networks={"gan": "g"})
