"""qcm-import's run: check an import config (configs/import.yaml), import the CSV recording(s), report.

    summary = run_import(compose("import", overrides=["input=drive.csv", "output=data/drive.h5"]))

One logger: data/importer.py; two loggers (base_input=, one clock each): data/two_loggers.py. Every
bad setting is one ValueError line naming the key and value; the summary is printed and saved as
RUN/summary.json.
"""

from __future__ import annotations

import json
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from hybridqcm.atomic import atomic_write_text
from hybridqcm.console import print_table
from hybridqcm.data.import_writer import import_recordings
from hybridqcm.data.two_loggers import import_two_loggers


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


def run_import(cfg: DictConfig) -> dict:
    """Read, check and write; returns the summary (also printed and saved as summary.json in the run folder)."""
    if OmegaConf.is_missing(cfg, "input") or cfg.input is None:
        raise ValueError("input=PATH is required: the CSV recording to import (see qcm-import --help)")
    source = Path(cfg.input)
    output = Path(cfg.output) if cfg.output is not None else Path(cfg.paths.data_dir) / f"{source.stem}.h5"
    if output.exists() and not cfg.overwrite:
        raise FileExistsError(f"output={output} exists; pass overwrite=true to replace it")
    if cfg.get("base_input") is not None:
        return _run_two_loggers(cfg, source, output)
    data = import_recordings(
        source,
        output,
        split=str(cfg.split),
        overwrite=bool(cfg.overwrite),
        progress=bool(cfg.get("progress", True)),
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
        "road": data.has_road,
        "known_mass": None if data.known_mass is None else sorted({float(x) for x in data.known_mass}),
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
            + (", road (in m)" if summary["road"] else "")
            + (", known_mass (in kg)" if data.known_mass is not None else ""),
        ],
        [
            "written",
            f"/{cfg.split}: {data.n_samples} sample(s) x {data.n_steps} steps"
            + (f" (window {data.window}, stride {data.stride})" if data.window else ""),
        ],
    ]
    print_table(f"{source} -> {output}", ["imported", "value"], rows)
    _save_summary(cfg, summary)
    return summary


def _save_summary(cfg: DictConfig, summary: dict) -> None:
    atomic_write_text(Path(cfg.paths.output_dir) / "summary.json", json.dumps(summary, indent=2))


def _run_two_loggers(cfg: DictConfig, seat: Path, output: Path) -> dict:
    """input = the seat's logger, base_input = the floor's (data/two_loggers.py): aligned, one grid, windows."""
    for key in ("recording_column",):
        if cfg.get(key) is not None:
            raise ValueError(f"{key}={cfg[key]!r} does not apply to two loggers (base_input=): one drive per pair")
    floor = Path(cfg.base_input)
    read = {
        "axes": _axes(cfg, "axes"),
        "time_column": cfg.time_column,
        "time_unit": str(cfg.time_unit),
        "units": str(cfg.units),
        "gap_factor": _number(cfg, "gap_factor"),
        "delimiter": cfg.delimiter,
        "rate_range": _rate_range(cfg),
    }
    base_read = dict(read, axes=_axes(cfg, "base_axes"), units=str(cfg.get("base_units") or cfg.units))
    rate = cfg.get("rate")
    layout, report = import_two_loggers(
        seat,
        floor,
        output,
        window=_optional_int(cfg, "window"),
        stride=_optional_int(cfg, "stride"),
        split=str(cfg.split),
        overwrite=bool(cfg.overwrite),
        progress=bool(cfg.get("progress", True)),
        read=read,
        base_read=base_read,
        rate=None if rate is None else _number(cfg, "rate"),
        min_overlap_s=_number(cfg, "min_overlap_s"),
    )
    summary = {
        "input": str(seat),
        "base_input": str(floor),
        "output": str(output),
        "split": str(cfg.split),
        "rate_hz": 1.0 / layout.h,
        "h": layout.h,
        "samples": layout.n_samples,
        "n_steps": layout.n_steps,
        "window": layout.window,
        "stride": layout.stride,
        "two_loggers": report,
    }
    drift = (
        f"{report['drift_ppm']:+.1f} ± {report['drift_sd_ppm']:.1f} ppm, "
        + ("applied" if report["drift_applied"] else "not applied (not determined over this overlap)")
        if report["drift_ppm"] == report["drift_ppm"]
        else "not estimated (overlap too short)"
    )
    rows = [
        [
            "loggers",
            f"seat {report['seat']['rate_hz']:.6g} Hz, tilt {report['seat']['tilt_deg']:.2f} deg; "
            f"floor {report['floor']['rate_hz']:.6g} Hz, tilt {report['floor']['tilt_deg']:.2f} deg",
        ],
        ["clock offset", f"t_floor - t_seat = {report['offset_s']:.6f} s"],
        ["clock drift", drift],
        [
            "grid",
            f"{report['rate_hz']:.6g} Hz over {report['overlap_s']:.6g} s in common (floor clock from {report['t0_s']:.6g} s)",
        ],
        [
            "written",
            f"/{cfg.split}: {layout.n_samples} sample(s) x {layout.n_steps} steps of a3 (seat), a2 (floor)"
            + (f" (window {layout.window}, stride {layout.stride})" if layout.window else ""),
        ],
    ]
    print_table(f"{seat} + {floor} -> {output}", ["imported", "value"], rows)
    _save_summary(cfg, summary)
    return summary


def _axes(cfg: DictConfig, key: str) -> list[str] | None:
    value = cfg.get(key)
    if value is None:
        return None
    value = OmegaConf.to_container(value, resolve=True) if not isinstance(value, (str, list)) else value
    if isinstance(value, str) or len(value) != 3:
        raise ValueError(f"{key} must list the three axis columns, e.g. {key}=[ax,ay,az], got {value!r}")
    return [str(v) for v in value]
