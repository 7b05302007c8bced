"""HybridEstimator (networks from checkpoints) + GaussNewtonRefinement callback, end to end."""

import math

import lightning
import pytest
import torch

from hybridqcm.errors import CheckpointError
from hybridqcm.estimation.front import HybridEstimator, equation_error_params
from hybridqcm.estimation.refinement import GaussNewtonRefinement, GaussNewtonStage, RefinementSettings
from hybridqcm.estimation.restarts import Restarts
from hybridqcm.estimation.solver import GaussNewton, SolverConfig, SolverStatus
from hybridqcm.models.checkpoint import load_checkpoint
from hybridqcm.testing import synthetic_samples, train_tiny_checkpoints

H = 0.01


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Real (tiny, 3-step) checkpoints of the project's CNN, U-Net and CAE modules."""
    samples = synthetic_samples(32, n_steps=160, seed=0)
    return train_tiny_checkpoints(tmp_path_factory.mktemp("ckpt"), samples, steps=3, window=128)


@pytest.fixture(scope="module")
def batch():
    s = synthetic_samples(12, n_steps=160, seed=7)
    from hybridqcm.physics import reference_params

    g = torch.Generator().manual_seed(0)
    init = reference_params().expand(12, 10) * (1 + 0.1 * torch.randn(12, 10, generator=g, dtype=torch.float64))
    init[:, [2, 4]] = s["params"][:, [2, 4]]
    return {
        "accel": s["accel"],
        "road": s["road"],
        "pu": s["params"][:, 9] - s["params"][:, 8],
        "init": init,
        "index": torch.arange(12),
        "params": s["params"],
    }


def _loader(batch, size=6):
    keys = ("accel", "road", "pu", "init", "index")
    chunks = [{k: batch[k][i : i + size] for k in keys} for i in range(0, batch["accel"].shape[0], size)]
    return torch.utils.data.DataLoader(chunks, batch_size=None)


def _trainer(callback):
    return lightning.Trainer(
        accelerator="cpu",
        devices=1,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[callback],
        inference_mode=False,
    )


def test_equation_error_exact_on_clean_full_observation(batch):
    known = torch.zeros(10, dtype=torch.bool)
    p = equation_error_params(batch["accel"][:, :100], batch["road"][:, :100], H, batch["init"], known)
    torch.testing.assert_close(p, batch["params"], rtol=1e-8, atol=0)
    known[[2, 4]] = True
    forcing = batch["pu"][:, None] * batch["road"][:, :100]
    p = equation_error_params(batch["accel"][:, :100], forcing, H, batch["init"], known, scaled_road=True)
    torch.testing.assert_close(p, batch["params"], rtol=1e-8, atol=0)


def test_hybrid_end_to_end_with_tiny_checkpoints(checkpoints, batch, tmp_path):
    module = HybridEstimator(
        cnn_ckpt=str(checkpoints["cnn"]),
        unet_ckpt=str(checkpoints["unet"]),
        cae_ckpt=str(checkpoints["cae"]),
        observed=["a3"],
        n_steps=100,
        h=H,
        equation_error_init=True,
        known=["p3", "p5"],
        pu_known=True,
    )
    assert module.completes and module.required_steps() == 128
    known = torch.zeros(10, dtype=torch.bool)
    known[[2, 4]] = True
    stages = [
        GaussNewtonStage("completed", GaussNewton(SolverConfig(max_iterations=3)), "all"),
        GaussNewtonStage("observed", GaussNewton(SolverConfig(max_iterations=8)), "observed", n_steps=60),
    ]
    callback = GaussNewtonRefinement(
        stages, RefinementSettings(known=known, pu_known=True, h=H, log_dir=tmp_path / "tb"), restarts=Restarts(count=1)
    )
    _trainer(callback).predict(module, dataloaders=_loader(batch), return_predictions=False)
    out = callback.collect()
    r = out.result
    assert r.params.shape == (12, 10) and torch.equal(out.index, torch.arange(12))
    assert not torch.isnan(r.params).any() and not torch.isnan(r.std).any()
    assert torch.equal(r.params[:, [2, 4]], batch["init"][:, [2, 4]])  # known: bit-identical
    assert set(r.status.tolist()) <= {s.value for s in SolverStatus}
    assert set(out.stage_loss) == {"completed", "observed"} and len(out.stage_loss["observed"]) >= 2
    assert list((tmp_path / "tb").glob("events.out.tfevents.*")), "per-iteration losses go to TensorBoard"
    # the (3-step) networks are garbage, so only the mechanics are checked: GN lowers its loss
    assert out.stage_loss["observed"][-1] <= out.stage_loss["observed"][0]
    assert out.restarts is not None and out.relative_loss.shape == (12,)


