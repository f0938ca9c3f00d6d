"""The filter runner: analytic vs autodiff paths, event timing and dispatch, GNSS gating, long-run health,
smoothing."""
import math
from dataclasses import dataclass, field

import pytest
import torch

from flowins.data.synthetic import (
    ImuErrors,
    Walk,
    WalkConfig,
    corrupt_imu,
    gnss_track,
    sample_times,
)
from flowins.filter.ekf import Gate
from flowins.measurements.gnss import gnss_fixes, GnssFix
from flowins.filter.augmentation import PoseAugmentation, with_window
from flowins.filter.chain import BatchEvent
from flowins.filter.runner import FilterInput, chain_bytes, run_filter, run_filters
from flowins.filter.smoother import rts_smooth
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import InitialUncertainty, still_prior
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2, ProcessNoise, mechanize
from flowins.measurements.gnss import gnss_noise
from flowins.state import NOISE_DIM, STATE, STATE_DIM

F64 = torch.float64


def simulate(duration_s, seed, config=None):
    """A walk, its noisy IMU at jittered ~100 Hz and a stationary prior with the true yaw."""
    gen = torch.Generator().manual_seed(seed)
    walk = Walk(config or WalkConfig(duration_s=duration_s))
    t = sample_times(duration_s, 100.0, 0.1, gen)
    f_true, w_true = walk.imu(t)
    acc, gyro, _ = corrupt_imu(t, f_true, w_true, ImuErrors(), gen)
    yaw = float(quat.to_euler(walk.quaternion(t[0]))[2])
    still = min(walk.config.stationary_s, 5.0) - 0.05
    first = t <= t[0] + still
    mean0, cov0 = still_prior(acc[first], gyro[first], yaw_rad=yaw, position_m=walk.position(t[0]))
    return walk, t, acc, gyro, mean0, cov0, gen


@pytest.fixture(scope="module")
def short_run():
    config = WalkConfig(duration_s=3.0, stationary_s=0.5, ramp_s=1.0)
    return simulate(3.0, seed=3, config=config)


# --------------------------------------------------------------------------- analytic == autodiff


@pytest.mark.parametrize("scheme", ["midpoint", "paper"])
def test_analytic_jacobians_equal_autodiff_reference(short_run, scheme):
    walk, t, acc, gyro, mean0, cov0, gen = short_run
    t_gnss = torch.tensor([0.7234, 1.5117, 2.3391], dtype=F64)
    assert not torch.isin(t_gnss, t).any()  # fixes between IMU samples
    _, z, h_acc, v_acc = gnss_track(walk, t_gnss, gen, min_acc_m=1.0, max_acc_m=3.0)
    events = gnss_fixes(t_gnss, z, gnss_noise(h_acc, v_acc), gate=Gate(mode="off"))
    events += [PoseAugmentation(1.1057), PoseAugmentation(2.0123, mode="limit")]
    runs = {
        jac: run_filter(
            t_s=t,
            acc_mps2=acc,
            gyro_rps=gyro,
            mean0=mean0,
            cov0=cov0,
            noise=ProcessNoise(acc_bias_walk=1e-4, gyro_bias_walk=1e-5),
            events=events,
            jacobians=jac,
            scheme=scheme,
        )
        for jac in ("analytic", "autodiff")
    }
    a, r = runs["analytic"], runs["autodiff"]
    assert torch.equal(a.t_s, r.t_s)
    assert len(a.log) == len(r.log) == 3
    for name in ("node_mean", "pred_mean", "transition", "node_cov", "pred_cov"):
        x, y = getattr(a, name), getattr(r, name)
        scale = max(1.0, float(y.abs().max()))
        err = float((x - y).abs().max())
        assert err <= 1e-9 * scale, f"{name}: max difference {err:.3e} (scale {scale:.3g})"


# --------------------------------------------------------------------------- event timing


def test_output_every_one_has_a_node_at_every_imu_time(short_run):
    _, t, acc, gyro, mean0, cov0, _ = short_run
    track = run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=mean0, cov0=cov0, noise=ProcessNoise(), output_every=1)
    assert torch.equal(track.t_s, t)
    track10 = run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=mean0, cov0=cov0, noise=ProcessNoise(), output_every=10)
    expected = torch.unique(torch.cat((t[::10], t[-1:])))
    assert torch.equal(track10.t_s, expected)
    # coarser output does not change the estimate at shared times
    shared = torch.searchsorted(t, track10.t_s)
    torch.testing.assert_close(track10.node_mean, track.node_mean[shared], rtol=0, atol=1e-12)
    torch.testing.assert_close(track10.node_cov, track.node_cov[shared], rtol=0, atol=1e-12)


