"""qcm-estimate: Gauss-Newton (and hybrid) parameter estimation on an HDF5 dataset (SPEC §7 exps 5-10).

    qcm-estimate experiment=exp5_random_init data.path=FILE [n_samples=2000 noise_sigma=0.05 seed=0]
    qcm-estimate experiment=exp10_hybrid data.path=FILE cnn_ckpt=CKPT unet_ckpt=CKPT hydra.run.dir=DIR
    qcm-estimate ... trainer=ddp trainer.devices=2          (2 processes; trainer.accelerator=auto: a GPU)

Every bad input (unknown or non-estimation experiment, missing/wrong-kind checkpoint, a key or
channel the pipeline needs but the file lacks, NaN, a window longer than the stored steps) is
reported in one line naming the file, key and value, before any work is done.

The run: plan (apps/estimate_plan.py) -> the file streamed in blocks of batch_size recordings
(apps/estimate_inputs.py) -> Lightning predict on the trainer group's accelerator/devices/nodes,
each rank writing the shards of its blocks (apps/estimate_shards.py) -> one process merges them
into estimates.csv / status.csv and computes the metrics (apps/estimate_report.py).
"""

from __future__ import annotations

import functools
import json
import math
import resource
import time
import warnings
from pathlib import Path

import lightning
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from lightning.fabric.utilities.rank_zero import rank_zero_only
from lightning.pytorch.accelerators import CUDAAccelerator
from lightning.pytorch.strategies import DDPStrategy
from omegaconf import DictConfig

from hybridqcm import config, runfolder
from hybridqcm.apps import common
from hybridqcm.apps.common import fail
from hybridqcm.apps.estimate_inputs import InputSettings, RankBlocks, RecordingBlocks, block_rows, build_inputs
from hybridqcm.apps.estimate_occupant import build_selection, plot_first_recordings
from hybridqcm.apps.estimate_plan import (
    CHANNELS,
    INITIAL_STATES,
    MODELS,
    PARAM_NAMES,
    check_experiment_overrides,
    check_known_keys,
    check_positive_params,
    resolve_model,
    solver_settings,
    validate,
)
from hybridqcm.apps.estimate_report import (
    SEAT_COLUMNS,
    STATUS_HEADER,
    block_stage_stats,
    block_tables,
    coverage_95,
    estimates_header,
    log_stage_losses,
    merge_block_tables,
    merge_stage_stats,
    noise_label,
    print_report,
    skipped_tables,
    write_metrics,
)
from hybridqcm.apps.estimate_shards import BlockRefinement, ShardStore, ShardWriter, run_fingerprint
from hybridqcm.atomic import atomic_write_text
from hybridqcm.errors import ConfigError, DatasetError, HybridQCMError
from hybridqcm.estimation.drive_plan import drive_columns, drive_plan, drive_skipped_columns, model_names
from hybridqcm.estimation.front import HybridEstimator
from hybridqcm.estimation.refinement import GaussNewtonStage
from hybridqcm.estimation.response import base_excitation_response, quarter_car_response
from hybridqcm.estimation.solver import build_solver
from hybridqcm.physics.parameters import PhysicalConstants
from hybridqcm.reports.drive import aggregate_drives


def build_module(cfg, plan) -> HybridEstimator:
    """The network front (CNN init, U-Net completion, CAE denoising) and the GN window."""
    return HybridEstimator(
        cnn_ckpt=cfg.cnn_ckpt if cfg.init.cnn else None,
        unet_ckpt=cfg.unet_ckpt,
        cae_ckpt=cfg.cae_ckpt,
        observed=plan["observed"],
        n_steps=plan["n_steps"],
        h=plan["h"],
        cnn_init=bool(cfg.init.cnn),
        equation_error_init=bool(cfg.init.equation_error),
        known=[PARAM_NAMES[j] for j in plan["known"]],
        pu_known=bool(cfg.pu_known),
        cnn_a2_from_data=bool(cfg.cnn_a2_from_file),
        base_excitation=plan["base_excitation"],
        input_margin=plan["input_margin"],
        cnn_prior_rel_std=cfg.init.get("cnn_prior_rel_std"),
        cnn_prior=cfg.init.get("cnn_prior"),
        cnn_prior_scale=float(cfg.init.get("cnn_prior_scale", 1.0)),
    )


