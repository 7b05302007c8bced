"""Networks (weight counts, shapes), physics residual, LightningModules (fast_dev_run, checkpoint round trip, inference API)."""

from __future__ import annotations

import lightning as L
import pytest
import torch

from conftest import tiny_datamodule
from hybridqcm.data.simulate import simulate_samples
from hybridqcm.errors import CheckpointError
from hybridqcm.models import (
    CompletionUNet,
    DenoisingAutoencoder,
    DenoisingCAE,
    LabelledEstimator,
    ParameterCNN,
    PhysicsResidualEstimator,
    SpectralCNN,
    UNet1d,
    count_parameters,
    least_squares_p12,
    physics_residual,
    physics_residual_loss,
)
from hybridqcm.models.checkpoint import load_module
from hybridqcm.models.physics_losses import balanced_residual_loss
from hybridqcm.models.schedule import one_cycle_lr
from hybridqcm.physics import RoadProfile, build_prior
from test_datamodules import make_tiny_dataset

SMALL_CNN = {
    "_target_": "hybridqcm.models.networks.ParameterCNN",
    "channels": [8, 8],
    "kernels": [10, 5],
    "hidden": [16, 8],
}
SMALL_SPECTRAL = {"_target_": "hybridqcm.models.networks.SpectralCNN", "channels": [6], "kernels": [9], "hidden": [8]}
SMALL_CAE = {"_target_": "hybridqcm.models.networks.DenoisingCAE", "channels": [4, 8], "kernel_size": 9}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("data") / "tiny.h5")


@pytest.fixture(scope="module")
def clean_batch():
    generator = torch.Generator().manual_seed(1)
    return simulate_samples(
        build_prior("thesis"), RoadProfile(n_waves=300), torch.tensor([0, 1, 2, 1]), 300, 0.01, 30 / 3.6, generator
    )


def _aux(arrays):
    acc, vel, disp = arrays["accel"], arrays["vel"], arrays["disp"]
    return torch.stack([acc[..., 0], vel[..., 0], vel[..., 1], disp[..., 0], disp[..., 1]], 1)


# -- networks ---------------------------------------------------------------------------------------------
def test_reference_weight_counts():
    assert count_parameters(ParameterCNN(window=500)) == 1_361_332
    assert count_parameters(DenoisingCAE()) == 1_010_302
    assert 25_000 <= count_parameters(UNet1d()) <= 35_000


@pytest.mark.parametrize("n", [500, 512, 333])
def test_signal_networks_keep_length(n):
    x = torch.randn(2, 2, n)
    assert DenoisingCAE(channels=(4, 8), kernel_size=9)(x).shape == (2, 2, n)
    assert UNet1d()(x).shape == (2, 2, n)
    assert ParameterCNN(window=n, channels=(4, 4), hidden=(8,))(x).shape == (2, 2)


# -- physics residual -------------------------------------------------------------------------------------
def test_spectral_cnn_energies_are_each_filters_log_mean_square():
    """Against numpy's own convolution: filter i of the bank is sum_c w[i, c] (*) x_c + b_i over the valid part."""
    import numpy as np

    torch.manual_seed(0)
    net = SpectralCNN(window=120, channels=(5,), kernels=(11,), hidden=(4,), remove_mean=False).double()
    x = torch.randn(3, 2, 120, dtype=torch.float64) + 0.5
    conv = net.features[0]
    w, b = conv.weight.detach().numpy(), conv.bias.detach().numpy()
    expected = np.empty((3, 5))
    for s in range(3):
        for i in range(5):
            # torch's conv1d is a cross-correlation: numpy's convolve with the kernel reversed.
            y = sum(np.convolve(x[s, c].numpy(), w[i, c, ::-1], mode="valid") for c in range(2)) + b[i]
            expected[s, i] = np.log(np.mean(y**2) + 1e-6)
    np.testing.assert_allclose(net.band_energies(x).detach().numpy(), expected, rtol=1e-12)


def test_spectral_cnn_does_not_care_where_a_stationary_window_is_cut():
    """A periodic signal whose period divides the window and the filters' valid length gives the same output
    at every cut:
    the estimate of a window cut mid-drive does not depend on the phase at which it starts. The source's
    flattening CNN does not have this property (checked as the negative control)."""
    torch.manual_seed(0)
    period, kernel, window = 20, 21, 120  # window 6 periods (its mean is the signal's), valid length 5
    t = torch.arange(window + period, dtype=torch.float64)
    signal = torch.stack(
        [
            torch.sin(2 * torch.pi * t / period) + 0.3 * torch.cos(6 * torch.pi * t / period),
            torch.cos(2 * torch.pi * t / period + 0.4),
        ]
    )
    cuts = torch.stack([signal[:, s : s + window] for s in range(0, period, 3)])
    spectral = SpectralCNN(window=window, channels=(8,), kernels=(kernel,), hidden=(16,)).double()
    out = spectral(cuts)
    assert torch.allclose(out, out[:1].expand_as(out), atol=1e-12, rtol=0)
    flat = ParameterCNN(window=window, channels=(4, 4), hidden=(8,)).double()
    out = flat(cuts)
    assert not torch.allclose(out, out[:1].expand_as(out), atol=1e-6, rtol=0)


