"""Recovery after frames whose flow is nearly all gated: a filter sure of a wrong gyroscope
bias rejects every point of a scene it moves through, unless it inflates and lets them in."""
from __future__ import annotations

import pytest
import torch

from flowins.data.simulate.scenario import CameraConfig
from flowins.measurements.flow_update import FlowFrame, FlowRecovery, FlowUpdate
from flowins.filter.runner import run_filter
from flowins.flow.points import FlowPoints
from flowins.ins.initialization import InitialUncertainty, still_prior
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2 as G
from flowins.ins.mechanization import ProcessNoise
from flowins.measurements.flow import FlowCamera
from flowins.state import STATE

F64 = torch.float64
SPEED = torch.tensor([1.0, 0.0, 0.0], dtype=F64)  # level, forward along body x = world x


def project(points_w: torch.Tensor, position: torch.Tensor, camera: CameraConfig) -> torch.Tensor:
    """Pixels ``(M, 2)`` of world points seen by the level, unrotated body at ``position``."""
    T = camera.imu_to_camera()
    x_c = (T.rotation_matrix @ (points_w - position).T).T + T.translation_m
    K = camera.intrinsics().K
    return torch.stack((K[0, 0] * x_c[:, 0] / x_c[:, 2] + K[0, 2], K[1, 1] * x_c[:, 1] / x_c[:, 2] + K[1, 2]), -1)


ROLL_BIAS = 0.4  # rad/s on the gyroscope's x axis, the camera's optical axis


def run(recovery: FlowRecovery):
    """3 s at 1 m/s without turning through 200 points 6–15 m ahead. The gyroscope reads a
    roll rate of 0.4 rad/s that is all bias; the prior is sure the bias is 0 (σ 1e-5 rad/s).
    A roll turns the image about its centre, across the epipolar lines of the forward
    motion, so the predicted flow misses most points."""
    gen = torch.Generator().manual_seed(0)
    cc = CameraConfig()
    scene = torch.stack((6 + 9 * torch.rand(200, generator=gen, dtype=F64), -4 + 8 * torch.rand(200, generator=gen, dtype=F64),
                         -1 + 4 * torch.rand(200, generator=gen, dtype=F64)), -1)
    n = 301
    t = torch.arange(n, dtype=F64) / 100
    acc = torch.tensor([0.0, 0.0, G], dtype=F64).expand(n, 3)
    gyro = torch.tensor([ROLL_BIAS, 0.0, 0.0], dtype=F64).expand(n, 3)
    sure = InitialUncertainty(velocity_mps=1e-3, roll_pitch_rad=1e-4, yaw_rad=1e-4, acc_bias_mps2=1e-4, gyro_bias_rps=1e-5,
                              acc_scale=1e-5)
    mean, cov = still_prior(acc[:50], torch.zeros(50, 3, dtype=F64), uncertainty=sure)
    mean[STATE.v] = SPEED
    camera = FlowCamera.from_calibration(cc.intrinsics(), cc.imu_to_camera())
    update = FlowUpdate(recovery=recovery)
    events = []
    for k, tk in enumerate(torch.arange(0.0, 3.0 + 1e-9, 0.1, dtype=F64).tolist()):
        if k == 0:
            points = FlowPoints(*(torch.zeros(0, 2, dtype=F64),) * 3)
        else:
            uv1 = project(scene, SPEED * (tk - 0.1), cc)
            flow = project(scene, SPEED * tk, cc) - uv1
            points = FlowPoints(uv1, flow, torch.full_like(uv1, 0.1))
        events.append(FlowFrame(tk, points, camera, update, f"frame {k}"))
    return run_filter(t_s=t, acc_mps2=acc, gyro_rps=gyro, mean0=mean, cov0=cov, noise=ProcessNoise(), events=events)


@pytest.mark.parametrize("after", [0, 5])
def test_a_filter_sure_of_a_wrong_gyro_bias_inflates_after_gated_frames_and_recovers(after):
    track = run(FlowRecovery(after_frames=after, gyro_bias_sigma_rps=2.0))
    frames = [e for e in track.log if e.get("kind") == "flow"]
    inflations = [e for e in frames if e.get("inflated")]
    share = [e["accepted"] / e["valid"] for e in frames]
    assert max(share[:5]) <= 0.3  # most points disagree with the roll
    b_w = track.node_mean[-1, STATE.b_w]
    if after == 0:
        assert not inflations and max(share) <= 0.3  # locked out: most of the flow stays out ...
        assert float(b_w.norm()) < 1e-3  # ... and the bias is never learnt
    else:
        assert len(inflations) == 1 and inflations[0]["gated_frames"] == after
        assert abs(inflations[0]["t_s"] - 0.1 * after) < 1e-9
        assert min(share[after:after + 5]) > 0.9  # the flow is let in ...
        assert abs(float(b_w[0]) - ROLL_BIAS) < 0.02  # ... and sets the bias
        assert float(torch.linalg.eigvalsh(track.node_cov[-1]).min()) > 0


def test_flow_recovery_settings_name_the_bad_key():
    """From code the field (``tests/test_config.py``: from a config, the key)."""
    with pytest.raises(ValueError, match=r"FlowRecovery\.max_accepted=1\.5: expected a number < 1"):
        FlowRecovery(max_accepted=1.5)
    with pytest.raises(ValueError, match=r"FlowRecovery\.after_frames=-1: expected an integer >= 0"):
        FlowRecovery(after_frames=-1)