def test_event_between_samples_splits_the_step(short_run):
    _, t, acc, gyro, mean0, cov0, _ = short_run
    k = 137
    t_event = float(t[k - 1] + 0.37 * (t[k] - t[k - 1]))
    noise = ProcessNoise()
    track = run_filter(
        t_s=t,
        acc_mps2=acc,
        gyro_rps=gyro,
        mean0=mean0,
        cov0=cov0,
        noise=noise,
        events=[PoseAugmentation(t_event, mode="limit")],
        output_every=1,
    )
    j = int(torch.nonzero(track.t_s == t_event)[0])  # the first node exactly at the event time
    assert float(track.t_s[j - 1]) == float(t[k - 1]) and float(track.t_s[j + 1]) == t_event
    assert float(track.t_s[j + 2]) == float(t[k])
    # both parts of the split step are driven by the sample ã_k, ω̃_k
    zeros = torch.zeros(NOISE_DIM, dtype=F64)
    dt1 = torch.tensor(t_event, dtype=F64) - t[k - 1]
    expected_event = mechanize(track.node_mean[j - 1], zeros, acc[k], gyro[k], dt1)
    torch.testing.assert_close(track.node_mean[j], expected_event, rtol=0, atol=1e-12)
    expected_after = mechanize(track.node_mean[j + 1], zeros, acc[k], gyro[k], t[k] - t_event)
    torch.testing.assert_close(track.node_mean[j + 2], expected_after, rtol=0, atol=1e-12)
    # the limit augmentation node copied the pose at the event time
    idx_new, idx_old = STATE.indices("p", "q"), STATE.indices("p_prev", "q_prev")
    torch.testing.assert_close(track.node_mean[j + 1][idx_old], track.node_mean[j][idx_new], rtol=0, atol=1e-15)


@pytest.mark.parametrize("offset_s", [-0.25, 0.5])
def test_event_outside_imu_span_raises_naming_it(short_run, offset_s):
    _, t, acc, gyro, mean0, cov0, _ = short_run
    t_bad = float(t[0]) + offset_s if offset_s < 0 else float(t[-1]) + offset_s
    fix = GnssFix(t_bad, torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64), name="GNSS row 42")
    ok = GnssFix(float(t[10]) + 1e-3, torch.zeros(3, dtype=F64), torch.eye(3, dtype=F64), name="GNSS row 1")
    with pytest.raises(ValueError, match="GNSS row 42"):
        run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=mean0, cov0=cov0, noise=ProcessNoise(), events=[ok, fix])


# --------------------------------------------------------------------------- event dispatch


@dataclass(frozen=True)
class _Plain:
    """A toy event that records the rows it is applied to."""

    time_s: float
    calls: list = field(compare=False)
    name: str = "plain"

    def apply(self, chain):
        self.calls.append(("apply", chain.row))


@dataclass(frozen=True)
class _Batched(_Plain):
    """A toy batched event that records each ``apply_batch`` call."""

    name: str = "batched"

    def apply(self, chain):
        raise AssertionError("a batched event is applied by apply_batch")

    def batch_key(self):
        return "toy"

    @classmethod
    def apply_batch(cls, chain, rows, events):
        events[0].calls.append(("apply_batch", list(rows), [e.time_s for e in events]))


def test_a_batched_event_gets_its_rows_in_one_call_and_a_plain_one_each_row_alone():
    t, acc, gyro, _, mean0, cov0 = resting_device()
    calls = []
    assert isinstance(_Batched(0.5, calls), BatchEvent) and not isinstance(_Plain(0.5, calls), BatchEvent)
    runs = [FilterInput(t, acc, gyro, mean0, cov0, [_Plain(0.25, calls), _Batched(0.5, calls)]) for _ in range(2)]
    run_filters(runs, noise=ProcessNoise())
    assert calls == [("apply", 0), ("apply", 1), ("apply_batch", [0, 1], [0.5, 0.5])]


# --------------------------------------------------------------------------- GNSS gating


def resting_device():
    """2 s of a device at rest, level, with a (2 m)² position prior: t, acc, gyro, p0, mean0, cov0."""
    n = 201
    t = torch.linspace(0.0, 2.0, n, dtype=F64)
    acc = torch.tensor([0.0, 0.0, STANDARD_GRAVITY_MPS2], dtype=F64).expand(n, 3)
    gyro = torch.zeros(n, 3, dtype=F64)
    p0 = torch.tensor([10.0, -20.0, 2.0], dtype=F64)
    first = t <= t[0] + 5.0
    mean0, cov0 = still_prior(acc[first], gyro[first], position_m=p0, uncertainty=InitialUncertainty(position_m=2.0))
    return t, acc, gyro, p0, mean0, cov0


