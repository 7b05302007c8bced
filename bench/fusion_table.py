"""Issue 13 table: occupant mass m3 from the CNN alone, Gauss-Newton alone (CNN start) and the fused
MAP estimate (CNN mean and variance as the prior of the last GN stage), per sensor noise level.

    PYTHONPATH=src .venv/bin/python bench/fusion_table.py --cnn CKPT --data data/cont_small.h5 \
        [--experiment occupant_roadfree] [--unet CKPT] [--samples 300] [--sigmas 0 0.01 0.05 0.1] \
        [--out outputs/fusion] [--extra n_steps=496 ...] [--correlation]

GN alone and fused are `qcm-estimate` runs (the commands are printed); their m3 and 95 % interval
come from estimates.csv. The CNN alone is read from the same inputs as the runs (the app's own
validate/build_inputs, same sensor noise per sample; for exp 10 the U-Net-completed a2): median
K3 / exp(log p2) and the image of log p2 ± 1.96 s. Metrics: estimation.fusion.interval_summary.
Prints one markdown table. With --correlation also, per level, the correlation of the CNN's and GN's
relative m3 errors and the best fixed-weight combination w CNN + (1 - w) GN with w fitted on the truth
(an oracle: the most any linear fusion of the two could reach).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch


def _estimate_cmd(args, sigma: float, mode: str, run_dir: Path) -> list[str]:
    cmd = [
        str(Path(sys.executable).parent / "qcm-estimate"),
        f"experiment={args.experiment}",
        f"data.path={args.data}",
        f"n_samples={args.samples}",
        f"cnn_ckpt={args.cnn}",
        "init.cnn=true",
        "sensor=additive",
        f"sensor.sigma={sigma}",
        "plots=false",
        "tensorboard=false",
        "progress=false",
        "overwrite=true",
        f"hydra.run.dir={run_dir}",
        *args.extra,
    ]
    if args.unet:
        cmd.append(f"unet_ckpt={args.unet}")
    if mode == "fused":
        cmd.append("init.cnn_prior=network")
    return cmd


def _from_run(run_dir: Path) -> dict[str, torch.Tensor]:
    with open(run_dir / "estimates.csv") as handle:
        rows = list(csv.DictReader(handle))
    get = lambda key: torch.tensor([float(r[key]) for r in rows], dtype=torch.float64)  # noqa: E731
    summary = json.loads((run_dir / "summary.json").read_text())
    return {"m3": get("m3"), "low": get("m3_low"), "high": get("m3_high"), "seconds": summary["seconds_solve"]}


def _cnn_alone(args, sigma: float) -> dict[str, torch.Tensor]:
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR
    from hybridqcm.estimation.blocks import build_inputs
    from hybridqcm.estimation.front import HybridEstimator
    from hybridqcm.estimation.plan import validate

    overrides = [o for o in _estimate_cmd(args, sigma, "fused", Path("."))[1:] if not o.startswith("hydra.")]
    with initialize_config_dir(str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("estimate", overrides=overrides)
    plan = validate(cfg)
    inputs = build_inputs(cfg, plan)
    module = HybridEstimator(
        cnn_ckpt=args.cnn,
        unet_ckpt=args.unet,
        observed=plan["observed"],
        n_steps=plan["n_steps"],
        h=plan["h"],
        pu_known=bool(cfg.pu_known),
        base_excitation=plan["base_excitation"],
        input_margin=plan["input_margin"],
        cnn_prior="network",
    )
    t0 = time.perf_counter()
    prepared = module.prepare({k: v for k, v in inputs.items() if k != "true"})
    seconds = time.perf_counter() - t0
    p2, log_std = prepared["prior_p12"][:, 1], prepared["prior_p12_std"][:, 1] / prepared["prior_p12"][:, 1]
    K3 = float(cfg.K3)
    return {
        "m3": K3 / p2,
        "low": K3 / (p2 * torch.exp(1.96 * log_std)),
        "high": K3 / (p2 * torch.exp(-1.96 * log_std)),
        "true": K3 / inputs["true"][:, 1],
        "seconds": seconds,
    }


def main() -> None:
    from hybridqcm.estimation.fusion import interval_summary

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cnn", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--experiment", default="occupant_roadfree")
    parser.add_argument("--unet", default=None)
    parser.add_argument("--samples", type=int, default=300)
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.0, 0.01, 0.05, 0.1])
    parser.add_argument("--out", default="outputs/fusion")
    parser.add_argument("--extra", nargs="*", default=[])
    parser.add_argument("--correlation", action="store_true", help="print the oracle fusion of CNN and GN")
    args = parser.parse_args()
    oracle = []

    lines = [
        f"{args.experiment}, {args.samples} samples of {args.data}, additive noise per channel",
        "",
        "| noise | method | m3 mean err | m3 p95 err | 95 % coverage | mean width | median width | s / 1000 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for sigma in args.sigmas:
        cnn = _cnn_alone(args, sigma)
        truth = cnn["true"]
        results = {"CNN alone": cnn}
        for mode in ("gn", "fused"):
            run_dir = Path(args.out) / f"{args.experiment}_{mode}_{sigma:g}"
            cmd = _estimate_cmd(args, sigma, mode, run_dir)
            print(" ".join(cmd[1:]), flush=True)
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            results["GN alone" if mode == "gn" else "fused"] = _from_run(run_dir)
        for name, r in results.items():
            s = interval_summary(r["m3"], r["low"], r["high"], truth)
            lines.append(
                f"| {100 * sigma:g} % | {name} | {100 * s['mean_rel_err']:.3g} % | {100 * s['p95_rel_err']:.3g} % | "
                f"{100 * s['coverage_95']:.1f} % | {100 * s['mean_rel_width']:.3g} % | "
                f"{100 * s['median_rel_width']:.3g} % | {1000 * r['seconds'] / args.samples:.1f} |"
            )
        print("\n".join(lines[-3:]), flush=True)
        if args.correlation:
            oracle.append(_oracle(sigma, results["CNN alone"]["m3"], results["GN alone"]["m3"], truth))
    print("\n".join(lines + oracle))


def _oracle(sigma: float, cnn: torch.Tensor, gn: torch.Tensor, truth: torch.Tensor) -> str:
    """Correlation of the two relative m3 errors and the best fixed-weight combination of them."""
    ec, eg = (cnn / truth - 1).numpy(), (gn / truth - 1).numpy()
    ok = np.isfinite(ec) & np.isfinite(eg)
    ec, eg = ec[ok], eg[ok]
    rho, sc, sg = np.corrcoef(ec, eg)[0, 1], ec.std(), eg.std()
    w = (sg**2 - rho * sc * sg) / (sc**2 + sg**2 - 2 * rho * sc * sg)  # minimum-variance weight on the CNN
    best = np.abs(w * ec + (1 - w) * eg).mean()
    return (
        f"{100 * sigma:g} %: error std CNN {100 * sc:.3g} % / GN {100 * sg:.3g} %, correlation {rho:.2f}; "
        f"oracle fusion (w = {w:.2f} on the CNN) mean {100 * best:.3g} %"
    )


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
