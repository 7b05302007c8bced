"""qcm-import: a CSV recording from a user's logger into an HDF5 dataset (SPEC § 9, schema 2).

Examples:
    qcm-import input=drive.csv output=data/drive.h5 units=g
    qcm-import input=SEAT.csv base_input=FLOOR.csv output=data/drive.h5 window=500     (two loggers, two clocks)
    qcm-import input=drive.csv output=data/drive.h5 columns.a3=seat_z columns.a2=floor_z window=500 stride=250
    qcm-import --help                               # every key

The work itself: data/import_run.py.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from hybridqcm.apps.common import check_task_name_overrides, fail, install_signal_handlers, interrupted_exit, run_folder
from hybridqcm.config import CONFIG_DIR


@hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name="import")
def _main(cfg: DictConfig) -> None:
    from hybridqcm.data.import_run import run_import

    with run_folder("qcm-import"):
        try:
            run_import(cfg)
        except (ValueError, FileExistsError, OSError) as error:
            fail(error)


def main() -> None:
    install_signal_handlers()  # Ctrl-C / SIGTERM: the .partial removed, one line, exit 130 / 143
    try:
        check_task_name_overrides(sys.argv[1:])  # task_name=../../x would put the run folder outside outputs/
    except ValueError as error:
        fail(error)
    try:
        _main()
    except KeyboardInterrupt as error:
        interrupted_exit(error)


if __name__ == "__main__":
    sys.exit(main())