def test_gnss_gate_rejects_an_outlier_and_accepts_a_consistent_fix():
    t, acc, gyro, p0, mean0, cov0 = resting_device()
    R = 25.0 * torch.eye(3, dtype=F64)  # 5 m accuracy
    z_outlier = p0 + torch.tensor([100.0, 0.0, 0.0], dtype=F64)
    z_good = p0 + torch.tensor([2.0, -1.5, 1.0], dtype=F64)  # within 1σ of S = (4 + 25) I
    t_out, t_good = 0.505, 1.005
    events = [
        GnssFix(t_out, z_outlier, R, Gate(mode="hard"), name="outlier"),
        GnssFix(t_good, z_good, R, Gate(mode="hard"), name="good"),
    ]
    track = run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=mean0, cov0=cov0, noise=ProcessNoise(), events=events)
    assert [e["name"] for e in track.log] == ["outlier", "good"]
    assert [e["t_s"] for e in track.log] == [t_out, t_good]

    j_out = int(torch.nonzero(track.t_s == t_out)[0])
    P_pred = track.pred_cov[j_out]
    S = P_pred[STATE.p, STATE.p] + R
    v = z_outlier - track.pred_mean[j_out, STATE.p]
    assert abs(track.log[0]["nis"] - float(v @ torch.linalg.solve(S, v))) <= 1e-9 * track.log[0]["nis"]
    assert track.log[0]["nis"] > 300.0
    assert track.log[0]["accepted"] == 0.0
    assert torch.equal(track.node_mean[j_out], track.pred_mean[j_out])
    assert torch.equal(track.node_cov[j_out], track.pred_cov[j_out])

    j_good = int(torch.nonzero(track.t_s == t_good)[0])
    m_pred, P_pred = track.pred_mean[j_good], track.pred_cov[j_good]
    assert track.log[1]["accepted"] == 1.0
    H = torch.zeros(3, STATE_DIM, dtype=F64)
    H[:, STATE.p] = torch.eye(3, dtype=F64)
    S = H @ P_pred @ H.T + R
    v = z_good - m_pred[STATE.p]
    assert track.log[1]["nis"] < 3.0
    K = P_pred @ H.T @ torch.linalg.inv(S)
    expected = m_pred + K @ v
    for name in ("q", "q_prev"):  # the filter re-normalises the quaternions after an update
        expected[STATE.slice(name)] /= expected[STATE.slice(name)].norm()
    torch.testing.assert_close(track.node_mean[j_good], expected, rtol=0, atol=1e-12)
    P_post = (torch.eye(STATE_DIM, dtype=F64) - K @ H) @ P_pred
    torch.testing.assert_close(track.node_cov[j_good], 0.5 * (P_post + P_post.T), rtol=0, atol=1e-12)
    # the mean moved towards the fix, by about P_pp / (P_pp + R) of the innovation
    before = float((z_good - m_pred[STATE.p]).norm())
    after = float((z_good - track.node_mean[j_good, STATE.p]).norm())
    assert after < before * (1.0 - 0.1)


def test_the_run_sums_the_innovation_likelihood_of_the_accepted_fixes_per_row():
    """With ``likelihood=True`` each row's track holds -log N(v; 0, S) (less ½ d log 2π) summed
    over its accepted fixes, and their count in scalars; the gated outlier adds nothing."""
    t, acc, gyro, p0, mean0, cov0 = resting_device()
    R = 25.0 * torch.eye(3, dtype=F64)
    fixes = [(0.505, p0 + torch.tensor([100.0, 0.0, 0.0], dtype=F64)), (1.005, p0 + torch.tensor([2.0, -1.5, 1.0], dtype=F64)),
             (1.505, p0 + torch.tensor([-3.0, 1.0, 0.5], dtype=F64))]
    runs = [FilterInput(t, acc, gyro, mean0, cov0, [GnssFix(tf, z, R, Gate(mode="hard")) for tf, z in fixes]),
            FilterInput(t, acc, gyro, mean0, cov0, [GnssFix(tf, z, R, Gate(mode="hard")) for tf, z in fixes[2:]])]
    tracks = run_filters(runs, noise=ProcessNoise(), likelihood=True)
    for track, used in zip(tracks, (fixes[1:], fixes[2:])):
        expected = 0.0
        for tf, z in used:
            j = int(torch.nonzero(track.t_s == tf)[0])
            S = track.pred_cov[j, STATE.p, STATE.p] + R
            density = torch.distributions.MultivariateNormal(track.pred_mean[j, STATE.p], covariance_matrix=S)
            expected += float(-density.log_prob(z)) - 1.5 * math.log(2 * math.pi)
        assert abs(float(track.nll) - expected) <= 1e-10 * abs(expected)
        assert track.nll_count == 3.0 * len(used)
    plain = run_filters(runs, noise=ProcessNoise())
    assert plain[0].nll is None and plain[0].nll_count == 0.0
    assert torch.equal(plain[0].node_mean, tracks[0].node_mean)


