"""The SBI peer (estimation/sbi_peer.py): closed-form posterior recovery, safe save/load, missing extra."""

from __future__ import annotations

import math
import sys

import pytest
import torch

pytest.importorskip("sbi")

from hybridqcm.errors import CheckpointError, ConfigError  # noqa: E402
from hybridqcm.estimation.sbi_evaluation import central_interval, evaluation_row  # noqa: E402
from hybridqcm.estimation.sbi_peer import PeerSettings, SBIPeer, import_sbi  # noqa: E402
from hybridqcm.estimation.sbi_training import TrainSettings, train_peer  # noqa: E402

WINDOW = 32
SMALL = dict(
    window=WINDOW,
    features=6,
    cnn_channels=(8,),
    cnn_kernels=(5,),
    cnn_strides=(2,),
    cnn_hidden=(32,),
    hidden_features=24,
    num_transforms=2,
)


def _toy(n: int, generator: torch.Generator):
    """Linear-Gaussian simulator in θ = log(p1, p2): a3(t) = G θ + σ ε, a2(t) = cos(ω t) (a fixed reference
    with constant RMS, so the peer's per-sample scaling by a2's RMS is a constant). Prior θ ~ N(m0, s0² I)."""
    t = torch.arange(WINDOW, dtype=torch.float64)
    G = torch.stack([torch.sin(2 * math.pi * t / WINDOW), torch.cos(2 * math.pi * 3 * t / WINDOW)], 1)  # [T, 2]
    m0, s0, sigma = torch.tensor([2.0, 7.0], dtype=torch.float64), 0.3, 0.6
    theta = m0 + s0 * torch.randn(n, 2, generator=generator, dtype=torch.float64)
    accel = torch.zeros(n, WINDOW, 3, dtype=torch.float64)
    accel[..., 0] = theta @ G.T + sigma * torch.randn(n, WINDOW, generator=generator, dtype=torch.float64)
    accel[..., 1] = torch.cos(2 * math.pi * 5 * t / WINDOW)
    accel[..., 2] = 1.0
    params = torch.ones(n, 10, dtype=torch.float64)
    params[:, :2] = theta.exp()
    # closed form: precision Λ = I/s0² + GᵀG/σ², mean Λ⁻¹ (Gᵀ a3/σ² + m0/s0²)
    precision = torch.eye(2, dtype=torch.float64) / s0**2 + G.T @ G / sigma**2
    cov = torch.linalg.inv(precision)
    mean = (accel[..., 0] @ G / sigma**2 + m0 / s0**2) @ cov.T
    return accel.float(), params, mean, cov.diagonal().sqrt(), s0


@pytest.fixture(scope="module")
def trained_toy():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small layers: one thread is many times faster than two fighting over a loaded CPU
    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(0)
    accel, params, _, _, _ = _toy(3000, generator)
    peer = SBIPeer.fit_spaces(PeerSettings(**SMALL, flow="maf"), accel, params)
    recipe = TrainSettings(
        epochs=25, max_seconds=None, batch_size=100, lr=3e-3, noise_min=1e-6, noise_max=1e-6, shift=False, flip=False
    )
    try:
        train_peer(peer, accel, params, recipe, log=lambda _: None)
    finally:
        torch.set_num_threads(threads)
    return peer


def test_peer_recovers_the_closed_form_gaussian_posterior(trained_toy):
    peer = trained_toy
    accel, params, mean, std, s0 = _toy(200, torch.Generator().manual_seed(1))
    torch.manual_seed(2)
    theta = peer.sample_params(2000, peer.inputs_of(accel)).log()  # [S, B, 2]
    assert float(std.max()) < 0.5 * s0  # the data are informative: the check is not the prior's
    mean_err = (theta.mean(0) - mean).abs() / std  # in units of the exact posterior std
    assert float(mean_err.mean()) < 0.25, mean_err.mean(0)
    ratio = theta.std(0).mean(0) / std
    assert torch.all((ratio > 0.8) & (ratio < 1.25)), ratio
    # calibrated: about 95 % of the truths inside the central 95 % interval
    low, high = central_interval(theta)
    truth = params[:, :2].log()
    coverage = ((low <= truth) & (truth <= high)).double().mean()
    assert 0.88 <= float(coverage) <= 0.99


