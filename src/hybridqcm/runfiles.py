"""A run folder's own files: a lock while a run writes into it, and the manifest of what runs wrote there.

    RUN/.hybridqcm-run.lock     the pid of the run writing here (O_EXCL; a dead pid's lock is taken over)
    RUN/.hybridqcm-files.json   {"state": "running" | "finished", "files": [paths relative to RUN], ...}

`overwrite=true` removes the files a manifest lists and nothing else: a figure the user put in
plots/ or another model in checkpoints/ stays. The list is what changed under the folder while a
run ran (size, mtime or inode differs from the snapshot taken when it began), so it covers what
third-party writers create too (TensorBoard event files, Lightning checkpoints, matplotlib
figures). Only files under the app's own output names count (`begin`'s artefacts, globs and
scratch names): a user's file changed elsewhere in the folder meanwhile is never listed. A run
that was killed leaves state "running" and its snapshot: what changed since then under those
names is counted as that run's files (so a file added by hand after such a crash, before the next
overwrite, is taken for the run's; a finished run's list is frozen). Hydra's own files
(.hydra/, the top-level <task>.log) are never listed: Hydra rewrites them for every run.

A folder without a manifest (a version before them): a finished run's files are told by its
completion marker, written last — the files of our output names no later than it; files added
after it (a figure put in plots/ afterwards) stay. Without a marker either (a killed run of such
a version, or somebody else's files named like ours) the folder is refused, with overwrite too:
nothing is removed on a guess.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import os
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

from hybridqcm.atomic import atomic_write_text
from hybridqcm.errors import ConfigError

LOCK = ".hybridqcm-run.lock"
MANIFEST = ".hybridqcm-files.json"
_NEVER_LISTED = (LOCK, MANIFEST, ".hydra")

# pid of this process -> the run folder whose run began here (set by `begin`, finished by `session`)
_begun: dict[int, Path] = {}


def pid_alive(pid: int) -> bool:
    """Whether a process of that pid exists (one of another user counts: it is alive)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def lock_holder(run_dir: str | os.PathLike) -> dict | None:
    """{"pid", "app", "since"} of the live run holding the folder's lock, None when free (or stale)."""
    try:
        record = json.loads((Path(run_dir) / LOCK).read_text())
        pid = int(record.get("pid", 0))
    except (OSError, ValueError, AttributeError):
        return None
    return record if pid > 0 and pid_alive(pid) else None


def _busy(run_dir: Path, holder: dict) -> ConfigError:
    return ConfigError(
        f"hydra.run.dir={run_dir} is in use by another run ({holder.get('app', '?')}, pid {holder.get('pid')}, "
        f"since {holder.get('since', '?')}); wait for it to finish or choose another folder"
    )


def lock(run_dir: str | os.PathLike, app: str) -> Path:
    """Take the folder's lock for this process (again: a no-op); ConfigError naming the live holder otherwise."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK
    record = {"pid": os.getpid(), "app": app, "since": time.strftime("%Y-%m-%dT%H:%M:%S")}
    for _ in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = lock_holder(run_dir)
            if holder is None:  # its run died (or the file is unreadable): take it over
                path.unlink(missing_ok=True)
                continue
            if int(holder["pid"]) == os.getpid():
                return path
            raise _busy(run_dir, holder) from None
        with os.fdopen(fd, "w") as handle:
            handle.write(json.dumps(record) + "\n")
        return path
    raise ConfigError(f"hydra.run.dir={run_dir}: could not take the run folder's lock {path}")


def unlock(run_dir: str | os.PathLike) -> None:
    """Release the lock if this process holds it."""
    holder = lock_holder(run_dir)
    if holder is not None and int(holder["pid"]) == os.getpid():
        (Path(run_dir) / LOCK).unlink(missing_ok=True)


def check_free(run_dir: str | os.PathLike) -> None:
    """ConfigError if another live process holds the folder (called before Hydra writes into it)."""
    holder = lock_holder(run_dir)
    if holder is not None and int(holder["pid"]) != os.getpid():
        raise _busy(Path(run_dir), holder)


def _listed(rel: str) -> bool:
    first = rel.split("/", 1)[0]
    return first not in _NEVER_LISTED and not (first == rel and rel.endswith(".log"))


def snapshot(run_dir: str | os.PathLike) -> dict[str, list[int]]:
    """{relative path: [size, mtime_ns, inode]} of the files under the folder that a manifest may list."""
    root = Path(run_dir)
    out: dict[str, list[int]] = {}
    for folder, dirs, files in os.walk(root):
        base = Path(folder).relative_to(root).as_posix()
        if base == ".":
            dirs[:] = [d for d in dirs if d not in _NEVER_LISTED]
        for name in files:
            rel = name if base == "." else f"{base}/{name}"
            if not _listed(rel):
                continue
            try:
                st = os.lstat(Path(folder) / name)
            except OSError:
                continue
            out[rel] = [int(st.st_size), int(st.st_mtime_ns), int(st.st_ino)]
    return out


def _read(run_dir: Path) -> dict | None:
    try:
        data = json.loads((run_dir / MANIFEST).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as error:
        raise ConfigError(f"{run_dir / MANIFEST}: unreadable run-folder manifest ({error}); remove it") from None
    return data if isinstance(data, dict) else None


def recorded_files(run_dir: str | os.PathLike) -> list[str]:
    """The files runs wrote here that still exist (relative paths); a killed run's: what changed since it began."""
    run_dir = Path(run_dir)
    manifest = _read(run_dir) or {}
    files = set(manifest.get("files") or [])
    if manifest.get("state") == "running":
        before = manifest.get("before") or {}
        names, globs = manifest.get("names"), manifest.get("globs") or []
        files |= {
            rel
            for rel, sig in snapshot(run_dir).items()
            if before.get(rel) != sig and (names is None or _owned(rel, names, globs))
        }
    return sorted(rel for rel in files if _listed(rel) and (run_dir / rel).is_file())


