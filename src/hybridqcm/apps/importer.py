"""qcm-import: a CSV recording from a user's logger into an HDF5 dataset (SPEC § 9, schema 2).

Examples:
    qcm-import input=drive.csv output=data/drive.h5 units=g
    qcm-import input=drive.csv output=data/drive.h5 columns.a3=seat_z columns.a2=floor_z window=500 stride=250
    qcm-import --help                               # every key
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from hybridqcm.apps.common import (
    CONFIG_DIR,
    check_task_name_overrides,
    fail,
    install_signal_handlers,
    interrupted_exit,
    print_table,
    run_folder,
)
from hybridqcm.atomic import atomic_write_text
from hybridqcm.data.importer import read_recordings, write_recordings


def _optional_int(cfg: DictConfig, key: str) -> int | None:
    value = cfg[key]
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{key} must be an integer, got {value!r}")
    return value


def _number(cfg: DictConfig, key: str) -> float:
    value = cfg[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{key} must be a number, got {value!r}")
    return float(value)


def _mapping(cfg: DictConfig, key: str) -> dict:
    value = OmegaConf.to_container(cfg[key], resolve=True) if cfg[key] is not None else {}
    if not isinstance(value, dict):
        raise ValueError(f"{key} must be a mapping like {key}.a3=NAME, got {value!r}")
    return value


def _rate_range(cfg: DictConfig) -> tuple[float, float]:
    value = OmegaConf.to_container(cfg.rate_range, resolve=True) if cfg.get("rate_range") is not None else None
    if (
        not isinstance(value, list)
        or len(value) != 2
        or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value)
        or not 0 < value[0] < value[1]
    ):
        raise ValueError(f"rate_range={value!r} must be [LOW, HIGH] in Hz with 0 < LOW < HIGH")
    return float(value[0]), float(value[1])


def run(cfg: DictConfig) -> dict:
    """Read, check and write; returns the summary (also printed and saved as summary.json in the run folder)."""
    if OmegaConf.is_missing(cfg, "input") or cfg.input is None:
        raise ValueError("input=PATH is required: the CSV recording to import (see qcm-import --help)")
    source = Path(cfg.input)
    output = Path(cfg.output) if cfg.output is not None else Path(cfg.paths.data_dir) / f"{source.stem}.h5"
    if output.exists() and not cfg.overwrite:
        raise FileExistsError(f"output={output} exists; pass overwrite=true to replace it")
    data = read_recordings(
        source,
        units=str(cfg.units),
        column_units=_mapping(cfg, "column_units"),
        columns=_mapping(cfg, "columns"),
        time_column=cfg.time_column,
        time_unit=str(cfg.time_unit),
        recording_column=cfg.recording_column,
        window=_optional_int(cfg, "window"),
        stride=_optional_int(cfg, "stride"),
        rate_tolerance=_number(cfg, "rate_tolerance"),
        gap_factor=_number(cfg, "gap_factor"),
        delimiter=cfg.delimiter,
        rate_range=_rate_range(cfg),
    )
    write_recordings(output, data, split=str(cfg.split), source=str(source), overwrite=bool(cfg.overwrite))
    duration = sum(data.rows) * data.h
    summary = {
        "input": str(source),
        "output": str(output),
        "split": str(cfg.split),
        "rate_hz": 1.0 / data.h,
        "h": data.h,
        "recordings": len(data.recordings),
        "rows": int(sum(data.rows)),
        "duration_s": duration,
        "channels": list(data.channels),
        "road": data.road is not None,
        "units": data.source_units,
        "samples": data.n_samples,
        "n_steps": data.n_steps,
        "window": data.window,
        "stride": data.stride,
    }
    rows = [
        ["rate", f"{summary['rate_hz']:.6g} Hz (h = {data.h:.6g} s)"],
        ["duration", f"{duration:.6g} s in {summary['rows']} rows, {len(data.recordings)} recording(s)"],
        [
            "channels",
            ", ".join(f"{c} (in {data.source_units[c]})" for c in data.channels)
            + (", road (in m)" if summary["road"] else ""),
        ],
        [
            "written",
            f"/{cfg.split}: {data.n_samples} sample(s) x {data.n_steps} steps"
            + (f" (window {data.window}, stride {data.stride})" if data.window else ""),
        ],
    ]
    print_table(f"{source} -> {output}", ["imported", "value"], rows)
    atomic_write_text(Path(cfg.paths.output_dir) / "summary.json", json.dumps(summary, indent=2))
    return summary


@hydra.main(version_base="1.3", config_path=str(CONFIG_DIR), config_name="import")
def _main(cfg: DictConfig) -> None:
    with run_folder("qcm-import"):
        try:
            run(cfg)
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
