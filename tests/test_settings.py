"""estimation/settings.py: configs/estimate.yaml as a structured config. The schema is held against the YAML
files themselves (every key typed, none left without its value), and refuses the bad inputs the hand parsing
refused before, each in one line naming the key and value."""

from __future__ import annotations

import dataclasses
import re
import typing

import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from hybridqcm.config import CONFIG_DIR, app_experiments, check_schema_overrides, schema_type
from hybridqcm.errors import ConfigError
from hybridqcm.estimation import settings
from hybridqcm.estimation.settings import EstimateSettings


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        return compose("estimate", overrides=list(overrides))


def _keys(data: dict, prefix: str = "") -> list[str]:
    out = []
    for key, value in data.items():
        if isinstance(value, dict) and schema_type(EstimateSettings, f"{prefix}{key}") not in (None, object):
            out += [f"{prefix}{key}"] + _keys(value, f"{prefix}{key}.")
        else:
            out.append(f"{prefix}{key}")
    return out


def _fields(schema, prefix: str = "") -> list[str]:
    out = []
    for item in dataclasses.fields(schema):
        kind = typing.get_type_hints(schema)[item.name]
        out += _fields(kind, f"{prefix}{item.name}.") if dataclasses.is_dataclass(kind) else [f"{prefix}{item.name}"]
    return out


def test_the_schema_types_every_key_of_estimate_yaml_and_its_experiments():
    files = [CONFIG_DIR / "estimate.yaml", *sorted((CONFIG_DIR / "apps" / "estimate" / "experiment").glob("*.yaml"))]
    assert len(files) == 1 + len(app_experiments("estimate")) > 5
    for path in files:
        data = {k: v for k, v in yaml.safe_load(path.read_text()).items() if k not in ("defaults", "hydra")}
        untyped = [key for key in _keys(data) if schema_type(EstimateSettings, key) is None]
        assert not untyped, (path.name, untyped)
    # ... and estimate.yaml gives every field its value (the schema holds types, no defaults of its own)
    data = yaml.safe_load((CONFIG_DIR / "estimate.yaml").read_text())
    given = set(_keys(data)) | {next(iter(entry)).split()[-1] for entry in data["defaults"] if isinstance(entry, dict)}
    assert set(_fields(EstimateSettings)) <= given, set(_fields(EstimateSettings)) - given
    assert OmegaConf.get_type(_compose()) is EstimateSettings


@pytest.mark.parametrize("name", app_experiments("estimate"))
def test_every_estimation_experiment_composes_against_the_schema(name):
    cfg = _compose(f"experiment={name}")
    assert OmegaConf.get_type(cfg) is EstimateSettings and cfg.task_name == name
    settings.check(cfg)


BAD = [
    # before: check_setting_types (tests/test_config.py, test_occupant.py, test_app_vehicles.py)
    (["n_samples=abc"], r"n_samples='abc': give a whole number or null"),
    (["batch_size=2.5"], r"batch_size=2.5: give a whole number"),
    (["noise_sigma=x"], r"noise_sigma='x': give a number"),
    (["plots=maybe"], r"plots='maybe': give true or false"),
    (["delay_max_ms=abc"], r"delay_max_ms='abc': give a whole number"),
    (["experiment=occupant_roadfree", "restarts.count=1.5"], r"restarts.count=1.5: give a whole number"),
    # before: not checked (a list's elements, a vehicle constant, one value of a sweep)
    (["restarts.mass_factors=[1.0,big]"], r"restarts.mass_factors\[1\]='big': give a number"),
    (["vehicle.C3=soft"], r"vehicle.C3='soft': give a number"),
    (["n_samples=4,many"], r"n_samples='many': give a whole number or null"),
    (["skip_windows.clip_samples=x"], r"skip_windows.clip_samples='x': give a whole number or null"),
    # before: check_known_keys, or Hydra's page ("Could not override ... Key 'pathh' is not in struct")
    (
        ["foo=1"],
        r"unknown setting foo=1 \(qcm-estimate does not use it\); known under the top level: \['K3', .*'x0_start'\]",
    ),
    (
        ["data.pathh=x.h5"],
        r"unknown setting data.pathh='x.h5' \(qcm-estimate does not use it\); known under data: "
        r"\['path', 'split'\]",
    ),
]


@pytest.mark.parametrize("overrides, message", BAD)
def test_bad_settings_are_refused_in_one_line_before_composing(overrides, message):
    with pytest.raises(ConfigError, match=f"^{message}$"):
        settings.check_overrides(overrides)
    with pytest.raises(ConfigError, match=f"^{message}$"):  # as the apps find the schema: schema/estimate
        check_schema_overrides(overrides, "estimate")
    with pytest.raises(ConfigCompositionException):  # the schema refuses it while Hydra composes, too
        _compose(*overrides)


