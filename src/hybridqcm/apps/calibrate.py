"""qcm-calibrate: the mass scale of a real seat from drives with known loads (issue 31).

    qcm-calibrate data.path=data/calibration.h5 output=seat.json [law=auto n_samples=40 fit='[sensor=additive]']
        (law: auto | power | linear | power_without_pan | proportional; configs/calibrate.yaml)
    qcm-estimate experiment=occupant_roadfree data.path=FILE seat_file=seat.json    (then: occupant_mass)

Each recording's (p1, p2) comes from qcm-estimate's road-free seat model, rigid occupant, one clock, run in
this process into RUN/fit; the seat's law over the load and the pan mass from estimation/calibration.py
(the run: estimation/calibration_run.py). Bad input (no /<split>/known_mass, a negative or non-finite load,
all loads equal, an existing output) is one line naming the file and key, found before any fitting.
"""

from __future__ import annotations

import csv
from pathlib import Path

from omegaconf.errors import MissingMandatoryValue

from hybridqcm.apps import common
from hybridqcm.errors import ConfigError, DatasetError, HybridQCMError


def fit_recordings(cfg, run_dir: Path) -> list[dict]:
    """qcm-estimate's road-free rigid seat fit of every recording (RUN/fit) -> its estimates.csv rows."""
    from hydra import compose

    from hybridqcm.apps import estimate

    overrides = [
        "experiment=occupant_roadfree",
        "occupant.models=[rigid]",
        "delay=null",
        f"data.path={Path(cfg.data.path).resolve()}",
        f"data.split={cfg.data.split}",
        "plots=false",
        "tensorboard=false",
        f"progress={str(bool(cfg.progress)).lower()}",
        f"n_samples={'null' if cfg.n_samples is None else int(cfg.n_samples)}",
        *[str(o) for o in cfg.get("fit") or []],
    ]
    estimate_cfg = compose("estimate", overrides=overrides)
    estimate.run(estimate_cfg, run_dir=run_dir / "fit")
    with open(run_dir / "fit" / "estimates.csv", newline="") as handle:
        return list(csv.DictReader(handle))


def _hydra_entry(cfg) -> None:
    from hybridqcm.estimation.calibration_run import run_calibration

    try:
        run_calibration(cfg, fit_recordings)
    except MissingMandatoryValue as error:
        common.fail(f"{error.full_key}: required (qcm-calibrate data.path=FILE output=SEAT.json)")
    except (HybridQCMError, ConfigError, DatasetError, FileNotFoundError) as error:
        common.fail(error)


def main() -> None:
    common.run_hydra_app("calibrate", "calibrate", _hydra_entry)


if __name__ == "__main__":
    main()
