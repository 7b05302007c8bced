"""qcm-estimate: Gauss-Newton (and hybrid) parameter estimation on an HDF5 dataset (SPEC §7 exps 5-10).

    qcm-estimate experiment=exp5_random_init data.path=FILE [n_samples=2000 noise_sigma=0.05 seed=0]
    qcm-estimate experiment=exp10_hybrid data.path=FILE cnn_ckpt=CKPT unet_ckpt=CKPT hydra.run.dir=DIR
    qcm-estimate ... trainer=ddp trainer.devices=2          (2 processes; trainer.accelerator=auto: a GPU)

Every bad input (unknown or non-estimation experiment, missing/wrong-kind checkpoint, a key or
channel the pipeline needs but the file lacks, NaN, a window longer than the stored steps) is
reported in one line naming the file, key and value, before any work is done.

The run, in the library: plan (estimation/plan.py) -> the file streamed in blocks of batch_size
recordings (estimation/blocks.py) -> Lightning predict on the trainer group's accelerator/devices/nodes,
each rank writing the shards of its blocks (estimation/shards.py, estimation/runner.py) -> one process
merges them into estimates.csv / status.csv and computes the metrics (reports/estimate.py).
"""

from __future__ import annotations

import time
from pathlib import Path

from hydra.core.hydra_config import HydraConfig

from hybridqcm.apps import common
from hybridqcm.apps.common import fail
from hybridqcm.errors import ConfigError, DatasetError, HybridQCMError
from hybridqcm.estimation import runner
from hybridqcm.estimation.drive_fit import JointDrives
from hybridqcm.estimation.drive_plan import drive_columns, drive_plan, drive_skipped_columns, model_names
from hybridqcm.estimation.plan import validate
from hybridqcm.estimation.plan_seat import seat_plan
from hybridqcm.reports.drive import aggregate_drives
from hybridqcm.reports.estimate import finish_run


def run(cfg, run_dir: Path | None = None) -> dict:
    """The estimation run into ``run_dir`` (default: the Hydra job's folder, else the working directory)."""
    if run_dir is None:
        run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path(".")
    if str(cfg.get("vehicle_model", "quarter_car")) != "quarter_car":  # the half and full car (issue 30)
        from hybridqcm.estimation.vehicle_runner import solve_vehicle
        from hybridqcm.reports.vehicle import finish_vehicle_run

        seat_plan(cfg, None)
        solved = solve_vehicle(cfg, runner.build_trainer, run_dir)
        return {} if solved is None else finish_vehicle_run(cfg, solved, run_dir)
    t_start = time.perf_counter()
    plan = validate(cfg)
    seat = seat_plan(cfg, plan)
    drive = drive_plan(cfg, plan)  # aggregate=drive: the file's drives checked now (None: per window only)
    inputs_used = [plan["path"], cfg.cnn_ckpt, cfg.unet_ckpt, cfg.cae_ckpt, cfg.get("seat_file")]
    store = runner.prepare_run(cfg, plan, run_dir, inputs_used)
    refinement = runner.build_refinement(cfg, plan)
    tables = runner.estimate_tables(cfg, plan, refinement, seat)
    aggregate = None
    if drive is not None:  # each window's shared parameters and covariance travel with its block
        n_theta = refinement.response.n_params
        tables = runner.EstimateTables(
            tables.header,
            drive_columns(tables.rows, refinement, n_theta),
            drive_skipped_columns(tables.skipped, n_theta, len(model_names(refinement))),
        )
        names = list(refinement.response.theta_names)[:n_theta]

        def aggregate(columns):
            prior = getattr(refinement, "log_prior", None)  # an occupant-model selection's model prior
            joint = None
            if drive.joint != "none":  # the segments fitted jointly from the file's windows
                layout = list(refinement.response.theta_names)[:n_theta]
                joint = JointDrives(cfg, plan, refinement, layout, drive.per_window)
            return aggregate_drives(
                cfg, plan, drive, columns, run_dir, model_names(refinement), names, prior, seat=seat, joint=joint
            )

    solved = runner.solve(cfg, plan, run_dir, store, refinement, tables)
    if solved is None:  # not rank 0: the merge and the report are rank 0's
        return {}
    summary = finish_run(cfg, plan, solved, run_dir, seat, inputs_used, t_start, aggregate)
    if not cfg.get("keep_shards", False):
        store.remove()
    return summary


def _hydra_entry(cfg) -> None:
    try:
        run(cfg)
    except (HybridQCMError, ConfigError, DatasetError, FileNotFoundError) as error:
        fail(error)


def main() -> None:
    common.run_hydra_app("estimate", "estimate", _hydra_entry)


if __name__ == "__main__":
    main()
