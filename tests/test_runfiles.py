"""Run folders: overwrite removes only what runs wrote (the manifest), a folder is one run's at a time."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hybridqcm import runfiles, runfolder
from hybridqcm.errors import ConfigError

BIN = Path(sys.executable).parent


def _write(path: Path, text: str = "x") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _a_run(run_dir: Path, overwrite: bool = False, finish: bool = True) -> None:
    """What an estimation run does to its folder: begin, write tables and plots, finish."""
    runfolder.prepare_run_dir(run_dir, runfolder.ESTIMATE_ARTEFACTS, overwrite, app="test")
    _write(run_dir / "estimates.csv", "new")
    _write(run_dir / "plots" / "sorted_p1.png", "new")
    _write(run_dir / "tb" / "events.out.tfevents.1", "new")
    if finish:
        runfiles.finish(run_dir)


def test_overwrite_removes_only_the_files_runs_wrote(tmp_path):
    _a_run(tmp_path)
    manifest = json.loads((tmp_path / runfiles.MANIFEST).read_text())
    assert manifest["state"] == "finished"
    assert manifest["files"] == ["estimates.csv", "plots/sorted_p1.png", "tb/events.out.tfevents.1"]
    # the user's own files, added later: a figure in plots/, another model in checkpoints/, notes
    paper = _write(tmp_path / "plots" / "paper_figure.png", "user")
    model = _write(tmp_path / "checkpoints" / "other_model.ckpt", "user")
    notes = _write(tmp_path / "notes.txt", "user")
    with pytest.raises(ConfigError, match=r"already holds another run's outputs \(estimates.csv, plots, tb\)"):
        runfolder.prepare_run_dir(tmp_path, runfolder.ESTIMATE_ARTEFACTS, overwrite=False)
    runfolder.prepare_run_dir(tmp_path, runfolder.ESTIMATE_ARTEFACTS, overwrite=True)
    assert not (tmp_path / "estimates.csv").exists() and not (tmp_path / "plots" / "sorted_p1.png").exists()
    assert not (tmp_path / "tb").exists()  # emptied by the removal: gone
    assert paper.read_text() == model.read_text() == notes.read_text() == "user"
    runfiles.finish(tmp_path)


def test_a_killed_runs_files_are_what_changed_since_it_began(tmp_path):
    keep = _write(tmp_path / "plots" / "paper_figure.png", "user")  # there before the run
    _a_run(tmp_path, finish=False)  # killed: the manifest still says running
    assert json.loads((tmp_path / runfiles.MANIFEST).read_text())["state"] == "running"
    assert runfiles.recorded_files(tmp_path) == ["estimates.csv", "plots/sorted_p1.png", "tb/events.out.tfevents.1"]
    _a_run(tmp_path, overwrite=True)
    assert keep.read_text() == "user" and (tmp_path / "estimates.csv").read_text() == "new"


def test_a_run_claims_only_files_under_its_own_output_names(tmp_path):
    """hydra.run.dir=. (a project folder): a file of the user's written meanwhile is never the run's."""
    runfolder.prepare_run_dir(tmp_path, runfolder.ESTIMATE_ARTEFACTS, False, scratch=("shards",), app="test")
    _write(tmp_path / "estimates.csv", "new")
    _write(tmp_path / "shards" / "block-000000.csv", "new")
    _write(tmp_path / "src" / "module.py", "the user's edit during the run")
    _write(tmp_path / "notes.txt", "the user's")
    assert runfiles.recorded_files(tmp_path) == ["estimates.csv", "shards/block-000000.csv"]  # killed now: these
    runfiles.finish(tmp_path)
    runfolder.prepare_run_dir(tmp_path, runfolder.ESTIMATE_ARTEFACTS, True, scratch=("shards",), app="test")
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file() and not p.name.startswith(".")) == [
        "module.py",
        "notes.txt",
    ]


def test_outputs_no_run_recorded_are_never_removed(tmp_path):
    """An older version's folder (or a user's files named like ours): refused, overwrite or not."""
    old = _write(tmp_path / "estimates.csv", "old")
    _write(tmp_path / "plots" / "sorted_p1.png", "old")
    for overwrite in (False, True):
        with pytest.raises(ConfigError, match=r"holds estimates.csv, named like this app's outputs"):
            runfolder.prepare_run_dir(tmp_path, runfolder.ESTIMATE_ARTEFACTS, overwrite)
    assert old.read_text() == "old"
    # a folder of one of our names (plots/) with the user's figure in it is no evidence of a run
    fresh = tmp_path / "fresh"
    _write(fresh / "plots" / "paper_figure.png", "user")
    runfolder.prepare_run_dir(fresh, runfolder.ESTIMATE_ARTEFACTS, False)
    assert runfiles.recorded_files(fresh) == []


def test_a_finished_run_of_a_version_without_manifests_is_told_by_its_completion_marker(tmp_path):
    """outputs/ of runs made before manifests: overwrite removes what the run wrote before its marker."""
    import os

    run = [_write(tmp_path / n, "old") for n in ("estimates.csv", "plots/sorted_p1.png", "tb/events.1")]
    mine = _write(tmp_path / "plots" / "paper_figure.png", "user")  # put there after the run finished
    marker = runfolder.write_completion_marker(tmp_path, "qcm-estimate", [])
    done = marker.stat().st_mtime_ns
    for path in run:
        os.utime(path, ns=(done - 10**9, done - 10**9))
    os.utime(mine, ns=(done + 10**9, done + 10**9))
    with pytest.raises(ConfigError, match=r"already holds another run's outputs \(estimates.csv, plots, tb"):
        runfolder.prepare_run_dir(tmp_path, runfolder.ESTIMATE_ARTEFACTS, False)
    runfolder.prepare_run_dir(tmp_path, runfolder.ESTIMATE_ARTEFACTS, True)
    assert [p for p in run + [marker] if p.exists()] == [] and mine.read_text() == "user"


def test_overwrite_never_clears_an_input_of_the_run(tmp_path):
    runfolder.prepare_run_dir(tmp_path, runfolder.TRAIN_ARTEFACTS, False, app="test")
    ckpt = _write(tmp_path / "checkpoints" / "last.ckpt", "weights")
    runfiles.finish(tmp_path)
    with pytest.raises(ConfigError, match="is an input of this run"):
        runfolder.prepare_run_dir(tmp_path, runfolder.TRAIN_ARTEFACTS, True, inputs=[ckpt])
    assert ckpt.read_text() == "weights"


def _holder(run_dir: Path) -> subprocess.Popen:
    """Another process holding the folder's lock (as a running app does) until it is killed."""
    code = f"from hybridqcm import runfiles; import time; runfiles.lock({str(run_dir)!r}, 'qcm-x'); print('ok', flush=True); time.sleep(120)"
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ok"
    return proc