def build_refinement(cfg, plan):
    """The GN stages, the response model they fit, weighting and multi-start settings; with several
    occupant models or a channel delay (plan["occupant"]), one such refinement per candidate model
    and the per-recording selection over them (estimation/occupant.py)."""
    n_params = plan["n_params"]
    known_mask = torch.zeros(n_params, dtype=torch.bool)
    known_mask[plan["known"]] = True
    if plan["base_excitation"] is None:
        response = quarter_car_response(
            plan["model"],
            plan["h"],
            bool(cfg.pu_known),
            plan["initial_state"],
            str(cfg.hold),
            int(cfg.substeps),
            int(cfg.get("spline_degree", 5)),
        )
    else:
        response = base_excitation_response(
            plan["base_excitation"],
            plan["h"],
            plan["initial_state"],
            str(cfg.hold),
            int(cfg.substeps),
            int(cfg.get("spline_degree", 5)),
        )
    # The reference vehicle (vehicle:) on the model's own p: the vehicle prior's mean, the restarts' centre.
    names = response.theta_names[: response.n_params]
    p_ref = PhysicalConstants(**{k: float(v) for k, v in cfg.vehicle.items()}).to_params()
    reference = torch.stack([p_ref[PARAM_NAMES.index(n)] for n in names])
    param_prior = None
    if plan["vehicle_prior"] is not None:
        listed = torch.tensor([n in plan["vehicle_prior"]["params"] for n in names])
        if bool(listed.any()):
            param_prior = (reference, torch.where(listed, plan["vehicle_prior"]["rel_std"] * reference, math.inf))
    centre = reference if plan["restarts_around"] == "reference" else None
    if plan.get("occupant") is not None:
        return build_selection(
            cfg,
            plan,
            plan["occupant"],
            lambda r, k, prior, restarts=True, centre=None: _refinement(cfg, plan, r, k, prior, centre, True, restarts),
        )
    return _refinement(cfg, plan, response, known_mask, param_prior, centre)


def _refinement(
    cfg, plan, response, known_mask, param_prior, restart_center, noise_leverage: bool = False, restarts: bool = True
) -> BlockRefinement:
    """One GaussNewtonRefinement of ``response`` with the run's stages, weighting and multi-start settings
    (``noise_leverage``: the noise variances corrected for the fit's leverage, the occupant models';
    ``restarts`` false: a single attempt, the occupant selection's candidates, restarted only where chosen)."""
    stages = [
        GaussNewtonStage(s["name"], build_solver(s["method"], **s["settings"]), s["channels"], s["n_steps"], s["guard"])
        for s in plan["stages"]
    ]
    sigma = float(cfg.noise_sigma)
    # Restart threshold on L/(½Σa²): noise-free fits end near 1e-15; with noise the floor is ~σ².
    threshold = float(cfg.restarts.threshold) if sigma == 0 else max(float(cfg.restarts.threshold), 4.0 * sigma**2)
    if plan["model"] == "exact":  # the loss floor is the hold's model error: restarts go by status alone
        threshold = math.inf
    reweight = str(cfg.residual_weighting)
    if reweight == "auto":
        reweight = "spectral" if plan["model"] == "exact" else False
    elif reweight != "spectral":
        reweight = reweight.lower() == "true"
    return BlockRefinement(
        stages,
        known=known_mask,
        pu_known=bool(cfg.pu_known),
        observed=tuple(plan["observed"]),  # what a finished fit is weighed on without the module (occupant models)
        h=plan["h"],
        response=response,
        reweight=reweight,
        peer_factor=cfg.get("misfit_peer_factor", 10.0),
        log_dir=None,  # the merged stage losses are logged once, after the merge
        restarts=int(cfg.restarts.count) if restarts else 0,
        restart_threshold=threshold,
        restart_sigma=float(cfg.restarts.sigma),
        seed=int(cfg.seed),
        restart_mass_factors=list(cfg.restarts.get("mass_factors") or []),
        restart_batch=int(cfg.restarts.get("batch", 64)),
        # the exact model's extra attempts for wrong basins; the Euler reproduction keeps the source's protocol
        restarts_failed=int(cfg.restarts.get("failed", 0)) if plan["model"] == "exact" and restarts else 0,
        restart_far=cfg.restarts.get("far_from_start"),
        x0_start=plan["x0_start"],
        param_prior=param_prior,
        restart_center=restart_center,
        noise_leverage=noise_leverage,
    )


class ForkedCPUDDP(DDPStrategy):
    """DDP over CPU processes forked from the app rather than spawned: a spawned rank imports torch,
    Lightning and the app again and unpickles the module (13 s to start two ranks here, against
    0.3 s forked). Each forked rank runs torch at one thread: GNU OpenMP is not fork-safe once the
    parent has used its thread pool (a child's parallel region then hangs), and one thread per rank
    is what n ranks on n cores want anyway."""

    def __init__(self, **kwargs):
        kwargs["start_method"] = "fork"
        super().__init__(**kwargs)

    def setup_environment(self) -> None:
        torch.set_num_threads(1)
        super().setup_environment()


