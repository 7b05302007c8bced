"""Temporary files and stop requests (hybridqcm.atomic): a Ctrl-C or SIGTERM, wherever it lands between a temporary
file's creation and its writer's own cleanup, leaves nothing behind once the app exits as it does after a stop
(apps/common.interrupted_exit), and the one line it prints says so truly.

The signal is sent by the process to itself inside mkstemp, right after the file exists: the moment before the
writer's try block, which the subprocess test in tests/test_importer.py reaches only by chance (a fresh-clone CI run
caught a `.partial` left there)."""

import os
import signal
import tempfile

import numpy as np
import pytest


@pytest.fixture
def stops():
    """The apps' stop handlers installed (SIGINT and SIGTERM raise Interrupted); the test runner's restored after."""
    from hybridqcm import interrupt

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    interrupt.install()
    yield interrupt
    for s, handler in saved.items():
        signal.signal(s, handler)
    interrupt._pending = None


def _signal_inside_mkstemp(monkeypatch, signum: int) -> list[str]:
    """mkstemp that creates its file and then has ``signum`` delivered; returns the names it made."""
    real, made = tempfile.mkstemp, []

    def mkstemp(*args, **kwargs):
        fd, name = real(*args, **kwargs)
        made.append(name)
        os.kill(os.getpid(), signum)  # handled at this thread's next bytecode: before mkstemp's caller sees the name
        return fd, name

    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    return made


def _exit_as_after_a_stop(error, capsys) -> str:
    from hybridqcm.apps.common import interrupted_exit

    with pytest.raises(SystemExit) as exit_info:
        interrupted_exit(error)
    assert exit_info.value.code == 128 + error.signum
    return capsys.readouterr().err.strip()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_as_a_temporary_file_is_made_leaves_no_file(stops, monkeypatch, tmp_path, capsys, signum):
    from hybridqcm.atomic import atomic_create_text

    made = _signal_inside_mkstemp(monkeypatch, signum)
    with pytest.raises(stops.Interrupted) as raised:
        atomic_create_text(tmp_path / "summary.json", "{}\n")
    assert len(made) == 1 and not (tmp_path / "summary.json").exists()
    name = signal.Signals(signum).name
    assert _exit_as_after_a_stop(raised.value, capsys) == (
        f"error: interrupted by {name}; temporary files removed, outputs left as they were"
    )
    assert list(tmp_path.iterdir()) == []  # the temporary file, made before any writer's cleanup, is gone


def test_a_stop_as_an_import_makes_its_partial_leaves_no_partial(stops, monkeypatch, tmp_path, capsys):
    """The importer's path of the CI failure: write_windows' `.partial` made, the stop before its try block."""
    from hybridqcm.data.import_writer import import_recordings

    csv = tmp_path / "drive.csv"
    t = np.arange(400) * 0.01
    np.savetxt(csv, np.stack([t, np.sin(t), np.cos(t)], 1), delimiter=",", header="t,a3,a2", comments="", fmt="%.6f")
    out = tmp_path / "out" / "drive.h5"
    made = _signal_inside_mkstemp(monkeypatch, signal.SIGTERM)
    with pytest.raises(stops.Interrupted) as raised:
        import_recordings(csv, out, window=100, stride=100)
    assert len(made) == 1 and made[0].endswith(".partial")
    _exit_as_after_a_stop(raised.value, capsys)
    assert list(out.parent.iterdir()) == []


def test_what_a_writer_renamed_or_removed_is_not_touched_by_the_sweep(tmp_path):
    """remove_temporaries removes only files still at a name new_temporary gave and nothing forgotten: a finished
    output, a temporary renamed into place, and a user's file that reuses a forgotten temporary's name stay."""
    from hybridqcm.atomic import atomic_write_text, forget, new_temporary, remove_temporaries

    done = atomic_write_text(tmp_path / "done.txt", "complete\n")
    renamed = new_temporary(tmp_path / "a.h5", ".partial")
    os.replace(renamed, tmp_path / "a.h5")
    forgotten = new_temporary(tmp_path / "b.h5")
    forgotten.unlink()
    forget(forgotten)
    forgotten.write_text("a user's file\n")
    left = new_temporary(tmp_path / "c.h5", ".partial")
    assert remove_temporaries() == [left]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["done.txt", "a.h5", forgotten.name])
    assert done.read_text() == "complete\n" and remove_temporaries() == []


def test_the_sbi_peers_save_writes_whole_or_nothing_without_the_sbi_extra(tmp_path):
    """SBIPeer.save (estimation/sbi_peer.py) on a stand-in that has only checkpoint() (the peer itself needs the
    optional sbi extra): the file complete and readable by torch.load, mode 0644, nothing remembered after; and
    where checkpoint() fails, no file and no temporary left."""
    import torch

    from hybridqcm import atomic
    from hybridqcm.estimation.sbi_peer import SBIPeer

    class Stub:
        def checkpoint(self):
            return {"hybridqcm_class": "stub", "state_dict": {"w": torch.arange(3.0)}}

    class Broken:
        def checkpoint(self):
            raise RuntimeError("no state")

    path = SBIPeer.save(Stub(), tmp_path / "peer.ckpt")
    assert torch.equal(torch.load(path, weights_only=True)["state_dict"]["w"], torch.arange(3.0))
    assert oct(path.stat().st_mode & 0o777) == "0o644" and [p.name for p in tmp_path.iterdir()] == ["peer.ckpt"]
    with pytest.raises(RuntimeError, match="no state"):
        SBIPeer.save(Broken(), tmp_path / "other.ckpt")
    assert [p.name for p in tmp_path.iterdir()] == ["peer.ckpt"]
    assert not any(name.startswith(str(tmp_path)) for name in atomic._LIVE)


def test_a_plot_is_written_whole_or_not_at_all(tmp_path):
    """plots.save_figure: a PNG (its signature) with mode 0644 and nothing else beside it; a drawing that fails
    half-way leaves the earlier plot of that name as it was and no temporary file."""
    from hybridqcm.plots import close, plt, save_figure

    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = tmp_path / "plots" / "m3.png"
    save_figure(fig, path)
    first = path.read_bytes()
    assert first[:8] == b"\x89PNG\r\n\x1a\n" and oct(path.stat().st_mode & 0o777) == "0o644"

    def half_drawn(target, **kwargs):
        with open(target, "wb") as handle:
            handle.write(b"\x89PNG half")
        raise OSError("disk full")

    fig.savefig = half_drawn
    with pytest.raises(OSError, match="disk full"):
        save_figure(fig, path)
    assert path.read_bytes() == first and [p.name for p in path.parent.iterdir()] == ["m3.png"]
    close(fig)
