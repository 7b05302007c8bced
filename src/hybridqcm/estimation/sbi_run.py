"""Train the SBI peer (estimation/sbi_peer.py) on a dataset and evaluate it beside the hybrid (qcm-sbi's work).

train_and_save: fits the posterior on data.train_split (clean recordings; additive noise of a
per-sample level is drawn every epoch), writes RUN/posterior.pt (tensors and plain data only) and
training.csv. evaluate: on the first evaluate.n_samples recordings of data.test_split, at every
noise level of evaluate.sigmas (sensor=none) or at the given sensor's level, writes sbi_metrics.csv
(columns named as qcm-estimate's summary), and the checks: SBC ranks and TARP (sbc.csv,
checks.json, plots/sbc_ranks.png, plots/tarp.png). `run` checks the inputs (one ConfigError line,
before any work) and does either, per configs/sbi.yaml.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from hybridqcm import config, runfolder
from hybridqcm.atomic import atomic_write_csv, atomic_write_text
from hybridqcm.console import print_table
from hybridqcm.errors import ConfigError

MODES = ("train", "evaluate")
ARTEFACTS = ("posterior.pt", "training.csv", "sbi_metrics.csv", "sbc.csv", "checks.json", "plots", runfolder.MARKER)
METRIC_COLUMNS = (
    "method",
    "sensor_sigma",
    "n",
    "m3_mean_rel_err",
    "m3_p95_rel_err",
    "m3_within_1pct",
    "m3_coverage_95",
    "m3_interval_median_rel_width",
    "p1_mean_rel_err",
    "p1_coverage_95",
    "p1_interval_median_rel_width",
    "p2_mean_rel_err",
    "p2_coverage_95",
    "p2_interval_median_rel_width",
    "seconds_per_1000",
    "posterior_samples",
)


def _read(path, split: str, n: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(accel [M, T, 3] float32, params [M, 10] float64) of a split (first n rows)."""
    from hybridqcm.data.hdf5 import read_split

    arrays = read_split(path, split, keys=("accel", "params"), index=None if n is None else slice(0, int(n)))
    return torch.from_numpy(np.asarray(arrays["accel"], dtype=np.float32)), torch.from_numpy(
        np.asarray(arrays["params"], dtype=np.float64)
    )


def train_and_save(cfg, run_dir: Path):
    """Fit the peer per cfg.peer / cfg.train on data.train_split; writes posterior.pt and training.csv."""
    from omegaconf import OmegaConf

    from hybridqcm.estimation.sbi_peer import PeerSettings, SBIPeer
    from hybridqcm.estimation.sbi_training import TrainSettings, train_peer

    settings = PeerSettings.from_mapping(OmegaConf.to_container(cfg.peer, resolve=True))
    train_cfg = OmegaConf.to_container(cfg.train, resolve=True)
    unknown = sorted(set(train_cfg) - set(TrainSettings.__dataclass_fields__))
    if unknown:
        raise ConfigError(f"train: unknown setting(s) {unknown}; known: {sorted(TrainSettings.__dataclass_fields__)}")
    recipe = TrainSettings(**train_cfg).validate()
    accel, params = _read(cfg.data.path, cfg.data.train_split)
    peer = SBIPeer.fit_spaces(settings, accel, params)
    print(
        f"training the SBI peer on {accel.shape[0]} recordings of {cfg.data.path}:{cfg.data.train_split}; "
        f"posterior over {list(settings.params)} (flow dimension {peer.settings.latent_dim}), "
        f"budget {recipe.max_seconds} s",
        flush=True,
    )
    result = train_peer(peer, accel, params, recipe, log=lambda line: print(line, flush=True))
    peer.save(run_dir / "posterior.pt")
    atomic_write_csv(
        run_dir / "training.csv",
        ["epoch", "train_loss", "val_loss", "seconds"],
        [[h["epoch"], repr(h["train_loss"]), repr(h["val_loss"]), repr(h["seconds"])] for h in result["history"]],
    )
    print(
        f"best epoch {result['best_epoch']} (validation NLL {result['best_val_loss']:.4f}), "
        f"{result['seconds']:.0f} s -> {run_dir / 'posterior.pt'}",
        flush=True,
    )
    return peer, result