def _resolves_to_cpu(accelerator: str) -> bool:
    return accelerator == "cpu" or (accelerator == "auto" and not CUDAAccelerator.is_available())


def build_trainer(cfg, callbacks, run_dir: Path) -> lightning.Trainer:
    """Lightning Trainer for predict from the trainer group: accelerator, devices, num_nodes, strategy
    (its training keys are not used here). Several devices without a strategy: DDP, spawned. On CPU a
    spawned DDP strategy (configs/trainer/ddp.yaml) is run forked instead (ForkedCPUDDP): the same
    ranks and results, without the start-up of a fresh interpreter per rank."""
    group = cfg.get("trainer") or {}
    devices, nodes = group.get("devices", 1), int(group.get("num_nodes", 1))
    accelerator = str(group.get("accelerator", "cpu"))
    strategy = group.get("strategy", None) or "auto"
    if isinstance(strategy, DictConfig):
        settings = dict(strategy)
        target = str(settings.pop("_target_", ""))
        if (
            target.endswith("DDPStrategy")
            and settings.get("start_method", "popen") == "spawn"
            and _resolves_to_cpu(accelerator)
            and nodes == 1
        ):
            settings.pop("start_method")
            strategy = ForkedCPUDDP(**settings)
        else:
            strategy = instantiate(strategy)
    elif strategy == "auto" and (nodes > 1 or str(devices) not in ("1", "auto")):
        strategy = "ddp_spawn"  # a re-executed command line (Lightning's default) would re-enter Hydra
    return lightning.Trainer(
        accelerator=accelerator,
        devices=devices,
        num_nodes=nodes,
        strategy=strategy,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=bool(cfg.progress),
        enable_model_summary=False,
        callbacks=callbacks,
        default_root_dir=str(run_dir),
        inference_mode=False,
        use_distributed_sampler=False,  # the blocks are sharded over ranks by RankBlocks
    )


# --------------------------------------------------------------------------------------------------
def seat_plan(cfg, plan):
    """The seat file's law (seat_file=, estimation/calibration.py) or None; only the road-free seat model
    reads one. The key is not ``seat``: that names a seat of a half / full car file (apps/estimate_seat.py)."""
    path = cfg.get("seat_file")
    if path is None:
        return None
    from hybridqcm.estimation.calibration import load_seat

    if plan is None or plan["base_excitation"] != "seat":
        raise ConfigError(
            f"seat_file={path}: a seat calibration is used by the road-free seat model "
            f"(experiment=occupant_roadfree, base_excitation: seat); this run fits "
            f"{'the ' + str(cfg.get('vehicle_model')) if plan is None else plan['base_excitation'] or 'the road'}"
        )
    return load_seat(path)


