"""Flow frames in the filter: INS + optical flow on a simulated walk."""
import math

import pytest
import torch

from flowins.data.simulate.render import exact_flow, render
from flowins.data.simulate.scenario import CameraConfig, CameraTrajectory, SimulationConfig, simulate_imu
from flowins.data.simulate.world import build_city
from flowins.data.synthetic import Walk, WalkConfig
from flowins.measurements.flow_update import FlowFrame
from flowins.flow.points import FlowPoints
from flowins.filter.runner import FilterInput, run_filter, run_filters
from flowins.ins.initialization import augmented_covariance
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow import FlowCamera
from flowins.state import STATE, make_state

F64 = torch.float64


def test_flow_frames_bound_the_inertial_drift_and_reveal_the_gyro_bias():
    """10 s of walking, iPad-grade IMU errors, exact flow + 0.3 px noise at 100 points
    per frame (10 Hz) on near scene points: the drift shrinks by well over 10x."""
    run, walk, truth = _flow_run(5.0, 15.0, 100, 5, own_camera=False)
    t, acc, gyro, x0, cov0, events = run.t_s, run.acc_mps2, run.gyro_rps, run.mean0, run.cov0, run.events
    errors = {}
    for label, ev in (("ins", []), ("ins+flow", events)):
        track = run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=x0, cov0=cov0, noise=ProcessNoise(), events=ev)
        errors[label] = float((track.mean[-1, STATE.p] - walk.position(track.t[-1:])[0]).norm())
        assert torch.isfinite(track.node_cov).all()
    assert errors["ins"] > 5.0  # the inertial drift is real
    assert errors["ins+flow"] < errors["ins"] / 10, errors
    b_w_err = (track.mean[-1, STATE.b_w] - truth["b_w"][-1]).norm()
    assert float(b_w_err) < 0.3 * float(truth["b_w"][-1].norm())
    flows = [e for e in track.log if e.get("kind") == "flow"]
    assert len(flows) == len(events) - 1 and sum(e["valid"] + e["low_parallax"] for e in flows) >= 0.99 * 100 * len(flows)


def _flow_run(t0, t1, n_points, seed, *, own_camera):
    """INS + flow frames on the walk from ``t0`` to ``t1``: exact flow + 0.3 px noise at ``n_points``
    near scene points per frame (10 Hz), and a prior from the truth; with ``own_camera`` the
    frames carry a camera object of their own (equal values). Returns the run, the walk and
    the simulated truth."""
    walk = Walk(WalkConfig(duration_s=20.0))
    t, acc, gyro, truth = simulate_imu(walk, SimulationConfig(duration_s=20.0), torch.Generator().manual_seed(0))
    keep = (t >= t0) & (t <= t1 + 0.01)
    t, acc, gyro = t[keep], acc[keep], gyro[keep]
    cc = CameraConfig(width=160, height=120)
    cam, T_ci = cc.intrinsics(), cc.imu_to_camera()
    city = build_city(walk, seed=0)
    times = torch.arange(math.ceil(float(t[0]) * 10) / 10, float(t[-1]), 0.1, dtype=F64)
    R, P = CameraTrajectory(walk, T_ci).pose(times)
    camera = FlowCamera.from_calibration(cam, T_ci)
    if own_camera:
        camera = FlowCamera(camera.K.clone(), camera.R_ci.clone(), camera.t_ci.clone())
    gen = torch.Generator().manual_seed(seed)
    events, previous = [], None
    empty = torch.zeros(0, 2, dtype=F64)
    for i, ti in enumerate(times.tolist()):
        frame = render(city, cam, R[i], P[i], ti)
        if previous is None:
            events.append(FlowFrame(ti, FlowPoints(empty, empty, empty), camera))
        else:
            truth_flow = exact_flow(city, cam, previous[0], previous[1], (R[i], P[i], ti), frame)
            ok = (truth_flow.valid & truth_flow.static & (truth_flow.depth < 8.0)).nonzero()
            pick = ok[torch.randperm(ok.shape[0], generator=gen)[:n_points]]
            uv1 = torch.stack((pick[:, 1], pick[:, 0]), -1).to(F64)
            flow = truth_flow.flow[pick[:, 0], pick[:, 1]].to(F64) + 0.3 * torch.randn(pick.shape[0], 2, generator=gen, dtype=F64)
            events.append(FlowFrame(ti, FlowPoints(uv1, flow, torch.full_like(flow, 0.3)), camera))
        previous = (frame, (R[i], P[i], ti))
    x0 = make_state(p=walk.position(t[:1])[0], v=walk.velocity(t[:1])[0], q=walk.quaternion(t[:1])[0])
    sigma = torch.cat((torch.full((3,), 0.01), torch.full((3,), 0.01), torch.full((4,), 1e-3),
                       torch.full((3,), 0.05), torch.full((3,), 0.01), torch.full((3,), 0.02))).to(F64)
    return FilterInput(t, acc, gyro, x0, augmented_covariance(torch.diag(sigma**2), 1e-9), events), walk, truth


