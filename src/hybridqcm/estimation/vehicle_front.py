"""The half car's and full car's GN problem per batch (qcm-estimate experiment=hcm_full_observation | ...).

Every acceleration of the vehicle is measured and every wheel's road input is known (the quarter
car's exp 5 for the larger vehicles): the model is physics/vehicle_model.VehicleModel, fitted by
its exact discretisation (estimation/response.ExactResponse) with the initial state estimated, so
no network completes or initialises anything. :class:`VehicleFront` only cuts each batch into the
problem GaussNewtonRefinement solves:

    batch   = {"accel" [b, T, n_dof], "inputs" [b, T, n_in] (road heights, and velocities where tyres
               are damped), "init" [b, P], "index" [b], optional "noise_std" [b, n_dof]}
    problem = {"targets" [b, N, n_dof] (the GN window), "road" [b, T', n_in] (the window with its input
               margins), "init", "index", "input_offset", optional "weights" = 1/noise_std}
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from lightning.pytorch import LightningModule
from torch import Tensor


class VehicleFront(LightningModule):
    """Batches of vehicle recordings -> GN problems (module docstring); no trainable part.

    ``equation_error``: (layout, param_names, known [P] bool, h, seats_only) — the start moved from the
    batch's init to the equation-error estimate of the GN window (estimation/vehicle_init.py; seats_only:
    the seats' quantities only); None: the init as given."""

    def __init__(self, n_steps: int, input_margin: Sequence[int] = (4, 8), equation_error: tuple | None = None) -> None:
        super().__init__()
        self.n_steps = int(n_steps)
        self.input_margin = tuple(int(m) for m in input_margin)
        if self.n_steps < 2 or len(self.input_margin) != 2 or min(self.input_margin) < 0:
            raise ValueError(f"VehicleFront: n_steps >= 2 and two margins >= 0, got {n_steps}, {list(input_margin)}")
        self.equation_error = equation_error

    @torch.no_grad()
    def prepare(self, batch: Mapping[str, Tensor]) -> dict:
        accel, inputs = batch["accel"].double(), batch["inputs"].double()
        before, after = self.input_margin
        if accel.shape[1] < before + self.n_steps:
            raise ValueError(f"the GN window needs {before + self.n_steps} samples, the batch has {accel.shape[1]}")
        stop = min(inputs.shape[1], before + self.n_steps + after)
        problem = {
            "targets": accel[:, before : before + self.n_steps],
            "road": inputs[:, :stop],
            "init": batch["init"].double(),
            "index": batch["index"],
            "input_offset": before,
        }
        if self.equation_error is not None:
            from .vehicle_init import equation_error_start

            layout, names, known, h, seats_only = self.equation_error
            window = inputs[:, before : before + self.n_steps]
            problem["init"] = equation_error_start(
                layout, names, problem["targets"], window, h, problem["init"], known, seats_only=seats_only
            )
        if batch.get("noise_std") is not None:  # a known sensor noise floor per channel
            problem["weights"] = 1.0 / batch["noise_std"].double()
        return problem

    def forward(self, batch: Mapping[str, Tensor]) -> dict:
        return self.prepare(batch)

    def predict_step(self, batch: Mapping[str, Tensor], batch_idx: int = 0) -> dict:
        return self.prepare(batch)


__all__ = ["VehicleFront"]