def _owned(rel: str, names: Sequence[str], globs: Sequence[str]) -> bool:
    """Under one of the app's output names (a file or folder at the top), or a top-level file matching
    one of its patterns: the bound on what a run can claim (a file of the user's changed meanwhile elsewhere
    in the folder, say with hydra.run.dir=., is never listed)."""
    top = rel.split("/", 1)[0]
    return top in names or ("/" not in rel and any(fnmatch.fnmatchcase(rel, g) for g in globs))


def _remove(run_dir: Path, files: Iterable[str]) -> None:
    """Remove the files, then the folders they leave empty (never the run folder itself)."""
    parents: set[Path] = set()
    for rel in files:
        path = run_dir / rel
        path.unlink(missing_ok=True)
        parents.update(p for p in path.parents if run_dir in p.parents)
    for folder in sorted(parents, key=lambda p: len(p.parts), reverse=True):
        with contextlib.suppress(OSError):
            folder.rmdir()  # only when empty: a user's file keeps its folder


def _finished_before_manifests(run_dir: Path, named: Iterable[str], marker: Path) -> list[str]:
    """A finished run of a version without manifests: its outputs (top-level files of our names, and
    files under our folders) written no later than its completion marker, the marker included."""
    done = marker.stat().st_mtime_ns
    files = [marker.name]
    for name in named:
        path = run_dir / name
        if path.is_file():
            files.append(name)
        elif path.is_dir():
            files += [
                p.relative_to(run_dir).as_posix()
                for p in path.rglob("*")
                if p.is_file() and not p.is_symlink() and p.stat().st_mtime_ns <= done
            ]
    return sorted({f for f in files if _listed(f)})


