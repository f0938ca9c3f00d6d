"""Batched filtering: B runs in one pass equal each run alone (float64, 1e-10)."""
import pytest
import torch

from flowins.data.synthetic import ImuErrors, Walk, WalkConfig, corrupt_imu, gnss_track, sample_times
from flowins.filter.augmentation import PoseAugmentation
from flowins.filter.ekf import Gate
from flowins.filter.runner import FilterInput, run_filter, run_filters
from flowins.filter.smoother import rts_smooth
from flowins.geometry import quaternion as quat
from flowins.ins.initialization import still_prior
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.gnss import GnssRecovery, gnss_fixes, gnss_noise
from flowins.measurements.zero_velocity import ZeroVelocity

F64 = torch.float64
NOISE = ProcessNoise(acc_bias_walk=1e-4, gyro_bias_walk=1e-5)


def _run(seed: int, duration_s: float, rate_hz: float, gnss_every_s: float, *, augment_s: float | None = None,
         noise: ProcessNoise | None = None, gate: float = 0.99) -> FilterInput:
    """A walk's noisy IMU at ``rate_hz``, GNSS fixes between samples, a zero velocity at the
    start and pose augmentations: a run whose events fall at its own times."""
    gen = torch.Generator().manual_seed(seed)
    walk = Walk(WalkConfig(duration_s=duration_s, stationary_s=0.5, ramp_s=1.0))
    t = sample_times(duration_s, rate_hz, 0.1, gen)
    f_true, w_true = walk.imu(t)
    acc, gyro, _ = corrupt_imu(t, f_true, w_true, ImuErrors(), gen)
    yaw = float(quat.to_euler(walk.quaternion(t[0]))[2])
    first = t <= t[0] + 0.45  # the walk's still start
    mean0, cov0 = still_prior(acc[first], gyro[first], yaw_rad=yaw, position_m=walk.position(t[0]))
    t_gnss = torch.arange(0.37 + 0.1 * seed, float(t[-1]), gnss_every_s, dtype=F64)
    _, z, h_acc, v_acc = gnss_track(walk, t_gnss, gen, min_acc_m=1.0, max_acc_m=3.0)
    events = gnss_fixes(t_gnss, z, gnss_noise(h_acc, v_acc), gate=Gate(probability=gate),
                        recovery=GnssRecovery(after_rejections=1))
    events += [ZeroVelocity(float(t[0]), 0.02), ZeroVelocity(0.3, 0.02)]
    if augment_s is not None:
        events += [PoseAugmentation(float(s), mode="limit") for s in torch.arange(0.2, float(t[-1]), augment_s)]
        events += [PoseAugmentation(float(t[-1]) - 0.013, mode="paper")]
    return FilterInput(t, acc, gyro, mean0, cov0, events, noise)


def _assert_same(batched, alone):
    assert torch.equal(batched.t_s, alone.t_s)
    assert torch.equal(batched.updated, alone.updated)
    # the chain keeps predictions only where an update acted: everywhere else the filtered
    # mean is the predicted one, exactly (a node an update moved is flagged, wherever it moves)
    for track in (batched, alone):
        kept = ~track.updated
        assert torch.equal(track.node_mean[kept], track.pred_mean[kept])
        assert int(track.updated.sum()) == track.updated_pred_cov.shape[0]
    assert len(batched.log) == len(alone.log)
    for a, b in zip(batched.log, alone.log):
        assert a.keys() == b.keys() and a["t_s"] == b["t_s"]
    for name in ("node_mean", "pred_mean", "transition", "node_cov", "pred_cov"):
        x, y = getattr(batched, name), getattr(alone, name)
        assert x.shape == y.shape, name
        scale = max(1.0, float(y.abs().max()))
        torch.testing.assert_close(x, y, rtol=0, atol=1e-10 * scale, msg=name)


def _unequal_runs() -> list[FilterInput]:
    return [
        _run(0, 6.0, 100.0, 1.0, augment_s=0.25),
        _run(1, 3.5, 200.0, 0.7, gate=0.2),  # shorter, faster IMU, other fix times, no augmentation, resets
        _run(2, 5.0, 50.0, 0.45, augment_s=0.4, noise=ProcessNoise(acc_noise=1e-2)),  # its own noise
    ]


def _fixes_only(run: FilterInput) -> FilterInput:
    """``run`` with its GNSS fixes alone: in a batch of such runs every row owns every node column."""
    fixes = [e for e in run.events if type(e).__name__ == "GnssFix"]
    return FilterInput(run.t_s, run.acc_mps2, run.gyro_rps, run.mean0, run.cov0, fixes, run.noise)


# a few rows gather their nodes row by row; more than four join the chain's parts first, each row
# then taking its columns (unequal runs) or, where every row owns every column, a view of the join
@pytest.mark.parametrize("batch", ["three unequal", "six unequal", "five alike"])
def test_unequal_runs_in_one_batch_equal_each_run_alone(batch):
    runs = {"three unequal": _unequal_runs,
            "six unequal": lambda: _unequal_runs() + [_run(3, 3.0, 100.0, 0.5, augment_s=0.3), _run(4, 4.0, 100.0, 0.8),
                                                      _run(5, 2.0, 100.0, 0.5)],
            "five alike": lambda: [_fixes_only(_run(3, 3.0, 100.0, 0.5))] * 5}[batch]()
    batched = run_filters(runs, noise=NOISE)
    if batch != "five alike":
        assert any(e.get("kind") == "gnss_reset" for e in batched[1].log)  # a prediction on one row only
    for run, track in zip(runs, batched):
        alone = run_filter(t_s=run.t_s, acc_mps2=run.acc_mps2, gyro_rps=run.gyro_rps, mean0=run.mean0,
                           cov0=run.cov0, noise=run.noise or NOISE, events=run.events)
        _assert_same(track, alone)
        # the smoother solves with predicted covariances made nearly singular by the pose copy's
        # nugget: it magnifies rounding-level differences of the filter (1e-14) about 10⁵-fold
        smoothed, smoothed_alone = rts_smooth(track), rts_smooth(alone)
        torch.testing.assert_close(smoothed.mean, smoothed_alone.mean, rtol=0, atol=1e-8)


