"""The half and full car from the console scripts (issue 30): files, runs, and one line per bad input."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from conftest import app_in_process
from hybridqcm.config import CONFIG_DIR, check_schema_overrides
from hybridqcm.data.hdf5 import LAYOUT, dataset_info, read_split
from hybridqcm.data.vehicle_files import read_seat_split
from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation.plan import validate
from hybridqcm.estimation.plan_vehicle import validate_vehicle

ENV = {**os.environ, "COLUMNS": "160", "PYTHONWARNINGS": "ignore"}
SMALL = ["n_steps=160", "samples_per_profile=2", "splits.test.profiles={A: 2, B: 1, C: 0}", "~splits.train"]


def _script(name: str) -> list[str]:
    script = Path(sys.executable).parent / name
    module = {"qcm-simulate": "simulate", "qcm-estimate": "estimate"}[name]
    return [str(script)] if script.exists() else [sys.executable, "-m", f"hybridqcm.apps.{module}"]


def _run(name: str, folder: Path, *overrides: str, timeout: float = 300) -> subprocess.CompletedProcess:
    command = _script(name) + [*overrides, f"hydra.run.dir={folder}", "progress=false"]
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=ENV, cwd=folder.parent)


def _names(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in values]


def _one_line_error(proc: subprocess.CompletedProcess, message: str) -> None:
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines and lines[-1].startswith("error:") and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert message in lines[-1], lines[-1]


def _simulate(folder: Path, *overrides: str) -> dict:
    """qcm-simulate's run() in this process (its config composed as the console composes it)."""
    from hybridqcm.data.simulate_run import run_simulation

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(
            "simulate",
            overrides=[*overrides, f"paths.root_dir={folder}", f"paths.output_dir={folder}", "progress=false"],
        )
    return run_simulation(cfg)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """A half car (the source's seat) and a full car (driver + rear_left, damped tyres) from qcm-simulate's run()."""
    root = tmp_path_factory.mktemp("vehicles")
    out = {}
    for key, overrides in {
        "hcm": ["vehicle=half_car"],
        "fcm": ["vehicle=full_car", "seats=[driver,rear_left]", "tyre_damping=true"],
    }.items():
        out[key] = root / f"{key}.h5"
        _simulate(root, *overrides, *SMALL, f"output={out[key]}")
    return out


def _cfg(*overrides):
    """As qcm-estimate composes: the schema's one-line refusals of the command line first."""
    check_schema_overrides(overrides, "estimate")
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("estimate", overrides=list(overrides))


def test_simulated_files_name_their_columns(files):
    info = dataset_info(files["fcm"])
    assert info["attrs"]["vehicle"] == "full_car" and info["attrs"]["road_coherence"] == "isotropic"
    assert json.loads(info["attrs"]["layout"])["tyre_damping"] is True
    with h5py.File(files["fcm"]) as f:
        g = f["test"]
        dofs = ["z3_driver", "z3_rear_left", "z2", "z1fl", "z1fr", "z1bl", "z1br", "pitch", "roll"]
        for key in ("accel", "vel", "disp"):
            assert _names(g[key].attrs["dofs"]) == dofs
            assert g[key].shape == (6, 160, 9)
        assert _names(g["road"].attrs["wheels"]) == ["fl", "fr", "bl", "br"] and g["road"].shape == (6, 160, 4)
        assert g["road_vel"].shape == (6, 160, 4)
        names = _names(g["physical"].attrs["names"])
        assert names[:4] == ["m1fl", "m1fr", "m1bl", "m1br"] and "m3_driver" in names and "y_s_rear_left" in names
        assert "c1fl" in names and float(g["physical"][0, names.index("c1fl")]) > 0
        assert g["accel"].dtype == np.float32 and g["disp"].dtype == np.float64
    with h5py.File(files["hcm"]) as f:
        assert _names(f["test/accel"].attrs["dofs"]) == ["z3", "z2", "z1f", "z1b", "pitch"]
        assert "road_vel" not in f["test"]
        names = _names(f["test/physical"].attrs["names"])
        assert {"m3", "k3", "c3", "x_s", "I_pitch", "l_f", "l_b"} <= set(names) and "I_roll" not in names


