"""qcm-estimate: outputs of a run, and a clear error for every bad input before any work."""

import csv
import json
import subprocess
import sys

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from hybridqcm.config import CONFIG_DIR, check_experiment_overrides
from hybridqcm.errors import ConfigError, DatasetError
from hybridqcm.estimation.blocks import build_inputs
from hybridqcm.estimation.plan import validate
from hybridqcm.testing import synthetic_samples, train_tiny_checkpoints, write_dataset


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    samples = synthetic_samples(32, n_steps=160, seed=0)
    return train_tiny_checkpoints(tmp_path_factory.mktemp("ckpt"), samples, steps=3, window=128)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("estimate_files")
    samples = synthetic_samples(8, n_steps=160, seed=4)
    out = {
        "no_params": write_dataset(root / "no_params.h5", samples, with_params=False),
        "good": write_dataset(root / "good.h5", samples),
    }
    # A file that lacks the road (another producer's partial file)
    with h5py.File(root / "no_road.h5", "w") as f:
        f.attrs["schema"] = "hybridqcm.dataset/1"
        f.create_dataset("test/accel", data=samples["accel"].numpy().astype(np.float32))
        f.create_dataset("test/params", data=samples["params"].numpy())
    out["no_road"] = root / "no_road.h5"
    # NaN in an acceleration (written raw: the project's writer refuses non-finite values)
    accel = samples["accel"].numpy().astype(np.float32)
    accel[3, 17, 0] = np.nan
    with h5py.File(root / "nan.h5", "w") as f:
        f.attrs["schema"] = "hybridqcm.dataset/1"
        f.create_dataset("test/accel", data=accel)
        f.create_dataset("test/road", data=samples["road"].numpy().astype(np.float32))
        f.create_dataset("test/params", data=samples["params"].numpy())
    out["nan"] = root / "nan.h5"
    return out


def _cfg(overrides):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("estimate", overrides=list(overrides))


def _run_app(tmp_path, *overrides):
    cmd = [sys.executable, "-m", "hybridqcm.apps.estimate", *overrides, f"hydra.run.dir={tmp_path}", "progress=false"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300)


def _rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


# ---------------------------------------------------------------------------------------------- runs
def test_exp5_run_writes_everything(tiny_dataset, tmp_path):
    proc = _run_app(tmp_path, "experiment=exp5_random_init", f"data.path={tiny_dataset}", "n_samples=16")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = _rows(tmp_path / "estimates.csv")
    assert len(rows) == 16
    header = list(rows[0])
    assert header[:12] == ["index", *[f"p{i}" for i in range(1, 11)], "status"]
    assert header[12:] == [*[f"std_p{i}" for i in range(1, 11)], "m3", "m3_std", "m3_low", "m3_high"]
    assert {r["status"] for r in rows} <= {"converged", "max_iterations", "singular", "diverged", "stalled", "misfit"}
    for r in rows:  # the m3 interval is the image of p2's 95 % interval under m3 = K3/p2
        assert float(r["m3_low"]) <= float(r["m3"]) <= float(r["m3_high"])
    table = _rows(tmp_path / "error_distribution.csv")
    assert [r["param"] for r in table] == [f"p{i}" for i in range(1, 11)]
    assert "sensor noise: none" in (tmp_path / "error_distribution.md").read_text().splitlines()[0]
    assert [r["param"] for r in _rows(tmp_path / "calibration.csv")][-1] == "m3"
    assert (tmp_path / "plots" / "sorted_p3.png").exists() and (tmp_path / "plots" / "sorted_m3.png").exists()
    assert list((tmp_path / "tb").glob("events.out.tfevents.*"))
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 0, "tensors": 0}).Reload()
    assert "estimation/sorted_m3" in events.Tags()["images"]  # plots and table beside the GN losses
    assert any(tag.startswith("estimation/error_distribution") for tag in events.Tags()["tensors"])
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["all_within_1pct"] >= 0.9  # noise-free: GN recovers all ten parameters
    assert summary["compiled_loops"] is True
    assert "within 1 %" in proc.stdout


