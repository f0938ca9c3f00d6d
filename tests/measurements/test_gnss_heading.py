"""Heading alignment from GNSS fixes (flowins.measurements.gnss_heading) and correlated GNSS noise."""
import dataclasses
import math

import pytest
import torch

from flowins.measurements.gnss_heading import (
    HeadingAlignment,
    HeadingFit,
    aligned_prior_covariance,
    fit_from_record,
    fit_record,
    fit_heading,
    fit_heading_batch,
    heading_jacobian,
    heading_noise,
    heading_transform,
    rotation_2d,
)
from flowins.geometry import quaternion as quat
from flowins.measurements.gnss import correlation_inflation
from flowins.state import STATE, make_state, split

F64 = torch.float64


def _random_state(gen: torch.Generator, pitch_rad: float = 0.3) -> torch.Tensor:
    q = quat.from_euler(torch.tensor(0.2, dtype=F64), torch.tensor(pitch_rad, dtype=F64), torch.tensor(1.1, dtype=F64))
    q_prev = quat.from_euler(torch.tensor(-0.1, dtype=F64), torch.tensor(pitch_rad, dtype=F64), torch.tensor(0.9, dtype=F64))
    r = lambda: torch.randn(3, generator=gen, dtype=F64)
    return make_state(p=5 * r(), v=r(), q=q, b_a=0.1 * r(), b_w=0.01 * r(), T_a=1 + 0.01 * r(), p_prev=5 * r(), q_prev=q_prev)


@pytest.mark.parametrize("pitch_rad", [0.3, math.pi / 2 - 1e-3])  # level-ish, and a phone held upright
def test_heading_jacobian_measures_rotation_about_the_vertical(pitch_rad):
    x = _random_state(torch.Generator().manual_seed(0), pitch_rad)
    h = heading_jacobian(x)
    q = split(x).q
    for axis, expected in ((2, 1.0), (0, 0.0), (1, 0.0)):
        eps = 1e-6
        rotvec = torch.zeros(3, dtype=F64)
        rotvec[axis] = eps
        dq = quat.multiply(quat.from_rotation_vector(rotvec), q) - q  # world-frame rotation
        assert float(h[STATE.q] @ dq) / eps == pytest.approx(expected, abs=1e-5)


def test_fit_heading_recovers_the_rotation_with_the_stated_spread():
    gen = torch.Generator().manual_seed(1)
    n, sigma, psi = 40, 2.0, 2.0
    steps = torch.randn(n, 2, generator=gen, dtype=F64) * 3.0 + torch.tensor([1.5, 0.5], dtype=F64)
    track = torch.cumsum(steps, 0)
    world = (rotation_2d(torch.tensor(psi, dtype=F64)) @ track.unsqueeze(-1)).squeeze(-1) + torch.tensor([10.0, -4.0], dtype=F64)
    var = torch.full((n,), sigma**2, dtype=F64)
    estimates, sigmas = [], []
    for _ in range(400):
        fixes = world + sigma * torch.randn(n, 2, generator=gen, dtype=F64)
        fit = fit_heading(track, fixes, var)
        estimates.append(float(fit.yaw_rad))
        sigmas.append(float(fit.sigma_rad))
    est = torch.tensor(estimates, dtype=F64)
    assert float(est.mean()) == pytest.approx(psi, abs=3 * sigmas[0] / 20)
    # the stated σ_ψ is the spread of the estimate (Fisher information of the fit)
    assert float(est.std()) == pytest.approx(sigmas[0], rel=0.15)


def test_fit_heading_leaves_out_a_multipath_fix_and_a_still_track_has_no_heading():
    gen = torch.Generator().manual_seed(2)
    track = torch.cumsum(torch.full((20, 2), 1.0, dtype=F64) + torch.randn(20, 2, generator=gen, dtype=F64), 0)
    fixes = (rotation_2d(torch.tensor(-1.0, dtype=F64)) @ track.unsqueeze(-1)).squeeze(-1)
    fixes = fixes + 0.5 * torch.randn(20, 2, generator=gen, dtype=F64)
    fixes[7] += torch.tensor([40.0, 0.0], dtype=F64)
    fit = fit_heading(track, fixes, torch.full((20,), 0.25, dtype=F64))
    assert not bool(fit.used[7]) and int(fit.used.sum()) == 19
    assert float(fit.yaw_rad) == pytest.approx(-1.0, abs=0.05)
    still = fit_heading(torch.zeros(5, 2, dtype=F64), fixes[:5], torch.ones(5, dtype=F64))
    assert math.isinf(float(still.sigma_rad))
    with pytest.raises(ValueError, match="at least 2"):
        fit_heading(track[:1], fixes[:1], torch.ones(1, dtype=F64))


