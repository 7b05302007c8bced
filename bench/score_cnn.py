"""A trained (a3, a2) -> (p1, p2) CNN on any file with `/test/accel` and `/test/params`, e.g. another
simulator's (bench/foreign_sim.py): several files in one call, one line each, without a run folder.
Loaded through the safe loader; prints each parameter's mean and max relative error. (`qcm-train
train=false ckpt_path=CKPT data.path=FILE` gives the same numbers with the full test report.)

    PYTHONPATH=src .venv/bin/python bench/score_cnn.py CKPT data/foreign_clean.h5 [data/foreign_n5.h5 ...]
"""

from __future__ import annotations

import argparse

import h5py
import torch

from hybridqcm.models.checkpoint import load_checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("ckpt")
    parser.add_argument("files", nargs="+")
    args = parser.parse_args()
    module = load_checkpoint(args.ckpt, "cnn")  # any (a3, a2) -> (p1, p2) estimator, nothing else
    for path in args.files:
        with h5py.File(path, "r") as handle:
            accel = torch.as_tensor(handle["test/accel"][()], dtype=torch.float64)
            truth = torch.as_tensor(handle["test/params"][()], dtype=torch.float64)[:, :2]
        error = (module.estimate(accel[..., 0], accel[..., 1]) / truth - 1).abs()
        cells = ", ".join(
            f"p{j + 1} mean {100 * error[:, j].mean():.3g} % max {100 * error[:, j].max():.3g} %" for j in range(2)
        )
        print(f"{path}: {len(truth)} recordings; {cells}")


if __name__ == "__main__":
    main()
