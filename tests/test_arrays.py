"""The README's Python API snippet, run as written on simulated recordings: the estimate of a noise-free
recording of the continuous-time model (another code path than the estimator's exact discretisation)
is close to the truth it was simulated with, and its interval holds the truth."""

import re

import numpy as np
import pytest
import torch

from conftest import REPO_ROOT
from hybridqcm.data.simulate import simulate_samples
from hybridqcm.physics.prior import build_prior
from hybridqcm.physics.road import RoadProfile
from hybridqcm.testing import synthetic_samples, train_tiny_checkpoints


def readme_snippet() -> str:
    """The first ```python block of the README's "Python API" section."""
    text = (REPO_ROOT / "README.md").read_text()
    section = text.split("## Python API", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert blocks, "README: the Python API section has no python block"
    return blocks[0]


@pytest.fixture(scope="module")
def recordings():
    """Two noise-free windows cut mid-drive (1-2 s after the start) from the continuous-time model."""
    generator = torch.Generator().manual_seed(3)
    prior = build_prior("thesis", h=0.01)
    samples = simulate_samples(
        prior, RoadProfile(), torch.tensor([0, 1]), 300, 0.01, 30 / 3.6, generator, physics="continuous",
        warmup_s=(1.0, 2.0),
    )  # fmt: skip
    return samples["accel"].numpy(), samples["road"].numpy(), samples["params"].numpy()


def test_the_readme_snippet_estimates_the_occupant_with_an_interval(recordings, tmp_path, capsys):
    accel, road, params = recordings
    checkpoints = train_tiny_checkpoints(tmp_path, synthetic_samples(32, n_steps=160, seed=0), steps=3, window=128)
    namespace = {"accel": accel, "road": road, "cnn_ckpt": checkpoints["cnn"]}
    exec(compile(readme_snippet(), "README.md (Python API)", "exec"), namespace)
    rows = namespace["rows"]
    K3 = float(namespace["cfg"].K3)
    truth_m3 = K3 / params[:, 1]
    assert [row["index"] for row in rows] == [0, 1]
    for row, true, m3 in zip(rows, params, truth_m3):
        assert row["status"] == "converged"
        np.testing.assert_allclose([row[f"p{i}"] for i in range(1, 11)], true, rtol=2e-2)
        assert abs(row["m3"] - m3) < 1e-4 * m3  # the occupant mass to 0.01 %
        assert row["m3_low"] <= m3 <= row["m3_high"]  # the 95 % interval holds the truth
        assert row["m3_high"] - row["m3_low"] < 1e-3 * m3
    printed = capsys.readouterr().out
    assert f"0: converged, m3 = {rows[0]['m3']:.2f} kg" in printed


def test_recordings_in_memory_get_one_line_errors(recordings):
    from hydra import compose, initialize_config_dir

    from hybridqcm.config import CONFIG_DIR
    from hybridqcm.errors import ConfigError
    from hybridqcm.estimation.arrays import estimate_recordings

    accel, road, _ = recordings
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        exp7 = compose("estimate", overrides=["experiment=exp7_known_p3p5"])
        exp5 = compose("estimate", overrides=["experiment=exp5_random_init"])
    with pytest.raises(ConfigError, match="known_source=reference"):
        estimate_recordings(exp7, accel, road)
    with pytest.raises(ConfigError, match=r"accel has shape \[300, 3\]"):
        estimate_recordings(exp5, accel[0], road)
    with pytest.raises(ConfigError, match="road=None"):
        estimate_recordings(exp5, accel, None)
    bad = accel.copy()
    bad[1, 5, 0] = np.nan
    with pytest.raises(ConfigError, match=r"<arrays>.*channel a3 has NaN/inf \(sample 1\)"):
        estimate_recordings(exp5, bad, road)