def test_a_batch_of_one_and_the_order_of_runs_do_not_matter():
    runs = [_run(3, 3.0, 100.0, 0.5, augment_s=0.3), _run(4, 4.0, 100.0, 0.8)]
    forward = run_filters(runs, noise=NOISE)
    backward = run_filters(runs[::-1], noise=NOISE)[::-1]
    for a, b in zip(forward, backward):
        _assert_same(a, b)


def test_runs_of_different_dtypes_are_refused():
    run = _run(5, 2.0, 100.0, 0.5)
    other = FilterInput(run.t_s, run.acc_mps2, run.gyro_rps, run.mean0.float(), run.cov0.float())
    with pytest.raises(ValueError, match="one dtype"):
        run_filters([run, other], noise=NOISE)


def test_the_cholesky_jitter_one_covariance_needs_leaves_the_others_of_the_batch_alone(monkeypatch):
    from flowins.filter.ekf import _cholesky_psd

    gen = torch.Generator().manual_seed(1)
    A = torch.randn(6, 6, generator=gen, dtype=F64)
    good = A @ A.T + torch.eye(6, dtype=F64)
    Q, _ = torch.linalg.qr(torch.randn(6, 6, generator=gen, dtype=F64))
    # an eigenvalue of -1e-15 of the largest: the first jitter (1e-16) fails, the second works
    bad = Q @ torch.diag(torch.tensor([1.0, 0.5, 0.2, 0.1, 0.05, -1e-15], dtype=F64)) @ Q.T
    assert int(torch.linalg.cholesky_ex(bad + 1e-16 * torch.eye(6, dtype=F64))[1]) != 0
    both, failed = _cholesky_psd(torch.stack((good, bad)))
    assert not bool(failed.any())
    assert torch.equal(both[0], _cholesky_psd(good)[0]) and torch.equal(both[1], _cholesky_psd(bad)[0])
    assert not torch.equal(both[0], torch.linalg.cholesky(good + 1e-14 * good.diagonal().max() * torch.eye(6, dtype=F64)))
    # the ladder in one batched call (a GPU, torch.compile) gives the same factors
    monkeypatch.setattr("flowins.filter.ekf.waits_cost", lambda t: True)
    at_once, failed = _cholesky_psd(torch.stack((good, bad)))
    assert torch.equal(at_once, both) and not bool(failed.any())
    # a covariance no jitter rescues (an eigenvalue of -1e-3 of the largest) is flagged, not raised
    worse = Q @ torch.diag(torch.tensor([1.0, 0.5, 0.2, 0.1, 0.05, -1e-3], dtype=F64)) @ Q.T
    for waits in (True, False):
        monkeypatch.setattr("flowins.filter.ekf.waits_cost", lambda t, waits=waits: waits)
        _, failed = _cholesky_psd(torch.stack((good, worse)))
        assert failed.tolist() == [False, True]


@pytest.mark.parametrize("flush_bytes, capacity", [(None, None), (1, None), (1, 1), (100_000, 3)])
def test_row_stores_hand_over_exactly_the_nodes_the_chunks_do(monkeypatch, flush_bytes, capacity):
    """Without a gradient a chain of a few rows moves its finished nodes to stores of their own
    as it goes (at every append with ``FLUSH_BYTES = 1``; from one reserved node, growing, with
    ``capacity = 1``); its tracks are the ones the chunk lists give with a gradient, bit for bit."""
    import flowins.filter.chain as chain
    import flowins.filter.runner as runner

    runs = _unequal_runs() + [_run(3, 3.0, 100.0, 0.5, augment_s=0.3)]
    reference = run_filters(runs, noise=NOISE)
    if flush_bytes is not None:
        monkeypatch.setattr(chain, "FLUSH_BYTES", flush_bytes)
    if capacity is not None:
        monkeypatch.setattr(runner, "expected_nodes", lambda run, output_every: capacity)
    with torch.inference_mode():
        stored = run_filters(runs, noise=NOISE)
        chain_rows = chain.BatchChain(len(runs), capacity=[1] * len(runs))
    assert chain_rows._stores is not None  # the path under test
    assert any(e.get("kind") == "gnss_reset" for e in stored[1].log)  # a prediction on one row only
    for got, want in zip(stored, reference):
        assert got.updated.dtype == torch.bool and int(got.updated.sum()) > 0
        for name in ("t_s", "updated", "updated_pred_cov", "node_mean", "node_cov", "pred_mean", "transition"):
            x, y = getattr(got, name), getattr(want, name)
            assert x.shape == y.shape and torch.equal(x, y), name
        assert got.log == want.log


def test_a_chain_keeps_no_stores_with_a_gradient_or_many_rows():
    import flowins.filter.chain as chain

    assert chain.BatchChain(2, capacity=[5, 5])._stores is None  # grad mode: the chunks' path
    with torch.inference_mode():
        assert chain.BatchChain(chain.STORE_ROWS + 1, capacity=[5] * (chain.STORE_ROWS + 1))._stores is None
        assert chain.BatchChain(2)._stores is None  # no capacity given