def run(cfg, run_dir: Path | None = None) -> dict:
    """The estimation run into ``run_dir`` (default: the Hydra job's folder, else the working directory)."""
    if str(cfg.get("vehicle_model", "quarter_car")) != "quarter_car":  # the half and full car (issue 30)
        from hybridqcm.estimation.vehicle_runner import run_vehicle

        seat_plan(cfg, None)
        if run_dir is None:
            run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path(".")
        return run_vehicle(cfg, build_trainer, run_dir)
    t_start = time.perf_counter()
    plan = validate(cfg)
    seat = seat_plan(cfg, plan)
    drive = drive_plan(cfg, plan)  # aggregate=drive: the file's drives checked now (None: per window only)
    if run_dir is None:
        run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path(".")
    config.check_writable_dir(run_dir)  # a read-only folder is found now, not after all the solving
    inputs_used = [plan["path"], cfg.cnn_ckpt, cfg.unet_ckpt, cfg.cae_ckpt, cfg.get("seat_file")]
    store = ShardStore(run_dir, run_fingerprint(cfg, inputs_used))
    if rank_zero_only.rank == 0:  # under a cluster launcher every rank runs this: one clears
        runfolder.prepare_run_dir(
            run_dir,
            runfolder.ESTIMATE_ARTEFACTS,
            bool(cfg.get("overwrite", False)),
            scratch=runfolder.ESTIMATE_SCRATCH,
        )
        if cfg.get("overwrite", False):
            store.remove()
    n_samples, n_params = plan["n_samples"], plan["n_params"]
    # a block holds at most block_samples time steps (recordings x steps read): long windows, fewer per block
    per_block = int(cfg.batch_size)
    if cfg.get("block_samples"):
        per_block = min(per_block, max(1, int(cfg.block_samples) // int(plan["n_read_steps"])))
    blocks = block_rows(n_samples, per_block)
    pending = store.pending(blocks)  # a finished block (matching marker) of an interrupted run is kept

    refinement = build_refinement(cfg, plan)
    theta_names = list(refinement.response.theta_names)
    n_theta_params = refinement.response.n_params  # with body modes and a delay: more than the n_params scored
    extra = list(getattr(refinement, "extra_columns", []))
    tables = functools.partial(
        block_tables, n_params=n_theta_params, K3=float(cfg.K3), n_scored=n_params, extra=extra, seat=seat
    )
    header = estimates_header(theta_names, n_theta_params, [*extra, *(SEAT_COLUMNS if seat is not None else ())])
    skipped = functools.partial(skipped_tables, header=header, n_scored=n_params)
    if drive is not None:  # each window's shared parameters and covariance travel with its block
        tables = drive_columns(tables, refinement, n_theta_params)
        skipped = drive_skipped_columns(skipped, n_theta_params)
    writer = ShardWriter(
        store,
        refinement,
        header,
        STATUS_HEADER,
        tables,
        block_stage_stats,
        skipped,
        merge_block_tables,
    )
    trainer = build_trainer(cfg, [writer], run_dir)
    if trainer.world_size > 1:
        # Spawned ranks receive the module's tensors through shared memory; the default file-descriptor
        # passing fails in containers with a small fd/shm allowance ("unable to resize file").
        torch.multiprocessing.set_sharing_strategy("file_system")
    t_solve = time.perf_counter()
    if pending:
        if len(pending) < len(blocks):
            print(f"resuming: {len(blocks) - len(pending)} of {len(blocks)} blocks already estimated in {store.root}")
        if trainer.world_size > len(pending) and rank_zero_only.rank == 0:
            print(
                f"note: {len(pending)} block(s) to estimate on {trainer.world_size} processes, "
                f"{trainer.world_size - len(pending)} idle (batch_size={int(cfg.batch_size)}; "
                f"batch_size<={-(-n_samples // trainer.world_size)} gives each one a share)"
            )
        loader = torch.utils.data.DataLoader(
            RecordingBlocks(InputSettings.from_config(cfg), plan, pending),
            batch_size=None,
            sampler=RankBlocks(len(pending)),
        )
        module = build_module(cfg, plan)
        module.allow_zero_length_dataloader_with_multiple_devices = True  # fewer blocks than ranks
        with warnings.catch_warnings():  # the writer keys shards by block, not by sampler indices
            warnings.filterwarnings("ignore", message="Couldn't infer the batch indices")
            warnings.filterwarnings("ignore", message=".*within local rank has zero length")
            trainer.predict(module, dataloaders=loader, return_predictions=False)
    solve_seconds = time.perf_counter() - t_solve
    rss_solve = _max_rss_mib()
    trainer.strategy.barrier("qcm-estimate merge")
    if not trainer.is_global_zero:
        return {}

    columns, markers = store.merge(blocks, n_samples)
    # a person at a glance: fitted apparent mass vs the measured a3/a2
    if plan.get("occupant") is not None and cfg.plots and {"a3", "a2"} <= set(plan["observed"]):
        pictures = plot_first_recordings(run_dir, plan, run_dir / "estimates.csv")
        if cfg.tensorboard and pictures:
            from hybridqcm.tracking import log_estimation_to_tensorboard

            log_estimation_to_tensorboard(run_dir / "tb", [], pictures, prefix="occupant")
    stage_names = [s["name"] for s in plan["stages"]]
    stage_names += [k for k in dict.fromkeys(k for m in markers for k in m["stages"]) if k not in stage_names]
    stage_loss, stage_status = merge_stage_stats([m["stages"] for m in markers], stage_names)
    if cfg.tensorboard:
        log_stage_losses(run_dir / "tb", stage_loss)
    summary = {
        "experiment": cfg.experiment_name,
        "data": str(plan["path"]),
        "split": plan["split"],
        "n_samples": int(n_samples),
        "n_steps": plan["n_steps"],
        "noise_sigma": float(cfg.noise_sigma),
        "seed": int(cfg.seed),
        "observed": plan["observed"],
        "known": [PARAM_NAMES[j] for j in plan["known"]],
        "model": plan["model"],
        "initial_state": plan["initial_state"],
        "x0_start": plan["x0_start"],
        "base_excitation": plan["base_excitation"],
        "hold": str(cfg.hold) if plan["model"] == "exact" else None,
        "sensor": {k: v for k, v in vars(plan["sensor"]).items() if not k.startswith("_")},
        "input_margin": list(plan["input_margin"]),
        "interval_covariance": plan["stages"][-1]["settings"].get("covariance", "model"),  # auto resolved
        "stages": stage_status,
        "stage_mean_loss": stage_loss,
        "seconds_solve": solve_seconds,
        "processes": int(trainer.world_size),
        "blocks": len(blocks),
        "blocks_resumed": len(blocks) - len(pending),
        # per process: seconds spent solving blocks (the rest of seconds_solve is start-up and reading)
        "seconds_blocks_per_process": _per_process_seconds(markers),
        "cpu_seconds_blocks": sum(float(m.get("cpu_seconds", math.nan)) for m in markers),
        "predict_devices": sorted({m["device"] for m in markers if m.get("device")}),  # the networks' device(s)
    }
    noise = noise_label(cfg.noise_sigma, plan["sensor"])
    metrics, table_rows = write_metrics(
        cfg, columns, columns.get("true"), plan["known"], run_dir, plan["n_steps"], noise=noise
    )
    summary.update(metrics)
    if drive is not None:
        summary["drive_aggregate"] = aggregate_drives(
            cfg, plan, drive, columns, run_dir, model_names(refinement), theta_names[:n_theta_params]
        )
    summary["noise"] = noise
    summary["mass_scale"] = _mass_scale(cfg, seat, columns, run_dir)
    summary["seconds_total"] = time.perf_counter() - t_start
    # This process's peak resident memory after the solve and at the end (spawned ranks excluded).
    summary["max_rss_mib"] = {"solve": rss_solve, "total": _max_rss_mib(), "ranks": _max_rss_mib(children=True)}
    atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2))
    runfolder.write_completion_marker(run_dir, "qcm-estimate", runfolder.task_overrides(), inputs_used)
    if not cfg.get("keep_shards", False):
        store.remove()
    print_report(cfg, summary, table_rows, run_dir)
    return summary