def test_flow_frames_of_unequal_runs_in_one_batch_equal_each_run_alone():
    """Two runs with their own spans, point counts (padded and masked in the batch) and camera
    objects, and frames that are not at the same times: each equals its run alone."""
    runs = [_flow_run(5.0, 9.0, 60, 1, own_camera=False)[0], _flow_run(6.03, 8.5, 90, 2, own_camera=True)[0]]
    batched = run_filters(runs, noise=ProcessNoise())
    for run, track in zip(runs, batched):
        alone = run_filter(t_s=run.t_s, acc_mps2=run.acc_mps2, gyro_rps=run.gyro_rps, mean0=run.mean0,
                           cov0=run.cov0, noise=ProcessNoise(), events=run.events)
        assert torch.equal(track.t_s, alone.t_s)
        assert [e["accepted"] for e in track.log] == [e["accepted"] for e in alone.log]
        for name in ("node_mean", "node_cov"):
            x, y = getattr(track, name), getattr(alone, name)
            torch.testing.assert_close(x, y, rtol=0, atol=1e-10 * max(1.0, float(y.abs().max())))


def test_a_batch_of_unequal_runs_copies_as_much_to_its_device_for_10_frames_as_for_20(fake_device):
    """Two runs with their own spans, point counts and frame times in one pass on the fake
    device (``conftest.FakeDevice``): the rows that take part in an event differ from event to
    event and the frames' points are padded to one count with a mask, yet the pass copies the
    same host data for 10 frames as for 20 (a set of rows' index once, the mask from the counts
    placed with the points) and reads nothing until its end."""
    import dataclasses

    runs = [_flow_run(5.0, 7.0, 60, 1, own_camera=False)[0], _flow_run(5.03, 6.6, 90, 2, own_camera=True)[0]]
    waits = []
    for end_s in (6.0, 6.0, 7.0):  # the first pass builds the constants the device keeps
        with fake_device() as mode:
            cut = [dataclasses.replace(run, mean0=run.mean0.to("meta"), cov0=run.cov0.to("meta"),
                                       events=[e for e in run.events if e.time_s <= end_s]) for run in runs]
            run_filters(cut, noise=ProcessNoise())
        assert mode.slips == {}, mode.slips
        waits.append((mode.reads, mode.copies))
    (reads, copies), (reads_20, copies_20) = waits[1:]
    assert reads == reads_20 and all(" at flowins/filter/chain.py" in key for key in reads), waits[1:]
    # no place copies more for 20 frames (the end moves each part's column indices at once, when it has any)
    assert copies_20.keys() <= copies.keys() and all(copies_20[k] <= copies[k] for k in copies_20), waits[1:]