def test_sets_of_fixes_fitted_together_are_each_fitted_as_alone():
    """``fit_heading_batch``: sets of 20, 6 and 5 fixes (one with a multipath fix, one a still
    track), padded to 20 with far-off rows, give each set's own fit, its outlier left out, as
    :func:`fit_heading` on that set alone; the padding is never used."""
    gen = torch.Generator().manual_seed(9)
    track = torch.cumsum(torch.full((20, 2), 1.0, dtype=F64) + torch.randn(20, 2, generator=gen, dtype=F64), 0)
    fixes = (rotation_2d(torch.tensor(0.4, dtype=F64)) @ track.unsqueeze(-1)).squeeze(-1)
    fixes = fixes + 0.5 * torch.randn(20, 2, generator=gen, dtype=F64)
    fixes[3] += torch.tensor([0.0, 30.0], dtype=F64)
    var = 0.25 + torch.rand(20, generator=gen, dtype=F64)
    sets = [(track, fixes, var), (track[8:14], fixes[8:14], var[8:14]),
            (torch.zeros(5, 2, dtype=F64), fixes[:5], var[:5])]
    far = lambda x, n: torch.cat((x, torch.full((20 - n, *x.shape[1:]), 1e6, dtype=F64)))
    batch = fit_heading_batch(torch.stack([far(t, len(t)) for t, _, _ in sets]),
                              torch.stack([far(f, len(f)) for _, f, _ in sets]),
                              torch.stack([far(v, len(v)) for *_, v in sets]), [len(t) for t, _, _ in sets])
    for k, (t, f, v) in enumerate(sets):
        alone = fit_heading(t, f, v)
        n = len(t)
        assert torch.equal(batch.used[k, :n], alone.used) and not bool(batch.used[k, n:].any())
        for got, want in zip(batch[:-1], alone[:-1]):
            if torch.isinf(want).all():
                assert torch.isinf(got[k]).all()
            else:
                torch.testing.assert_close(got[k], want, rtol=1e-12, atol=1e-12)
    assert not bool(batch.used[0, 3]) and math.isinf(float(batch.sigma_rad[2]))
    with pytest.raises(ValueError, match="at least 2"):
        fit_heading_batch(track[None, :1], fixes[None, :1], var[None, :1], [1])


def _fit(psi=0.7, c_p=(1.0, 2.0), c_g=(-3.0, 5.0), sigma=0.1, var=4.0) -> HeadingFit:
    return HeadingFit(torch.tensor(psi, dtype=F64), torch.tensor(sigma, dtype=F64), torch.tensor(c_p, dtype=F64),
                      torch.tensor(c_g, dtype=F64), torch.tensor(var, dtype=F64), torch.ones(3, dtype=torch.bool))


def _rotate_state(x: torch.Tensor, fit: HeadingFit) -> torch.Tensor:
    """The alignment written out part by part (reference for heading_transform)."""
    s = split(x)
    R = rotation_2d(fit.yaw_rad)
    q_psi = quat.from_rotation_vector(torch.stack((torch.zeros_like(fit.yaw_rad), torch.zeros_like(fit.yaw_rad), fit.yaw_rad)))

    def move(p):
        return torch.cat((R @ (p[:2] - fit.centre_filter_m) + fit.centre_fix_m, p[2:]))

    return make_state(p=move(s.p), v=torch.cat((R @ s.v[:2], s.v[2:])), q=quat.multiply(q_psi, s.q), b_a=s.b_a,
                      b_w=s.b_w, T_a=s.T_a, p_prev=move(s.p_prev), q_prev=quat.multiply(q_psi, s.q_prev))


def test_heading_transform_rotates_every_world_quantity_and_keeps_body_ones():
    x = _random_state(torch.Generator().manual_seed(3))
    fit = _fit()
    A, b = heading_transform(fit)
    torch.testing.assert_close(A @ x + b, _rotate_state(x, fit), rtol=0, atol=1e-12)