def test_hybrid_completion_then_a3_recovers_truth(checkpoints, batch):
    """Without the CAE the measured a3 is left as it is, and GN on it recovers the truth (noise-free)
    even from the tiny U-Net's poor completion: the completion only shapes the start."""
    module = HybridEstimator(
        unet_ckpt=str(checkpoints["unet"]),
        observed=["a3"],
        n_steps=100,
        h=H,
        cnn_init=False,
        known=["p3", "p5"],
        pu_known=True,
    )
    known = torch.zeros(10, dtype=torch.bool)
    known[[2, 4]] = True
    stages = [
        GaussNewtonStage(f"w{n}", GaussNewton(SolverConfig(max_iterations=10)), "observed", n_steps=n)
        for n in (15, 30, 60)
    ]
    stages.append(GaussNewtonStage("observed", GaussNewton(SolverConfig(max_iterations=30)), "observed"))
    callback = GaussNewtonRefinement(
        stages, RefinementSettings(known=known, pu_known=True, h=H), restarts=Restarts(count=3)
    )
    # p1, p2 start where a decent CNN would put them (±8 %): the tiny test CNN is not one
    g = torch.Generator().manual_seed(5)
    cnn_like = dict(batch, init=batch["init"].clone())
    cnn_like["init"][:, :2] = batch["params"][:, :2] * (1 + 0.08 * torch.randn(12, 2, generator=g, dtype=torch.float64))
    _trainer(callback).predict(module, dataloaders=_loader(cnn_like), return_predictions=False)
    r = callback.collect().result
    err = (r.params - batch["params"]).abs() / batch["params"]
    assert (err <= 0.01).all(1).double().mean() >= 0.9


def test_callback_runs_in_test_loop_and_cnn_initialises(checkpoints, batch):
    module = HybridEstimator(cnn_ckpt=str(checkpoints["cnn"]), observed=["a3", "a2", "a1"], n_steps=100, h=H)
    prepared = module.prepare({k: batch[k] for k in ("accel", "road", "pu", "init", "index")})
    expected = load_checkpoint(checkpoints["cnn"], "cnn").estimate(
        batch["accel"][:, :, 0].float(), batch["accel"][:, :, 1].float()
    )
    torch.testing.assert_close(prepared["init"][:, :2], expected.double())
    torch.testing.assert_close(prepared["init"][:, 2:], batch["init"][:, 2:])
    assert prepared["targets"].shape == (12, 100, 3)
    callback = GaussNewtonRefinement(
        [GaussNewtonStage("gn", GaussNewton(SolverConfig(max_iterations=4)))], RefinementSettings(h=H)
    )
    _trainer(callback).test(module, dataloaders=_loader(batch), verbose=False)
    assert callback.collect().result.params.shape == (12, 10)


def test_networks_run_without_tf32_convolutions_and_the_setting_is_restored(checkpoints, batch, monkeypatch):
    """On a GPU, cuDNN's default TF32 convolutions would move the CNN's start ~1e-4 from the CPU's."""
    module = HybridEstimator(cnn_ckpt=str(checkpoints["cnn"]), observed=["a3", "a2", "a1"], n_steps=100, h=H)
    seen, estimate = [], type(module.cnn).estimate

    def recording(self, a3, a2):
        seen.append(torch.backends.cudnn.allow_tf32)
        return estimate(self, a3, a2)

    monkeypatch.setattr(type(module.cnn), "estimate", recording)
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", True)
    module.prepare({k: batch[k] for k in ("accel", "road", "pu", "init", "index")})
    assert seen == [False] and torch.backends.cudnn.allow_tf32 is True


