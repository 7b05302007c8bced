"""A full disk while writing a dataset (reproduced with the file-size limit, `ulimit -f`): one line
naming the file, no traceback, no segfault, and no half-written file left looking valid."""

from __future__ import annotations

import errno
import os
import resource
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from hybridqcm.data.dataset_writer import DatasetWriter
from hybridqcm.data.h5file import GuardedFile, open_guarded, raise_if_failed
from hybridqcm.data.hdf5 import read_split
from hybridqcm.errors import DatasetError

BIN = Path(sys.executable).parent
LIMIT = 256 * 1024  # bytes any one file of the process may have


def _run(command, tmp_path, limit: int = LIMIT):
    """The command with every file it writes limited to `limit` bytes (stdout and stderr are pipes)."""
    env = {**os.environ, "COLUMNS": "200"}

    def limited():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return subprocess.run(
        command, capture_output=True, text=True, timeout=300, preexec_fn=limited, env=env, cwd=tmp_path
    )


def _assert_one_line_and_nothing_left(result, out: Path):
    assert result.returncode == 2, result.stderr[-2000:]
    lines = result.stderr.strip().splitlines()
    assert lines == [
        f"error: {out}: could not be written: File too large (the file-size limit: ulimit -f); "
        + lines[0].split("ulimit -f); ", 1)[1]
    ], result.stderr[-2000:]
    assert lines[0].endswith("free on its disk; nothing was written")
    assert sorted(p.name for p in out.parent.iterdir()) == []  # no output, no .partial, no lock


def test_simulate_on_a_full_disk(tmp_path):
    """Before: 2 000+ lines of 'Exception ignored' tracebacks from HDF5's flushes, then a segfault (exit 139)."""
    out = tmp_path / "data" / "tiny.h5"
    result = _run(
        [str(BIN / "qcm-simulate"), "preset=tiny", f"output={out}", f"hydra.run.dir={tmp_path / 'run'}"], tmp_path
    )
    _assert_one_line_and_nothing_left(result, out)


def test_import_on_a_full_disk(tmp_path):
    n = 40_000
    csv = tmp_path / "drive.csv"
    rows = np.stack([np.arange(n) * 0.001, *np.random.default_rng(0).normal(size=(2, n))], 1)
    np.savetxt(csv, rows, delimiter=",", header="t,a3,a2", comments="", fmt="%.6f")
    out = tmp_path / "data" / "drive.h5"
    out.parent.mkdir()
    result = _run(
        [str(BIN / "qcm-import"), f"input={csv}", f"output={out}", f"hydra.run.dir={tmp_path / 'run'}"], tmp_path
    )
    _assert_one_line_and_nothing_left(result, out)


class _FullAfter(GuardedFile):
    """A GuardedFile whose disk is full after `room` bytes (no process limit needed)."""

    def __init__(self, path, room: int):
        super().__init__(path)
        self.room = room

    def write(self, data):
        size = memoryview(data).nbytes
        if self.error is None and self.tell() + size > self.room:
            self.error = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(data) if self.error is None else size


def test_a_write_that_fails_is_reported_and_the_file_is_not_published(tmp_path, monkeypatch):
    import hybridqcm.data.dataset_writer as dataset_writer

    def full_guard(path):
        guard = _FullAfter(path, 64 * 1024)
        return h5py.File(guard, "w"), guard

    monkeypatch.setattr(dataset_writer, "open_guarded", full_guard)
    target = tmp_path / "d.h5"
    rng = np.random.default_rng(0)
    with pytest.raises(DatasetError, match=rf"{target}: could not be written: No space left on device"):
        with DatasetWriter(target, compression=None) as writer:
            writer.create_split("test", 64, 512, keys=("accel",))
            for start in range(0, 64, 8):
                writer.write("test", start, accel=rng.normal(size=(8, 512, 3)).astype(np.float32))
    assert list(tmp_path.iterdir()) == []


def test_the_guarded_file_writes_what_h5py_writes(tmp_path):
    """Through the guard, a file holds the same data as one written by h5py's own driver."""
    data = np.random.default_rng(1).normal(size=(40, 100, 3)).astype(np.float32)
    handle, guard = open_guarded(tmp_path / "guarded.h5")
    with guard, handle:
        handle.create_dataset("test/accel", data=data, compression="gzip", chunks=(8, 100, 3))
    raise_if_failed(guard, tmp_path / "guarded.h5")
    with h5py.File(tmp_path / "plain.h5", "w") as plain:
        plain.create_dataset("test/accel", data=data, compression="gzip", chunks=(8, 100, 3))
    for name in ("guarded.h5", "plain.h5"):
        np.testing.assert_array_equal(read_split(tmp_path / name, "test", ("accel",))["accel"], data)


def test_estimate_on_a_full_disk_is_one_line(tiny_dataset, tmp_path):
    """Any output (a plot, TensorBoard's events) that cannot be written: one line, no traceback, and no
    summary or completion marker that would call the run done."""
    run_dir = tmp_path / "run"
    command = [str(BIN / "qcm-estimate"), "experiment=occupant_roadfree", f"data.path={tiny_dataset}", "n_samples=4"]
    command += ["occupant.models=[rigid]", "delay=null"]  # the full disk is the point, not the person
    # 20 KiB: Hydra's own files fit, a plot does not
    result = _run([*command, "progress=false", f"hydra.run.dir={run_dir}"], tmp_path, limit=20 * 1024)
    assert result.returncode == 2, result.stderr[-2000:]
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith(f"error: an output in hydra.run.dir={run_dir}: could not be written: File too large")
    assert line.endswith("the run is incomplete (no summary or completion marker): rerun it")
    assert not (run_dir / "summary.json").exists() and not (run_dir / ".hybridqcm-done.json").exists()
