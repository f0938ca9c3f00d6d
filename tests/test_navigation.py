"""navigate(): inference mode when nothing needs a gradient, the graph when something does."""
import dataclasses

import pytest
import torch

from flowins.data.synthetic import synthetic_walk_recording
from flowins.measurements.gnss_heading import HeadingAlignment
from flowins.navigation import NavigationConfig, NavigationRun, navigate


@pytest.fixture(scope="module")
def recording():
    return synthetic_walk_recording(duration_s=12.0, seed=5)


def test_navigate_gradient_matches_finite_differences_and_the_fast_path_matches_its_values(recording):
    """With a noise scale that needs a gradient the filter keeps its graph (autograd agrees
    with central differences); without, it runs in inference mode and gives the same numbers."""
    rec = recording

    def final_position(scale):
        result = navigate(NavigationRun(rec.imu, rec.gnss), config=NavigationConfig(gnss_noise_scale=scale, gnss_heading=HeadingAlignment(enabled=False)))
        return result, result.smoother.mean[-1, :2].sum() + result.filter.mean[-1, :2].sum()

    s0 = 1.5
    scale = torch.tensor(s0, dtype=torch.float64, requires_grad=True)
    tracked, value = final_position(scale)
    (grad,) = torch.autograd.grad(value, scale)
    eps = 1e-4
    fd = (final_position(s0 + eps)[1] - final_position(s0 - eps)[1]) / (2 * eps)
    assert torch.isfinite(grad)
    assert abs(float(grad) - float(fd)) <= 1e-5 * max(1.0, abs(float(fd)))

    fast, fast_value = final_position(s0)
    assert torch.is_inference(fast.filter.node_mean) and not torch.is_inference(tracked.filter.node_mean)
    assert torch.allclose(fast.filter.node_mean, tracked.filter.node_mean.detach(), rtol=0, atol=1e-12)
    assert torch.allclose(fast.smoother.node_cov, tracked.smoother.node_cov.detach(), rtol=0, atol=1e-12)
    assert float(fast_value) == pytest.approx(float(value.detach()), abs=1e-12)


def test_run_warnings_name_flow_pairs_outside_the_filter_span_and_fixes_before_the_start():
    from types import SimpleNamespace

    from flowins.evaluation.run_report import run_warnings
    from flowins.state import STATE_DIM

    cov = torch.eye(STATE_DIM, dtype=torch.float64).expand(3, STATE_DIM, STATE_DIM)
    track = SimpleNamespace(log=[], node_cov=cov, t_s=torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64))
    result = SimpleNamespace(filter=track, flow_pairs_outside=7, gnss_before_start=2, start=SimpleNamespace(t_s=1.25))
    assert run_warnings(result) == [
        "flow: 7 frame pairs outside the filter's span (its start at 1.25 s to the IMU's last sample) are not used",
        "GNSS: 2 fixes before the filter's start (1.25 s) are not used",
    ]
    quiet = SimpleNamespace(filter=track, flow_pairs_outside=0, gnss_before_start=0, start=SimpleNamespace(t_s=1.25))
    assert run_warnings(quiet) == []