def test_checkpoint_kind_errors(checkpoints, tmp_path):
    with pytest.raises(CheckpointError, match="cnn_ckpt=.*CompletionUNet.*cnn needs"):
        HybridEstimator(cnn_ckpt=str(checkpoints["unet"]))
    with pytest.raises(CheckpointError, match="does not exist"):
        HybridEstimator(unet_ckpt=str(tmp_path / "missing.ckpt"))
    junk = tmp_path / "junk.ckpt"
    junk.write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable"):
        load_checkpoint(junk, "cae")


def test_cnn_needs_a2(checkpoints):
    module = HybridEstimator(cnn_ckpt=str(checkpoints["cnn"]), observed=["a3"], n_steps=100)
    s = synthetic_samples(2, n_steps=160, seed=1)
    with pytest.raises(ValueError, match="reads a2"):
        module.prepare(
            {"accel": s["accel"], "road": s["road"], "pu": torch.ones(2), "init": s["params"], "index": torch.arange(2)}
        )


def test_guarded_stage_never_worsens_the_measured_fit(batch):
    """A stage on badly completed channels is kept only where it fits the measured a3 better."""
    from hybridqcm.estimation.sensitivity import euler_accelerations

    known = torch.zeros(10, dtype=torch.bool)
    known[[2, 4]] = True
    targets = batch["accel"][:, :100].clone()
    g = torch.Generator().manual_seed(3)
    targets[:, :, 1:] *= 1 + torch.randn(targets[:, :, 1:].shape, generator=g, dtype=torch.float64)  # 100 % error
    outputs = {
        "targets": targets,
        "road": batch["road"][:, :100],
        "pu": batch["pu"],
        "index": torch.arange(12),
        "init": batch["init"],
    }
    stage = GaussNewtonStage("completed", GaussNewton(SolverConfig(max_iterations=5)), "all", guard=True)
    callback = GaussNewtonRefinement([stage], RefinementSettings(known=known, pu_known=True, h=H, observed=["a3"]))
    params = callback.refine(outputs)["params"]
    forcing = batch["pu"][:, None] * batch["road"][:, :100]

    def a3_loss(p):
        return (euler_accelerations(p, forcing, H, scaled_road=True)[:, :, 0] - targets[:, :, 0]).square().sum(1)

    assert (a3_loss(params) <= a3_loss(batch["init"])).all()


def test_restart_attempts_for_few_samples_run_in_one_solver_call():
    """Seat model, noise-free, started at a tenth of the true p1, p2 (ten times the occupant's mass):
    the mass ladder of restarts recovers every sample, one attempt per call (restart_batch=1) or all
    attempts for the few failed samples in one call (the default), with the same answer."""
    from hybridqcm.estimation.response import base_excitation_response
    from hybridqcm.testing import seat_recordings

    b, margin = 16, 8
    p, a2, a3 = seat_recordings(b, 200, margin, seed=3, h=H, substeps=4)
    outputs = {"targets": a3, "road": a2, "init": p * 0.1, "index": torch.arange(b), "input_offset": margin}
    results, calls = {}, {}
    for restart_batch in (1, 64):  # 64: all attempts for the few failed samples at once
        callback = GaussNewtonRefinement(
            [GaussNewtonStage("seat", GaussNewton(SolverConfig(max_iterations=30)))],
            RefinementSettings(h=H, response=base_excitation_response("seat", H), peer_factor=None),
            restarts=Restarts(
                count=6, threshold=math.inf, mass_factors=[0.6, 1.6, 0.4, 2.5, 0.8, 1.25], batch=restart_batch
            ),
        )
        calls[restart_batch] = []
        run = callback.run_stages

        def spy(outputs, init, *args, _calls=calls[restart_batch], _run=run, **kwargs):
            _calls.append(init.shape[0])
            return _run(outputs, init, *args, **kwargs)

        callback.run_stages = spy
        results[restart_batch] = callback.refine(outputs)
    for out in results.values():
        assert int((out["restarts"] > 0).sum()) >= 2  # the ladder was needed
        assert float(((out["params"][:, :2] - p) / p).abs().max()) < 1e-6
    assert len(calls[1]) > 2 and len(calls[64]) == 2, calls  # the first fit, then one call for all attempts
    assert calls[64][1] == 6 * int((results[64]["restarts"] > 0).sum())