@pytest.mark.parametrize(
    "override, message",
    [
        ("+data.pathh=x.h5", r"unknown setting data.pathh='x.h5' \(qcm-estimate does not use it\); known under data"),
        ("+foo=1", r"unknown setting foo=1 \(qcm-estimate does not use it\)"),
        ("+init.cnn_priors=network", r"unknown setting init.cnn_priors='network'"),
    ],
)
def test_keys_added_with_plus_are_refused_after_composing(override, message):
    settings.check_overrides([override])  # a new key: Hydra adds it to the schema's config ...
    cfg = _compose(override)
    with pytest.raises(ConfigError, match=f"^{message}"):  # ... and the check of the composed config names it
        settings.check(cfg)
    assert "\n" not in message


@pytest.mark.parametrize(
    "overrides, key, value",
    [
        (["n_samples=null"], "n_samples", None),
        (["n_samples=3"], "n_samples", 3),
        (["skip_windows.clip_samples=null"], "skip_windows.clip_samples", None),
        (["vehicle_prior.rel_std=null"], "vehicle_prior.rel_std", None),
        (["misfit_peer_factor=null"], "misfit_peer_factor", None),
        (["restarts.far_from_start=0.25"], "restarts.far_from_start", 0.25),
        (["init.cnn_prior=network"], "init.cnn_prior", "network"),
        (["noise_sigma=0"], "noise_sigma", 0.0),
        (["n_steps=max"], "n_steps", "max"),
        (["experiment=occupant_roadfree", "delay=5"], "delay", 5),
        (["experiment=occupant_roadfree", "delay=estimate"], "delay", "estimate"),
        (["input_margin=[2,3]"], "input_margin", [2, 3]),
        (["residual_weighting=spectral"], "residual_weighting", "spectral"),
        (["residual_weighting=true"], "residual_weighting", True),
        (["experiment=hcm_full_observation", "init.equation_error=seats"], "init.equation_error", "seats"),
        (["solver.max_iterations=7"], "solver.max_iterations", 7),
        (["+trainer.num_nodes=1"], "trainer.num_nodes", 1),
        (["seat=driver"], "seat", "driver"),
        (["data.path=${paths.data_dir}/other.h5"], "data.path", None),  # an interpolation: resolved later
    ],
)
def test_values_of_every_documented_kind_pass(overrides, key, value):
    settings.check_overrides(overrides)
    cfg = _compose(*overrides)
    settings.check(cfg)
    if value is not None or "null" in overrides[-1]:
        got = OmegaConf.select(cfg, key)
        assert (OmegaConf.to_container(got) if OmegaConf.is_config(got) else got) == value
        assert type(got) is type(value) or OmegaConf.is_config(got)


def test_a_config_not_composed_against_the_schema_is_checked_alike():
    """A plain config (the Python API's, a test's dict): the same refusals, by `check` alone."""
    plain = OmegaConf.to_container(_compose("experiment=exp5_random_init"), resolve=False)
    settings.check(OmegaConf.create(plain))
    for key, bad, message in [
        ("n_samples", "abc", "n_samples='abc': give a whole number or null"),
        ("plots", "maybe", "plots='maybe': give true or false"),
        ("pathh", "x", "unknown setting pathh='x' (qcm-estimate does not use it)"),
    ]:
        cfg = OmegaConf.create(plain)
        OmegaConf.update(cfg, key, bad, force_add=True)
        with pytest.raises(ConfigError, match=f"^{re.escape(message)}"):
            settings.check(cfg)
    cfg = OmegaConf.create(plain)
    cfg.init.equation_error = "maybe"  # the quarter car: true or false
    with pytest.raises(ConfigError, match=r"^init.equation_error='maybe': give true or false$"):
        settings.check(cfg)
    cfg.vehicle_model = "half_car"  # a half / full car also takes seats; its plan checks the value
    settings.check(cfg)


def test_overrides_the_schema_leaves_to_others_pass_the_pre_check():
    """Groups (their own schemas), Hydra's keys, deletions and flags: not the schema's to judge."""
    settings.check_overrides(
        [
            "experiment=exp8_occupant_only",
            "solver=levenberg_marquardt",
            "sensor.sigma=0.05",
            "trainer.devices=2",
            "hydra.run.dir=/tmp/x",
            "hydra/launcher=basic",
            "~seat",
            "--cfg",
            "job",
            "-m",
        ]
    )