def evaluate(cfg, run_dir: Path, peer) -> list[dict]:
    """The peer on data.test_split at each noise level: sbi_metrics.csv (one row per level) and, with
    evaluate.checks, the SBC / TARP checks."""
    from hybridqcm.data.sensor import SensorModel, build_sensor
    from hybridqcm.estimation.sbi_evaluation import evaluation_row, posterior_summary, rank_statistics
    from hybridqcm.estimation.sbi_training import log_uniform, noisy

    ev = cfg.evaluate
    K3 = float(cfg.K3)
    sensor = build_sensor(cfg.get("sensor"))
    if sensor.active and (sensor.kind != "additive" or not sensor.relative):
        raise ConfigError(
            f"sensor.kind={sensor.kind!r}, relative={sensor.relative}: qcm-sbi evaluates additive noise relative to the channel RMS"
        )
    n = int(ev.n_samples)
    accel, true = _read(cfg.data.path, cfg.data.test_split, n)
    if sensor.active:
        sensors = [sensor]
    else:
        sensors = [
            SensorModel(kind="additive", sigma=float(s), seed=int(ev.seed)).validate() if float(s) > 0 else None
            for s in ev.sigmas
        ]
    names = list(peer.settings.params)
    rows = []
    for s in sensors:
        sigma = float(s._sigma[0]) if s is not None else 0.0
        # The same per-sample noise as qcm-estimate (seed, salt 0, sample index): the rows compare on identical inputs.
        measured = s.apply(accel.double(), torch.arange(accel.shape[0])).float() if s is not None else accel
        x = peer.inputs_of(measured)
        t0 = time.perf_counter()
        summary = posterior_summary(peer, x, n_samples=int(ev.posterior_samples), K3=K3)
        seconds = time.perf_counter() - t0
        row = {"method": "sbi_peer", "sensor_sigma": sigma, **evaluation_row(summary, true, names, K3)}
        row["seconds_per_1000"] = seconds * 1000.0 / x.shape[0]
        row["posterior_samples"] = int(ev.posterior_samples)
        rows.append(row)
    atomic_write_csv(
        run_dir / "sbi_metrics.csv",
        METRIC_COLUMNS,
        [[r.get(c, "") if not isinstance(r.get(c), float) else repr(r[c]) for c in METRIC_COLUMNS] for r in rows],
    )
    print_table(
        f"SBI peer on {n} recordings of {cfg.data.path}:{cfg.data.test_split} (posterior median; 95 % central interval)",
        ["σ", "m3 mean", "m3 p95", "m3 cover", "m3 width", "p1 cover", "p2 cover", "s / 1000"],
        [
            [
                f"{r['sensor_sigma']:g}",
                f"{100 * r.get('m3_mean_rel_err', float('nan')):.3g} %",
                f"{100 * r.get('m3_p95_rel_err', float('nan')):.3g} %",
                f"{100 * r.get('m3_coverage_95', float('nan')):.1f} %",
                f"{100 * r.get('m3_interval_median_rel_width', float('nan')):.3g} %",
                f"{100 * r.get('p1_coverage_95', float('nan')):.1f} %",
                f"{100 * r.get('p2_coverage_95', float('nan')):.1f} %",
                f"{r['seconds_per_1000']:.2f}",
            ]
            for r in rows
        ],
    )
    if bool(ev.checks):
        _checks(cfg, run_dir, peer, names, log_uniform, noisy, rank_statistics)
    return rows


