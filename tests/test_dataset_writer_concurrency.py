"""Concurrent and interrupted runs: nothing is silently replaced, nothing half-written is left behind."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hybridqcm import runfolder
from hybridqcm.data.dataset_writer import DatasetWriter, acquire_write_lock
from hybridqcm.data.hdf5 import read_split

SRC = str(Path(__file__).resolve().parents[1] / "src")
ENV = {**os.environ, "PYTHONPATH": SRC}


def _write(path: Path, value: float, overwrite: bool = False) -> None:
    with DatasetWriter(path, overwrite=overwrite, compression=None) as writer:
        writer.create_split("test", 2, 4, keys=["road"])
        writer.write("test", 0, road=np.full((2, 4), value, np.float32))


def test_second_writer_fails_while_the_first_holds_the_path(tmp_path):
    path = tmp_path / "x.h5"
    with DatasetWriter(path, compression=None) as first:
        first.create_split("test", 2, 4, keys=["road"])
        with pytest.raises(FileExistsError, match=r"x.h5 is being written by another process \(pid \d+"):
            _write(path, 2.0)
        first.write("test", 0, road=np.ones((2, 4), np.float32))
    assert read_split(path, "test", ["road"])["road"][0, 0] == 1.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.h5"]  # lock and temp file gone


def test_a_file_that_appears_meanwhile_is_never_replaced(tmp_path):
    """overwrite=false: the existence check at the start is not enough; the final link refuses."""
    path = tmp_path / "x.h5"
    with pytest.raises(FileExistsError, match="appeared while this run was writing it"):
        with DatasetWriter(path, compression=None) as writer:
            writer.create_split("test", 2, 4, keys=["road"])
            writer.write("test", 0, road=np.ones((2, 4), np.float32))
            path.write_bytes(b"someone else's file")
    assert path.read_bytes() == b"someone else's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.h5"]


def test_lock_of_a_dead_writer_and_its_partial_are_cleaned(tmp_path):
    path = tmp_path / "x.h5"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    (tmp_path / ".x.h5.lock").write_text(dead.stdout)
    (tmp_path / ".x.h5.abc123.partial").write_bytes(b"\0" * 100)
    with DatasetWriter(path, compression=None) as writer:
        writer.create_split("test", 1, 4, keys=["road"])
        assert [p.name for p in writer.stale] == [".x.h5.abc123.partial"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.h5"]
    lock = acquire_write_lock(path)  # free again
    lock.unlink()


def _simulate(tmp_path: Path, output: Path, name: str, *extra: str) -> subprocess.Popen:
    cmd = [
        sys.executable,
        "-c",
        "from hybridqcm.apps.simulate import main; main()",
        "preset=tiny",
        f"output={output}",
        "progress=false",
        f"hydra.run.dir={tmp_path / name}",
        *extra,
    ]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)


def test_two_concurrent_qcm_simulate_runs_exactly_one_succeeds(tmp_path):
    output = tmp_path / "same.h5"
    runs = [_simulate(tmp_path, output, f"run{i}") for i in range(2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in runs]
    codes = sorted(code for code, _ in results)
    assert codes == [0, 2], results
    loser = next(err for code, err in results if code == 2)
    assert len(loser.strip().splitlines()) == 1
    assert "being written by another process" in loser or "exists" in loser
    assert read_split(output, "test", ["params"])["params"].shape == (32, 10)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_stops_qcm_simulate_and_leaves_no_partial(tmp_path, signum):
    output = tmp_path / "big.h5"
    # Enough work to be interrupted mid-way (the reference split sizes, a few s per chunk).
    proc = _simulate(
        tmp_path,
        output,
        "run",
        "samples_per_profile=85",
        "n_steps=512",
        "splits.train.profiles={A:200,B:140,C:60}",
        "splits.test.profiles={A:100,B:70,C:30}",
    )
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".big.h5.*.partial")):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.2)
    time.sleep(1.0)
    start = time.monotonic()
    proc.send_signal(signum)
    code = proc.wait(timeout=60)
    assert time.monotonic() - start < 30
    assert code == 128 + signum
    assert "interrupted by" in proc.stderr.read()
    assert not output.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_run_folders_are_unique_per_process():
    import yaml

    text = (Path(__file__).resolve().parents[1] / "configs" / "hydra" / "default.yaml").read_text()
    config = yaml.safe_load(text)
    for section in ("run", "sweep"):
        assert "%f" in config[section]["dir"] and "${hybridqcm_pid:}" in config[section]["dir"]


def test_completion_marker_names_the_inputs(tmp_path):
    data = tmp_path / "d.h5"
    data.write_text("v1")
    runfolder.write_completion_marker(tmp_path, "qcm-estimate", ["experiment=exp5_random_init"], [data])
    marker = json.loads((tmp_path / runfolder.MARKER).read_text())
    assert marker["overrides"] == ["experiment=exp5_random_init"] and str(data) in marker["inputs"]
    assert runfolder.marker_matches(tmp_path, ["experiment=exp5_random_init"])
    assert not runfolder.marker_matches(tmp_path, ["experiment=exp6_cnn_init"])
    data.write_text("v2, rewritten")  # the input changed: the stage is no longer done
    assert not runfolder.marker_matches(tmp_path, ["experiment=exp5_random_init"])


def test_pipeline_stage_without_marker_is_not_done(tmp_path):
    from hybridqcm.pipelines.catalog import demo_stages

    stage = next(s for s in demo_stages(str(tmp_path), str(tmp_path / "d.h5")) if s.app == "qcm-estimate")
    run_dir = Path(stage.run_dir)
    run_dir.mkdir(parents=True)
    for name in stage.done_when:  # leftovers of a killed or foreign run
        (run_dir / name).write_text("stale")
    assert not stage.is_done()
    assert "overwrite=true" in stage.command()
    runfolder.write_completion_marker(run_dir, stage.app, stage.task_overrides())
    assert stage.is_done()
