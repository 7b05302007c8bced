"""The occupant-model selection (estimation/occupant.py) for models where the person rides on a vehicle.

:class:`OccupantSelection` was written for the road-free seat, whose parameters are (p1, p2, body...).
The sprung road-free model and the road-driven quarter car carry the vehicle's p1..pN first (N = 6 or
10) and the person's body parameters (r_i, k_i, c_i) after them (physics/linear_models.py
SprungOccupantBaseExcitation, QuarterCarOccupantRoad). :class:`VehicleOccupantSelection` is the same
selection with three things made to fit that layout, without touching its logic:

* start: each candidate starts at the batch's vehicle (its p3..pN, known ones at their values per
  recording) with the selection's (p1, p2) and the candidate's body start after them;
* BIC: over the channels the fit measures (exp 8 and 10 observe a3 only; the file's or the U-Net's a2,
  a1 are not the measurement), the road scaled by p_u where the model takes the wheel forcing;
* diagnostics (f_i, ζ_i, masses, rigid part): from the columns named p1, p2, r_i, k_i, c_i.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor

from hybridqcm.physics.occupant import MODE_PARAMS, derived

from .occupant import OccupantSelection

# the batch's start of the vehicle's parameters, handed through the selection to each candidate
_VEHICLE_START = "occupant_vehicle_start"


class _VehicleStart:
    """A candidate's refinement started at (p1, p2 as the selection gives them, the batch's p3..pN, the
    candidate's own start values); ``response`` and ``known`` are the refinement's."""

    def __init__(self, refinement, n_vehicle: int) -> None:
        self.refinement, self.n_vehicle = refinement, int(n_vehicle)
        self.response, self.known = refinement.response, refinement.known

    def refine_block(self, outputs: Mapping, module, block: int) -> dict:
        start = outputs["init"].double()
        vehicle = outputs[_VEHICLE_START].double()[:, 2 : self.n_vehicle]
        inputs = {k: v for k, v in outputs.items() if k != _VEHICLE_START}
        inputs["init"] = torch.cat([start[:, :2], vehicle, start[:, 2:]], 1)
        if hasattr(self.refinement, "refine_block"):
            return self.refinement.refine_block(inputs, module, block)
        return self.refinement.refine(inputs, module)


class _MeasuredResponse:
    """What the selection's BIC reads of a response: its outputs on the measured channels only."""

    def __init__(self, response, channels: Sequence[int]) -> None:
        self.response, self.channels = response, list(channels)

    def outputs(self, theta: Tensor, inputs, start: int = 0, n_steps: int | None = None) -> Tensor:
        return self.response.outputs(theta, inputs, start, n_steps)[:, :, self.channels]


class _MeasuredView:
    def __init__(self, candidate: _VehicleStart, channels: Sequence[int]) -> None:
        self.known = candidate.known
        self.response = _MeasuredResponse(candidate.response, channels)


class VehicleOccupantSelection(OccupantSelection):
    """OccupantSelection over candidates whose parameters are (p1..pN, body..., ) (module docstring).

    ``n_vehicle``: N, the vehicle's parameters before the body's (6 sprung, 10 quarter car); ``observed``:
    the measured channels (names); the others in a candidate's outputs stay out of the BIC."""

    def __init__(
        self,
        candidates: Mapping,
        starts: Mapping[str, Tensor],
        K3: float,
        interval_weight: float,
        n_vehicle: int,
        observed: Sequence[str],
    ) -> None:
        self.n_vehicle = int(n_vehicle)
        super().__init__(
            {name: _VehicleStart(r, self.n_vehicle) for name, r in candidates.items()}, starts, K3, interval_weight
        )
        outputs = self.response.output_names
        self.channels = [i for i, name in enumerate(outputs) if name in set(observed)]
        if not self.channels:
            raise ValueError(f"occupant selection: none of the outputs {list(outputs)} is observed ({list(observed)})")

    def refine(self, outputs: Mapping, module=None) -> dict:
        if outputs["init"].shape[1] < self.n_vehicle:
            raise ValueError(
                f"occupant selection: init has {outputs['init'].shape[1]} parameters, the vehicle {self.n_vehicle}"
            )
        record = super().refine({**outputs, _VEHICLE_START: outputs["init"]}, module)
        record["extra"].update(self._body_diagnostics(record))
        return record

    def _bic(self, refinement, outputs: Mapping, record: dict) -> Tensor:
        road = outputs["road"].double()
        inner = refinement.refinement
        if getattr(inner, "pu_known", False) and getattr(inner, "quarter_car", False):
            road = outputs["pu"].double()[:, None] * road  # the model's input is the wheel forcing p_u u
        measured = {**outputs, "road": road, "targets": outputs["targets"][:, :, self.channels]}
        return super()._bic(_MeasuredView(refinement, self.channels), measured, record)

    def _body_diagnostics(self, record: dict) -> dict:
        """derived() of the chosen model's (p1, p2, body) per recording; NaN for modes it has not."""
        names = self.response.theta_names[: self.response.n_params]
        wanted = ["p1", "p2"] + [f"{k}{i}" for i in range(1, self.max_modes + 1) for k in MODE_PARAMS]
        params = record["params"][:, [names.index(n) for n in wanted]].double()
        out = derived(torch.nan_to_num(params, nan=0.0), self.K3)
        chosen = record["extra"]["occupant_model"]
        modes = torch.tensor([self._modes(self.candidates[name]) for name in chosen])
        for i in range(1, self.max_modes + 1):
            for key in (f"f{i}_hz", f"zeta{i}", f"mass{i}_kg"):
                out[key] = torch.where(modes >= i, out[key], torch.full_like(out[key], math.nan))
        return out