@pytest.mark.slow
def test_flow_frames_in_float32_mix_no_dtypes_and_agree_with_float64(mixed_dtypes):
    """Every tensor the flow update, the pose augmentation, the recovery and the smoother build
    follows the state's dtype (and so its device): a float32 run with float64 as the default
    dtype mixes none (:class:`conftest.MixedDtypes`); with a tight gate (so the recovery
    inflates) too. Without it, the float32 run ends within 0.2 m of float64 (filter and smoother)."""
    from flowins.filter.ekf import Gate
    from flowins.filter.smoother import rts_smooth
    from flowins.measurements.flow_update import FlowRecovery, FlowUpdate

    run, walk, _ = _flow_run(5.0, 9.0, 60, 3, own_camera=False)
    plain = FlowUpdate(iterations=2, n_points=40)
    tight = FlowUpdate(iterations=2, n_points=40, gate=Gate(probability=0.9),
                       recovery=FlowRecovery(after_frames=2, max_accepted=0.99))
    ends = {}
    for dtype, update in ((torch.float64, plain), (torch.float32, plain), (torch.float32, tight)):
        events = [FlowFrame(e.time_s, e.points, e.camera, update) for e in run.events]
        with mixed_dtypes() as mode:
            track = run_filter(t_s=run.t_s, acc_mps2=run.acc_mps2, gyro_rps=run.gyro_rps, mean0=run.mean0.to(dtype),
                               cov0=run.cov0.to(dtype), noise=ProcessNoise(), events=events)
            smoothed = rts_smooth(track)
        assert mode.slips == {}, mode.slips
        assert track.node_mean.dtype == dtype and smoothed.node_cov.dtype == dtype
        inflated = any(e.get("inflated") for e in track.log)
        assert inflated == (update is tight)
        ends[dtype, update is tight] = torch.stack((track.node_mean[-1, STATE.p], smoothed.node_mean[0, STATE.p])).double()
    # float32 rounds the pose copy and the flow update (why filter.dtype refuses it): 4 s drift apart by ~0.1 m
    assert float((ends[torch.float32, False] - ends[torch.float64, False]).norm(dim=-1).max()) < 0.2


@pytest.mark.slow
def test_flow_frames_on_another_device_are_the_cpu_run(fake_device):
    """The flow update (stacked and sequential, iterated, with the recovery's inflation), the
    pose augmentation (exact and the paper's forgetting) and the smoother on the fake device of
    ``conftest.FakeDevice``: no op meets a CPU tensor there, and the numbers are the CPU run's."""
    from flowins.filter.ekf import Gate
    from flowins.filter.smoother import rts_smooth
    from flowins.measurements.flow_update import FlowRecovery, FlowUpdate

    run, _, _ = _flow_run(5.0, 7.0, 60, 3, own_camera=False)
    updates = (FlowUpdate(iterations=2, n_points=40, gate=Gate(probability=0.9),
                          recovery=FlowRecovery(after_frames=2, max_accepted=0.99)),
               FlowUpdate(sequential=True, n_points=20, augmentation_mode="paper", selection="grid"))
    for update in updates:
        events = [FlowFrame(e.time_s, e.points, e.camera, update) for e in run.events]
        tracks = []
        for device in ("cpu", "meta"):
            with fake_device() as mode:
                track = run_filter(t_s=run.t_s, acc_mps2=run.acc_mps2, gyro_rps=run.gyro_rps,
                                   mean0=run.mean0.to(device), cov0=run.cov0.to(device), noise=ProcessNoise(), events=events)
                tracks.append((track, rts_smooth(track)))
                assert track.node_mean.device.type == device and tracks[-1][1].node_cov.device.type == device
            assert mode.slips == {}, mode.slips
        (cpu, cpu_smoothed), (moved, smoothed) = tracks[-2:]
        assert torch.equal(moved.node_mean, cpu.node_mean) and torch.equal(smoothed.node_cov, cpu_smoothed.node_cov)
        assert any(e.get("inflated") for e in moved.log) == (update is updates[0])


def _every_event_kind(end_s):
    """The flow run of 5-7 s up to ``end_s`` with every kind of event: flow frames (iterated,
    gated, with the recovery counting and inflating), GNSS fixes (from 5.4 s on 30 m off, so that
    the third of them resets the filter), a zero-velocity and two vehicle updates."""
    from flowins.filter.ekf import Gate
    from flowins.measurements.flow_update import FlowRecovery, FlowUpdate
    from flowins.measurements.gnss import GnssFix, GnssRecovery
    from flowins.measurements.vehicle import VehicleSettings, VehicleUpdate
    from flowins.measurements.zero_velocity import ZeroVelocity

    run, walk, _ = _flow_run(5.0, 7.0, 60, 3, own_camera=False)
    update = FlowUpdate(iterations=2, n_points=40, gate=Gate(probability=0.9),
                        recovery=FlowRecovery(after_frames=2, max_accepted=0.99))
    vehicle = VehicleSettings(mode="on", mount_yaw_rad=0.03, lever_forward_m=-1.0)
    gate, recovery = Gate(), GnssRecovery()
    R = 0.25 * torch.eye(3, dtype=F64)
    off = torch.tensor([30.0, 0.0, 0.0], dtype=F64)
    events = [FlowFrame(e.time_s, e.points, e.camera, update) for e in run.events if e.time_s <= end_s]
    events += [ZeroVelocity(5.55, sigma_mps=0.5), VehicleUpdate(5.75, vehicle, run.gyro_rps[0]),
               VehicleUpdate(5.95, vehicle, run.gyro_rps[1])]
    events += [GnssFix(t, walk.position(torch.tensor([t], dtype=F64))[0] + (off if t > 5.3 else 0.0), R, gate,
                       recovery=recovery) for t in (5.15, 5.35, 5.55, 5.75, 5.95, 6.15) if t <= end_s]
    return run, events