def test_quarter_car_files_are_unchanged(tmp_path):
    """vehicle=quarter_car (the default) writes exactly what the quarter car's writer writes: the same
    keys, dtypes, attributes and bytes (created_by and the timings in summary aside), nothing new."""
    from omegaconf import OmegaConf

    from hybridqcm.data.simulate import write_dataset
    from hybridqcm.physics.prior import build_prior
    from hybridqcm.physics.road import RoadProfile

    cli = tmp_path / "cli.h5"
    _simulate(tmp_path, "preset=tiny", f"output={cli}", "n_steps=64")
    direct = tmp_path / "direct.h5"
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("simulate", overrides=["preset=tiny", "n_steps=64"])
    write_dataset(
        direct,
        OmegaConf.to_container(cfg.splits),
        build_prior("thesis", h=None, sigma=0.1, mass_range=(30.0, 150.0)),  # continuous: no Euler map to check
        RoadProfile(),
        n_steps=64,
        h=0.01,
        speed_mps=30 / 3.6,
        samples_per_profile=int(cfg.samples_per_profile),
        seed=0,
        progress=False,
        physics="continuous",
        warmup_s=(2.0, 20.0),
    )
    with h5py.File(cli) as a, h5py.File(direct) as b:
        volatile = {"created_by", "summary"}
        assert set(a.attrs) == set(b.attrs) and "vehicle" not in a.attrs
        for key in set(a.attrs) - volatile:
            assert np.array_equal(np.asarray(a.attrs[key]), np.asarray(b.attrs[key])), key
        for split in ("train", "test"):
            assert sorted(a[split].keys()) == sorted(LAYOUT)
            for key in LAYOUT:
                assert dict(a[split][key].attrs) == {} and a[split][key].dtype == b[split][key].dtype
                assert a[split][key][()].tobytes() == b[split][key][()].tobytes(), (split, key)


