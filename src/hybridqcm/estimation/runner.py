"""qcm-estimate's run on a checked plan: the networks' front, the GN refinement, the trainer, the solve.

    plan = validate(cfg)                                     (estimation/plan.py: every input checked)
    refinement = build_refinement(cfg, plan)                 (the GN stages, response model, restarts)
    store = prepare_run(cfg, plan, run_dir, inputs_used)     (the run folder and its shard store)
    solved = solve(cfg, plan, run_dir, store, refinement, estimate_tables(cfg, plan, refinement, seat))

The file is streamed in blocks of batch_size recordings (estimation/blocks.py) through Lightning's
predict on the trainer group's accelerator/devices/nodes, each rank writing the shards of its blocks
(estimation/shards.py); one process merges them into estimates.csv / status.csv. The metrics, the
summary and the console table come after (reports/estimate.py). Hydra-free: ``cfg`` is the composed
configuration (configs/estimate.yaml and an experiment), ``run_dir`` the folder written into.
"""

from __future__ import annotations

import functools
import math
import resource
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import lightning
import torch
from hydra.utils import instantiate
from lightning.fabric.utilities.rank_zero import rank_zero_only
from lightning.pytorch.accelerators import CUDAAccelerator
from lightning.pytorch.strategies import DDPStrategy
from omegaconf import DictConfig

from hybridqcm import config, runfolder
from hybridqcm.errors import ConfigError
from hybridqcm.estimation._kernels import preload as preload_kernels
from hybridqcm.estimation.blocks import InputSettings, RankBlocks, RecordingBlocks, block_rows
from hybridqcm.estimation.front import HybridEstimator
from hybridqcm.estimation.plan_occupant import build_selection
from hybridqcm.estimation.refinement import GaussNewtonStage, RefinementSettings
from hybridqcm.estimation.response import base_excitation_response, quarter_car_response
from hybridqcm.estimation.restarts import Restarts
from hybridqcm.estimation.shards import BlockRefinement, ShardStore, ShardWriter, run_fingerprint
from hybridqcm.estimation.solver import build_solver
from hybridqcm.estimation.tables import (
    SEAT_COLUMNS,
    STATUS_HEADER,
    block_stage_stats,
    block_tables,
    estimates_header,
    merge_block_tables,
    skipped_tables,
)
from hybridqcm.estimation.weighting import NoiseWeighting
from hybridqcm.physics.parameters import PARAM_NAMES, PhysicalConstants

