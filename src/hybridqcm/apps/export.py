"""qcm-export: a trained network checkpoint -> TorchScript (.pt) + ONNX (.onnx) + contract (.json).

    qcm-export outputs/demo/exp2_physics/checkpoints/last.ckpt --data data/demo.h5 --out exports/
    qcm-export CKPT --format torchscript            # without onnx / onnxruntime installed

The exported graph is the checkpoint's physical-unit inference (models/export.py): raw
accelerations [batch, channels, time] in m/s² in, parameters or signals out, normalisation
inside, batch axis dynamic. Each export is checked against the checkpoint's own `estimate` /
`denoise` / `complete` on held-out recordings (`--data`, default split test) or, without a data
file, on synthetic smooth signals; a deviation beyond --tol fails the command (exit 1).
Bad input (missing file, foreign checkpoint, missing package) exits 2 with a one-line error.
The work itself: models/export_files.py.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from hybridqcm.apps.common import fail
from hybridqcm.errors import ConfigError
from hybridqcm.models.export_files import FORMATS, ParityError, export


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="qcm-export",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Export a trained network (CNN estimator, CAE denoiser, U-Net completion) to TorchScript and ONNX.\n"
        "Input: raw accelerations [batch, channels, time] float32 in m/s² (normalisation inside);\n"
        "output: parameters [batch, P] float64 (estimators) or signals [batch, 2, time] in m/s².\n"
        "Writes STEM.pt, STEM.onnx and STEM.json (the input/output contract and the parity check).",
        epilog="example: qcm-export outputs/demo/exp2_physics/checkpoints/last.ckpt --data data/demo.h5 --out exports/",
    )
    parser.add_argument("ckpt", help="checkpoint (.ckpt) written by qcm-train")
    parser.add_argument("--out", default=None, help="output folder (default: the checkpoint's folder)")
    parser.add_argument("--name", default=None, help="file stem of the exports (default: the checkpoint's stem)")
    parser.add_argument(
        "--format",
        nargs="+",
        default=list(FORMATS),
        choices=FORMATS,
        dest="formats",
        help="what to write (default: both; onnx needs pip install -e '.[export]')",
    )
    parser.add_argument(
        "--time-steps",
        type=int,
        default=None,
        help="length of the time axis of the denoiser / U-Net export (default: the training window; "
        "estimators always take exactly their window)",
    )
    parser.add_argument(
        "--data", default=None, help="HDF5 dataset whose recordings check parity (default: synthetic signals)"
    )
    parser.add_argument(
        "--split", default="test", help="split of --data to take held-out recordings from (default: test)"
    )
    parser.add_argument("--n-check", type=int, default=64, help="recordings in the parity check (default: 64)")
    parser.add_argument("--tol", type=float, default=1e-5, help="largest relative deviation accepted (default: 1e-5)")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an existing export of the same name (default: refuse)"
    )
    return parser


def main(argv: Sequence[str] | None = None) -> None:
    from hybridqcm.errors import CheckpointError, DatasetError

    args = build_parser().parse_args(argv)
    if args.n_check < 1:
        fail(f"--n-check {args.n_check}: must be >= 1")
    try:
        sidecar = export(
            args.ckpt,
            args.out,
            args.name,
            args.formats,
            args.time_steps,
            args.data,
            args.split,
            args.n_check,
            args.tol,
            args.overwrite,
        )
    except (ConfigError, DatasetError, CheckpointError, FileNotFoundError) as error:
        fail(error)
    except ParityError as error:
        fail(error, code=1)
    out = Path(args.out) if args.out else Path(args.ckpt).parent
    parity = ", ".join(f"{k} {v:.2e}" for k, v in sidecar["parity"].items())
    print(
        f"{sidecar['model_class']}: {', '.join(str(out / f) for f in sidecar['files'].values())} + "
        f"{out / ((args.name or Path(args.ckpt).stem) + '.json')}; parity ({sidecar['parity_measure']}): {parity}"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
