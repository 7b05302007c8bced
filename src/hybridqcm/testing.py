"""Small synthetic problems and tiny trained networks for tests, benchmarks and demos.

Samples come from the project's own generator (thesis prior with rejection, ISO 8608 road,
semi-explicit Euler), so estimates can be checked against known truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor


def synthetic_samples(
    n: int,
    n_steps: int = 100,
    seed: int = 0,
    h: float = 0.01,
    speed_mps: float = 30 / 3.6,
    road_classes: tuple[int, ...] = (0, 1, 2),
) -> dict[str, Tensor]:
    """accel [n, n_steps, 3], vel, disp, road [n, n_steps], params [n, 10] (float64, noise-free)."""
    from hybridqcm.physics import RoadProfile, build_prior, simulate

    generator = torch.Generator().manual_seed(seed)
    params = build_prior("thesis", h=h).sample(n, generator).params
    classes = torch.tensor(road_classes)[torch.randint(0, len(road_classes), (n,), generator=generator)]
    road = RoadProfile().sample(classes, n_steps, h, speed_mps, generator)
    trajectory = simulate(params, road, h)
    return {
        "accel": trajectory.accel,
        "vel": trajectory.vel,
        "disp": trajectory.disp,
        "road": road,
        "params": params,
        "road_class": classes,
    }


def seat_recordings(
    b: int, T: int, margin: int = 8, sigma: float = 0.0, seed: int = 0, h: float = 0.01, substeps: int = 16
) -> tuple[Tensor, Tensor, Tensor]:
    """Seat base-excitation recordings with known truth: (p [b, 2], a2 [b, T + 2 margin, 1], a3 [b, T, 1]).

    a2 is a sum of 12 random sinusoids (0.5-14.5 Hz), a3 the exact seat response (spline hold at
    ``substeps``) from rest at the first input sample, cut to the T samples after ``margin``; p1 in
    [6, 14], p2 in [900, 2400]; white noise of ``sigma`` x each channel's RMS on both (float64)."""
    import math

    from hybridqcm.estimation.exact import exact_outputs
    from hybridqcm.physics.linear_models import SeatBaseExcitation

    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T + 2 * margin, dtype=torch.float64)[None, :] * h
    freq = torch.rand(b, 12, generator=g, dtype=torch.float64) * 14 + 0.5
    phase = torch.rand(b, 12, generator=g, dtype=torch.float64) * 2 * math.pi
    a2 = torch.sin(2 * math.pi * freq[:, :, None] * t[:, None] + phase[:, :, None]).sum(1)[..., None]
    p = torch.stack(
        [
            torch.rand(b, generator=g, dtype=torch.float64) * 8 + 6,
            torch.rand(b, generator=g, dtype=torch.float64) * 1500 + 900,
        ],
        1,
    )
    a3 = exact_outputs(SeatBaseExcitation(), p, None, a2, h, substeps=substeps)
    rms2, rms3 = a2.square().mean(1, keepdim=True).sqrt(), a3.square().mean(1, keepdim=True).sqrt()
    a2 = a2 + sigma * rms2 * torch.randn(a2.shape, generator=g, dtype=torch.float64)
    a3 = a3 + sigma * rms3 * torch.randn(a3.shape, generator=g, dtype=torch.float64)
    return p, a2, a3[:, margin : margin + T]


def write_dataset(
    path: str | Path, samples: dict[str, Tensor], split: str = "test", with_params: bool = True, h: float = 0.01
) -> Path:
    """Write ``samples`` as a SPEC §5 file (float32 signals); optionally without /params."""
    from hybridqcm.data.dataset_writer import DatasetWriter

    n, n_steps = samples["road"].shape
    keys = ["accel", "vel", "disp", "road"] + (["params"] if with_params else [])
    with DatasetWriter(
        path,
        attrs={
            "h": h,
            "n_steps": n_steps,
            "speed_mps": 30 / 3.6,
            "prior": "thesis",
            "seed": 0,
            "created_by": "hybridqcm.testing",
            "physics": "euler",
            "warmup_s": [0.0, 0.0],
        },
        overwrite=True,
        compression=None,
    ) as writer:
        writer.create_split(split, n, n_steps, keys=keys)
        writer.write(
            split,
            0,
            **{k: np.asarray(samples[k].numpy(), dtype=np.float64 if k == "params" else np.float32) for k in keys},
        )
    return Path(path)


class _Batches(torch.utils.data.Dataset):
    def __init__(self, tensors: dict[str, Tensor]):
        self.tensors = tensors
        self.n = next(iter(tensors.values())).shape[0]

    def __len__(self):
        return self.n

    def __getitems__(self, indices):
        idx = torch.as_tensor(indices)
        return {k: v[idx] for k, v in self.tensors.items()}


def _fit(module, tensors: dict[str, Tensor], path: Path, steps: int) -> Path:
    import lightning

    module.fit_normalisation({k: v for k, v in tensors.items()})
    loader = torch.utils.data.DataLoader(_Batches(tensors), batch_size=16, shuffle=True, collate_fn=lambda b: b)
    trainer = lightning.Trainer(
        accelerator="cpu",
        devices=1,
        max_steps=steps,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
    )
    trainer.fit(module, train_dataloaders=loader)
    path.parent.mkdir(parents=True, exist_ok=True)
    trainer.save_checkpoint(str(path))
    return path


def train_tiny_checkpoints(
    directory: str | Path, samples: dict[str, Tensor], steps: int = 3, window: int = 128
) -> dict[str, Path]:
    """Train tiny CNN / U-Net / CAE for a few steps on ``samples`` (n_steps >= window) and save them.

    Their accuracy is irrelevant (a few steps); what matters is that they are real checkpoints of
    the project's LightningModules, loaded the way the app loads them.
    """
    from hybridqcm.models import CompletionUNet, DenoisingAutoencoder, PhysicsResidualEstimator

    directory = Path(directory)
    accel = samples["accel"].float()
    a3, a2, a1 = accel[..., 0], accel[..., 1], accel[..., 2]
    pu_u = ((samples["params"][:, 9] - samples["params"][:, 8])[:, None] * samples["road"]).float()
    index = torch.arange(accel.shape[0])
    x_cnn = torch.stack([a3, a2], 1)[..., :window]
    vel, disp = samples["vel"].double(), samples["disp"].double()
    # PhysicsResidualEstimator aux channels: (a3, v3, v2, q3, q2)
    aux = torch.stack([a3.double(), vel[..., 0], vel[..., 1], disp[..., 0], disp[..., 1]], 1)[..., :window]
    torch.manual_seed(0)
    cnn = PhysicsResidualEstimator(
        net={"channels": [4, 4], "kernels": [16, 8], "strides": [4, 2], "hidden": [8, 4]}, window=window
    )
    paths = {
        "cnn": _fit(
            cnn,
            {"x": x_cnn, "y": samples["params"][:, :2].double(), "aux": aux, "index": index},
            directory / "cnn.ckpt",
            steps,
        )
    }
    unet = CompletionUNet(net={"filters": [2, 4], "kernel_size": 5}, window=window)
    paths["unet"] = _fit(
        unet,
        {"x": torch.stack([a3, pu_u], 1)[..., :window], "y": torch.stack([a2, a1], 1)[..., :window], "index": index},
        directory / "unet.ckpt",
        steps,
    )
    cae = DenoisingAutoencoder(net={"channels": [4, 4], "kernel_size": 9}, window=window)
    paths["cae"] = _fit(cae, {"x": x_cnn, "y": x_cnn, "index": index}, directory / "cae.ckpt", steps)
    return paths