def _checks(cfg, run_dir: Path, peer, names, log_uniform, noisy, rank_statistics) -> dict:
    """SBC and TARP on held-out recordings with noise drawn from the training law (what the posterior claims)."""
    from hybridqcm.plots import close, plot_rank_histograms, plot_tarp_curve

    ev = cfg.evaluate
    accel, true = _read(cfg.data.path, cfg.data.test_split, int(ev.check_samples))
    generator = torch.Generator().manual_seed(int(ev.seed) + 1)
    low, high = float(cfg.train.noise_min), float(cfg.train.noise_max)
    x = noisy(peer.inputs_of(accel), log_uniform(accel.shape[0], low, high, generator), generator)
    torch.manual_seed(int(ev.seed))
    stats = rank_statistics(peer, x, peer.normalise(true), n_samples=int(ev.check_posterior_samples))
    ranks = stats["ranks"].numpy()
    atomic_write_csv(
        run_dir / "sbc.csv", ["index", *[f"rank_{n}" for n in names]], [[i, *map(int, r)] for i, r in enumerate(ranks)]
    )
    m = int(ev.check_posterior_samples)
    # The same fraction from the ranks: a truth with rank in [2.5 %, 97.5 %] of m lies in the central 95 % interval.
    inside = ((ranks >= 0.025 * m) & (ranks <= 0.975 * m)).mean(0)
    checks = {
        "n": int(ranks.shape[0]),
        "posterior_samples": m,
        "noise_law": f"additive, log-uniform [{low}, {high}] x channel RMS per sample",
        "sbc_ks_pvals": dict(zip(names, map(float, stats["ks_pvals"]))),
        "sbc_c2st_ranks": dict(zip(names, map(float, stats["c2st_ranks"]))),
        "sbc_c2st_dap": float(np.mean(np.asarray(stats["c2st_dap"], dtype=float))),
        "rank_coverage_95": dict(zip(names, map(float, inside))),
        "tarp_atc": stats["tarp_atc"],
        "tarp_ks_pval": stats["tarp_ks_pval"],
    }
    atomic_write_text(run_dir / "checks.json", json.dumps(checks, indent=2) + "\n")
    close(plot_rank_histograms(ranks, names, m, run_dir / "plots" / "sbc_ranks.png", title="SBC ranks (held out)"))
    close(plot_tarp_curve(stats["ecp"].numpy(), stats["alpha"].numpy(), run_dir / "plots" / "tarp.png", title="TARP"))
    print(
        f"SBC KS p-values {checks['sbc_ks_pvals']}, C2ST(DAP, prior) {checks['sbc_c2st_dap']:.3f}; "
        f"TARP ATC {checks['tarp_atc']:.4f} (KS p {checks['tarp_ks_pval']:.3f}) -> {run_dir}",
        flush=True,
    )
    return checks


def run(cfg) -> list[dict] | None:
    """qcm-sbi's run: cfg.mode train (then evaluate, with evaluate_after) or evaluate ckpt; returns the metric rows."""
    from hydra.core.hydra_config import HydraConfig

    from hybridqcm.estimation.sbi_peer import SBIPeer, import_sbi

    mode = str(cfg.mode)
    if mode not in MODES:
        raise ConfigError(f"mode={mode!r}: qcm-sbi runs {' | '.join(MODES)}")
    import_sbi()
    if not Path(str(cfg.data.path)).is_file():
        raise ConfigError(f"data.path={cfg.data.path}: file does not exist")
    if mode == "evaluate" and not cfg.ckpt:
        raise ConfigError("qcm-sbi evaluate needs ckpt=PATH (the posterior.pt written by qcm-sbi train)")
    run_dir = Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path(".")
    config.check_writable_dir(run_dir)
    runfolder.prepare_run_dir(run_dir, ARTEFACTS, bool(cfg.overwrite), inputs=[cfg.ckpt])
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    torch.manual_seed(int(cfg.train.seed))
    if mode == "train":
        peer, _ = train_and_save(cfg, run_dir)
        rows = evaluate(cfg, run_dir, peer) if bool(cfg.evaluate_after) else None
    else:
        peer = SBIPeer.load(cfg.ckpt, config_key="ckpt")
        rows = evaluate(cfg, run_dir, peer)
    runfolder.write_completion_marker(run_dir, "qcm-sbi", runfolder.task_overrides(), [cfg.data.path, cfg.ckpt])
    return rows
