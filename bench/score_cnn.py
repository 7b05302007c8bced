"""A trained (a3, a2) -> (p1, p2) CNN on any file with `/test/accel` and `/test/params`, e.g. another
simulator's (bench/foreign_sim.py): several files in one call, one line each, without a run folder.
Loaded through the safe loader; prints each parameter's mean and max relative error, and the occupant's
mass K3/p2 (the static mass on a file of seated persons: its p2 is K3/M): mean error and within 5 / 10 %,
per true occupant where the file says (`truth_occupant`). (`qcm-train train=false ckpt_path=CKPT
data.path=FILE` gives the parameters' numbers with the full test report.)

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
            kind = torch.as_tensor(handle["test/truth_occupant"][()]) if "truth_occupant" in handle["test"] else None
        estimate = module.estimate(accel[..., 0], accel[..., 1])
        error = (estimate / truth - 1).abs()
        cells = ", ".join(
            f"p{j + 1} mean {100 * error[:, j].mean():.3g} % max {100 * error[:, j].max():.3g} %" for j in range(2)
        )
        print(f"{path}: {len(truth)} recordings; {cells}")
        mass = (truth[:, 1] / estimate[:, 1] - 1).abs()  # K3/p2 against K3/p2_true: K3 cancels
        groups = {"all": torch.ones_like(mass, dtype=torch.bool)}
        if kind is not None:
            groups |= {name: kind == i for i, name in enumerate(("rigid", "body1", "body2")) if bool((kind == i).any())}
        for name, sel in groups.items():
            e = mass[sel]
            print(
                f"  m3 = K3/p2, {name} ({int(sel.sum())}): mean {100 * e.mean():.3g} %, within 5 % "
                f"{100 * (e <= 0.05).double().mean():.3g} %, within 10 % {100 * (e <= 0.10).double().mean():.3g} %"
            )


if __name__ == "__main__":
    main()