def test_spectral_cnn_ignores_a_constant_sensor_bias():
    torch.manual_seed(0)
    x = torch.randn(4, 2, 200, dtype=torch.float64)
    bias = torch.tensor([0.3, -1.2], dtype=torch.float64)[:, None]
    net = SpectralCNN(window=200, channels=(6,), kernels=(25,), hidden=(8,)).double()
    assert torch.allclose(net(x + bias), net(x), atol=1e-12, rtol=0)
    net.remove_mean = False  # the control: without the mean removed, the bias is seen
    assert not torch.allclose(net(x + bias), net(x), atol=1e-3, rtol=0)


def test_spectral_cnn_refuses_bad_sizes():
    with pytest.raises(ValueError, match="shorter than the longest kernel 25"):
        SpectralCNN(window=20, kernels=(25,), channels=(4,))
    with pytest.raises(ValueError, match="equal lengths"):
        SpectralCNN(channels=(4, 4), kernels=(9,))
    with pytest.raises(ValueError, match=r"expects \[B, 2, 500\]"):
        SpectralCNN()(torch.zeros(1, 2, 400))


def test_physics_residual_zero_for_true_parameters(clean_batch):
    aux, p = _aux(clean_batch), clean_batch["params"][:, :2]
    r = physics_residual(p, aux)
    assert r.abs().max() < 1e-10 * aux[:, 0].abs().max()
    assert physics_residual_loss(p, aux).max() < 1e-25
    assert physics_residual_loss(p * 1.01, aux).min() > 1e-8  # and not zero elsewhere
    assert torch.allclose(least_squares_p12(aux), p, rtol=1e-9)