def test_a_pass_of_every_event_kind_waits_for_its_device_only_when_it_ends(fake_device):
    """On the fake device (``conftest.FakeDevice``, which records every host read of a device
    tensor and every copy of host data to it, as a GPU would wait for each), a pass of flow
    frames, GNSS fixes with a reset, zero-velocity and vehicle updates (:func:`_every_event_kind`)
    reads nothing back while it runs, and copies the same host data for 10 frames as for 20 (the
    points, the fixes, the steps and the node plans move once per pass); its end reads its logs
    and its failure flags once each. The logs then hold the values of the same run on the CPU."""
    waits = []
    for end_s in (6.0, 6.0, 7.0):  # the first pass builds the constants each device keeps
        run, events = _every_event_kind(end_s)
        logs = {}
        for device in ("cpu", "meta"):
            with fake_device() as mode:
                track = run_filter(t_s=run.t_s, acc_mps2=run.acc_mps2, gyro_rps=run.gyro_rps, mean0=run.mean0.to(device),
                                   cov0=run.cov0.to(device), noise=ProcessNoise(), events=events)
            assert mode.slips == {}, mode.slips
            logs[device] = track.log
        waits.append((mode.reads, mode.copies))
        assert {"flow", "gnss", "zero_velocity", "vehicle"} <= {e["kind"] for e in track.log}
        assert any(e.get("inflated") for e in track.log)  # the flow recovery acted in the pass
        resets = [e for e in track.log if e["kind"] == "gnss_reset"]
        assert [(round(e["t_s"], 2), e["rejected"], e["velocity"]) for e in resets] == [(5.75, 3, True)], resets
        assert abs(resets[0]["offset_m"] - 30.0) < 1.0
        assert logs["meta"] == logs["cpu"]
    (reads, copies), (reads_20, copies_20) = waits[1:]
    assert reads == reads_20 and copies == copies_20, waits[1:]  # as many for 10 frames as for 20 ...
    assert sum(reads.values()) <= 2 and all(" at flowins/filter/chain.py" in key for key in reads), reads  # ... at the end


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (torch.cuda.is_available())")
def test_a_pass_of_every_event_kind_on_a_gpu_synchronises_as_often_for_10_frames_as_for_20():
    """The pass of :func:`_every_event_kind` on a GPU under ``torch.cuda.set_sync_debug_mode``:
    the operations that wait for the GPU (reads, copies from pageable memory) are the pass's
    set-up and end, as many for 10 frames as for 20, and a handful in all (run by
    ``benchmarks/gpu.sh``'s section 1)."""
    import warnings

    counts = []
    for end_s in (6.0, 6.0, 7.0):  # the first pass builds the constants the GPU keeps
        run, events = _every_event_kind(end_s)
        mean0, cov0 = run.mean0.to("cuda"), run.cov0.to("cuda")
        torch.cuda.synchronize()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                run_filter(t_s=run.t_s, acc_mps2=run.acc_mps2, gyro_rps=run.gyro_rps, mean0=mean0, cov0=cov0,
                           noise=ProcessNoise(), events=events)
            finally:
                torch.cuda.set_sync_debug_mode("default")
        counts.append(sum("synchroniz" in str(w.message) for w in caught))
    assert counts[1] == counts[2] <= 24, counts  # the set-up's copies and the end's two reads