def test_heading_noise_is_the_fit_uncertainty_pushed_through_the_transform():
    x = _random_state(torch.Generator().manual_seed(4))
    fit = _fit(sigma=0.2, var=3.0)
    x1 = _rotate_state(x, fit)
    eps = 1e-6
    cols = []
    for k in range(3):  # θ = (ψ, c_g,x, c_g,y), central differences
        def at(delta, k=k):
            d = torch.zeros(3, dtype=F64)
            d[k] = delta
            f = fit._replace(yaw_rad=fit.yaw_rad + d[0], centre_fix_m=fit.centre_fix_m + d[1:])
            return _rotate_state(x, f)
        cols.append((at(eps) - at(-eps)) / (2 * eps))
    J = torch.stack(cols, -1)
    expected = J @ torch.diag(torch.tensor([0.2**2, 3.0, 3.0], dtype=F64)) @ J.T
    torch.testing.assert_close(heading_noise(x1, fit), expected, rtol=1e-7, atol=1e-9)


def test_aligned_prior_covariance_is_the_prior_conditioned_on_its_heading_then_rotated():
    """The Joseph-form update of the prior on its own heading, mapped by the fit's transform,
    plus the fit's noise at the aligned mean; the heading's variance is ``σ_ψ²`` plus what the
    conditioning left of the prior's (``v σ_c² / (v + σ_c²)``); a fit read back from its log
    record gives the same."""
    from flowins.filter.ekf import joseph_update

    gen = torch.Generator().manual_seed(5)
    x = _random_state(gen)
    L = torch.randn(26, 26, generator=gen, dtype=F64)
    P = 0.01 * L @ L.T + 1e-3 * torch.eye(26, dtype=F64)
    h = heading_jacobian(x)
    P = P + 3.0 * torch.outer(P @ h, P @ h) / float(h @ P @ h)  # a large yaw variance, correlated with the rest
    fit, cond = _fit(sigma=0.15, var=2.5), 1e-3
    aligned = _rotate_state(x, fit)
    cov = aligned_prior_covariance(x, P, aligned, fit, condition_sigma_rad=cond)
    _, Pc, _ = joseph_update(x, P, torch.zeros(1, dtype=F64), h.reshape(1, -1), torch.full((1, 1), cond**2, dtype=F64))
    A, _ = heading_transform(fit)
    torch.testing.assert_close(cov, A @ Pc @ A.T + heading_noise(aligned, fit), rtol=1e-9, atol=1e-12)
    v = float(h @ P @ h)
    h1 = heading_jacobian(aligned)
    assert float(h1 @ cov @ h1) == pytest.approx(0.15**2 + v * cond**2 / (v + cond**2), rel=1e-6)
    assert float(torch.linalg.eigvalsh(cov).min()) > -1e-12
    again = aligned_prior_covariance(x, P, aligned, fit_from_record(fit_record(fit)), condition_sigma_rad=cond)
    torch.testing.assert_close(again, cov, rtol=0, atol=0)


def test_correlation_inflation_is_the_variance_of_the_mean_of_gauss_markov_errors():
    """Exact variance of the mean of n AR(1) samples: σ²/n [1 + 2 Σ_k (1 - k/n) ρ^k]."""
    tau, dt, n = 10.0, 1.0, 20000
    rho = math.exp(-dt / tau)
    k = torch.arange(1, n, dtype=F64)
    exact = 1.0 + 2.0 * ((1.0 - k / n) * rho**k).sum()
    t = torch.arange(n, dtype=F64) * dt
    factor = correlation_inflation(t, tau)
    assert float(factor[0]) == pytest.approx(float(exact), rel=1e-3)
    torch.testing.assert_close(factor, factor[:1].expand(n))
    torch.testing.assert_close(correlation_inflation(t[:5], 0.0), torch.ones(5, dtype=F64))
    with pytest.raises(ValueError, match=">= 0"):
        correlation_inflation(t, -1.0)


def test_heading_alignment_config_rejects_nonsense():
    with pytest.raises(ValueError, match="min_fixes"):
        HeadingAlignment(min_fixes=1)
    with pytest.raises(ValueError, match="baseline_m"):
        HeadingAlignment(baseline_m=-1.0)


def _early_error(rec, entry, track) -> float:
    """Horizontal RMS error of ``track`` against ``rec``'s truth before the heading was set."""
    before = track.t < entry["t_s"] - 1.0
    i = torch.searchsorted(rec.truth.t_s, track.t[before]).clamp(max=rec.truth.t_s.shape[0] - 1)
    e = track.mean[before][:, STATE.p][:, :2] - rec.truth.pos_m[i][:, :2]
    return float(e.pow(2).sum(-1).mean().sqrt())


