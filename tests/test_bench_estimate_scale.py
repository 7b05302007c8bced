"""bench/bench_estimate_scale.py's run helpers, which the GPU bench (bench/bench_gpu.py) stands on: a finished run's
shards read back agree with its own summary.json (another code path: the app's merge), and a run stopped by the
bench's timeout is killed with its children (no estimate left running on a lent machine) and leaves its finished
blocks readable."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from conftest import REPO_ROOT, make_foreign

sys.path.insert(0, str(REPO_ROOT / "bench"))
from bench_estimate_scale import RowTimeout, estimate, shard_progress  # noqa: E402

# the Euler model, p1 free, one GN iteration: the blocks' path at the least cost (the bench's --cheap)
CHEAP = [
    "experiment=exp5_random_init",
    "dynamics=euler",
    "initial_state=rest",
    "known=[p2,p3,p4,p5,p6,p7,p8,p9,p10]",
    "stages=[{name: gn, channels: all, max_iterations: 1}]",
]


def _processes_naming(text: str) -> list[int]:
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if text in (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace"):
                    pids.append(int(entry.name))
            except OSError:
                pass
    return pids


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scale") / "f.h5"
    make_foreign(path, n=16)
    return path


def test_shard_progress_of_a_finished_run_is_its_summary(recordings, tmp_path):
    run = tmp_path / "run"
    _, summary, _ = estimate([*CHEAP, f"data.path={recordings}", "batch_size=4", "keep_shards=true"], run)
    done = shard_progress(run)
    assert done["blocks"] == 4 and done["rows"] == summary["n_samples"] == 16
    assert done["status_counts"] == {k: v for k, v in summary["status_counts"].items() if v}
    assert 0 < done["seconds_min"] <= done["seconds_max"] <= done["seconds"]


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="reads /proc")
def test_a_timed_out_run_is_killed_with_its_children(recordings, tmp_path):
    run = tmp_path / "stopped"
    with pytest.raises(RowTimeout) as stopped:
        estimate([*CHEAP, f"data.path={recordings}", "batch_size=4"], run, timeout=1.0)  # inside the app's start
    assert stopped.value.run_dir == run and stopped.value.seconds >= 1.0
    assert _processes_naming(f"hydra.run.dir={run}") == [], "the estimate under the probe still runs"
    assert shard_progress(run)["blocks"] == 0  # stopped before any block: nothing reported as done