def test_noise_label_names_both_noise_sources():
    from hybridqcm.data.sensor import build_sensor
    from hybridqcm.reports.estimate import noise_label

    assert noise_label(0.0, build_sensor(None)) == "none"
    assert noise_label(0.05, build_sensor(None)) == "source multiplicative σ = 0.05"
    additive = build_sensor({"kind": "additive", "sigma": 0.01})
    assert noise_label(0.0, additive) == "additive noise 1 % of channel RMS"
    assert noise_label(0.02, additive) == "source multiplicative σ = 0.02; additive noise 1 % of channel RMS"


def test_exp10_hybrid_with_noise_and_denoiser(tiny_dataset, checkpoints, tmp_path):
    proc = _run_app(
        tmp_path,
        "experiment=exp10_hybrid",
        f"data.path={tiny_dataset}",
        "n_samples=8",
        f"cnn_ckpt={checkpoints['cnn']}",
        f"unet_ckpt={checkpoints['unet']}",
        f"cae_ckpt={checkpoints['cae']}",
        "noise_sigma=0.05",
        "seed=3",
        "plots=false",
        "restarts.count=1",
        "stages=[{name:completed,channels:all,max_iterations:2},{name:a3,channels:observed,max_iterations:5}]",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = _rows(tmp_path / "estimates.csv")
    with h5py.File(tiny_dataset) as f:
        true = f["test/params"][:8]
    for i, r in enumerate(rows):  # known parameters are echoed from the file, exactly
        assert float(r["p3"]) == true[i, 2] and float(r["p5"]) == true[i, 4]
        assert float(r["std_p3"]) == 0.0
        assert all(np.isfinite(float(r[f"p{j}"])) for j in range(1, 11))
    assert [r["param"] for r in _rows(tmp_path / "error_distribution.csv")] == [
        "p1",
        "p2",
        "p4",
        "p6",
        "p7",
        "p8",
        "p9",
        "p10",
    ]


def test_inference_without_params(files, tmp_path):
    proc = _run_app(
        tmp_path,
        "experiment=exp5_random_init",
        f"data.path={files['no_params']}",
        "stages=[{name:gn,channels:all,max_iterations:3}]",
        "restarts.count=0",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert len(_rows(tmp_path / "estimates.csv")) == 8
    assert not (tmp_path / "error_distribution.csv").exists()


# ---------------------------------------------------------------------------------------------- bad inputs
@pytest.mark.parametrize(
    "overrides, message",
    [
        (["n_samples=abc"], "n_samples='abc': give a whole number or null"),
        (["restarts.mass_factors=[1.0,big]"], "restarts.mass_factors[1]='big': give a number"),
        (["-m", "n_samples=2,abc"], "n_samples='abc': give a whole number or null"),  # a sweep: before any job
        (["+data.pathh=x.h5"], "unknown setting data.pathh='x.h5' (qcm-estimate does not use it)"),
    ],
)
def test_the_settings_schema_refuses_on_the_console_in_one_line(tiny_dataset, tmp_path, overrides, message):
    """Typed by estimation/settings.py's schema (registered as schema/estimate when the plan imports it). Two
    on the console; the others through the checks run_hydra_app makes before Hydra, in-process (the same
    ConfigError the console prints as its one line)."""
    args = ["experiment=exp5_random_init", f"data.path={tiny_dataset}", *overrides, f"hydra.run.dir={tmp_path}"]
    if overrides[0] in ("-m", "+data.pathh=x.h5"):
        main = "import hybridqcm.estimation.settings; from hybridqcm.apps.estimate import main; main()"
        proc = subprocess.run([sys.executable, "-c", main, *args], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2 and proc.stderr.startswith(f"error: {message}"), proc.stderr[-2000:]
        assert len(proc.stderr.strip().splitlines()) == 1
    else:
        import hybridqcm.estimation.settings  # noqa: F401 - registers schema/estimate, as in the console run
        from hybridqcm.apps.common import check_task_name_overrides
        from hybridqcm.config import check_schema_overrides

        with pytest.raises(ConfigError) as error:
            check_experiment_overrides(args, "estimate")
            check_schema_overrides(args, "estimate")
            check_task_name_overrides(args)
        assert str(error.value).startswith(message) and "\n" not in str(error.value), error.value
    assert not (tmp_path / "estimates.csv").exists()


def test_unknown_and_training_experiments(tmp_path):
    with pytest.raises(ConfigError, match="unknown experiment 'nope'.*qcm-estimate experiments: .*exp5_random_init"):
        check_experiment_overrides(["experiment=nope"], "estimate")
    with pytest.raises(ConfigError, match="'exp2_physics' is a qcm-train experiment.*run it with qcm-train"):
        check_experiment_overrides(["experiment=exp2_physics"], "estimate")
    check_experiment_overrides(["experiment=exp8_occupant_only", "n_samples=3"], "estimate")  # fine
    proc = _run_app(tmp_path, "experiment=exp1_labelled")
    assert proc.returncode == 2 and "'exp1_labelled' is a qcm-train experiment" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not (tmp_path / "estimates.csv").exists()


def test_missing_and_wrong_kind_checkpoints(files, checkpoints, tmp_path):
    base = ["experiment=exp6_cnn_init", f"data.path={files['good']}"]
    with pytest.raises(ConfigError, match=r"cnn_ckpt=.*missing\.ckpt: checkpoint file does not exist"):
        validate(_cfg(base + [f"cnn_ckpt={tmp_path / 'missing.ckpt'}"]))
    with pytest.raises(ConfigError, match="cnn_ckpt=.*CompletionUNet checkpoint, but cnn needs"):
        validate(_cfg(base + [f"cnn_ckpt={checkpoints['unet']}"]))
    with pytest.raises(ConfigError, match="unet_ckpt=.*DenoisingAutoencoder"):
        validate(
            _cfg(
                [
                    "experiment=exp10_hybrid",
                    f"data.path={files['good']}",
                    f"cnn_ckpt={checkpoints['cnn']}",
                    f"unet_ckpt={checkpoints['cae']}",
                ]
            )
        )
    with pytest.raises(ConfigError, match="give cnn_ckpt=PATH"):
        validate(_cfg(base))
    proc = _run_app(tmp_path, *base, f"cnn_ckpt={tmp_path / 'missing.ckpt'}")
    assert proc.returncode == 2 and "missing.ckpt" in proc.stderr and "Traceback" not in proc.stderr


def test_missing_channel_nan_and_window(files, tiny_dataset):
    with pytest.raises(DatasetError, match=r"no_road\.h5.*lacks dataset 'road'"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={files['no_road']}"]))
    cfg = _cfg(["experiment=exp5_random_init", f"data.path={files['nan']}"])
    with pytest.raises(DatasetError, match=r"nan\.h5.*/test/accel.*non-finite.*\(3, 17, 0\)"):
        build_inputs(cfg, validate(cfg))
    with pytest.raises(DatasetError, match=r"n_steps = 600 steps but /test/accel stores 512"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "n_steps=600"]))
    with pytest.raises(DatasetError, match="split 'val' not found"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "data.split=val"]))
    with pytest.raises(DatasetError, match="does not exist"):
        validate(_cfg(["experiment=exp5_random_init", "data.path=/nonexistent/file.h5"]))
    with pytest.raises(ConfigError, match="noise_sigma"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "noise_sigma=-1"]))
    with pytest.raises(ConfigError, match=r"restarts\.batch must be an integer >= 1, got 0"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "restarts.batch=0"]))
    with pytest.raises(ConfigError, match=r"restarts\.failed must be an integer >= 0, got -1"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "restarts.failed=-1"]))
    with pytest.raises(ConfigError, match=r"restarts\.far_from_start must be null or a number > 0, got -0\.5"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "restarts.far_from_start=-0.5"]))
    with pytest.raises(ConfigError, match=r"restarts\.around='nearby': choose auto, start or reference"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "restarts.around=nearby"]))
    for dynamics, around in (("exact", "reference"), ("euler", "start")):  # auto: the source's protocol on Euler
        plan = validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", f"dynamics={dynamics}"]))
        assert plan["restarts_around"] == around
    with pytest.raises(ConfigError, match=r"solver\.decrement_tol must be null or a finite number >= 0, got -1"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "solver.decrement_tol=-1"]))
    with pytest.raises(ConfigError, match=r"vehicle_prior\.rel_std=-0\.3: must be null or a finite number > 0"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "vehicle_prior.rel_std=-0.3"]))
    with pytest.raises(ConfigError, match=r"vehicle_prior\.params: 'p11' is not a parameter name"):
        validate(_cfg(["experiment=exp5_random_init", f"data.path={tiny_dataset}", "vehicle_prior.params=[p3,p11]"]))
    with pytest.raises(DatasetError, match="no 'params'.*known_source=reference"):
        validate(_cfg(["experiment=exp7_known_p3p5", f"data.path={files['no_params']}", "init.cnn=false"]))