def test_the_drift_warning_counts_the_position_sigma_only_after_the_fixes_set_a_free_heading():
    """A position σ of 300 m before the heading alignment (the free yaw's spread) is no drift; the
    same σ after it is, and so is either one in a run that never tries to align. An alignment
    given up says so."""
    from types import SimpleNamespace

    from flowins.evaluation.run_report import run_warnings
    from flowins.state import STATE, STATE_DIM

    def warnings(sigma_m, log):
        cov = torch.eye(STATE_DIM, dtype=torch.float64).repeat(4, 1, 1)
        cov[:, STATE.p, STATE.p] *= torch.tensor(sigma_m, dtype=torch.float64).square().view(4, 1, 1) / 2
        track = SimpleNamespace(log=log, node_cov=cov, t_s=torch.tensor([0.0, 10.0, 20.0, 30.0], dtype=torch.float64))
        result = SimpleNamespace(filter=track, flow_pairs_outside=0, gnss_before_start=0, start=SimpleNamespace(t_s=0.0))
        return [w for w in run_warnings(result) if "position σ" in w or "heading" in w]

    aligned = [{"t_s": 15.0, "kind": "heading", "status": "aligned"}]
    assert warnings([1.0, 300.0, 5.0, 5.0], aligned) == []
    assert warnings([1.0, 300.0, 5.0, 5.0], []) == [
        "the filter's own horizontal position σ reaches 300 m (at 10 s): nothing bounds the position there, the "
        "error is inertial drift"]
    assert warnings([1.0, 5.0, 5.0, 300.0], aligned) == [
        "the filter's own horizontal position σ reaches 300 m (at 30 s): nothing bounds the position there, the "
        "error is inertial drift"]
    given_up = [{"t_s": 15.0, "kind": "heading", "status": "given up", "reason": "the track drifted"}]
    assert warnings([1.0, 300.0, 5.0, 5.0], given_up) == [
        "GNSS heading: the held fixes did not set the free heading; given up at 15.0 s (the track drifted; "
        "filter.gnss_heading)"]


@pytest.mark.slow
def test_the_whole_navigation_in_float32_stays_float32_and_agrees_with_float64(mixed_dtypes):
    """Every tensor a run builds follows the state's dtype: a float64 constant slipped into a
    float32 run (or a device's into another's) would promote the nodes or raise. The still start
    with its zero-velocity updates, the GNSS heading alignment and fixes, and the vehicle
    constraint, 30 s of a walk; the float32 track stays within 5 cm of the float64 one, plus 1 %
    of the largest horizontal position σ the filter has had so far: until the held fixes are
    given up (at 25 s) the yaw is free (σ π) and the position σ grows from 44 to 78 m, and
    float32's rounding moves that dead-reckoned track by decimetres, which the fixes then take
    seconds to pull back."""
    from flowins.measurements.vehicle import VehicleSettings
    from flowins.state import STATE

    rec = synthetic_walk_recording(duration_s=30.0, seed=1)
    tracks = {}
    for dtype in (torch.float64, torch.float32):
        config = NavigationConfig(dtype=dtype, measurements={"vehicle": VehicleSettings(mode="on")})
        with mixed_dtypes() as mode:
            result = navigate(NavigationRun(rec.imu, rec.gnss), config=config)
        assert mode.slips == {}, mode.slips  # no op mixes float32 with float64 (the default dtype inside)
        kinds = {e.get("kind") for e in result.filter.log}
        assert {"zero_velocity", "gnss", "vehicle"} <= kinds, kinds
        assert result.filter.node_mean.dtype == dtype and result.filter.node_cov.dtype == dtype
        assert result.smoother.node_mean.dtype == dtype
        tracks[dtype] = result.filter.node_mean[:, STATE.p].double()
        if dtype == torch.float64:
            sigma = result.filter.node_cov[:, STATE.p, STATE.p].diagonal(dim1=-2, dim2=-1)[:, :2].sum(-1).sqrt()
    difference = (tracks[torch.float32] - tracks[torch.float64]).norm(dim=-1)
    bound = 0.05 + 0.01 * sigma.cummax(0).values
    assert bool((difference < bound).all()), float((difference - bound).max())


@pytest.mark.slow
@pytest.mark.parametrize("second_pass", [False, True])
def test_the_navigation_on_another_device_is_the_cpu_run_and_leaves_no_tensor_behind(fake_device, second_pass,
                                                                                    wrong_heading_walk):
    """``NavigationConfig.device``: the start, the GNSS heading alignment and fixes, the
    zero-velocity updates, the vehicle constraint and the smoother (and, on a walk whose fixes
    set the heading, its second pass) run on the fake device of ``conftest.FakeDevice`` (a
    GPU's stand-in) with no op meeting a CPU tensor there, and give the CPU run's numbers exactly."""
    from flowins.measurements.vehicle import VehicleSettings

    if second_pass:
        rec, run, config = wrong_heading_walk(2, duration_s=60.0, second_pass=True)
    else:
        rec = synthetic_walk_recording(duration_s=30.0, seed=1)
        run, config = NavigationRun(rec.imu, rec.gnss), NavigationConfig()
    config = dataclasses.replace(config, measurements={"vehicle": VehicleSettings(mode="on")})
    cpu = navigate(run, config=config)
    with fake_device() as mode:
        moved = navigate(run, config=dataclasses.replace(config, device="meta"))
        assert moved.filter.node_mean.device == torch.device("meta") and moved.smoother.node_cov.device.type == "meta"
    assert mode.slips == {}, mode.slips
    assert {"zero_velocity", "gnss", "vehicle", "heading"} <= {e.get("kind") for e in moved.filter.log}
    assert torch.equal(moved.filter.node_mean, cpu.filter.node_mean)
    assert torch.equal(moved.smoother.node_cov, cpu.smoother.node_cov)
    assert (moved.smoother_pass is not None) == second_pass