def begin(
    run_dir: str | os.PathLike,
    app: str,
    overwrite: bool,
    artefacts: Sequence[str],
    globs: Sequence[str] = (),
    inputs: Iterable[str | os.PathLike | None] = (),
    scratch: Sequence[str] = (),
    marker: str | None = None,
) -> Path:
    """Start a run in the folder: refuse another run's outputs (unless overwrite), remove them
    (only the files a manifest lists) when overwriting, and record the snapshot this run's files
    are told apart by. ``artefacts`` / ``globs``: names (top level) of the app's final outputs;
    ``scratch``: names it also writes under that are no final output (shards, a logger's folder).
    A run's files are those changed since its start under these names only.

    inputs: files the run reads; removing one of them (a checkpoint inside the folder) is refused.
    marker: the app's completion marker, written last by a finished run: in a folder of a version
    without manifests, the files it names are that run's if no later than the marker (a file added
    to plots/ afterwards is the user's). Raises ConfigError (one line) before any work."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    has_manifest = (run_dir / MANIFEST).exists()
    ours = recorded_files(run_dir)
    named = {n for n in artefacts if (run_dir / n).exists() and n not in (LOCK, MANIFEST)}
    for pattern in globs:
        named |= {p.name for p in run_dir.glob(pattern)}
    if not has_manifest and marker and (run_dir / marker).is_file():
        ours = _finished_before_manifests(run_dir, named, run_dir / marker)
    elif not has_manifest:  # files named like our outputs, but no run recorded writing them (folders of
        # our names, plots/ or checkpoints/, may be the user's own: they are no evidence)
        unknown = sorted(n for n in named if not (run_dir / n).is_dir())
        if unknown:
            shown = ", ".join(unknown[:4]) + (" ..." if len(unknown) > 4 else "")
            raise ConfigError(
                f"hydra.run.dir={run_dir} holds {shown}, named like this app's outputs but written by no run that "
                f"recorded its files ({MANIFEST}: an older version, or not a run); nothing is removed on a guess: "
                f"move them away or choose another folder"
            )
    ours_top = {rel.split("/", 1)[0] for rel in ours}
    outputs = sorted((n for n in named if n in ours_top), key=lambda n: (n.startswith("."), n))  # markers last
    if outputs and not overwrite:
        shown = ", ".join(outputs[:4]) + (" ..." if len(outputs) > 4 else "")
        raise ConfigError(
            f"hydra.run.dir={run_dir} already holds another run's outputs ({shown}); "
            f"pass overwrite=true to clear them first (only files a run wrote), or choose another folder"
        )
    for given in (i for i in inputs if i) if overwrite else ():
        resolved = Path(given).resolve()
        for rel in ours:
            if resolved == (run_dir / rel).resolve():
                raise ConfigError(
                    f"{given} is an input of this run but was written by an earlier run in hydra.run.dir={run_dir}, "
                    f"which overwrite would clear; choose another hydra.run.dir"
                )
    kept = ours
    if overwrite:
        _remove(run_dir, ours)
        kept = []
    record = {
        "app": app,
        "state": "running",
        "pid": os.getpid(),
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "files": kept,
        "names": sorted({*artefacts, *scratch}),
        "globs": list(globs),
        "before": snapshot(run_dir),
    }
    atomic_write_text(run_dir / MANIFEST, json.dumps(record) + "\n")
    _begun[os.getpid()] = run_dir
    return run_dir


def finish(run_dir: str | os.PathLike | None = None) -> None:
    """Freeze the list of this run's files (those changed since `begin`) in the manifest."""
    run_dir = Path(run_dir) if run_dir is not None else _begun.get(os.getpid())
    if run_dir is None:
        return
    _begun.pop(os.getpid(), None)
    try:
        manifest = _read(run_dir) or {}
    except ConfigError:
        return
    if manifest.get("state") != "running" or int(manifest.get("pid", -1)) != os.getpid():
        return
    files = recorded_files(run_dir)
    record = {k: v for k, v in manifest.items() if k != "before"}
    record.update(state="finished", files=files, finished=time.strftime("%Y-%m-%dT%H:%M:%S"))
    with contextlib.suppress(OSError):  # a full disk: the running state still lists them
        atomic_write_text(run_dir / MANIFEST, json.dumps(record, indent=1) + "\n")


def release(run_dir: str | os.PathLike) -> None:
    """End of a run: freeze the manifest of a run begun here, release the lock if this process holds it."""
    if os.getpid() in _begun:
        finish()
    unlock(run_dir)


@contextlib.contextmanager
def session(run_dir: str | os.PathLike, app: str) -> Iterator[Path]:
    """Hold the folder's lock for a run; on the way out (errors and Ctrl-C too) `release` it."""
    run_dir = Path(run_dir)
    lock(run_dir, app)
    try:
        yield run_dir
    finally:
        release(run_dir)


def remove_tree_files(folder: str | os.PathLike, *patterns: str) -> None:
    """Remove the files matching ``patterns`` in ``folder``, and the folder if that leaves it empty."""
    folder = Path(folder)
    for pattern in patterns:
        for path in folder.glob(pattern):
            if path.is_file() or path.is_symlink():
                path.unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        folder.rmdir()


__all__ = [
    "LOCK",
    "MANIFEST",
    "lock",
    "unlock",
    "lock_holder",
    "check_free",
    "snapshot",
    "recorded_files",
    "begin",
    "finish",
    "release",
    "session",
    "remove_tree_files",
]