def test_hcm_full_observation_run(files, tmp_path):
    # qcm-estimate's run in-process (the vehicles' console: test_bad_vehicle_inputs_on_the_console)
    overrides = ["experiment=hcm_full_observation", f"data.path={files['hcm']}", "n_samples=4", "progress=false"]
    app_in_process("estimate", tmp_path / "run", *overrides)
    with open(tmp_path / "run" / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4
    truth = read_split(files["hcm"], "test", ("physical",))["physical"]
    with h5py.File(files["hcm"]) as f:
        names = _names(f["test/physical"].attrs["names"])
    for i, row in enumerate(rows):
        assert row["status"] == "converged"
        assert float(row["m3_low"]) <= float(row["m3"]) <= float(row["m3_high"])
        for name in ("m3", "m2", "I_pitch", "k2b", "x_s"):
            assert abs(float(row[name]) / truth[i, names.index(name)] - 1) < 0.01, name
        assert float(row["k3"]) == truth[i, names.index("k3")]  # known: held at the file's value
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["vehicle"] == "half_car" and summary["known"] == ["k3"]
    assert summary["m3_within_0.5pct"] == 1.0 and summary["all_within_1pct"] == 1.0
    assert (tmp_path / "run" / "calibration.csv").exists() and (tmp_path / "run" / "error_distribution.md").exists()


def test_road_free_seat_of_a_full_car(files):
    """occupant_roadfree seat=<name> reads the seat's z3 and its base z2 + x_s pitch + y_s roll."""
    seat = read_seat_split(files["fcm"], "test", "rear_left", ("accel", "params"))
    raw = read_split(files["fcm"], "test", ("accel", "physical"))
    with h5py.File(files["fcm"]) as f:
        dofs = _names(f["test/accel"].attrs["dofs"])
        names = _names(f["test/physical"].attrs["names"])
    P = {n: raw["physical"][:, j] for j, n in enumerate(names)}
    a = raw["accel"].astype(np.float64)
    base = (
        a[..., dofs.index("z2")]
        + P["x_s_rear_left"][:, None] * a[..., dofs.index("pitch")]
        + P["y_s_rear_left"][:, None] * a[..., dofs.index("roll")]
    )
    np.testing.assert_allclose(seat["accel"][..., 1], base, rtol=1e-6, atol=1e-6 * np.abs(base).max())
    np.testing.assert_array_equal(seat["accel"][..., 0], raw["accel"][..., dofs.index("z3_rear_left")])
    assert np.isnan(seat["accel"][..., 2]).all() and np.isnan(seat["params"][:, 2:]).all()
    np.testing.assert_allclose(seat["params"][:, 1], P["k3_rear_left"] / P["m3_rear_left"], rtol=1e-12)
    # the quarter car's road-free pipeline reads it: the plan names the seat, the batch is the seat's
    from hybridqcm.estimation.blocks import build_inputs

    cfg = _cfg("experiment=occupant_roadfree", f"data.path={files['fcm']}", "seat=rear_left", "n_samples=2")
    plan = validate(cfg)
    assert plan["seat"] == "rear_left" and plan["has_params"] and plan["base_excitation"] == "seat"
    # occupant_roadfree's default: the persons' selection (rigid, body1, body2, delay auto) on a seat too
    assert plan["occupant"]["models"] == ["rigid", "body1", "body2"] and plan["occupant"]["delay"] == "auto"
    batch = build_inputs(cfg, plan)
    T = plan["n_read_steps"]
    torch.testing.assert_close(batch["accel"][:, :, :2], torch.as_tensor(seat["accel"][:2, :T, :2]).double())
    torch.testing.assert_close(batch["true"][:, :2], torch.as_tensor(seat["params"][:2, :2]))


def test_apparent_mass_plot_of_a_seat(files, tmp_path, monkeypatch):
    """The occupant selection's plots on a seat view show the seat's z3 over its base z2 + x_s pitch + y_s
    roll (composed here from the stored chassis motion), not the file's first two columns."""
    import scipy.signal

    import hybridqcm.plots
    from hybridqcm.reports.estimate import plot_first_recordings

    plan = validate(_cfg("experiment=occupant_roadfree", f"data.path={files['fcm']}", "seat=rear_left", "n_samples=2"))
    raw = read_split(files["fcm"], "test", ("accel", "physical"), index=slice(1, 2))
    with h5py.File(files["fcm"]) as f:
        dofs = _names(f["test/accel"].attrs["dofs"])
        names = _names(f["test/physical"].attrs["names"])
    P = {n: raw["physical"][0, j] for j, n in enumerate(names)}
    a = raw["accel"][0].astype(np.float64)
    a3 = a[:, dofs.index("z3_rear_left")]
    a2 = (
        a[:, dofs.index("z2")]
        + P["x_s_rear_left"] * a[:, dofs.index("pitch")]
        + P["y_s_rear_left"] * a[:, dofs.index("roll")]
    )
    p2 = P["k3_rear_left"] / P["m3_rear_left"]
    table = tmp_path / "estimates.csv"
    table.write_text(
        "index,status,p1,p2,m3,m3_low,m3_high\n"
        + f"1,converged,{P['c3_rear_left'] / P['m3_rear_left']},{p2},{P['m3_rear_left']},0,1000\n"
    )
    seen = []
    monkeypatch.setattr(hybridqcm.plots, "plot_apparent_mass", lambda f, measured, *rest: seen.append((f, measured)))
    monkeypatch.setattr(hybridqcm.plots, "close", lambda figure: None)
    plot_first_recordings(tmp_path, plan, table)
    assert len(seen) == 1
    nper = min(256, a2.shape[0])
    freq, s22 = scipy.signal.welch(a2, fs=1 / plan["h"], nperseg=nper)
    _, s23 = scipy.signal.csd(a2, a3, fs=1 / plan["h"], nperseg=nper)
    band = (freq >= 0.5) & (freq <= 15)
    np.testing.assert_allclose(seen[0][0], freq[band])
    np.testing.assert_allclose(seen[0][1], (s23 / s22)[band], rtol=1e-4)


@pytest.mark.slow
def test_road_free_seat_run(files, tmp_path):
    """experiment=occupant_roadfree seat=rear_left from the console: the seat's occupant within 0.5 %."""
    raw = read_split(files["fcm"], "test", ("physical",))
    with h5py.File(files["fcm"]) as f:
        names = _names(f["test/physical"].attrs["names"])
    P = {n: raw["physical"][:, j] for j, n in enumerate(names)}
    proc = _run(
        "qcm-estimate",
        tmp_path / "run",
        "experiment=occupant_roadfree",
        f"data.path={files['fcm']}",
        "seat=rear_left",
        "n_samples=4",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    with open(tmp_path / "run" / "estimates.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4
    for i, row in enumerate(rows):
        assert abs(float(row["m3"]) / P["m3_rear_left"][i] - 1) < 0.005
        assert row["occupant_model"] == "rigid"  # the simulated seats hold rigid occupants: the selection says so
    assert len(list((tmp_path / "run" / "plots").glob("apparent_mass_*.png"))) == 4


def test_seat_view_trains_a_cnn(files):
    from hybridqcm.data.datamodules import HDF5DataModule

    module = HDF5DataModule(
        str(files["fcm"]),
        train_split="test",
        test_split="test",
        seat="driver",
        inputs=("a3", "a2"),
        targets=("p1", "p2"),
        window=128,
        val_fraction=0.25,
    )
    module.setup("fit")
    batch = module.data_train.__getitems__([0, 1])
    assert batch["x"].shape == (2, 2, 128) and batch["y"].shape == (2, 2)
    seat = read_seat_split(files["fcm"], "test", "driver", ("accel", "params"), n_steps=128)
    rows = batch["index"].tolist()
    torch.testing.assert_close(batch["y"], torch.as_tensor(seat["params"][rows, :2]))
    with pytest.raises(DatasetError, match="not one of the file's seats"):
        HDF5DataModule(
            str(files["fcm"]), train_split="test", seat="pilot", inputs=("a3", "a2"), targets=("p1", "p2"), window=128
        ).setup("fit")


# ------------------------------------------------------------------------------------------- bad input
def _edited(files, tmp_path, key: str, edit, name: str) -> Path:
    path = tmp_path / f"edited_{key}_{name}.h5"
    shutil.copy(files[key], path)
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


def _rename(group_key: str, attr: str, old: str, new: str):
    def edit(f):
        values = _names(f[group_key].attrs[attr])
        values[values.index(old)] = new
        f[group_key].attrs[attr] = np.array(values, dtype=h5py.string_dtype())

    return edit


def _set_physical(name: str, value: float):
    def edit(f):
        names = _names(f["test/physical"].attrs["names"])
        data = f["test/physical"][()]
        data[1, names.index(name)] = value
        f["test/physical"][...] = data

    return edit


def test_bad_vehicle_inputs_are_one_line(files, tmp_path, tiny_dataset):
    fcm, hcm = (f"data.path={files[k]}" for k in ("fcm", "hcm"))
    cases = [
        (validate_vehicle, ["experiment=hcm_full_observation", fcm], "attribute vehicle = 'full_car'"),
        (
            validate_vehicle,
            ["experiment=fcm_full_observation", f"data.path={tiny_dataset}"],
            "attribute vehicle = 'quarter_car'",
        ),
        (
            validate,
            ["experiment=exp5_random_init", fcm],
            "holds a full_car (attribute vehicle), but experiment exp5 fits the quarter car",
        ),
        (validate_vehicle, ["experiment=hcm_full_observation", hcm, "known=[k9]"], "known: 'k9' is not a parameter"),
        (validate_vehicle, ["experiment=hcm_full_observation", hcm, "known=[l_f]"], "one common factor of every mass"),
        (validate_vehicle, ["experiment=hcm_full_observation", hcm, "init.equation_error=maybe"], "choose false, true"),
        (
            validate_vehicle,
            ["experiment=fcm_full_observation", fcm, "occupant.models=[rigid,body1]"],
            "the full_car's model seats rigid occupants",
        ),
        (validate_vehicle, ["experiment=hcm_full_observation", hcm, "delay=5"], "the half_car is fitted on one clock"),
        (
            validate_vehicle,
            ["experiment=fcm_full_observation", fcm, "sensor=additive", "sensor.sigma=[0.01,0.02,0.03]"],
            "give one number each",
        ),
        (
            validate,
            ["experiment=occupant_roadfree", fcm],
            "has seats ['driver', 'rear_left']: choose one with seat=<name>",
        ),
        (validate, ["experiment=occupant_roadfree", fcm, "seat=pilot"], "seat='pilot' is not one of the file's seats"),
        (
            validate,
            ["experiment=occupant_roadfree", f"data.path={tiny_dataset}", "seat=driver"],
            "is a quarter-car file",
        ),
        (validate, ["experiment=occupant_roadfree", fcm, "seat=driver", "K3=1000"], "pass K3=98935.0"),
        # main's setting checks hold for the vehicles' runs too
        (validate_vehicle, ["experiment=hcm_full_observation", hcm, "n_samples=abc"], "n_samples='abc': give a whole"),
        (validate_vehicle, ["experiment=hcm_full_observation", hcm, "trainer.devices=0"], "trainer.devices=0: give"),
    ]
    edits = {
        "dofs": (_rename("test/accel", "dofs", "pitch", "yaw"), "attribute dofs = ["),
        "wheels": (_rename("test/road", "wheels", "fl", "front_left"), "attribute wheels = ["),
        "names": (_rename("test/physical", "names", "I_roll", "I_yaw"), "attribute names = ["),
        "inertia": (_set_physical("I_pitch", -1.0), "(I_pitch) = -1.0: an inertia must be > 0"),
        "seat": (_set_physical("x_s_driver", 4.0), "seat 'driver' at (x, y) = (4, "),
    }
    for name, (edit, message) in edits.items():
        path = _edited(files, tmp_path, "fcm", edit, name)
        cases.append((validate_vehicle, ["experiment=fcm_full_observation", f"data.path={path}"], message))
    for check, overrides, message in cases:
        with pytest.raises((ConfigError, DatasetError)) as error:
            check(_cfg(*overrides))
        text = str(error.value)
        assert message in text and "\n" not in text, (overrides, text)
    # init.equation_error takes `seats` besides true and false on a vehicle (not a switch's type error)
    assert validate_vehicle(_cfg("experiment=hcm_full_observation", hcm, "init.equation_error=seats"))["known"]


def test_bad_vehicle_inputs_on_the_console(files, tmp_path):
    _one_line_error(
        _run("qcm-estimate", tmp_path / "e", "experiment=hcm_full_observation", f"data.path={files['fcm']}"),
        "attribute vehicle = 'full_car'",
    )
    _one_line_error(
        _run(
            "qcm-simulate",
            tmp_path / "s1",
            "vehicle=full_car",
            "seats={far: [3.0, 0.0]}",
            *SMALL,
            f"output={tmp_path / 'x.h5'}",
        ),
        "seat 'far' at (x, y) = (3, 0) m is outside the chassis",
    )
    with pytest.raises(ValueError, match=r"vehicle='van': choose one of \['quarter_car', 'half_car', 'full_car'\]"):
        _simulate(tmp_path, "vehicle=van", *SMALL, f"output={tmp_path / 'y.h5'}")
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "y.h5").exists()
