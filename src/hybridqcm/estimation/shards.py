"""qcm-estimate's shards: each block's results written by the rank that solved it, merged once.

    RUN/shards/block-000007.csv         estimates.csv rows of block 7 (with the header)
    RUN/shards/block-000007.status.csv  status.csv rows
    RUN/shards/block-000007.pt          per-sample columns for the metrics (params, std, status, truth)
    RUN/shards/block-000007.done.json   written last: rows, stage statistics, the run's fingerprint

A block is done when its marker exists (every file is renamed into place complete, the marker
last), so a run killed at any point restarts where it stopped: rerun the same command into the
same hydra.run.dir and the finished blocks are skipped, under any number of processes. A marker
whose fingerprint (the settings that change estimates, and the size/mtime of every input file)
differs from this run's is refused in one line naming it. The merge (one process) streams the
shards into estimates.csv and status.csv in block order, each index exactly once, checked
against 0..M-1, written to temporary files renamed into place: never half-written.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path

import torch
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities import move_data_to_device
from omegaconf import OmegaConf

from hybridqcm import runfiles, runfolder
from hybridqcm.atomic import atomic_open, atomic_write_csv, atomic_write_text
from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation.refinement import GaussNewtonRefinement

SHARDS = "shards"
# Settings that do not change a single estimate: where and how the run happens, what it draws.
_NOT_IN_FINGERPRINT = ("trainer", "progress", "plots", "tensorboard", "overwrite", "keep_shards", "paths", "hydra")


def run_fingerprint(cfg, input_files: Iterable[str | os.PathLike | None]) -> dict:
    """{"settings": the config minus _NOT_IN_FINGERPRINT, "inputs": {file: [size, mtime_ns]}, "hash"}."""
    try:
        settings = OmegaConf.to_container(cfg, resolve=True)
    except Exception:  # outside Hydra (tests compose the config): ${hydra:...} cannot resolve
        settings = OmegaConf.to_container(cfg, resolve=False)
    settings = {k: v for k, v in settings.items() if k not in _NOT_IN_FINGERPRINT}
    inputs = runfolder.fingerprint(str(Path(p).resolve()) for p in input_files if p)
    digest = hashlib.sha256(json.dumps([settings, inputs], sort_keys=True, default=str).encode()).hexdigest()[:16]
    return {"hash": digest, "settings": settings, "inputs": inputs}


def _differences(old: Mapping, new: Mapping) -> list[str]:
    keys = sorted(
        k
        for k in set(old.get("settings", {})) | set(new["settings"])
        if old.get("settings", {}).get(k) != new["settings"].get(k)
    )
    if old.get("inputs") != new["inputs"]:
        keys.append("input files " + ", ".join(sorted(set(old.get("inputs") or {}) ^ set(new["inputs"])) or "changed"))
    return keys


class ShardStore:
    """The shard folder of one run: which blocks are done, writing a block, merging all of them."""

    def __init__(self, run_dir: str | os.PathLike, fingerprint: Mapping):
        self.run_dir = Path(run_dir)
        self.root = self.run_dir / SHARDS
        self.fingerprint = dict(fingerprint)

    def path(self, block: int, suffix: str) -> Path:
        return self.root / f"block-{block:06d}{suffix}"

    def marker(self, block: int) -> dict | None:
        """The block's done marker; ConfigError (one line, naming it) when another run wrote it."""
        path = self.path(block, ".done.json")
        try:
            record = json.loads(path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as error:
            raise ConfigError(f"{path}: unreadable shard marker ({error}); remove it to redo the block") from None
        if record.get("fingerprint", {}).get("hash") != self.fingerprint["hash"]:
            differs = _differences(record.get("fingerprint", {}), self.fingerprint)
            raise ConfigError(
                f"{path}: shard written by a different configuration or inputs (differs in {', '.join(differs) or 'hash'}); "
                f"rerun with those settings, pass overwrite=true, or choose another hydra.run.dir"
            )
        return record

    def pending(self, blocks: Sequence[tuple[int, int]]) -> list[tuple[int, int, int]]:
        """(block id, start, stop) of the blocks without a matching done marker."""
        out = []
        for k, (start, stop) in enumerate(blocks):
            record = self.marker(k)
            if record is None or record.get("rows") != [start, stop]:
                out.append((k, start, stop))
        return out

    def write(
        self,
        block: int,
        rows: tuple[int, int],
        header: Sequence[str],
        estimates,
        status_header,
        status,
        columns,
        stats,
        seconds: tuple[float, float] = (float("nan"), float("nan")),
        device: str | None = None,
        device_memory_mib: float | None = None,
        phase_seconds: dict | None = None,
    ) -> None:
        atomic_write_csv(self.path(block, ".csv"), header, estimates)
        atomic_write_csv(self.path(block, ".status.csv"), status_header, status)
        with atomic_open(self.path(block, ".pt"), "wb") as handle:
            torch.save(columns, handle)
        record = {
            "rows": list(rows),
            "stages": stats,
            # GN solve and formatting of this block (not the reading): wall and this process's CPU seconds
            "seconds": seconds[0],
            "cpu_seconds": seconds[1],
            "fingerprint": self.fingerprint,
            "pid": os.getpid(),
            "device": device,  # where the predict step (the networks) ran, e.g. cuda:0
            "device_memory_mib": device_memory_mib,  # peak of GN on that device (gn_device=accelerator)
            # an occupant selection's seconds by phase (estimation/occupant.PhaseClock), else None
            "phase_seconds": phase_seconds,
        }
        atomic_write_text(self.path(block, ".done.json"), json.dumps(record) + "\n")

    def merge(self, blocks: Sequence[tuple[int, int]], n_samples: int) -> tuple[dict, list[dict]]:
        """Write estimates.csv and status.csv from the shards; returns (columns [M, ...], markers per block).

        Raises DatasetError naming the first block that is missing (a rank died: rerun to finish)."""
        records = []
        for k, (start, stop) in enumerate(blocks):
            record = self.marker(k)
            if record is None or record.get("rows") != [start, stop]:
                raise DatasetError(
                    f"{self.path(k, '.done.json')}: block {k} (rows {start}..{stop - 1}) was not estimated; "
                    f"rerun the same command to finish the missing blocks"
                )
            records.append(record)
        for name, suffix in (("estimates.csv", ".csv"), ("status.csv", ".status.csv")):
            self._concatenate(self.run_dir / name, [self.path(k, suffix) for k in range(len(blocks))], n_samples)
        parts = [torch.load(self.path(k, ".pt"), weights_only=True) for k in range(len(blocks))]
        columns = {key: torch.cat([p[key] for p in parts]) for key in parts[0] if parts[0][key] is not None}
        if not torch.equal(columns["index"], torch.arange(n_samples)):
            raise DatasetError(f"{self.root}: the shards' sample indices are not 0..{n_samples - 1} in order")
        return columns, records

    @staticmethod
    def _concatenate(target: Path, parts: Sequence[Path], n_samples: int) -> None:
        """Every index 0..M-1 exactly once, in order (a repeated row is dropped, a gap is an error)."""
        expected = 0
        with atomic_open(target, "w", newline="") as out:
            writer = csv.writer(out)
            for i, part in enumerate(parts):
                with open(part, newline="") as handle:
                    reader = csv.reader(handle)
                    header = next(reader)
                    if i == 0:
                        writer.writerow(header)
                    for row in reader:
                        index = int(row[0])
                        if index < expected:
                            continue  # the same sample twice (a padded distributed sampler)
                        if index > expected:
                            raise DatasetError(f"{part}: sample {expected} is missing (next row is {index})")
                        writer.writerow(row)
                        expected += 1
            if expected != n_samples:
                raise DatasetError(f"{target}: the shards hold {expected} of {n_samples} samples")

    def remove(self) -> None:
        """The shards and their temporary files; the folder too, unless someone put something else in it."""
        runfiles.remove_tree_files(self.root, "block-*", ".block-*")


class BlockRefinement(GaussNewtonRefinement):
    """GaussNewtonRefinement for one block at a time: keeps nothing between blocks (the multi-start
    draws are per recording), so a block's result does not depend on which process solved it or what
    it solved before."""

    def refine_block(self, outputs: Mapping, module, block: int) -> dict:
        """The block's record (see GaussNewtonRefinement.refine); nothing is kept after it."""
        record = self.refine(outputs, module)
        self._batches.clear()
        return record


class ShardWriter(BasePredictionWriter):
    """Prediction writer: runs the GN stages on each predicted block (float64) and writes the block's
    shard. ``tables(record) -> (rows, status rows, columns)`` formats a block.

    GN runs on the CPU unless ``on_device`` builds a refinement for the predict device (gn_device=
    accelerator): then, on a non-CPU device, that refinement is built once per device and the block is
    solved under ``torch.device(device)``, so every tensor the solve makes (states, masks, line-search
    steps, the refinement's own constants) lives beside the block; the record comes back to the CPU
    for the tables. A block's peak device memory is in its marker (``device_memory_mib``)."""

    def __init__(
        self,
        store: ShardStore,
        refinement: BlockRefinement,
        header: Sequence[str],
        status_header: Sequence[str],
        tables: Callable,
        stage_stats: Callable,
        skipped_tables: Callable | None = None,
        merge_tables: Callable | None = None,
        on_device: Callable[[], BlockRefinement] | None = None,
    ):
        super().__init__(write_interval="batch")
        self.store, self.refinement = store, refinement
        self.on_device, self._device_refinements = on_device, {}
        self.header, self.status_header = list(header), list(status_header)
        self.tables, self.stage_stats = tables, stage_stats
        # windows kept from the fit (batch "skipped_index"/"skipped_status"): their rows, merged in index order
        self.skipped_tables, self.merge_tables = skipped_tables, merge_tables

    def _refine(self, prediction, pl_module, block: int) -> tuple[dict, float | None]:
        """(the block's record on the CPU, the solve's peak device memory in MiB or None on the CPU)."""
        device = pl_module.device
        if self.on_device is None or device.type == "cpu":
            return self.refinement.refine_block(move_data_to_device(prediction, "cpu"), pl_module, block), None
        with torch.device(device):
            refinement = self._device_refinements.get(str(device))
            if refinement is None:
                refinement = self._device_refinements[str(device)] = self.on_device()
            cuda = device.type == "cuda"
            if cuda:
                torch.cuda.reset_peak_memory_stats(device)
            record = refinement.refine_block(prediction, pl_module, block)
            memory = torch.cuda.max_memory_allocated(device) / 2**20 if cuda else None
        return move_data_to_device(record, "cpu"), memory

    def write_on_batch_end(self, trainer, pl_module, prediction, batch_indices, batch, batch_idx, dataloader_idx=0):
        t0, c0 = time.perf_counter(), time.process_time()
        block = int(batch["block"])
        tables, stats = None, {}
        memory, phases = None, None
        if int(batch["index"].shape[0]):  # a block of windows all kept from the fit has nothing to refine
            record, memory = self._refine(prediction, pl_module, block)
            tables, stats = self.tables(record), self.stage_stats(record)
            phases = record.get("phase_seconds")
            true = batch.get("true")
            tables[2]["true"] = None if true is None else true.detach().cpu().double()
        skipped = batch.get("skipped_index")
        if skipped is not None and int(skipped.shape[0]):
            rest = self.skipped_tables(skipped.cpu(), batch["skipped_status"].cpu(), batch.get("skipped_true"))
            tables = rest if tables is None else self.merge_tables(tables, rest)
        rows, status_rows, columns = tables
        start = int(columns["index"][0])
        self.store.write(
            block,
            (start, start + len(rows)),
            self.header,
            rows,
            self.status_header,
            status_rows,
            columns,
            stats,
            (time.perf_counter() - t0, time.process_time() - c0),
            str(pl_module.device),
            memory,
            phases,
        )


__all__ = ["SHARDS", "run_fingerprint", "ShardStore", "BlockRefinement", "ShardWriter"]