GN_DEVICES = ("cpu", "accelerator")  # gn_device: where Gauss-Newton runs


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
    (``noise_leverage``: the noise variances corrected for the fit's leverage and, on the seat, the input's
    bounded by its upper-band power, the occupant models';
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
        RefinementSettings(
            known=known_mask,
            pu_known=bool(cfg.pu_known),
            observed=tuple(plan["observed"]),  # what a finished fit is weighed on without the module (occupant models)
            h=plan["h"],
            response=response,
            peer_factor=cfg.get("misfit_peer_factor", 10.0),
            log_dir=None,  # the merged stage losses are logged once, after the merge
            x0_start=plan["x0_start"],
            param_prior=param_prior,
        ),
        # the input noise's band bound: measured on the seat (a2 in) only; the sprung model's a1 is not measured with it
        noise=NoiseWeighting(
            mode=reweight, leverage=noise_leverage, band_cap=noise_leverage and plan["base_excitation"] == "seat"
        ),
        restarts=Restarts(
            count=int(cfg.restarts.count) if restarts else 0,
            threshold=threshold,
            sigma=float(cfg.restarts.sigma),
            seed=int(cfg.seed),
            mass_factors=list(cfg.restarts.get("mass_factors") or []),
            batch=int(cfg.restarts.get("batch", 64)),
            # the exact model's extra attempts for wrong basins; the Euler reproduction keeps the source's protocol
            failed=int(cfg.restarts.get("failed", 0)) if plan["model"] == "exact" and restarts else 0,
            far_from_start=cfg.restarts.get("far_from_start"),
            center=restart_center,
        ),
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


def _strategy(group, accelerator: str, devices, nodes: int):
    """The trainer group's strategy: a spawned DDP on one CPU node forked instead (ForkedCPUDDP)."""
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
            return ForkedCPUDDP(**settings)
        return instantiate(strategy)
    if strategy == "auto" and (nodes > 1 or str(devices) not in ("1", "auto")):
        return "ddp_spawn"  # a re-executed command line (Lightning's default) would re-enter Hydra
    return strategy


def build_trainer(cfg, callbacks, run_dir: Path) -> lightning.Trainer:
    """Lightning Trainer for predict from the trainer group: accelerator, devices, num_nodes, strategy
    (its training keys are not used here). Several devices without a strategy: DDP, spawned. On CPU a
    spawned DDP strategy (configs/trainer/ddp.yaml) is run forked instead (ForkedCPUDDP): the same
    ranks and results, without the start-up of a fresh interpreter per rank."""
    group = cfg.get("trainer") or {}
    devices, nodes = group.get("devices", 1), int(group.get("num_nodes", 1))
    accelerator = str(group.get("accelerator", "cpu"))
    return lightning.Trainer(
        accelerator=accelerator,
        devices=devices,
        num_nodes=nodes,
        strategy=_strategy(group, accelerator, devices, nodes),
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
@dataclass
class EstimateTables:
    """How a block becomes rows: estimates.csv's ``header``; ``rows(record)`` of a refined block and
    ``skipped(index, status, true)`` of the windows kept from the fit -> (rows, status rows, columns)."""

    header: list[str]
    rows: Callable
    skipped: Callable


def estimate_tables(cfg, plan, refinement, seat=None) -> EstimateTables:
    """estimates.csv's layout for ``refinement`` (its θ names, the occupant selection's extra columns)
    and, with a seat law (estimation/calibration.py), the occupant's mass columns last; the metrics
    score the plan's n_params first parameters (those the file's truth holds)."""
    theta_names = list(refinement.response.theta_names)
    n_theta_params = refinement.response.n_params  # with body modes and a delay: more than the n_params scored
    n_scored = plan["n_params"]
    extra = list(getattr(refinement, "extra_columns", []))
    header = estimates_header(theta_names, n_theta_params, [*extra, *(SEAT_COLUMNS if seat is not None else ())])
    return EstimateTables(
        header,
        functools.partial(
            block_tables, n_params=n_theta_params, K3=float(cfg.K3), n_scored=n_scored, extra=extra, seat=seat
        ),
        functools.partial(skipped_tables, header=header, n_scored=n_scored),
    )


def prepare_run(cfg, plan, run_dir: Path, inputs_used) -> ShardStore:
    """The run folder checked writable and prepared (overwrite=true clears what an earlier run wrote)
    and the shard store keyed by the run's fingerprint (settings and input files)."""
    config.check_writable_dir(run_dir)  # a read-only folder is found now, not after all the solving
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
    return store


def gn_on_device(cfg, build: Callable, road_driven: bool = True):
    """``build`` (a refinement factory) where GN is to run on the trainer's device (gn_device=accelerator),
    else None (GN on the CPU). Refused in one line unless gn_device is cpu or accelerator, and for the
    models not validated on a GPU: only the road-driven quarter car's GN matched the CPU's there (the
    road-free occupant fit failed that test; docs/measurements/scaling.md, "Gauss-Newton on the GPU")."""
    where = str(cfg.get("gn_device", "cpu"))
    if where not in GN_DEVICES:
        raise ConfigError(f"gn_device={where!r}: choose one of {list(GN_DEVICES)}")
    if where == "accelerator" and not road_driven:
        raise ConfigError(
            "gn_device=accelerator: only the road-driven quarter car's Gauss-Newton is validated on a GPU; "
            "use gn_device=cpu here"
        )
    return build if where == "accelerator" else None


def run_blocks(cfg, plan) -> list[tuple[int, int]]:
    """The run's blocks [start, stop) of recordings: batch_size each, at most block_samples time steps."""
    per_block = int(cfg.batch_size)
    if cfg.get("block_samples"):  # long windows, fewer recordings per block
        per_block = min(per_block, max(1, int(cfg.block_samples) // int(plan["n_read_steps"])))
    return block_rows(plan["n_samples"], per_block)


@dataclass
class Solved:
    """A finished solve, merged (rank 0): the per-sample ``columns`` of the metrics, the blocks'
    ``markers`` (rows, stage statistics, timing), the block counts, processes, seconds and peak memory."""

    columns: dict
    markers: list
    blocks: int
    resumed: int
    processes: int
    seconds_solve: float
    rss_solve_mib: float


def solve(cfg, plan, run_dir: Path, store: ShardStore, refinement, tables: EstimateTables) -> Solved | None:
    """Every pending block estimated (Lightning predict over the trainer group's ranks, each writing the
    shards of its blocks), then merged into estimates.csv and status.csv by rank 0. None on other ranks."""
    blocks = run_blocks(cfg, plan)
    pending = store.pending(blocks)  # a finished block (matching marker) of an interrupted run is kept
    on_device = gn_on_device(cfg, lambda: build_refinement(cfg, plan), plan["base_excitation"] is None)
    writer = ShardWriter(
        store,
        refinement,
        tables.header,
        STATUS_HEADER,
        tables.rows,
        block_stage_stats,
        tables.skipped,
        merge_block_tables,
        on_device,
    )
    trainer = build_trainer(cfg, [writer], run_dir)
    if trainer.world_size > 1:
        # Spawned ranks receive the module's tensors through shared memory; the default file-descriptor
        # passing fails in containers with a small fd/shm allowance ("unable to resize file").
        torch.multiprocessing.set_sharing_strategy("file_system")
    if pending and on_device is None:
        preload_kernels()  # numba's import and set-up are the program's start-up, as torch's are, not the solve's
    t_solve = time.perf_counter()
    if pending:
        _predict(cfg, plan, trainer, blocks, pending, store)
    seconds = time.perf_counter() - t_solve
    rss_solve = max_rss_mib()
    trainer.strategy.barrier("qcm-estimate merge")
    if not trainer.is_global_zero:
        return None
    columns, markers = store.merge(blocks, plan["n_samples"])
    return Solved(
        columns, markers, len(blocks), len(blocks) - len(pending), int(trainer.world_size), seconds, rss_solve
    )


def _predict(cfg, plan, trainer, blocks, pending, store) -> None:
    """The pending blocks through the module and the writer (the trainer's callback) on every rank."""
    if len(pending) < len(blocks):
        print(f"resuming: {len(blocks) - len(pending)} of {len(blocks)} blocks already estimated in {store.root}")
    if trainer.world_size > len(pending) and rank_zero_only.rank == 0:
        print(
            f"note: {len(pending)} block(s) to estimate on {trainer.world_size} processes, "
            f"{trainer.world_size - len(pending)} idle (batch_size={int(cfg.batch_size)}; "
            f"batch_size<={-(-plan['n_samples'] // trainer.world_size)} gives each one a share)"
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


def max_rss_mib(children: bool = False) -> float:
    """Peak resident memory of this process, or of the largest of its finished child processes (the
    ranks of a multi-process run on CPU; 0 if none), in MiB."""
    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return resource.getrusage(who).ru_maxrss / 1024  # Linux reports KiB


__all__ = [
    "EstimateTables",
    "ForkedCPUDDP",
    "Solved",
    "build_module",
    "build_refinement",
    "gn_on_device",
    "build_trainer",
    "estimate_tables",
    "max_rss_mib",
    "prepare_run",
    "run_blocks",
    "solve",
]
