"""qcm-sbi: the SBI peer — train an amortised posterior (NPE) and evaluate it beside the hybrid.

    qcm-sbi train data.path=data/cont_small.h5 [train.max_seconds=540 hydra.run.dir=DIR]
    qcm-sbi evaluate ckpt=DIR/posterior.pt data.path=FILE [sensor=additive sensor.sigma=0.05]

train: fits the posterior on data.train_split (clean recordings; additive noise of a per-sample
level is drawn every epoch), writes DIR/posterior.pt (tensors and plain data only) and
training.csv, then (evaluate_after) evaluates. evaluate: on the first evaluate.n_samples
recordings of data.test_split, at every noise level of evaluate.sigmas (sensor=none) or at the
given sensor's level, writes sbi_metrics.csv (columns named as qcm-estimate's summary), and the
checks: SBC ranks and TARP (sbc.csv, checks.json, plots/sbc_ranks.png, plots/tarp.png).
Bad input (missing extra, file, checkpoint, unknown setting) is one line, before any work.
The work itself: estimation/sbi_run.py.
"""

from __future__ import annotations

import sys

from hybridqcm.apps import common
from hybridqcm.config import CONFIG_DIR
from hybridqcm.errors import ConfigError, HybridQCMError
from hybridqcm.estimation.sbi_run import MODES


def _hydra_entry(cfg) -> None:
    from hybridqcm.estimation.sbi_run import run

    try:
        run(cfg)
    except (HybridQCMError, ConfigError, FileNotFoundError) as error:
        common.fail(error)


def main() -> None:
    """`qcm-sbi train|evaluate [overrides]`: the first argument picks the mode (mode=... also works)."""
    import hydra

    common.install_signal_handlers()
    args = sys.argv[1:]
    if args and args[0] in MODES:
        args = [f"mode={args[0]}", *args[1:]]
    elif args and "=" not in args[0] and not args[0].startswith("-"):
        common.fail(ConfigError(f"qcm-sbi {args[0]!r}: the first argument is train or evaluate"))
    try:
        common.check_task_name_overrides(args)
    except ConfigError as error:
        common.fail(error)
    sys.argv = [sys.argv[0], *args]

    def job(cfg):
        common.quiet_third_party()
        with common.run_folder("qcm-sbi"), common.disk_full_is_one_line():
            return _hydra_entry(cfg)

    try:
        hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name="sbi")(job)()
    except KeyboardInterrupt as error:
        common.interrupted_exit(error)


if __name__ == "__main__":
    main()
