"""One stage of a pipeline: a console-script call with its own run folder, and when it counts as done.

A stage is done when its outputs exist and, for the apps that write one (qcm-train, qcm-estimate),
the completion marker (written last, runfolder.py) names the same overrides, so the leftovers of a
killed or foreign run do not count. The builders make the three kinds of stage the pipelines list:
training a network, evaluating a checkpoint on a dataset (qcm-train train=false), estimating.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

from hybridqcm.runfolder import marker_matches

BIN = Path(sys.executable).parent
MARKED_APPS = ("qcm-train", "qcm-estimate")  # apps that write a completion marker (runfolder.py)
# qcm-estimate's checkpoint keys, in the order a stage passes them
NETWORK_KEYS = {"cnn": "cnn_ckpt", "unet": "unet_ckpt", "cae": "cae_ckpt"}


@dataclass
class Stage:
    name: str
    app: str  # qcm-simulate | qcm-train | qcm-estimate
    overrides: list[str]
    run_dir: str
    done_when: list[str]  # files (relative to run_dir, or absolute) that mark the stage finished
    minutes: float  # expected cost on 2 CPU cores, for the plan
    table: str | None = None  # thesis table id answered (e.g. "5.11"), or None
    experiment: str | None = None  # thesis experiment key (exp1 ... exp10)
    setting: str = ""
    needs: list[str] = field(default_factory=list)
    noise: float | None = None  # additive sensor noise (fraction of each channel's RMS) of a noise-sweep stage
    requires: list[str] = field(default_factory=list)  # files made outside this pipeline (another's checkpoints)

    def task_overrides(self) -> list[str]:
        """The overrides the app sees; a stage that is not done clears its folder's leftovers (overwrite=true)."""
        return [*self.overrides, "overwrite=true"] if self.app in MARKED_APPS else list(self.overrides)

    def command(self) -> list[str]:
        return [str(BIN / self.app), *self.task_overrides(), f"hydra.run.dir={self.run_dir}"]

    def is_done(self) -> bool:
        """Outputs present and, for train/estimate, the completion marker (written last) names these inputs."""
        files = all((Path(self.run_dir) / f if not os.path.isabs(f) else Path(f)).exists() for f in self.done_when)
        return files and (self.app not in MARKED_APPS or marker_matches(self.run_dir, self.task_overrides()))


def checkpoint(root: str, stage: str) -> str:
    """The last checkpoint of a training stage of the pipeline under ``root``."""
    return f"{root}/{stage}/checkpoints/last.ckpt"


def train_stage(name, experiment, dataset, root, minutes, table=None, thesis=None, setting="", extra=()) -> Stage:
    """qcm-train of ``experiment`` on ``dataset``; done when its last checkpoint and test metrics exist."""
    overrides = [f"experiment={experiment}", f"data.path={dataset}", *extra]
    done_when = ["checkpoints/last.ckpt", "test_metrics.json"]
    return Stage(name, "qcm-train", overrides, f"{root}/{name}", done_when, minutes, table, thesis, setting)


def evaluate_stage(
    name, experiment, dataset, root, checkpoint_stage, sigma, table, thesis, setting, denoiser_stage=None, done_when=()
) -> Stage:
    """qcm-train train=false: the checkpoint of ``checkpoint_stage`` tested on ``dataset`` at noise ``sigma``
    (after the CAE of ``denoiser_stage`` if given); done when ``done_when`` (error_distribution.csv) exists."""
    extra = ["train=false", f"ckpt_path={checkpoint(root, checkpoint_stage)}", f"data.noise_sigma={sigma}"]
    if denoiser_stage:
        extra.append(f"denoiser_ckpt={checkpoint(root, denoiser_stage)}")
    return Stage(
        name,
        "qcm-train",
        [f"experiment={experiment}", f"data.path={dataset}", *extra],
        f"{root}/{name}",
        list(done_when or ("error_distribution.csv",)),
        1.0,
        table,
        thesis,
        setting,
        needs=[checkpoint_stage] + ([denoiser_stage] if denoiser_stage else []),
    )


def estimate_stage(
    name, experiment, dataset, root, minutes, table=None, thesis=None, setting="", networks=None, extra=()
) -> Stage:
    """qcm-estimate of ``experiment`` on ``dataset``; ``networks`` maps cnn / unet / cae to the training
    stages whose checkpoints it uses (which it then needs). Done when estimates and error table exist."""
    networks = networks or {}
    if set(networks) - set(NETWORK_KEYS):
        raise ValueError(
            f"stage {name}: networks {sorted(set(networks) - set(NETWORK_KEYS))}; known {list(NETWORK_KEYS)}"
        )
    overrides = [f"experiment={experiment}", f"data.path={dataset}", *extra]
    needs = []
    for network, key in NETWORK_KEYS.items():
        stage = networks.get(network)
        if stage:
            overrides.append(f"{key}={checkpoint(root, stage)}")
            needs.append(stage)
    done_when = ["estimates.csv", "error_distribution.csv"]
    return Stage(name, "qcm-estimate", overrides, f"{root}/{name}", done_when, minutes, table, thesis, setting, needs)