def test_a_folder_is_one_runs_at_a_time_and_a_dead_runs_lock_is_taken_over(tmp_path):
    proc = _holder(tmp_path)
    try:
        with pytest.raises(
            ConfigError, match=rf"hydra.run.dir={tmp_path} is in use by another run \(qcm-x, pid {proc.pid}"
        ):
            runfiles.lock(tmp_path, "test")
    finally:
        proc.kill()
        proc.wait()
    assert runfiles.lock_holder(tmp_path) is None  # its holder is dead
    runfiles.lock(tmp_path, "test")
    runfiles.lock(tmp_path, "test")  # again in the same process: fine
    runfiles.unlock(tmp_path)
    assert not (tmp_path / runfiles.LOCK).exists()


@pytest.fixture(scope="module")
def seat_file(tmp_path_factory):
    """Four noise-free recordings (a3, a2) of the second simulator."""
    root = tmp_path_factory.mktemp("seat")
    path = root / "seat.h5"
    subprocess.run(
        [sys.executable, str(Path(__file__).parents[1] / "bench" / "foreign_sim.py"), "make", "--out", str(path)]
        + ["--n", "4", "--steps", "160"],
        check=True,
        capture_output=True,
    )
    return path


def _estimate(run_dir, data, *extra):
    command = [str(BIN / "qcm-estimate"), "experiment=occupant_roadfree", f"data.path={data}", "n_steps=100"]
    command += ["occupant.models=[rigid]", "delay=null"]  # the run folder is the point, not the person
    command += [
        "progress=false",
        f"hydra.run.dir={run_dir}",
        *extra,
    ]  # tensorboard on: it read plots/ (PIL on a user file)
    return subprocess.run(command, capture_output=True, text=True, timeout=300)


@pytest.mark.slow  # a faster check of the same behaviour stays in the default suite
def test_console_overwrite_keeps_the_users_files_and_a_busy_folder_is_refused(seat_file, tmp_path):
    run_dir = tmp_path / "run"
    first = _estimate(run_dir, seat_file)
    assert first.returncode == 0, first.stderr
    paper = _write(run_dir / "plots" / "paper_figure.png", "user")
    model = _write(run_dir / "checkpoints" / "mine.ckpt", "user")
    rerun = _estimate(run_dir, seat_file, "overwrite=true")
    assert rerun.returncode == 0, rerun.stderr
    assert paper.read_text() == model.read_text() == "user"
    assert (run_dir / "estimates.csv").exists() and (run_dir / "plots" / "sorted_m3.png").exists()
    assert not (run_dir / runfiles.LOCK).exists()  # released at the end
    # a second run into a folder another run holds: one line, before Hydra writes anything there
    proc = _holder(run_dir)
    try:
        start = time.monotonic()
        busy = _estimate(run_dir, seat_file, "overwrite=true")
    finally:
        proc.kill()
        proc.wait()
    assert busy.returncode == 2 and busy.stderr.strip().splitlines() == [
        f"error: hydra.run.dir={run_dir} is in use by another run (qcm-x, pid {proc.pid}, since "
        + busy.stderr.split("since ", 1)[1].split(")")[0]
        + "); wait for it to finish or choose another folder"
    ]
    assert time.monotonic() - start < 60 and (run_dir / "estimates.csv").exists()


def test_snapshot_leaves_hydra_files_out(tmp_path):
    _write(tmp_path / ".hydra" / "config.yaml")
    _write(tmp_path / "estimate.log")
    _write(tmp_path / "sub" / "x.log")
    assert sorted(runfiles.snapshot(tmp_path)) == ["sub/x.log"]
    assert np.all([len(v) == 3 for v in runfiles.snapshot(tmp_path).values()])
