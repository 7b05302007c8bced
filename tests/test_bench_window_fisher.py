"""bench/window_fisher.py: the finite window's Cramér–Rao bound of the static mass, against independent facts —
the closed-form transfer functions, scipy's continuous-time simulation, the periodic (DFT) bound where the window
is periodic, and a Monte-Carlo of least-squares fits."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import scipy.optimize
import scipy.signal

from conftest import REPO_ROOT

H = 0.01
RIGID = np.array([15.0, 1150.0])  # p1 = C3/M, p2 = K3/M: 5.4 Hz, damping ratio 0.22
BODY1 = np.array([3.0, 1200.0, 0.5, 900.0, 20.0])
BODY2 = np.array([3.0, 1200.0, 0.3, 0.2, 900.0, 20.0, 3000.0, 40.0])


def _module(name):
    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def wf():
    return _module("window_fisher")


@pytest.fixture(scope="module")
def crb():
    return _module("occupant_crb")


def _road_like(n: int, seed: int) -> np.ndarray:
    """A chassis-like a2 [n]: white noise through a 1.5 Hz and a 12 Hz resonance (body bounce, wheel hop)."""
    rng = np.random.default_rng(seed)
    w = rng.standard_normal(n + 400)
    out = np.zeros_like(w)
    for f, zeta, gain in ((1.5, 0.3, 1.0), (12.0, 0.2, 0.3)):
        wn = 2 * np.pi * f
        b, a = scipy.signal.cont2discrete(([gain * wn**2], [1, 2 * zeta * wn, wn**2]), H, method="bilinear")[:2]
        out += scipy.signal.lfilter(np.ravel(b), a, w)
    return out[400:]  # mid-drive: no start from rest


@pytest.mark.parametrize("model,theta", [("rigid", RIGID), ("body1", BODY1), ("body2", BODY2)])
def test_the_polynomials_are_the_closed_form_transfer_functions(wf, crb, model, theta):
    s = 2j * np.pi * np.linspace(0.2, 40.0, 200)
    num, den = wf.polynomials(model, theta)
    assert np.allclose(np.polyval(num, s) / np.polyval(den, s), crb.transfer(model, theta, s).ravel(), rtol=1e-10)


def test_t_u_plus_o_x0_is_scipys_continuous_simulation_with_a_first_order_hold(wf):
    n = 300
    u = _road_like(n, 1)
    T, O = wf._matrices("body1", BODY1, n, H)
    A, B, C, D = scipy.signal.tf2ss(*wf.polynomials("body1", BODY1))
    x0 = np.array([1.0, -2.0, 3.0, -4.0]) * 1e-6  # canonical coordinates: outputs of ~0.1 m/s²
    _, y, _ = scipy.signal.lsim((A, B, C, D), u, np.arange(n) * H, X0=x0, interp=True)
    free = scipy.signal.lsim((A, B, C, D), np.zeros(n), np.arange(n) * H, X0=x0, interp=True)[1]
    coef = np.linalg.lstsq(O, free, rcond=None)[0]
    assert np.allclose(O @ coef, free, atol=1e-9 * np.abs(free).max())  # O spans every free response
    # the hold of the first sample reaches back to -h (scipy's foh is the triangle around each sample) where
    # lsim's input starts at 0: the two differ by what that leaves in the seat at t = 0, a free response
    forced = y - free
    gap = T @ u - forced
    assert np.abs(gap).max() > 1e-3 * np.abs(forced).max()
    left = gap - O @ np.linalg.lstsq(O, gap, rcond=None)[0]
    assert np.abs(left).max() < 1e-8 * np.abs(forced).max()


def test_a_long_periodic_window_gives_the_periodic_bound(wf, crb):
    """Where the window is periodic (a multisine on the DFT's bins, in steady state) the DFT bound is exact up to
    the transient's few columns and the hold (< 1 % in amplitude below 6 Hz): they agree to 2 %. On a cut-out
    window of a chassis-like signal the finite window's bound is larger."""
    n = 2048
    k = np.arange(3, 120, 2)  # 0.15-5.8 Hz
    t = np.arange(n) * H
    rng = np.random.default_rng(0)
    u = sum(np.cos(2 * np.pi * kk * t / (n * H) + rng.uniform(0, 2 * np.pi)) for kk in k)
    T, O = wf._matrices("rigid", RIGID, n, H)
    y = T @ u
    periodic = crb.relative_sd("rigid", RIGID, u, 0.05, 0.0, H, False)
    finite = wf.relative_sd("rigid", RIGID, u, y, 0.05, 0.0, H, False)
    assert finite == pytest.approx(periodic, rel=0.02)
    cut = _road_like(512, 3)
    assert wf.relative_sd("rigid", RIGID, cut, cut, 0.05, 0.0, H, False) > 1.03 * crb.relative_sd(
        "rigid", RIGID, cut, 0.05, 0.0, H, False
    )


def test_least_squares_fits_scatter_as_the_bound_says(wf):
    """200 noisy windows of one recording (white noise on a3, scipy's simulation), each fitted by least squares
    over log p1, log p2 and the initial state: the spread of log p2 is the bound's (sampling error of a variance
    over 200 draws: 10 %), while the periodic bound is 15 % off on this window."""
    n = 200
    u = _road_like(n, 5)
    t = np.arange(n) * H
    sys_ = scipy.signal.tf2ss(*wf.polynomials("rigid", RIGID))
    x0 = np.array([0.02, -1e-4])
    clean = scipy.signal.lsim(sys_, u, t, X0=x0, interp=True)[1]
    sigma = 0.05 * np.sqrt(np.mean(clean**2))
    bound = wf.relative_sd("rigid", RIGID, u, clean, sigma, 0.0, H, False)

    def residual(logp, y):
        A, B, C, D = scipy.signal.tf2ss(*wf.polynomials("rigid", np.exp(logp)))
        forced = scipy.signal.lsim((A, B, C, D), u, t, interp=True)[1]
        free = np.column_stack(
            [scipy.signal.lsim((A, B, C, D), np.zeros(n), t, X0=e, interp=True)[1] for e in np.eye(2)]
        )
        r = y - forced
        return r - free @ np.linalg.lstsq(free, r, rcond=None)[0]  # the initial state profiled out

    rng = np.random.default_rng(11)
    logs = []
    for _ in range(200):
        y = clean + sigma * rng.standard_normal(n)
        fit = scipy.optimize.least_squares(residual, np.log(RIGID), args=(y,), x_scale=0.01, xtol=1e-10)
        logs.append(fit.x[1])
    spread = np.std(logs, ddof=1)
    assert spread == pytest.approx(bound, rel=0.2)
    assert abs(np.mean(logs) - np.log(RIGID[1])) < 3 * spread / np.sqrt(200)


def test_the_noise_floor_of_a_measured_a2_adds_no_information(wf):
    """A noisy a2 with its floor taken off gives the clean a2's bound on average (the correction is exact for J's
    expectation); without it the floor counts as excitation and the bound is too small."""
    n = 256
    u = _road_like(n, 7)
    floor = 0.3 * np.sqrt(np.mean(u**2))
    s3, s2 = 0.05, 0.05 * np.sqrt(np.mean(u**2))
    clean = wf.relative_sd("rigid", RIGID, u, u, s3, s2, H, True)
    rng = np.random.default_rng(2)
    corrected, raw = [], []
    for _ in range(30):
        noisy = u + floor * rng.standard_normal(n)
        corrected.append(wf.relative_sd("rigid", RIGID, noisy, u, s3, s2, H, True, floor2=floor))
        raw.append(wf.relative_sd("rigid", RIGID, noisy, u, s3, s2, H, True))
    assert np.mean(corrected) == pytest.approx(clean, rel=0.05)
    assert np.mean(raw) < 0.95 * clean


def test_the_cli_refuses_a_twin_that_is_not_the_same_recordings(crb, tmp_path):
    from conftest import make_foreign

    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    make_foreign(a, n=3, noise=0.05)
    make_foreign(b, n=4, noise=0.0)
    with pytest.raises(SystemExit, match="not the same recordings"):
        crb.main([str(a), "--file-noise", "0.05", "--clean", str(b)])
    with pytest.raises(SystemExit, match="one noise-free twin per file"):
        crb.main([str(a), "--clean", str(b), str(b)])


def test_a_prior_adds_its_information_and_nothing_when_it_is_vague(wf):
    """A vague prior changes nothing; a prior that pins the body's (r, k, c) gives the bound of a seat whose body
    is known, which no longer depends on how tight the pin is; in between the bound lies between."""
    n = 256
    u = _road_like(n, 9)
    args = ("body1", BODY1, u, u, 0.05, 0.05, H)
    free = wf.relative_sds(*args)
    vague = wf.relative_sds(*args, prior_sd=[np.nan, np.nan, *(1e9 * BODY1[2:])])
    pinned = wf.relative_sds(*args, prior_sd=[np.nan, np.nan, *(1e-7 * BODY1[2:])])
    pinned_harder = wf.relative_sds(*args, prior_sd=[np.nan, np.nan, *(1e-9 * BODY1[2:])])
    middle = wf.relative_sds(*args, prior_sd=[np.nan, np.nan, *(0.3 * BODY1[2:])])
    assert np.allclose(vague, free, rtol=1e-9)
    assert np.allclose(pinned, pinned_harder, rtol=1e-6)
    assert all(p < m < f for p, m, f in zip(pinned, middle, free))


def test_the_body_priors_bound_is_taken_at_its_noise_level(crb, tmp_path):
    """The prior's information does not scale with the noise: at a tiny noise the data dominate and the bound is
    the one without the prior, at 5 % the prior lowers it where the data leave the body open (the unit-noise scaling would have made the prior 20x
    tighter at 5 %)."""
    from conftest import make_foreign

    path = tmp_path / "persons.h5"
    make_foreign(path, n=2, occupant="body1")
    accel, h, truth = crb.read_file(path)
    free = crb.bounds(accel, h, truth, domain="time")["body1_unknown"]
    tiny = crb.bounds(accel, h, truth, domain="time", body_prior=True, level=1e-5)["body1_unknown"]
    noisy = crb.bounds(accel, h, truth, domain="time", body_prior=True, level=0.05)["body1_unknown"]
    assert np.allclose(tiny, free, rtol=1e-3)
    assert np.all(noisy <= free * (1 + 1e-9)) and np.any(noisy < 0.95 * free)
    with pytest.raises(SystemExit, match="one --noise level"):
        crb.main([str(path), "--body-prior", "--noise", "0.01", "0.05"])


def test_bound_checks_noisy_copies_repeat_each_recording_with_noise_on_the_asked_channels(tmp_path):
    import h5py

    from conftest import make_foreign

    bc = _module("bound_check")
    clean, out = tmp_path / "clean.h5", tmp_path / "a3.h5"
    make_foreign(clean, n=3)
    bc.write_noisy(clean, out, n=2, repeats=3, noise=0.05, case="a3", seed=0)
    with h5py.File(clean, "r") as f, h5py.File(out, "r") as g:
        a, b = f["test/accel"][:2], g["test/accel"][()]
        assert np.allclose(g["test/truth_m3"][()], np.repeat(f["test/truth_m3"][:2], 3))
    assert b.shape == (6, *a.shape[1:])
    diff = b - np.repeat(a, 3, axis=0)
    assert np.all(diff[:, :, 1] == 0)  # a2 untouched
    rms3 = np.sqrt(np.mean(np.repeat(a, 3, axis=0)[:, :, 0] ** 2, axis=1))
    assert np.allclose(diff[:, :, 0].std(axis=1) / rms3, 0.05, rtol=0.15)
    assert not np.allclose(diff[0, :, 0], diff[1, :, 0])  # each repeat its own noise


def test_a_drives_windows_carry_noise_of_the_drives_rms_not_their_own(crb, tmp_path):
    """drive_crb --window: the information of a drive's windows summed, each window's noise a fraction of the
    whole drive's RMS (as foreign_sim drives add it). A nearly silent second half adds almost nothing; taken at its
    own RMS it would count as much as the first."""
    from conftest import make_foreign

    dc = _module("drive_crb")
    path = tmp_path / "drive.h5"
    make_foreign(path, n=1)
    accel, h, truth = crb.read_file(path)
    accel = accel.copy()
    accel[:, 256:] *= 0.01
    drive = dc._windowed(crb, accel, h, truth, 256)["rigid_known"][0]
    rms = np.sqrt(np.mean(accel[:, :, :2] ** 2, axis=1))
    first = crb.bounds(accel[:, :256], h, truth, domain="time", rms=rms)["rigid_known"][0]
    own = crb.bounds(accel[:, 256:], h, truth, domain="time")["rigid_known"][0]
    assert drive == pytest.approx(first, rel=0.01)
    assert own < 1.5 * first  # at its own RMS the quiet half would look as informative as the loud one