def test_vehicle_prior_is_the_reference_vehicle_on_the_listed_unknowns(tiny_dataset):
    """Mean p_ref and std rel_std x p_ref on the listed parameters the model has; known ones and p1, p2
    (not listed) carry no prior; the seat model has none of the default list; off with rel_std=null."""
    from hybridqcm.estimation.runner import build_refinement
    from hybridqcm.physics import reference_params

    base = ["experiment=exp10_hybrid", f"data.path={tiny_dataset}", "init.cnn=false", "dynamics=exact"]
    cfg = _cfg(base)
    refinement = build_refinement(cfg, validate(cfg))
    mean, precision = refinement.param_prior
    p_ref = reference_params()
    listed = torch.tensor([False, False, False, True, False, True, True, True, True, True])  # p3, p5 known
    torch.testing.assert_close(mean[:10], torch.where(listed, p_ref, 0.0))
    torch.testing.assert_close(precision[:10], torch.where(listed, (0.3 * p_ref) ** -2, 0.0))
    assert (precision[10:] == 0).all()  # never on the initial state
    off = _cfg([*base, "vehicle_prior.rel_std=null"])
    assert build_refinement(off, validate(off)).param_prior is None
    seat = _cfg(
        ["experiment=occupant_roadfree", f"data.path={tiny_dataset}", "dynamics=exact", "occupant.models=[rigid]"]
    )
    seat.delay = None
    assert build_refinement(seat, validate(seat)).param_prior is None
    # exp 10's extra attempts for wrong basins: the exact model only (the Euler reproduction keeps its protocol)
    assert refinement.restarts.failed == 8
    euler = _cfg(["experiment=exp10_hybrid", f"data.path={tiny_dataset}", "init.cnn=false", "dynamics=euler"])
    assert build_refinement(euler, validate(euler)).restarts.failed == 0