def test_fits_far_from_the_networks_start_are_retried_and_keep_the_lowest_loss():
    """restart_far: a sample whose p1 or p2 ends more than that (relative) from its start is retried,
    one that stays near it is not; a retry never replaces a fit with a worse one (noise-free seat:
    every sample ends at the truth whatever the trigger did)."""
    from hybridqcm.estimation.response import base_excitation_response
    from hybridqcm.testing import seat_recordings

    b, margin = 8, 8
    p, a2, a3 = seat_recordings(b, 200, margin, seed=4, h=H, substeps=4)
    start = p.clone()
    start[: b // 2] *= 0.7  # these fits end 43 % from their start, the others 10 %
    start[b // 2 :] *= 1.1
    outputs = {"targets": a3, "road": a2, "init": start, "index": torch.arange(b), "input_offset": margin}
    for far, retried in ((None, []), (0.25, list(range(b // 2)))):
        callback = GaussNewtonRefinement(
            [GaussNewtonStage("seat", GaussNewton(SolverConfig(max_iterations=30)))],
            RefinementSettings(h=H, response=base_excitation_response("seat", H), peer_factor=None),
            restarts=Restarts(count=2, threshold=math.inf, far_from_start=far),
        )
        out = callback.refine(outputs)
        assert (out["restarts"] > 0).nonzero().squeeze(1).tolist() == retried
        assert float(((out["params"][:, :2] - p) / p).abs().max()) < 1e-6
    with pytest.raises(ValueError, match="restart_far must be None or > 0"):
        GaussNewtonRefinement([GaussNewtonStage("seat", GaussNewton())], restarts=Restarts(far_from_start=0.0))


def _converged(params, relative):
    """A SolverResult of converged fits at ``params`` [b, n] with relative losses ``relative`` [b], for
    tests that stand in for the GN stages."""
    from hybridqcm.estimation.solver import SolverResult

    b, n = params.shape
    return SolverResult(
        params=params.clone(),
        status=torch.full((b,), int(SolverStatus.CONVERGED)),
        iterations=torch.ones(b, dtype=torch.int64),
        loss=relative.clone(),
        loss_history=relative[None].clone(),
        std=torch.ones_like(params),
        covariance=torch.eye(n, dtype=torch.float64).expand(b, n, n).clone(),
        singular_values=torch.ones_like(params),
        residual_variance=relative.clone(),
        relative_residual=relative.sqrt(),
        whiteness=torch.zeros(b, dtype=torch.float64),
    )


def test_restarts_keep_the_attempt_the_posterior_prefers_not_the_smaller_misfit():
    """Attempts that all fit (converged) are ranked by -log posterior with the noise variance profiled
    out, ½ n log(residual power) + ½ λ (θ - μ)², not by the misfit alone. Sample 0: the restart has a
    residual 0.04 % smaller (½ 500 log 0.9996 = -0.1) but sits 8 prior standard deviations out (+32):
    the first fit is kept. Sample 1: a residual 10 % smaller (-26) at 3 standard deviations (+4.5): the
    restart is taken. Without a noise model the smaller misfit wins, as before."""
    from types import SimpleNamespace

    mean = torch.tensor([[10.0, 1000.0], [10.0, 1000.0]], dtype=torch.float64)
    precision = torch.tensor([[1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)  # std 1 on p1, none on p2
    problem = SimpleNamespace(prior_mean=mean, prior_precision=precision)
    first = (torch.tensor([[10.0, 1000.0], [10.0, 1000.0]]), torch.tensor([1e-3, 1e-3]))
    restart = (torch.tensor([[18.0, 2000.0], [13.0, 1500.0]]), torch.tensor([0.9996e-3, 0.9e-3]))
    for n_terms, kept in ((500, [True, False]), (None, [False, False])):
        attempts = iter([first, restart])

        def run_stages(outputs, init, module, restart=False, x0_at_rest=None, _n=n_terms, _a=attempts):
            params, relative = (t.double() for t in next(_a))
            result = _converged(params, relative)
            score = GaussNewtonRefinement._attempt_score(relative, _n, problem, params)
            return {}, result, params.clone(), relative.clone(), score

        callback = GaussNewtonRefinement(
            [GaussNewtonStage("gn", GaussNewton())],
            RefinementSettings(h=H, peer_factor=None),
            restarts=Restarts(count=1, threshold=0.0),
        )
        callback.run_stages = run_stages
        out = callback.refine({"init": torch.ones(2, 10, dtype=torch.float64), "index": torch.arange(2)})
        for i, keep in enumerate(kept):
            expected = first[0][i] if keep else restart[0][i]
            assert torch.equal(out["params"][i], expected.double()), (n_terms, i, out["params"][i])
    assert float(GaussNewtonRefinement._attempt_score(torch.tensor([1e-3]), 500, problem, mean[:1] + 2)[0]) == (
        pytest.approx(250 * math.log(1e-3) + 2.0)
    )


def test_restarts_around_the_reference_vehicle_draw_the_vehicle_there_and_keep_the_occupants_start():
    """restart_center: the vehicle's parameters (p3..p10) of every restart start lie within a few σ of
    the given vehicle, however far the first start was from it; p1, p2 stay around the first start,
    scaled by the mass ladder; known parameters keep their values."""
    from hybridqcm.physics import reference_params

    p_ref = reference_params().double()
    first = p_ref * torch.tensor([1.0, 1.0, 1.0, 1.5, 1.0, 0.6, 1.4, 0.7, 1.5, 0.5], dtype=torch.float64)
    seen = []

    def run_stages(outputs, init, module, restart=False, x0_at_rest=None):
        if restart:
            seen.append(init.clone())
        relative = torch.ones(init.shape[0], dtype=torch.float64)
        return {}, _converged(init, relative), init.clone(), relative.clone(), relative.clone()

    known = torch.zeros(10, dtype=torch.bool)
    known[[2, 4]] = True
    callback = GaussNewtonRefinement([GaussNewtonStage("gn", GaussNewton())], RefinementSettings(h=H, known=known, peer_factor=None), restarts=Restarts(count=4, threshold=0.0, batch=1, sigma=0.01, mass_factors=[1.0, 2.0], center=p_ref))  # fmt: skip
    callback.run_stages = run_stages
    callback.refine({"init": first.expand(8, 10).clone(), "index": torch.arange(8)})
    starts = torch.stack(seen)  # [attempt, recording, 10]
    assert starts.shape == (4, 8, 10)
    vehicle = [3, 5, 6, 7, 8, 9]
    assert ((starts[..., vehicle] / p_ref[vehicle] - 1).abs() < 0.06).all()  # around p_ref (σ = 1 %)
    assert ((starts[..., vehicle] / first[vehicle] - 1).abs() > 0.2).all()  # not around the first start
    assert torch.equal(starts[..., [2, 4]], first[[2, 4]].expand(4, 8, 2))  # known: unchanged
    ratio = starts[..., :2] / first[:2]
    assert ((ratio[0] - 1).abs() < 0.06).all() and ((ratio[1] - 2).abs() < 0.12).all()  # the mass ladder
    with pytest.raises(ValueError, match="restart_center"):
        GaussNewtonRefinement(
            [GaussNewtonStage("gn", GaussNewton())], RefinementSettings(h=H), restarts=Restarts(center=p_ref[:3])
        )


def test_failed_restarts_retry_only_the_misfit_recordings_and_can_rescue_them():
    """restarts=2 then restarts_failed=3: recording 0 fits at once, 1 is `far from start` for the first
    tier only (retried twice, never in the second), 2 stays misfit until its 4th attempt (the second
    tier rescues it: converged, attempts 0..3 run, not 4). With restarts_failed=0 recording 2 ends misfit."""
    from hybridqcm.estimation.solver import SolverStatus as S

    def make(failed_tier: int):
        calls: list[list[int]] = []

        def run_stages(outputs, init, module, restart=False, x0_at_rest=None):
            index = outputs["index"].tolist()
            if restart:
                calls.append(index)
            relative = torch.ones(init.shape[0], dtype=torch.float64)
            result = _converged(init, relative)
            attempts = [sum(c.count(i) for c in calls) for i in index]  # restarts so far, this one included
            for row, (i, n) in enumerate(zip(index, attempts, strict=True)):
                if i == 2 and (not restart or n < 4):
                    result.status[row] = int(S.MISFIT)
            return {}, result, init.clone(), relative.clone(), relative.clone()

        callback = GaussNewtonRefinement([GaussNewtonStage("gn", GaussNewton())], RefinementSettings(h=H, peer_factor=None), restarts=Restarts(count=2, failed=failed_tier, threshold=math.inf, batch=1))  # fmt: skip
        callback.run_stages = run_stages
        callback.far_from_start = lambda params, init: torch.tensor([False, True, False])
        record = callback.refine({"init": torch.ones(3, 10, dtype=torch.float64), "index": torch.arange(3)})
        return record, calls

    record, calls = make(3)
    assert calls == [[1, 2], [1, 2], [2], [2]]  # tier 1: both retried; tier 2: only the misfit one
    assert record["final"].status.tolist() == [int(S.CONVERGED)] * 3 and record["restarts"].tolist() == [0, 2, 4]
    record, calls = make(0)
    assert calls == [[1, 2], [1, 2]] and record["final"].status[2] == int(S.MISFIT)
    with pytest.raises(ValueError, match="restarts_failed"):
        GaussNewtonRefinement(
            [GaussNewtonStage("gn", GaussNewton())], RefinementSettings(h=H), restarts=Restarts(failed=-1)
        )


def test_a_recordings_restarts_do_not_depend_on_the_other_recordings_in_its_batch():
    """Each restart start is drawn from a stream of its own (seed, recording, attempt): recordings 4 and
    1 get the same restart starts in a batch of six and in a batch of just the two, in the other order,
    and another seed gives other starts."""
    from hybridqcm.physics import reference_params

    def starts_of(index: list[int], seed: int = 0) -> dict:
        seen: dict = {}

        def run_stages(outputs, init, module, restart=False, x0_at_rest=None):
            b = init.shape[0]
            if restart:
                for row, i in enumerate(outputs["index"].tolist()):
                    seen.setdefault(i, []).append(init[row].clone())
            relative = torch.ones(b, dtype=torch.float64)  # never good enough: every attempt is run
            result = _converged(init, relative)
            return {}, result, init.clone(), relative.clone(), relative.clone()

        callback = GaussNewtonRefinement([GaussNewtonStage("gn", GaussNewton())], RefinementSettings(h=H, peer_factor=None), restarts=Restarts(count=3, threshold=0.0, seed=seed, batch=1))  # fmt: skip
        callback.run_stages = run_stages
        init = reference_params().double().expand(len(index), 10).clone()
        callback.refine({"init": init, "index": torch.tensor(index)})
        return seen

    whole, pair, other_seed = starts_of([0, 1, 2, 3, 4, 5]), starts_of([4, 1]), starts_of([4, 1], seed=1)
    for i in (4, 1):
        assert len(whole[i]) == len(pair[i]) == 3
        for a, b in zip(whole[i], pair[i]):
            assert torch.equal(a, b)
        assert not torch.equal(whole[i][0], other_seed[i][0])
    assert not torch.equal(whole[4][0], whole[1][0])
