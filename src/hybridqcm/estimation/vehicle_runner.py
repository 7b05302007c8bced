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

import json
import math
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import torch
from lightning.fabric.utilities.rank_zero import rank_zero_only

from hybridqcm import config, runfolder
from hybridqcm.apps.estimate_inputs import RankBlocks, block_rows
from hybridqcm.apps.estimate_report import STATUS_HEADER, block_stage_stats, log_stage_losses, merge_stage_stats
from hybridqcm.apps.estimate_shards import ShardStore, ShardWriter, run_fingerprint
from hybridqcm.atomic import atomic_write_text
from hybridqcm.estimation.plan_vehicle import (
    VehicleBlocks,
    VehicleInputSettings,
    build_vehicle_refinement,
    validate_vehicle,
)
from hybridqcm.estimation.vehicle_front import VehicleFront
from hybridqcm.physics.vehicle_geometry import VehicleLayout
from hybridqcm.physics.vehicle_model import VehicleModel
from hybridqcm.reports.vehicle import (
    vehicle_block_tables,
    vehicle_estimates_header,
    vehicle_print_report,
    write_vehicle_metrics,
)


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


def _summary(cfg, plan: dict, stage_status, stage_loss, markers: list, counts: dict) -> dict:
    """summary.json's entries of the run itself (the metrics are added by reports/vehicle.py)."""
    layout: VehicleLayout = plan["layout"]
    return {
        "experiment": cfg.experiment_name,
        "vehicle": layout.kind,
        "seats": list(layout.seat_names),
        "tyre_damping": layout.tyre_damping,
        "data": str(plan["path"]),
        "split": plan["split"],
        "n_samples": int(plan["n_samples"]),
        "n_steps": plan["n_steps"],
        "seed": int(cfg.seed),
        "known": plan["known"],
        "model": "exact",
        "initial_state": plan["initial_state"],
        "hold": str(cfg.hold),
        "substeps": int(cfg.substeps),
        "spline_degree": plan["spline_degree"],
        "sensor": {k: v for k, v in vars(plan["sensor"]).items() if not k.startswith("_")},
        "input_margin": list(plan["input_margin"]),
        "stages": stage_status,
        "stage_mean_loss": stage_loss,
        "seconds_solve": counts["seconds_solve"],
        "processes": counts["processes"],
        "blocks": counts["blocks"],
        "blocks_resumed": counts["blocks_resumed"],
        "cpu_seconds_blocks": sum(float(m.get("cpu_seconds", math.nan)) for m in markers),
    }


def run_vehicle(cfg, build_trainer: Callable, run_dir: Path) -> dict:
    """qcm-estimate for vehicle_model=half_car|full_car into ``run_dir``; ``build_trainer(cfg, callbacks,
    run_dir)`` is apps/estimate.py's. Returns the summary (empty on ranks other than the first)."""
    t_start = time.perf_counter()
    plan = validate_vehicle(cfg)
    config.check_writable_dir(run_dir)
    store = ShardStore(run_dir, run_fingerprint(cfg, [plan["path"]]))
    if rank_zero_only.rank == 0:
        runfolder.prepare_run_dir(
            run_dir,
            runfolder.ESTIMATE_ARTEFACTS,
            bool(cfg.get("overwrite", False)),
            scratch=runfolder.ESTIMATE_SCRATCH,
        )
        if cfg.get("overwrite", False):
            store.remove()
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
        return {}
    columns, markers = store.merge(blocks, n_samples)
    stage_loss, stage_status = merge_stage_stats([m["stages"] for m in markers], [s["name"] for s in plan["stages"]])
    if cfg.tensorboard:
        log_stage_losses(run_dir / "tb", stage_loss)
    counts = {
        "seconds_solve": solve_seconds,
        "processes": int(trainer.world_size),
        "blocks": len(blocks),
        "blocks_resumed": len(blocks) - len(pending),
    }
    summary = _summary(cfg, plan, stage_status, stage_loss, markers, counts)
    noise = plan["sensor"].describe()
    metrics, table_rows = write_vehicle_metrics(cfg, columns, plan, run_dir, noise)
    summary.update(metrics)
    summary["noise"] = noise
    summary["seconds_total"] = time.perf_counter() - t_start
    atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2))
    runfolder.write_completion_marker(run_dir, "qcm-estimate", runfolder.task_overrides(), [plan["path"]])
    if not cfg.get("keep_shards", False):
        store.remove()
    vehicle_print_report(cfg, summary, table_rows, run_dir)
    return summary


__all__ = ["run_vehicle"]
