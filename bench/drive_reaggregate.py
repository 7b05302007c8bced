"""aggregate=drive again on a finished run's per-window columns, without refitting a window (issue 32).

    qcm-estimate experiment=occupant_roadfree data.path=W.h5 aggregate=drive keep_shards=true hydra.run.dir=RUN
    .venv/bin/python bench/drive_reaggregate.py RUN --data W.h5 --out OUT [--set weights=model prior=windows scale=none ...]
    .venv/bin/python bench/foreign_sim.py score-drives OUT --truth data/drives/truth.json --window-s 5

Reads RUN/shards/block-*.pt (the columns every block's windows carry, estimation/drive_plan.drive_columns) and
the file's profile_id / t_start, and writes drives.csv and drive_progress.csv into OUT under the run's drive
settings (configs/estimate.yaml's `drive:`) with `--set key=value` overriding them: the combination's choices
measured side by side on the same windows. Works on unfinished runs too (the blocks done so far; the drives
whose windows are all in them). The occupant models' prior (for the drive's model by evidence) is
configs/estimate.yaml's rigid_prior, the body models sharing the rest, as estimation/plan_occupant builds it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import h5py
import numpy as np
import torch
import yaml

from hybridqcm.estimation.drive_plan import DrivePlan
from hybridqcm.reports.drive import aggregate_drives

REPO = Path(__file__).resolve().parents[1]
NAMES = ("rigid", "body1", "body2", "rigid+delay", "body1+delay", "body2+delay")


def load_columns(run: Path) -> dict:
    parts = [torch.load(p, weights_only=True) for p in sorted((run / "shards").glob("block-*.pt"))]
    if not parts:
        raise SystemExit(f"{run}/shards: no block-*.pt (run qcm-estimate with keep_shards=true)")
    columns = {k: torch.cat([p[k] for p in parts]) for k in parts[0] if parts[0][k] is not None}
    if "drive_cand_model_cov" not in columns:  # shards written before the model-based covariance travelled
        columns["drive_cand_model_cov"] = columns["drive_cand_cov"]
    return columns


def _joint(run: Path, data: str, split: str, names, per_window):
    """The joint fits' JointDrives under the run's own config (its refinement, network front, inputs)."""
    from omegaconf import OmegaConf

    from hybridqcm.estimation import runner
    from hybridqcm.estimation.drive_fit import JointDrives
    from hybridqcm.estimation.plan import validate

    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    cfg.data.path, cfg.data.split = data, split
    plan = validate(cfg)
    refinement = runner.build_refinement(cfg, plan)
    layout = list(refinement.response.theta_names)[: refinement.response.n_params]
    return JointDrives(cfg, plan, refinement, layout, per_window)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("--data", required=True, help="the windows' file (qcm-import window=...)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--split", default="test")
    ap.add_argument("--set", nargs="*", default=[], help="drive settings: key=value (YAML values)")
    ap.add_argument("--K3", type=float, default=98935.0)
    ap.add_argument("--prior-per-window", action="store_true", help="the model prior as each window counts it")
    ap.add_argument("--model-cov", action="store_true", help="the model-based covariance as each window's own")
    ap.add_argument(
        "--assume-prior",
        action="store_true",
        help="drive.prior=once: ignore the shards' drive_cand_prior_* and assume the body prior on every body window",
    )
    ap.add_argument(
        "--joint",
        choices=("none", "final", "progress"),
        default=None,
        help="drive.joint: segments (and prefixes) by a joint fit of the windows, read again from --data with the "
        "run's config (RUN/.hydra/config.yaml)",
    )
    args = ap.parse_args(argv)
    config = yaml.safe_load((REPO / "configs" / "estimate.yaml").read_text())
    settings = dict(config["drive"])
    for item in args.set:
        key, value = item.split("=", 1)
        settings[key] = yaml.safe_load(value)
    columns = load_columns(Path(args.run))
    order = torch.argsort(columns["index"])
    columns = {k: v[order] for k, v in columns.items()}
    index = columns["index"].numpy()
    if args.assume_prior:
        columns.pop("drive_cand_prior_mean", None), columns.pop("drive_cand_prior_precision", None)
    if args.model_cov:
        if "drive_cov" in columns:  # early shards: the chosen candidate's model-based covariance only
            rows = torch.arange(len(index))
            columns["drive_cand_model_cov"] = columns["drive_cand_cov"].clone()
            columns["drive_cand_model_cov"][rows, columns["drive_model"]] = columns["drive_cov"]
        columns["drive_cand_cov"] = columns["drive_cand_model_cov"]
    with h5py.File(args.data, "r") as handle:
        group = handle[args.split]
        profile_id = np.asarray(group["profile_id"][()])[index]
        t_start = np.asarray(group["t_start"][()])[index]
        window_s = int(group["accel"].shape[1]) * float(handle.attrs["h"])
        names = json.loads(handle.attrs["recordings"]) if "recordings" in handle.attrs else []
    plan = DrivePlan(
        statuses=tuple(settings["statuses"]),
        weights=str(settings["weights"]),
        scale=str(settings["scale"]),
        alpha=float(settings["alpha"]),
        min_windows=int(settings["min_windows"]),
        outlier_alpha=float(settings["outlier_alpha"]),
        neighbours=int(settings["neighbours"]),
        plots=0,
        per_window=tuple(settings.get("per_window") or ()),
        profile_id=profile_id,
        t_start=t_start,
        names=tuple(names),
        window_s=window_s,
        joint=str(args.joint or settings.get("joint", DrivePlan.joint)),
        split=str(settings.get("split", DrivePlan.split)),
        space=str(settings.get("space", DrivePlan.space)),
        prior=str(settings.get("prior", DrivePlan.prior)),
        prior_from=str(settings.get("prior_from", DrivePlan.prior_from)),
    )
    n_models = columns["drive_cand_logz"].shape[1]
    names_m = list(NAMES[:n_models]) if n_models > 1 else ["rigid"]
    rigid_prior = float(config["occupant"]["rigid_prior"])
    bodies = [n for n in names_m if "+" not in n and n != "rigid"]
    log_prior = {"rigid": float(np.log(rigid_prior))} if bodies else {"rigid": 0.0}
    log_prior.update({b: float(np.log((1 - rigid_prior) / len(bodies))) for b in bodies})
    if args.prior_per_window:
        log_prior = None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("drives.csv", "drive_progress.csv"):
        (out / stale).unlink(missing_ok=True)
    cfg = type("Cfg", (), {"K3": args.K3, "plots": False, "tensorboard": False})()
    params = ("p1", "p2", "r1", "k1", "c1", "r2", "k2", "c2", "tau")[: columns["drive_cand_theta"].shape[2]]
    joint = None
    if plan.joint != "none":
        joint = _joint(Path(args.run), args.data, args.split, names_m, plan.per_window)
    summary = aggregate_drives(cfg, {}, plan, columns, out, names_m, params, log_prior, joint=joint)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