def _mass_scale(cfg, seat, columns, run_dir: Path) -> dict:
    """summary.json's word on the mass scale: uncalibrated (m3 = K3 / p2 with the reference K3) or the seat
    file's law, and how many occupant masses lie outside the calibration's loads (extrapolated, warned)."""
    if seat is None:
        return {"calibrated": False, "K3": float(cfg.K3), "note": "m3 = K3 / p2 with the reference seat's K3"}
    import csv

    with open(run_dir / "estimates.csv", newline="") as handle:
        occupant = np.array([float(r["occupant_mass"]) for r in csv.DictReader(handle)])
    fitted = np.isfinite(occupant)
    outside = int((fitted & ~seat.covers(occupant)).sum())
    if outside:
        print(
            f"warning: {outside} of {int(fitted.sum())} occupant masses lie outside the calibration's loads "
            f"{min(seat.loads):g}..{max(seat.loads):g} kg (the seat law extrapolated; calibrate with heavier or "
            f"lighter loads)"
        )
    return {
        "calibrated": True,
        "seat_file": str(cfg.seat_file),
        "law": seat.law,
        "K3_ref": seat.K3_ref,
        "exponent": seat.exponent,
        "pan_mass": seat.pan_mass,
        "loads_kg": seat.loads,
        "extrapolated": outside,
    }


def _per_process_seconds(markers) -> list[float]:
    busy: dict = {}
    for marker in markers:
        busy[marker.get("pid")] = busy.get(marker.get("pid"), 0.0) + float(marker.get("seconds", math.nan))
    return sorted(busy.values(), reverse=True)


def _max_rss_mib(children: bool = False) -> float:
    """Peak resident memory of this process, or of the largest of its finished child processes (the
    ranks of a multi-process run on CPU; 0 if none), in MiB."""
    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return resource.getrusage(who).ru_maxrss / 1024  # Linux reports KiB


def _hydra_entry(cfg) -> None:
    try:
        run(cfg)
    except (HybridQCMError, ConfigError, DatasetError, FileNotFoundError) as error:
        fail(error)


def main() -> None:
    common.run_hydra_app("estimate", "estimate", _hydra_entry)


__all__ = [
    "CHANNELS",
    "MODELS",
    "INITIAL_STATES",
    "PARAM_NAMES",
    "build_inputs",
    "build_module",
    "build_refinement",
    "build_trainer",
    "check_experiment_overrides",
    "check_known_keys",
    "check_positive_params",
    "coverage_95",
    "resolve_model",
    "run",
    "solver_settings",
    "validate",
]

if __name__ == "__main__":
    main()