def test_the_second_pass_reports_its_progress_under_its_own_name(monkeypatch, wrong_heading_walk):
    """With ``progress`` the job reports the first pass as ``filter`` and the smoother's second
    pass under its own name, each enabled."""
    import flowins.filter.runner as runner

    seen = []

    def record(items, **kw):
        seen.append((kw["description"], kw["enabled"]))
        return items

    monkeypatch.setattr(runner, "track_progress", record)
    _, run, config = wrong_heading_walk(2, duration_s=60.0, second_pass=True)
    navigate(run, config=config, progress=True)
    assert seen == [("filter", True), ("smoother's second pass", True)]


def test_memory_warning_compares_the_pass_s_estimated_peak_with_80_percent_of_the_free_memory():
    from flowins.filter.runner import FilterInput, chain_bytes
    from flowins.filter.runner import PEAK_OVER_CHAIN, memory_warning

    n = 1001
    t = torch.linspace(0.0, 10.0, n, dtype=torch.float64)
    inputs = [FilterInput(t, torch.zeros(n, 3, dtype=torch.float64), torch.zeros(n, 3, dtype=torch.float64),
                          torch.zeros(89, dtype=torch.float64), torch.eye(89, dtype=torch.float64))] * 2
    need = PEAK_OVER_CHAIN * chain_bytes(inputs, output_every=10)
    assert memory_warning(inputs, output_every=10, available=None) is None
    assert memory_warning(inputs, output_every=10, available=int(need / 0.8 * 1.01)) is None
    message = memory_warning(inputs, output_every=10, available=int(need / 0.8 * 0.99))
    assert message is not None
    for part in (f"{need / 2**20:.0f} MiB", "2 run(s)", "10 s", "89 entries, 10 cloned pose(s)", "filter.tracks.window",
                 "sequence.end_s"):
        assert part in message


def test_navigate_warns_before_a_pass_that_may_not_fit(monkeypatch, caplog, recording):
    import flowins.filter.runner as runner

    monkeypatch.setattr(runner, "available_memory_bytes", lambda device: 1)
    with caplog.at_level("WARNING", logger="flowins.navigation"):
        navigate(NavigationRun(recording.imu, recording.gnss))
    assert any(r.getMessage().startswith("warning: this filter pass may need about") for r in caplog.records)
    caplog.clear()
    monkeypatch.setattr(runner, "available_memory_bytes", lambda device: 1 << 50)
    with caplog.at_level("WARNING", logger="flowins.navigation"):
        navigate(NavigationRun(recording.imu, recording.gnss))
    assert not caplog.records


