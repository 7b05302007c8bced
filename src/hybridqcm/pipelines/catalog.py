"""The `qcm-pipeline` pipelines as data: the stages of demo, noise and reproduce, in order.

Each list is built from a table (one row a stage, or a stage per noise level) by the builders of
stage.py; `PIPELINES` names them. The runner (runner.py) runs a list and records the manifest
(reports/manifest.py) that `qcm-results` reads.
"""

from __future__ import annotations

import os

from hybridqcm.pipelines.stage import Stage, checkpoint, estimate_stage, evaluate_stage, train_stage

# The demo's networks (cnn / unet), each trained by the stage of that name.
_DEMO_TRAINED = {"cnn": "exp2_physics", "unet": "exp9_unet"}
# The demo's estimation runs: stage (= experiment), minutes, source table, thesis experiment, setting,
# networks (of _DEMO_TRAINED), extra overrides. exp10_hybrid: n_steps=100 is the source's N, beside its table
# (the experiment's default is max). occupant_roadfree: our generator's occupants are rigid and its channels
# share one clock, so the rigid model alone (the default fits persons too, and takes ~10x longer;
# docs/design/persons.md).
_DEMO_ESTIMATES = (
    ("exp5_random_init", 0.5, "5.11", "exp5", "GN full observation random init (exact model, x0 estimated)", "", ""),
    (
        "exp10_hybrid",
        1.5,
        "5.15",
        "exp10",
        "hybrid GN U-Net completion CNN init (exact model, x0 estimated)",
        "cnn unet",
        "n_steps=100",
    ),
    (
        "occupant_roadfree",
        0.5,
        None,
        "occupant",
        "occupant mass from the seat accelerometer pair, no road",
        "cnn",
        "init.cnn=true occupant.models=[rigid] delay=null",
    ),
)


def _networks(names: str, trained: dict[str, str]) -> dict[str, str]:
    """``"cnn unet"`` -> the training stages of those networks."""
    return {network: trained[network] for network in names.split()}


def demo_stages(
    root: str = "outputs/demo", dataset: str = "data/demo.h5", preset: str = "small", train_time: str = "00:00:04:00"
) -> list[Stage]:
    """Small end to end run on real-like recordings: continuous-time physics, windows cut mid-drive
    (SPEC § 9); train the physics CNN and the U-Net briefly on that physics; GN with the exact model
    and the initial state estimated (exps 5 and 10), and the occupant mass without the road.

    train_time bounds each training run (Lightning's DD:HH:MM:SS). The Euler-world tables of the
    source study are `reproduce`'s."""
    limit = [f"trainer.max_time={train_time}"]
    simulate = [f"preset={preset}", f"output={dataset}", "physics=continuous"]
    cnn_setting = "physics-residual CNN clean (continuous, mid-drive)"
    unet_setting = "U-Net completion (continuous, mid-drive)"
    stages = [
        Stage("simulate", "qcm-simulate", simulate, f"{root}/simulate", [os.path.abspath(dataset)], 0.5),
        train_stage("exp2_physics", "exp2_physics_continuous", dataset, root, 4.5, "5.2", "exp2", cnn_setting, limit),
        train_stage("exp9_unet", "exp9_unet_continuous", dataset, root, 4.5, None, "exp9", unet_setting, limit),
    ]
    for name, minutes, table, thesis, setting, networks, extra in _DEMO_ESTIMATES:
        used = _networks(networks, _DEMO_TRAINED)
        stages.append(estimate_stage(name, name, dataset, root, minutes, table, thesis, setting, used, extra.split()))
    return stages