def test_a_filter_started_at_a_wrong_heading_is_aligned_and_its_early_track_re_expressed(wrong_heading_walk):
    """INS + GNSS on a synthetic walk, a good IMU, the filter's yaw 2 rad off with σ = π:
    the held fixes set the heading; the filter's early nodes, re-expressed in the aligned
    frame, and the smoother's are metres from the truth, the causal ones are not."""
    from flowins.navigation import navigate

    rec, run, config = wrong_heading_walk(4)
    result = navigate(run, config=config)
    (entry,) = [e for e in result.filter.log if e.get("kind") == "heading"]
    assert entry["status"] == "aligned"
    held = [e for e in result.filter.log if e.get("status") == "held for heading"]
    (last,) = [e for e in result.filter.log if e.get("status") == "set the heading"]
    assert last["t_s"] == entry["t_s"]
    assert len(held) + 1 == entry["fixes"] + entry["outliers"]
    final = _early_error(rec, entry, result.filter.in_final_frame())
    causal, smoothed = _early_error(rec, entry, result.filter), _early_error(rec, entry, result.smoother)
    assert final < 6.0 and smoothed < 6.0, (final, smoothed)
    assert causal > 2.0 * final, (causal, final)
    assert torch.isfinite(result.smoother.node_cov).all()


@pytest.mark.parametrize("seed", [2, 4])
def test_the_smoothers_second_pass_uses_the_held_fixes(seed, wrong_heading_walk):
    """The walk above, the yaw 2 rad off: with ``second_pass`` the smoother runs on a filter
    started with the heading the held fixes set, which applies those fixes too, so its track
    before the alignment is nearer the truth than the one-pass smoother's (which only rotates
    that stretch); the filter's own (causal) estimates are the same either way."""
    from flowins.navigation import navigate

    results = {}
    for second in (True, False):
        rec, run, config = wrong_heading_walk(seed, second_pass=second)
        results[second] = navigate(run, config=config)
    (entry,) = [e for e in results[True].filter.log if e.get("kind") == "heading"]
    assert entry["status"] == "aligned"
    two, one = _early_error(rec, entry, results[True].smoother), _early_error(rec, entry, results[False].smoother)
    assert two < 0.6 * one, (two, one)
    assert torch.equal(results[True].filter.node_mean, results[False].filter.node_mean)
    assert torch.isfinite(results[True].smoother.node_cov).all()


def test_runs_aligned_in_one_batch_equal_each_run_alone(wrong_heading_walk, monkeypatch):
    """Two walks of different lengths, the yaw 2 rad off, in one batched pass: their held fixes
    are held, fitted (together) and set each run's heading as when the run is alone (the same
    log, the same alignment), and the filter and smoother tracks agree to rounding."""
    from flowins.measurements import gnss
    from flowins.navigation import navigate, navigate_batch

    fitted = []

    def spy(filter_xy, *args, **kwargs):
        fitted.append(filter_xy.shape[0])
        return fit_heading_batch(filter_xy, *args, **kwargs)

    monkeypatch.setattr(gnss, "fit_heading_batch", spy)
    made = [wrong_heading_walk(2, 90.0), wrong_heading_walk(4, 75.0)]
    config = made[0][2]
    together = navigate_batch([run for _, run, _ in made], config=config)
    assert max(fitted) == 2  # both runs' held fixes in one fit
    for (_, run, _), got in zip(made, together):
        alone = navigate(run, config=config)
        kinds = [(e["t_s"], e.get("kind"), e.get("status")) for e in alone.filter.log]
        assert [(e["t_s"], e.get("kind"), e.get("status")) for e in got.filter.log] == kinds
        assert any(e.get("status") == "aligned" for e in alone.filter.log)
        for name in ("node_mean", "node_cov"):
            torch.testing.assert_close(getattr(got.filter, name), getattr(alone.filter, name), rtol=1e-9, atol=1e-8)
        torch.testing.assert_close(got.smoother.node_mean, alone.smoother.node_mean, rtol=0, atol=1e-6)