def test_save_load_gives_identical_samples_with_a_fixed_seed(trained_toy, tmp_path):
    peer = trained_toy
    accel = _toy(16, torch.Generator().manual_seed(3))[0]
    x = peer.inputs_of(accel)
    torch.manual_seed(7)
    before = peer.sample_batched((50,), x)
    path = peer.save(tmp_path / "posterior.pt")
    raw = torch.load(path, weights_only=True)  # tensors and plain data only
    assert raw["hybridqcm_class"] == "SBIPeer" and raw["hyper_parameters"]["latent_dim"] == 2
    loaded = SBIPeer.load(path)
    torch.manual_seed(7)
    after = loaded.sample_batched((50,), x)
    assert torch.equal(before, after)


class _Payload:
    def __reduce__(self):
        return (print, ("code ran",))


def test_load_refuses_pickled_objects_and_foreign_settings(trained_toy, tmp_path):
    bad = tmp_path / "payload.pt"
    torch.save({"hybridqcm_class": "SBIPeer", "x": _Payload()}, bad)
    with pytest.raises(CheckpointError, match="refused"):
        SBIPeer.load(bad)
    state = trained_toy.checkpoint()
    state["hyper_parameters"] = {**state["hyper_parameters"], "surprise": 1}
    torch.save(state, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="surprise"):
        SBIPeer.load(tmp_path / "foreign.pt")
    state = trained_toy.checkpoint()
    state["hybridqcm_class"] = "LabelledEstimator"
    torch.save(state, tmp_path / "cnn.pt")
    with pytest.raises(CheckpointError, match="not an SBIPeer"):
        SBIPeer.load(tmp_path / "cnn.pt")


def test_a_direction_constant_on_the_prior_is_dropped():
    """Thesis prior: p1/p2 = C3/K3 for every sample, so (p1, p2) has one free direction; mapping back is exact."""
    generator = torch.Generator().manual_seed(0)
    m3 = 30 + 120 * torch.rand(64, generator=generator, dtype=torch.float64)
    params = torch.ones(64, 10, dtype=torch.float64)
    params[:, 0], params[:, 1] = 615.0 / m3, 98935.0 / m3
    params[:, 2] = 0.3 * (1 + 0.1 * torch.randn(64, generator=generator, dtype=torch.float64))
    accel = torch.randn(64, WINDOW, 3, generator=generator)
    peer = SBIPeer.fit_spaces(PeerSettings(**SMALL, params=("p1", "p2")), accel, params)
    assert peer.settings.latent_dim == 1
    z = peer.normalise(params)
    assert torch.allclose(peer.from_latent(peer.to_latent(z)), z, atol=1e-12)
    assert torch.allclose(peer.to_params(z), params[:, :2], rtol=1e-12)
    assert SBIPeer.fit_spaces(PeerSettings(**SMALL, params=("p1", "p3")), accel, params).settings.latent_dim == 2


def test_evaluation_row_counts_coverage_and_errors():
    true = torch.ones(4, 10, dtype=torch.float64)
    true[:, 1] = torch.tensor([100.0, 200.0, 400.0, 1000.0])
    summary = {
        "median": true[:, :2] * 1.1,
        "low": true[:, :2] * torch.tensor([[0.9], [0.9], [1.2], [0.9]]),
        "high": true[:, :2] * 1.3,
    }
    K3 = 1000.0
    summary.update(
        m3_median=K3 / summary["median"][:, 1], m3_low=K3 / summary["high"][:, 1], m3_high=K3 / summary["low"][:, 1]
    )
    row = evaluation_row(summary, true, ["p1", "p2"], K3=K3)
    assert row["p2_coverage_95"] == pytest.approx(0.75) and row["m3_coverage_95"] == pytest.approx(0.75)
    assert row["p2_mean_rel_err"] == pytest.approx(0.1)
    assert row["m3_mean_rel_err"] == pytest.approx(1 - 1 / 1.1)
    assert row["p2_interval_median_rel_width"] == pytest.approx(0.4)


def test_missing_extra_is_one_line_naming_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "sbi", None)  # `import sbi` now raises ImportError
    with pytest.raises(ConfigError, match=r"optional extra 'sbi'.*\.\[sbi\]") as info:
        import_sbi()
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="optional extra"):
        SBIPeer(PeerSettings(**SMALL, latent_dim=1))


def test_qcm_sbi_bad_input_is_one_line_before_any_work(tmp_path):
    import os
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root / "src")}
    run = subprocess.run(
        [sys.executable, "-m", "hybridqcm.apps.sbi", "evaluate", f"data.path={root / 'missing.h5'}"]
        + [f"hydra.run.dir={tmp_path / 'run'}"],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
    )
    assert run.returncode == 2
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "data.path=" in lines[0] and "does not exist" in lines[0], run.stderr
    assert not (tmp_path / "run" / "sbi_metrics.csv").exists()