# reproduce's networks, each trained by its stage train_<name> on freshly simulated samples
_REPRODUCE_NETWORKS = ("exp1_labelled", "exp2_physics", "exp4_denoiser", "exp9_unet")
_TRAINED = {"cnn": "train_exp2_physics", "unet": "train_exp9_unet", "cae": "train_exp4_denoiser"}
# Each network tested on the reference test split: stage (= experiment), noise, source table, setting, done when.
_CLEAN_TESTS = (
    ("exp1_labelled", 0.0, "5.1", "labelled CNN clean", None),
    ("exp2_physics", 0.0, "5.2", "physics-residual CNN clean", None),
    ("exp4_denoiser", 0.1, None, "CAE denoiser at noise 0.1, reference test split", ("mse_summary.csv",)),
    ("exp9_unet", 0.0, None, "U-Net completion, reference test split", ("mse_summary.csv",)),
)
# The CNNs under sensor noise: stage prefix, noise, thesis experiment, setting, through the CAE; per CNN,
# its label and the source tables of those four settings in order.
_NOISY_TESTS = (
    ("exp3a", 0.01, "exp3a", "noise 0.01", False),
    ("exp3b", 0.05, "exp3b", "noise 0.05", False),
    ("exp4_raw", 0.1, "exp4", "noise 0.1 raw", False),
    ("exp4_cae", 0.1, "exp4", "noise 0.1 after CAE", True),
)
_NOISY_TABLES = {
    "exp1_labelled": ("labelled CNN", ("5.3", "5.5", "5.7", "5.8")),
    "exp2_physics": ("physics-residual CNN", ("5.4", "5.6", "5.9", "5.10")),
}
# Estimation: stage (= experiment), minutes, source table, setting, networks (of _TRAINED), extra overrides.
_ESTIMATES = (
    ("exp5_random_init", 1, "5.11", "GN full observation random init", "", ""),
    ("exp6_cnn_init", 1, "5.12", "GN full observation CNN init of p1 p2", "cnn", ""),
    ("exp7_known_p3p5", 1, "5.13", "GN full observation p3 p5 known CNN init", "cnn", ""),
    ("exp8_occupant_only", 2, "5.14", "GN occupant only p3 p5 known CNN init", "cnn", ""),
    ("exp10_hybrid", 1, "5.15", "hybrid GN U-Net completion CNN init", "cnn unet", "n_steps=100"),
)
# Estimation under sensor noise, at each of _SIGMAS: stage prefix, experiment, minutes, setting, networks, extra.
_SIGMAS = (0.01, 0.05, 0.1)
_NOISY_ESTIMATES = (
    ("exp5", "exp5_random_init", 1, "GN alone", "", ""),
    ("exp8", "exp8_occupant_only", 2, "GN a3 only + CNN init", "cnn", ""),
    ("exp10", "exp10_hybrid", 1, "hybrid", "cnn unet", "n_steps=100"),
    ("exp10_cae", "exp10_hybrid", 1, "hybrid with CAE denoiser", "cnn unet cae", "n_steps=100"),
)


def _thesis(experiment: str) -> str:
    return experiment.split("_")[0]  # exp10_hybrid -> exp10


def reproduce_stages(root: str = "outputs/reproduce", dataset: str = "data/reference.h5") -> list[Stage]:
    """The reference protocol (51 000 samples): every experiment, noise sweeps, CPU-scale training recipes."""
    simulate = [f"output={dataset}", "physics=euler"]
    stages = [Stage("simulate", "qcm-simulate", simulate, f"{root}/simulate", [os.path.abspath(dataset)], 1.5)]
    # CPU recipes train on freshly simulated samples (the dataset file plays no part in training), then
    # every checkpoint is tested on the reference test split by its own stage.
    for name in _REPRODUCE_NETWORKS:
        trained, done_when = f"train_{name}", ["checkpoints/last.ckpt", "test_metrics.json"]
        overrides, setting = [f"experiment={name}"], f"{name}: training"
        stages.append(
            Stage(trained, "qcm-train", overrides, f"{root}/{trained}", done_when, 10, None, _thesis(name), setting)
        )
    for name, sigma, table, setting, done in _CLEAN_TESTS:
        trained = f"train_{name}"
        stages.append(
            evaluate_stage(name, name, dataset, root, trained, sigma, table, _thesis(name), setting, done_when=done)
        )
    for cnn, (label, tables) in _NOISY_TABLES.items():
        for (prefix, sigma, thesis, setting, denoised), table in zip(_NOISY_TESTS, tables, strict=True):
            denoiser = _TRAINED["cae"] if denoised else None
            test = (cnn, dataset, root, f"train_{cnn}", sigma, table, thesis, f"{label} {setting}", denoiser)
            stages.append(evaluate_stage(f"{prefix}_{cnn}", *test))
    for name, minutes, table, setting, networks, extra in _ESTIMATES:
        estimate = (name, dataset, root, minutes, table, _thesis(name), setting, _networks(networks, _TRAINED))
        stages.append(estimate_stage(name, *estimate, extra.split()))
    for sigma in _SIGMAS:
        for prefix, experiment, minutes, setting, networks, extra in _NOISY_ESTIMATES:
            setting, used = f"{setting}, noise {sigma}", _networks(networks, _TRAINED)
            estimate = (experiment, dataset, root, minutes, None, _thesis(experiment), setting, used)
            stages.append(estimate_stage(f"{prefix}_noise{sigma}", *estimate, [f"noise_sigma={sigma}", *extra.split()]))
    return stages