def test_cnn_window_longer_than_file(files, checkpoints):
    # the CNN reads 128 steps; the file stores 160: fine. With n_steps beyond the file: an error naming both.
    plan = validate(_cfg(["experiment=exp6_cnn_init", f"data.path={files['good']}", f"cnn_ckpt={checkpoints['cnn']}"]))
    assert plan["n_read_steps"] == 128
    with pytest.raises(DatasetError, match="n_steps = 200 steps but /test/accel stores 160"):
        validate(
            _cfg(
                [
                    "experiment=exp6_cnn_init",
                    f"data.path={files['good']}",
                    f"cnn_ckpt={checkpoints['cnn']}",
                    "n_steps=200",
                ]
            )
        )


@pytest.mark.parametrize(
    "name", ["exp5_random_init", "exp6_cnn_init", "exp7_known_p3p5", "exp8_occupant_only", "exp10_hybrid"]
)
def test_experiments_compose(name):
    cfg = _cfg([f"experiment={name}"])
    assert cfg.task_name == name and cfg.experiment_name == name.split("_")[0]
    assert len(cfg.stages) >= 1 and cfg.solver.method == "gauss_newton"


def test_the_jackknife_test_reaches_the_rigid_candidate_and_not_the_body_ones(tiny_dataset):
    """intervals.jackknife_test applies to the rigid model (plain, and as a candidate of the selection with and
    without the delay, restarts too); a body model keeps the uncorrected jackknife (plan_occupant._surplus_kept)."""
    from hybridqcm.estimation.runner import build_refinement

    cfg = _cfg(["experiment=occupant_roadfree", f"data.path={tiny_dataset}", "intervals.jackknife_test=0.01"])
    selection = build_refinement(cfg, validate(cfg))
    refinements = {**selection.all_models, **{f"{k} rescue": v for k, v in selection.rescue.items()}}
    assert len(refinements) == 12
    for name, refinement in refinements.items():
        wanted = 0.01 if name.startswith("rigid") else None
        last = refinement.stages[-1].solver.config  # the stage whose intervals are reported
        assert (last.covariance, last.jackknife_test) == ("robust_jackknife", wanted), name
        assert all(s.solver.config.jackknife_test in (wanted, 0.05) for s in refinement.stages[:-1])  # not used there
    plain = _cfg(["experiment=occupant_roadfree", f"data.path={tiny_dataset}", "occupant.models=[rigid]"])
    plain.delay = None
    assert build_refinement(plain, validate(plain)).stages[-1].solver.config.jackknife_test == 0.05