def test_physics_residual_gradient_matches_finite_differences(clean_batch):
    aux = _aux(clean_batch)
    p = (clean_batch["params"][:, :2] * torch.tensor([1.05, 0.97], dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: physics_residual_loss(q, aux).sum(), (p,), eps=1e-6, atol=1e-7, rtol=1e-4)
    assert torch.autograd.gradcheck(
        lambda q: balanced_residual_loss(q, aux).sum(), (p,), eps=1e-6, atol=1e-7, rtol=1e-4
    )


def test_balanced_residual_weighs_p1_and_p2_alike(clean_batch):
    aux, p = _aux(clean_batch), clean_batch["params"][:, :2]
    assert balanced_residual_loss(p, aux).max() < 1e-20
    for scale in ([1.01, 1.0], [1.0, 1.01]):
        off = p * torch.tensor(scale, dtype=torch.float64)
        assert torch.allclose(balanced_residual_loss(off, aux), torch.full((4,), 1e-4, dtype=torch.float64), rtol=1e-3)
    # The plain energy weighs a 1 % error of p1 (damping) far less than one of p2 (stiffness).
    ratio = physics_residual_loss(p * torch.tensor([1.0, 1.01], dtype=torch.float64), aux) / physics_residual_loss(
        p * torch.tensor([1.01, 1.0], dtype=torch.float64), aux
    )
    assert (ratio > 10).all()


# -- modules ------------------------------------------------------------------------------------------------
def _modules():
    return [
        LabelledEstimator(net=SMALL_CNN, train_noise_max=0.1, plot_every_n_epochs=0),
        PhysicsResidualEstimator(net=SMALL_CNN, lr_schedule={"max_lr": 1e-3}, plot_every_n_epochs=0),
        DenoisingAutoencoder(net=SMALL_CAE, plot_every_n_epochs=0),
        CompletionUNet(net={"_target_": "hybridqcm.models.networks.UNet1d", "filters": [2, 4]}, plot_every_n_epochs=0),
        PhysicsResidualEstimator(net=SMALL_SPECTRAL, residual_norm="balanced", plot_every_n_epochs=0),
    ]


@pytest.mark.parametrize("index", range(5))
def test_fast_dev_run_every_module(tiny, index):
    module = _modules()[index]
    dm = tiny_datamodule(tiny, module, noise_sigma=0.1 if isinstance(module, DenoisingAutoencoder) else 0.0)
    trainer = L.Trainer(
        fast_dev_run=True, accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False
    )
    trainer.fit(module, dm)
    assert bool(module.norm_fitted)
    trainer.test(module, dm)
    results = module.test_results
    if hasattr(module, "estimate"):
        assert results["pred"].shape == (16, 2) and results["true"].shape == (16, 2)
    else:
        assert results["mse"].shape == (16, 2) and torch.isfinite(results["mse"]).all()


@pytest.mark.parametrize("index", range(5))
def test_checkpoint_round_trip_and_inference_api(tiny, tmp_path, index):
    module = _modules()[index]
    dm = tiny_datamodule(tiny, module)
    trainer = L.Trainer(
        max_steps=2,
        limit_val_batches=1,
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
    )
    trainer.fit(module, dm)
    path = tmp_path / "model.ckpt"
    trainer.save_checkpoint(path)
    cls = type(module)
    loaded = cls.load_from_checkpoint(path, map_location="cpu")
    assert torch.equal(loaded.in_std, module.in_std) and bool(loaded.norm_fitted)
    dm.setup("test")
    test = dm.data_test.tensors
    x = test["x"][:5].double()
    if isinstance(module, (LabelledEstimator, PhysicsResidualEstimator)):
        a3, a2 = x[:, 0], x[:, 1]
        p = loaded.estimate(a3, a2)
        assert p.dtype == torch.float64 and p.shape == (5, 2) and (p > 0).all()
        assert torch.equal(p, module.estimate(a3, a2))
        with pytest.raises(ValueError, match="window"):
            loaded.estimate(a3[:, :100], a2[:, :100])
        # Only the first `window` steps count.
        longer = torch.cat([x, x], -1)
        assert torch.equal(loaded.estimate(longer[:, 0], longer[:, 1]), p)
    elif isinstance(module, DenoisingAutoencoder):
        out = loaded.denoise(x[..., :333])
        assert out.shape == (5, 2, 333) and out.dtype == torch.float64
        assert torch.equal(out, module.denoise(x[..., :333]))
    else:
        a3, pu_u = x[:, 0], x[:, 1]
        out = loaded.complete(a3[:, :300], pu_u[:, :300])
        assert out.shape == (5, 2, 300) and torch.equal(out, module.complete(a3[:, :300], pu_u[:, :300]))
    # A checkpoint of another class is refused with a clear message.
    other = DenoisingAutoencoder if cls is not DenoisingAutoencoder else CompletionUNet
    with pytest.raises(CheckpointError, match=f"holds a {cls.__name__} model, expected {other.__name__}"):
        load_module(str(path), other)


def test_estimate_is_scale_invariant_and_denoiser_attaches(tiny, tmp_path):
    module = LabelledEstimator(net=SMALL_CNN)
    dm = tiny_datamodule(tiny, module)
    dm.setup("fit")
    module.fit_normalisation(dm.stats_batch())
    x = dm.data_train.tensors["x"][:3].double()
    p = module.estimate(x[:, 0], x[:, 1])
    # The system is linear: a rougher road scales the accelerations, not the parameters.
    assert torch.allclose(module.estimate(4 * x[:, 0], 4 * x[:, 1]), p, rtol=1e-5)
    cae = DenoisingAutoencoder(net=SMALL_CAE)
    cae.fit_normalisation({"x": dm.stats_batch()["x"], "y": dm.stats_batch()["x"]})
    module.attach_denoiser(cae)
    assert module.denoiser is cae
    calls = []
    cae.register_forward_hook(lambda *args: calls.append(1))
    denoised = module.estimate(x[:, 0], x[:, 1])
    assert calls and denoised.shape == (3, 2) and not torch.equal(denoised, p)  # the CAE really runs first
    trainer = L.Trainer(
        max_steps=1,
        limit_val_batches=0,
        accelerator="cpu",
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
    )
    trainer.fit(module, dm)
    trainer.save_checkpoint(tmp_path / "m.ckpt")
    state = torch.load(tmp_path / "m.ckpt", weights_only=True)["state_dict"]
    assert not any(k.startswith("denoiser.") for k in state)  # never saved with the estimator


def test_one_cycle_schedule_shape():
    assert one_cycle_lr(0.0, 1.0) == pytest.approx(1 / 25)
    assert one_cycle_lr(0.25, 1.0) == pytest.approx(1.0)
    assert one_cycle_lr(1.0, 1.0) == pytest.approx(1 / 25 / 1e4)
    assert one_cycle_lr(2.0, 1.0) == one_cycle_lr(1.0, 1.0)


def test_invalid_hyperparameters():
    with pytest.raises(ValueError, match="train_noise_max"):
        LabelledEstimator(net=SMALL_CNN, train_noise_max=-1)
    with pytest.raises(ValueError, match="target_transform"):
        LabelledEstimator(net=SMALL_CNN, target_transform="sqrt")
    with pytest.raises(ValueError, match="exactly"):
        PhysicsResidualEstimator(net=SMALL_CNN, target_channels=["p1", "p3"])