NOISE_LEVELS = (0.0, 0.01, 0.05, 0.1)  # additive sensor noise, fraction of each channel's RMS
_NOISE_SETTINGS = {
    "exp10_noise": "road-based exp 10 (a3 only, road known)",
    "cnn_noise": "the demo's CNN alone (a3, a2 -> p1, p2)",
    "occupant_noise": "road-free seat model (a3, a2)",
}


def noise_stages(
    root: str = "outputs/noise", dataset: str = "data/demo.h5", networks: str = "outputs/demo", samples: int = 1200
) -> list[Stage]:
    """The occupant's mass with and without the road, at additive accelerometer noise 0, 1, 5, 10 %
    of each channel's RMS on continuous mid-drive recordings (issue 12's table): road-based exp 10
    (a3 only, road and p_u known, the demo's U-Net and CNN) beside the road-free seat model (a3 and
    a2, no road), both on the longest window the recordings allow (N = 500 of 512 stored samples);
    and the demo's CNN alone on the whole test split at each level (issue 10's table).
    Uses the demo's dataset and networks (run `make demo` first); ``samples`` bounds exp 10 (about 0.3 s
    per recording under noise on two processes). It is the whole test split (1 200), where a coverage is
    known to 0.6 %: subsets of 400 differed by up to 6 points (docs/measurements/real_recordings.md). The
    road-free model reads every test recording too."""
    cnn_path, unet_path = checkpoint(networks, "exp2_physics"), checkpoint(networks, "exp9_unet")
    estimated, tested = ["estimates.csv", "summary.json"], ["error_distribution.csv", "test_metrics.json"]
    stages = []
    for sigma in NOISE_LEVELS:
        sensor = ["sensor=additive", f"sensor.sigma={sigma:g}"]
        exp10 = ["experiment=exp10_hybrid", f"data.path={dataset}", f"n_samples={samples}", "n_steps=max"]
        exp10 += [f"cnn_ckpt={cnn_path}", f"unet_ckpt={unet_path}", *sensor]
        exp10 += ["trainer=ddp", "trainer.devices=2", f"batch_size={-(-samples // 6)}"]
        alone = ["experiment=exp2_physics_continuous", f"data.path={dataset}", "train=false", f"ckpt_path={cnn_path}"]
        roadfree = ["experiment=occupant_roadfree", f"data.path={dataset}", "occupant.models=[rigid]", "delay=null"]
        rows = (  # stage, app, overrides, done when, minutes, thesis experiment, files made outside this pipeline
            ("exp10_noise", "qcm-estimate", exp10, estimated, 7.0, "exp10", [cnn_path, unet_path, dataset]),
            ("cnn_noise", "qcm-train", alone + sensor, tested, 0.3, "exp2", [cnn_path, dataset]),
            ("occupant_noise", "qcm-estimate", roadfree + sensor, estimated, 1.0, "occupant", [dataset]),
        )
        for name, app, overrides, done_when, minutes, thesis, requires in rows:
            run_dir, setting = f"{root}/{name}{sigma:g}", f"{_NOISE_SETTINGS[name]}, additive noise {sigma:.0%}"
            stage = Stage(f"{name}{sigma:g}", app, overrides, run_dir, list(done_when), minutes, None, thesis, setting)
            stage.noise, stage.requires = sigma, requires
            stages.append(stage)
    return stages


PIPELINES = {"demo": demo_stages, "reproduce": reproduce_stages, "noise": noise_stages}


def stage_order() -> dict[str, list[str]]:
    """Each pipeline's stage names in order (of its default root and dataset), for the results page."""
    return {name: [stage.name for stage in build()] for name, build in PIPELINES.items()}
