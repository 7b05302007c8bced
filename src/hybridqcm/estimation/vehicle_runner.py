"""qcm-estimate for the half car and the full car (experiment=hcm_full_observation | fcm_full_observation).

The quarter car's run (apps/estimate.py) with the vehicle's model: plan (estimation/plan_vehicle.py: every
input checked first, one line per bad input) -> the file streamed in blocks
(:class:`~hybridqcm.estimation.plan_vehicle.VehicleBlocks`) -> Lightning predict
(:class:`~hybridqcm.estimation.vehicle_front.VehicleFront` cuts the GN problem) -> the GN stages and
restarts of estimation/refinement.py on each block, written as shards by the rank that solved it
(resumable, merged once) -> estimates.csv, status.csv, error tables, calibration, summary.json
(reports/vehicle.py).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from hybridqcm.estimation.blocks import RankBlocks, block_rows
from hybridqcm.estimation.plan_vehicle import (
    VehicleBlocks,
    VehicleInputSettings,
    build_vehicle_refinement,
    validate_vehicle,
)
from hybridqcm.estimation.runner import gn_on_device, prepare_run
from hybridqcm.estimation.shards import ShardStore, ShardWriter
from hybridqcm.estimation.tables import STATUS_HEADER, block_stage_stats, merge_stage_stats
from hybridqcm.estimation.vehicle_front import VehicleFront
from hybridqcm.estimation.vehicle_tables import vehicle_block_tables, vehicle_estimates_header
from hybridqcm.physics.vehicle_geometry import VehicleLayout
from hybridqcm.physics.vehicle_model import VehicleModel


def _predict(cfg, plan: dict, pending: list, trainer) -> None:
    """Lightning predict over the ``pending`` blocks: each rank solves its share and writes its shards."""
    model: VehicleModel = plan["model"]
    layout: VehicleLayout = plan["layout"]
    settings = VehicleInputSettings(
        int(cfg.seed), float(cfg.init.relative_sigma), str(cfg.known_source), bool(cfg.noise_weighting)
    )
    loader = torch.utils.data.DataLoader(
        VehicleBlocks(settings, plan, pending), batch_size=None, sampler=RankBlocks(len(pending))
    )
    start = None
    mode = cfg.init.get("equation_error", False)  # the rows of the equations of motion by least squares
    if mode:
        known = torch.tensor([n in plan["known"] for n in model.param_names])
        start = (layout, tuple(model.param_names), known, plan["h"], str(mode) == "seats")
    module = VehicleFront(plan["n_steps"], plan["input_margin"], start)
    module.allow_zero_length_dataloader_with_multiple_devices = True
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Couldn't infer the batch indices")
        warnings.filterwarnings("ignore", message=".*within local rank has zero length")
        trainer.predict(module, dataloaders=loader, return_predictions=False)


@dataclass
class VehicleSolved:
    """A solved half / full car run on the first rank, for reports/vehicle.finish_vehicle_run: the plan, the
    merged per-sample columns, the blocks' markers and stage statistics, the run's counts and its shard store."""

    plan: dict
    columns: dict
    markers: list
    stage_loss: dict
    stage_status: dict
    counts: dict
    store: ShardStore
    t_start: float


def solve_vehicle(cfg, build_trainer: Callable, run_dir: Path) -> VehicleSolved | None:
    """qcm-estimate for vehicle_model=half_car|full_car into ``run_dir`` up to the merged columns;
    ``build_trainer(cfg, callbacks, run_dir)`` is estimation/runner.py's. None on ranks other than the first."""
    t_start = time.perf_counter()
    plan = validate_vehicle(cfg)
    store = prepare_run(cfg, plan, run_dir, [plan["path"]])
    n_samples = plan["n_samples"]
    blocks = block_rows(n_samples, int(cfg.batch_size))
    pending = store.pending(blocks)
    refinement = build_vehicle_refinement(cfg, plan)
    model: VehicleModel = plan["model"]
    layout: VehicleLayout = plan["layout"]
    theta_names = list(refinement.response.theta_names)
    header = vehicle_estimates_header(theta_names, len(model.param_names), layout)
    writer = ShardWriter(
        store,
        refinement,
        header,
        STATUS_HEADER,
        lambda record: vehicle_block_tables(record, len(model.param_names), model.param_names, layout),
        block_stage_stats,
        on_device=gn_on_device(cfg, lambda: build_vehicle_refinement(cfg, plan), road_driven=False),
    )
    trainer = build_trainer(cfg, [writer], run_dir)
    if trainer.world_size > 1:  # as apps/estimate.py: tensors to spawned ranks through the file system
        torch.multiprocessing.set_sharing_strategy("file_system")
    t_solve = time.perf_counter()
    if pending:
        if len(pending) < len(blocks):
            print(f"resuming: {len(blocks) - len(pending)} of {len(blocks)} blocks already estimated in {store.root}")
        _predict(cfg, plan, pending, trainer)
    solve_seconds = time.perf_counter() - t_solve
    trainer.strategy.barrier("qcm-estimate merge")
    if not trainer.is_global_zero:
        return None
    columns, markers = store.merge(blocks, n_samples)
    stage_loss, stage_status = merge_stage_stats([m["stages"] for m in markers], [s["name"] for s in plan["stages"]])
    counts = {
        "seconds_solve": solve_seconds,
        "processes": int(trainer.world_size),
        "blocks": len(blocks),
        "blocks_resumed": len(blocks) - len(pending),
    }
    return VehicleSolved(plan, columns, markers, stage_loss, stage_status, counts, store, t_start)


__all__ = ["VehicleSolved", "solve_vehicle"]