def test_giving_up_the_heading_applies_the_fix_that_gives_up_and_every_later_one():
    """INS + GNSS without flow, the yaw 2 rad off: the track drifts before the held fixes
    can set the heading. The held fixes are left out (counted); the fix that gives up and
    all later ones update the filter, so every fix is either held or applied, once."""
    from flowins.data.synthetic import synthetic_walk_recording
    from flowins.navigation import NavigationConfig, NavigationRun, navigate
    from flowins.start import StartSettings

    rec = synthetic_walk_recording(duration_s=60.0, seed=1)
    result = navigate(NavigationRun(rec.imu, rec.gnss), config=NavigationConfig(start=StartSettings(yaw_rad=2.0)))
    (entry,) = [e for e in result.filter.log if e.get("kind") == "heading"]
    assert entry["status"] == "given up"
    gnss = [e for e in result.filter.log if e.get("kind") == "gnss"]
    held = [e for e in gnss if e.get("status") == "held for heading"]
    applied = [e for e in gnss if "nis" in e]
    assert len(held) == entry["fixes"] > 0
    assert len(held) + len(applied) == len(gnss) == len(rec.gnss)
    assert max(e["t_s"] for e in held) < entry["t_s"] == min(e["t_s"] for e in applied)


def test_fixes_still_held_when_the_run_ends_are_reported_as_never_set():
    """A good IMU (no drift, so no give-up) and a run too short for the fixes to reach the
    baseline: every fix is held to the end and the result says so, with the count."""
    from flowins.data.synthetic import ImuErrors, synthetic_walk_recording
    from flowins.ins.mechanization import ProcessNoise
    from flowins.navigation import NavigationConfig, NavigationRun, navigate
    from flowins.start import StartSettings

    rec = synthetic_walk_recording(duration_s=12.0, seed=4, imu_errors=ImuErrors(
        acc_noise=2e-4, gyro_noise=1e-5, acc_bias_std=0.002, gyro_bias_std=2e-5, acc_bias_walk=0.0,
        gyro_bias_walk=0.0, acc_scale_std=0.0))
    config = NavigationConfig(noise=ProcessNoise(acc_noise=2e-4, gyro_noise=1e-5), start=StartSettings(yaw_rad=2.0))
    result = navigate(NavigationRun(rec.imu, rec.gnss), config=config)
    gnss = [e for e in result.filter.log if e.get("kind") == "gnss"]
    assert len(gnss) == len(rec.gnss) and not any("nis" in e for e in gnss)
    (status,) = result.heading_status
    assert status["status"] == "never set" and status["fixes"] == len(rec.gnss)
    # with the heading known from the start nothing is held and nothing is reported
    known = navigate(NavigationRun(rec.imu, rec.gnss), config=dataclasses.replace(config, gnss_heading=HeadingAlignment(enabled=False)))
    assert known.heading_status == []


def test_a_drifted_track_aligns_with_a_fit_within_drifted_max_sigma_instead_of_giving_up():
    """The walk of the test above gives up at the fix where its track has drifted. There the
    fit of its held fixes is wider than ``max_sigma_rad``; with ``drifted_max_sigma_rad`` just
    above that fit's σ the row aligns at that same fix with it, just below it gives up."""
    from flowins.data.synthetic import synthetic_walk_recording
    from flowins.navigation import NavigationConfig, NavigationRun, navigate
    from flowins.start import StartSettings

    rec = synthetic_walk_recording(duration_s=60.0, seed=1)
    base = NavigationConfig(start=StartSettings(yaw_rad=2.0))

    def heading_entry(drifted_max_sigma_rad: float) -> dict:
        config = dataclasses.replace(base, gnss_heading=dataclasses.replace(
            base.gnss_heading, drifted_max_sigma_rad=drifted_max_sigma_rad))
        (entry,) = [e for e in navigate(NavigationRun(rec.imu, rec.gnss), config=config).filter.log
                    if e.get("kind") == "heading"]
        return entry

    given_up = heading_entry(base.gnss_heading.max_sigma_rad)
    assert given_up["status"] == "given up"
    any_fit = heading_entry(math.pi)
    assert any_fit["status"] == "aligned" and any_fit["t_s"] == given_up["t_s"]
    sigma = any_fit["sigma_rad"]
    assert sigma > base.gnss_heading.max_sigma_rad
    # the give-up names the fit it did not take, and the setting that would take it
    assert given_up["fit_sigma_rad"] == pytest.approx(sigma, rel=1e-9)
    assert f"their fit's σ {sigma:.3f} rad > filter.gnss_heading.drifted_max_sigma_rad=0.2" in given_up["reason"]
    assert heading_entry(0.99 * sigma)["status"] == "given up"
    just_above = heading_entry(1.01 * sigma)
    assert just_above["status"] == "aligned" and just_above["t_s"] == given_up["t_s"]
    assert just_above["sigma_rad"] == pytest.approx(sigma, rel=1e-9)