# --------------------------------------------------------------------------- long run


@pytest.fixture(scope="module")
def long_run():
    walk, t, acc, gyro, mean0, cov0, gen = simulate(300.0, seed=5)
    t_gnss = torch.arange(1.5, float(t[-1]) - 0.5, 1.0, dtype=F64)  # 1 Hz, between IMU samples
    _, z, h_acc, v_acc = gnss_track(walk, t_gnss, gen)
    events = gnss_fixes(t_gnss, z, gnss_noise(h_acc, v_acc))
    runs = {}
    for dtype in (torch.float64, torch.float32):
        runs[dtype] = run_filter(
            t_s=t,
            acc_mps2=acc,
            gyro_rps=gyro,
            mean0=mean0.to(dtype),
            cov0=cov0.to(dtype),
            noise=ProcessNoise(),
            events=events,
        )
    return walk, t, runs


def assert_symmetric_psd(covs, rel_eig):
    assert torch.isfinite(covs).all()
    asym = (covs - covs.transpose(-1, -2)).abs().amax(dim=(-1, -2))
    size = covs.abs().amax(dim=(-1, -2))
    assert bool((asym <= torch.finfo(covs.dtype).eps * size).all()), float(asym.max())
    eig = torch.linalg.eigvalsh(covs.to(F64))
    worst = float((eig[:, 0] / eig[:, -1]).min())
    assert worst >= -rel_eig, f"min eigenvalue / max eigenvalue = {worst:.3e}"


@pytest.mark.slow
@pytest.mark.parametrize("dtype,rel_eig", [(torch.float64, 1e-6), (torch.float32, 1e-5)])
def test_long_run_covariances_stay_symmetric_psd(long_run, dtype, rel_eig):
    _, t, runs = long_run
    track = runs[dtype]
    assert track.node_cov.dtype == dtype
    assert float(track.t_s[-1]) == float(t[-1]) and track.t_s.shape[0] > 3000
    assert torch.isfinite(track.node_mean).all()
    assert sum(e["accepted"] for e in track.log) >= 0.95 * len(track.log)
    assert_symmetric_psd(track.node_cov, rel_eig)
    assert_symmetric_psd(track.pred_cov, rel_eig)


@pytest.mark.slow
def test_smoother_covariances_psd_and_position_error_below_filter(long_run):
    walk, _, runs = long_run
    track = runs[torch.float64]
    smoothed = rts_smooth(track)
    assert_symmetric_psd(smoothed.node_cov, 1e-6)
    # smoothing never increases a marginal variance
    var_f = torch.diagonal(track.node_cov, dim1=-2, dim2=-1)
    var_s = torch.diagonal(smoothed.node_cov, dim1=-2, dim2=-1)
    assert bool((var_s <= var_f * (1 + 1e-6) + 1e-12).all())
    truth = walk.position(track.t)
    rmse_filter = float((track.mean[:, STATE.p] - truth).norm(dim=-1).pow(2).mean().sqrt())
    rmse_smooth = float((smoothed.mean[:, STATE.p] - truth).norm(dim=-1).pow(2).mean().sqrt())
    assert math.isfinite(rmse_filter) and rmse_smooth < 0.8 * rmse_filter, (rmse_filter, rmse_smooth)


# --------------------------------------------------------------------------- the chain's memory


def _stored_bytes(track):
    """What a finished track holds of its chain: every node's transition, covariance and means, and
    the updated nodes' predicted covariances."""
    return sum(x.nbytes for x in (track.transition, track.node_cov, track.updated_pred_cov, track.pred_mean,
                                  track.node_mean))


def test_chain_bytes_is_what_a_run_of_output_nodes_stores():
    t, acc, gyro, _, mean0, cov0 = resting_device()
    runs = [FilterInput(t, acc, gyro, mean0, cov0)]
    track = run_filters(runs, noise=ProcessNoise(), output_every=10)[0]
    assert len(track.t_s) == 201 // 10 + 1
    assert chain_bytes(runs, output_every=10) == _stored_bytes(track)


@pytest.mark.parametrize("window, mode", [(1, "paper"), (5, "limit")])
def test_chain_bytes_bounds_a_batch_with_events_from_above_within_2x(window, mode):
    t, acc, gyro, _, mean0, cov0 = resting_device()
    mean0, cov0 = with_window(mean0, cov0, window)
    events = [PoseAugmentation(0.1 * k, mode=mode) for k in range(1, 20)]
    runs = [FilterInput(t, acc, gyro, mean0, cov0, events)] * 3
    stored = sum(_stored_bytes(track) for track in run_filters(runs, noise=ProcessNoise()))
    assert stored <= chain_bytes(runs) <= 2 * stored
