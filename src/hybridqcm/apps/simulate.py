"""qcm-simulate: write a quarter-car dataset in the SPEC §5 HDF5 layout.

Examples:
    qcm-simulate                                   # reference protocol (51 000 samples)
    qcm-simulate preset=small                      # data/small.h5 (continuous physics, windows mid-drive)
    qcm-simulate preset=small physics=euler                  # the source protocol: Euler from rest
    qcm-simulate h=0.002 n_steps=2560              # a 500 Hz logger (same 5.12 s window)
    qcm-simulate preset=small occupant=body1       # seated persons: seat pan + one body mode
    qcm-simulate preset=small seat.law=power seat.exponent=0.5 seat.pan_mass=12 [seat.known_loads=[0,40,80,120]]
                                                   # a foam seat with a pan (and calibration drives; issue 31)
    qcm-simulate vehicle=full_car seats=[driver,rear_left] output=data/fcm.h5   # the full car (issue 30)
    qcm-simulate output=data/mine.h5 seed=7 prior=physical overwrite=true
    qcm-simulate --cfg job                         # show the resolved configuration

The work itself: data/simulate_run.py (quarter car) and data/vehicle_simulate_run.py (half, full car).
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from hybridqcm.apps.common import check_task_name_overrides, fail, install_signal_handlers, interrupted_exit, run_folder
from hybridqcm.config import CONFIG_DIR
from hybridqcm.errors import ConfigError


@hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name="simulate")
def _main(cfg: DictConfig) -> None:
    from hybridqcm.data.simulate_run import run_simulation

    with run_folder("qcm-simulate"):
        try:
            run_simulation(cfg)
        except (ValueError, FileExistsError, OSError, ConfigError) as error:
            fail(error)


def main() -> None:
    install_signal_handlers()
    try:
        check_task_name_overrides(sys.argv[1:])
    except ConfigError as error:
        fail(error)
    try:
        _main()
    except KeyboardInterrupt as error:
        interrupted_exit(error)


if __name__ == "__main__":
    sys.exit(main())