def test_a_batch_split_over_worker_processes_gives_each_run_its_own_result_in_order(caplog):
    """filter.workers=2: three different recordings (so a result in the wrong place shows) give what
    the batch in this process gives, up to rounding (another batch, one thread)."""
    from flowins.navigation import navigate_batch

    recs = [synthetic_walk_recording(duration_s=d, seed=s) for d, s in ((6.0, 1), (9.0, 2), (7.0, 3))]
    runs = [NavigationRun(r.imu, r.gnss) for r in recs]
    config = NavigationConfig(gnss_heading=HeadingAlignment(enabled=False))
    here = navigate_batch(runs, config=config)
    with caplog.at_level("INFO", logger="flowins"):
        there = navigate_batch(runs, config=dataclasses.replace(config, workers=2))
    assert any("3 runs in 2 worker processes" in r.getMessage() for r in caplog.records)
    for i, (a, b) in enumerate(zip(there, here)):
        assert a.filter.node_mean.shape == b.filter.node_mean.shape
        torch.testing.assert_close(a.filter.node_mean, b.filter.node_mean, rtol=0, atol=1e-9)
        torch.testing.assert_close(a.smoother.node_mean, b.smoother.node_mean, rtol=0, atol=1e-8)
        assert [e["kind"] for e in a.filter.log] == [e["kind"] for e in b.filter.log]
        assert a.start.index == b.start.index
        torch.testing.assert_close(a.gnss_enu_m, b.gnss_enu_m, rtol=0, atol=0)


def test_a_batch_that_carries_a_gradient_stays_in_this_process_and_workers_must_be_a_count(caplog):
    from flowins.navigation import navigate_batch

    recs = [synthetic_walk_recording(duration_s=5.0, seed=s) for s in (1, 2)]
    scale = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
    config = NavigationConfig(gnss_noise_scale=scale, gnss_heading=HeadingAlignment(enabled=False), workers=2)
    with caplog.at_level("INFO", logger="flowins"):
        results = navigate_batch([NavigationRun(r.imu, r.gnss) for r in recs], config=config)
    assert all(r.filter.node_mean.requires_grad for r in results)
    assert not any("worker processes" in r.getMessage() for r in caplog.records)
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="NavigationConfig.workers="):
            NavigationConfig(workers=bad)


def test_workers_started_by_spawn_take_pickled_runs_and_give_their_results(monkeypatch):
    """The start method off Linux: runs, config and results cross to and from the workers pickled."""
    import flowins.parallel as parallel
    from flowins.navigation import navigate_batch

    recs = [synthetic_walk_recording(duration_s=d, seed=s) for d, s in ((5.0, 4), (6.0, 5))]
    runs = [NavigationRun(r.imu, r.gnss) for r in recs]
    config = NavigationConfig(gnss_heading=HeadingAlignment(enabled=False))
    here = navigate_batch(runs, config=config)
    monkeypatch.setattr(parallel, "start_method", lambda: "spawn")
    there = navigate_batch(runs, config=dataclasses.replace(config, workers=2))
    for a, b in zip(there, here):
        torch.testing.assert_close(a.filter.node_mean, b.filter.node_mean, rtol=0, atol=1e-9)
        torch.testing.assert_close(a.smoother.node_mean, b.smoother.node_mean, rtol=0, atol=1e-8)


@pytest.mark.parametrize("gnss, alignment, yaw_sigma, expected", [
    (False, True, 2.5, 0.02), (True, True, 2.5, 2.5), (True, False, 2.5, 2.5), (False, True, 0.3, 0.3)])
def test_a_free_yaw_without_fixes_is_the_track_s_reference(recording, gnss, alignment, yaw_sigma, expected):
    """A still start leaves the yaw free. Without GNSS, where its σ (``yaw_rad``) says it is unknown,
    nothing can set it: the filter takes ``reference_yaw_rad``. With fixes it keeps ``yaw_rad`` (held
    fixes set the heading, or fixes that apply as they come turn it); a σ at or below
    ``unknown_yaw_sigma_rad`` (0.5) is a known yaw, kept as given."""
    from flowins.ins.initialization import InitialUncertainty
    from flowins.measurements.gnss_heading import heading_jacobian
    from flowins.navigation import prepare_navigation

    config = NavigationConfig(initial=InitialUncertainty(yaw_rad=yaw_sigma, reference_yaw_rad=0.02),
                              gnss_heading=HeadingAlignment(enabled=alignment))
    setup = prepare_navigation(NavigationRun(recording.imu, recording.gnss if gnss else None), config=config)
    h = heading_jacobian(setup.mean0)
    assert setup.start.mode == "still"
    assert float((h @ setup.cov0 @ h).sqrt()) == pytest.approx(expected, rel=1e-6)