def test_torch_kernels_give_the_compiled_loops_answer(tmp_path, monkeypatch):
    """The path a GPU takes (torch's kernels, HYBRIDQCM_KERNELS=torch) against the CPU's compiled loops, a whole
    noisy run (exp 8: noise model, intervals): the same statuses, every estimate within a thousandth of its
    standard deviation (measured: 4e-5 of it, and 1.5e-5 relative: fits end at the solver's tolerance, so
    rtol=1e-7 would not hold). tests/test_front_gpu.py holds a GPU run to the same rule."""
    from conftest import app_in_process, assert_same_answer, make_foreign
    from hybridqcm.estimation._kernels import compiled_loops

    if not compiled_loops():
        pytest.skip("numba absent: only torch's kernels here")
    data = tmp_path / "foreign.h5"
    make_foreign(data, n=8, seed=3)
    overrides = [
        "experiment=exp8_occupant_only",
        "n_samples=8",
        "noise_sigma=0.05",
        "init.cnn=false",
        f"data.path={data}",
        "batch_size=4",
        "progress=false",
        "plots=false",
        "tensorboard=false",
    ]
    summary = app_in_process("estimate", tmp_path / "compiled", *overrides)
    assert summary["compiled_loops"]
    monkeypatch.setenv("HYBRIDQCM_KERNELS", "torch")
    assert not app_in_process("estimate", tmp_path / "torch", *overrides)["compiled_loops"]
    compiled, torch_run = tmp_path / "compiled" / "estimates.csv", tmp_path / "torch" / "estimates.csv"
    assert_same_answer(torch_run, compiled, std_fraction=1e-3)
    with pytest.raises(AssertionError, match="estimates apart"):  # the rule bites: these runs are not bit-equal
        assert_same_answer(torch_run, compiled, rtol=1e-7)


def test_assert_same_answer_tells_a_different_answer_apart(tmp_path):
    """conftest.assert_same_answer, the rule the GPU and kernel tests use: a move within a thousandth of the std
    passes; another status, a NaN against a number, or a move beyond rtol without std_fraction does not."""
    from conftest import assert_same_answer

    def write(name, rows):
        path = tmp_path / name
        with open(path, "w", newline="") as handle:
            out = csv.writer(handle)
            out.writerow(["index", "p1", "status", "std_p1", "m3", "m3_std"])
            out.writerows(rows)
        return path

    diverged = [1, "nan", "diverged", "nan", 70.0, 1.0]
    reference = write("ref.csv", [[0, 1.0, "converged", 0.1, 80.0, 1.0], diverged])
    moved = write("moved.csv", [[0, 1.0 + 1e-5, "converged", 0.1, 80.0 + 1e-4, 1.0], diverged])
    assert_same_answer(moved, reference, std_fraction=1e-3)
    with pytest.raises(AssertionError, match="2 estimates apart"):
        assert_same_answer(moved, reference)
    cases = {
        "status.csv": [[0, 1.0, "misfit", 0.1, 80.0, 1.0], diverged],
        "nan.csv": [[0, 1.0, "converged", 0.1, 80.0, 1.0], [1, 2.0, "diverged", "nan", 70.0, 1.0]],
        "far.csv": [[0, 1.01, "converged", 0.1, 80.0, 1.0], diverged],
    }
    for name, rows in cases.items():
        with pytest.raises(AssertionError):
            assert_same_answer(write(name, rows), reference, std_fraction=1e-3)
