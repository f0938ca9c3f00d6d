"""The flow updater: a camera frame's flow points as a filter event (the paper's per-frame
order: flow update against the augmented previous pose, then pose forgetting and
augmentation), with the point selection, noise, gate and recovery settings."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from flowins.filter.augmentation import PoseAugmentation
from flowins.filter.ekf import Gate, ekf_update
from flowins.filter.runner import ChainBuilder
from flowins.flow.points import FlowPoints
from flowins.measurements.flow import FlowCamera, epipolar_update, flow_measurements
from flowins.measurements.selection import select_points
from flowins.state import STATE, normalize_quaternions


@dataclass(frozen=True)
class FlowRecovery:
    """What follows frames whose flow the filter rejects (config ``filter.flow.recovery``).

    A filter whose velocity or attitude has gone wrong finds most flow points
    outside its gate, and the gate keeps out the very measurements that would correct
    it. After ``after_frames`` consecutive frames with at least ``min_valid`` valid
    points of which at most ``max_accepted`` (a fraction) pass the gate, the velocity's
    σ is raised by ``velocity_sigma_mps`` and the gyroscope bias's by
    ``gyro_bias_sigma_rps`` (a logged ``flow_inflate`` step), so that the next frames can
    pull the filter back. 0 frames switches it off.
    """

    after_frames: int = 5
    max_accepted: float = 0.5
    min_valid: int = 8
    velocity_sigma_mps: float = 0.5
    gyro_bias_sigma_rps: float = 2e-3

    def __post_init__(self) -> None:
        for key in ("after_frames", "min_valid"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ValueError(f"filter.flow.recovery.{key} must be an integer >= 0, got {value!r}")
        if not 0.0 <= self.max_accepted < 1.0:
            raise ValueError(f"filter.flow.recovery.max_accepted must be in [0, 1), got {self.max_accepted!r}")
        for key in ("velocity_sigma_mps", "gyro_bias_sigma_rps"):
            if not getattr(self, key) >= 0.0:
                raise ValueError(f"filter.flow.recovery.{key} must be >= 0, got {getattr(self, key)!r}")

    def gated(self, valid: int, accepted: float) -> bool:
        """Whether a frame with ``valid`` points of which ``accepted`` passed counts as gated."""
        return valid >= max(self.min_valid, 1) and accepted <= self.max_accepted * valid

    def inflation(self, mean: Tensor) -> Tensor:
        """``Q (D, D)``: the covariance added to the state ``mean`` ``(D,)``."""
        Q = mean.new_zeros(mean.shape[-1], mean.shape[-1])
        Q[STATE.v, STATE.v] = self.velocity_sigma_mps**2 * torch.eye(3, dtype=mean.dtype)
        Q[STATE.b_w, STATE.b_w] = self.gyro_bias_sigma_rps**2 * torch.eye(3, dtype=mean.dtype)
        return Q


@dataclass(frozen=True)
class FlowUpdate:
    """How a frame's flow points update the filter (every field has a config entry).

    Attributes:
        n_points: points used per frame, chosen at the current state by ``selection``
            (:func:`flowins.measurements.selection.select_points`); None: all.
        selection: ``"parallax"`` | ``"sigma"`` | ``"grid"``; ``cell_px``: spreading cell.
        sigma_scale, sigma_floor_px: the flow noise used is
            ``σ = sqrt((sigma_scale σ_flow)² + sigma_floor_px²)`` per component.
        min_parallax_sigma: leave out points whose rotation-compensated parallax is
            below this many σ (0: keep all).
        parallax_inflation: inflate each point's noise by ``p² / (p² - σ²)`` (``p`` the
            measured parallax): the depth, and with it ``H_x``, is estimated from the same
            noisy flow, and without the correction a low-parallax point claims
            ``(p² + σ²) / p²`` times the information it has (errors in variables).
        gate: χ² gate on each point's scalar innovation (moving objects, bad flow).
        sequential: the paper's point-by-point update instead of one stacked update.
        iterations: relinearisations of the measurement (1: EKF, > 1: iterated EKF).
        augmentation: the pose forgetting + augmentation after the update.
        recovery: what follows frames whose flow is nearly all gated (:class:`FlowRecovery`).
    """

    n_points: int | None = 256
    selection: str = "parallax"
    cell_px: float = 80.0
    sigma_scale: float | Tensor = 1.0
    sigma_floor_px: float | Tensor = 0.25
    min_parallax_sigma: float = 1.0
    parallax_inflation: bool = True
    gate: Gate = field(default_factory=Gate)
    sequential: bool = False
    iterations: int = 1
    augmentation_mode: str = "limit"
    sigma_p0: float | Tensor = 1e3
    sigma_q0: float | Tensor = 1e2
    recovery: FlowRecovery = field(default_factory=FlowRecovery)

    def __post_init__(self) -> None:
        if self.n_points is not None and self.n_points < 1:
            raise ValueError(f"FlowUpdate.n_points must be >= 1 or None, got {self.n_points}")
        if self.iterations < 1:
            raise ValueError(f"FlowUpdate.iterations must be >= 1, got {self.iterations}")
        if self.min_parallax_sigma < 0:
            raise ValueError(f"FlowUpdate.min_parallax_sigma must be >= 0, got {self.min_parallax_sigma}")


#: every point used, no inflation, no parallax limit, no gate: the paper's update as written
PAPER_FLOW_UPDATE = FlowUpdate(n_points=None, min_parallax_sigma=0.0, parallax_inflation=False,
                               sigma_floor_px=0.0, gate=Gate(mode="off"))


@dataclass(frozen=True)
class FlowFrame:
    """A camera frame: flow updates against the augmented previous frame's pose, then
    pose forgetting and augmentation (the paper's per-frame order).

    ``points``: the flow points from the previous frame used by the filter to this
    one (:class:`~flowins.flow.points.FlowPoints`, ``M`` of them; ``M = 0`` for the
    first frame, which only augments). The update uses the epipolar component of each
    point (:func:`flowins.measurements.flow.epipolar_update`); degenerate points are
    skipped and counted in the log.
    """

    time_s: float
    points: FlowPoints
    camera: FlowCamera
    update: FlowUpdate = field(default_factory=FlowUpdate)
    name: str = "flow frame"
    #: ``"analytic"`` | ``"autodiff"``: how ``H_x``, ``H_r`` are computed
    #: (:func:`flowins.measurements.flow.flow_measurements`)
    jacobians: str = "analytic"

    def noise_sigma(self, sigma_px: Tensor) -> Tensor:
        u = self.update
        scale = torch.as_tensor(u.sigma_scale, dtype=sigma_px.dtype)
        floor = torch.as_tensor(u.sigma_floor_px, dtype=sigma_px.dtype)
        return torch.sqrt((scale * sigma_px) ** 2 + floor**2)

    def apply(self, chain: ChainBuilder) -> None:
        u = self.update
        points = self.points
        M = len(points)
        if M:
            mean, cov = chain.mean, chain.cov
            points = type(points)(points.uv1_px.to(mean), points.flow_px.to(mean), self.noise_sigma(points.sigma_px.to(mean)))
            if u.n_points is not None and M > u.n_points:
                keep = select_points(mean, points, self.camera.K, self.camera.R_ci, n_points=u.n_points,
                                     method=u.selection, cell_px=u.cell_px)
                points = points.take(keep)
            sigma = points.sigma_px
            min_parallax = u.min_parallax_sigma * torch.linalg.vector_norm(sigma, dim=-1) / 2**0.5
            x_i, result = mean, None
            for _ in range(u.iterations):
                m = flow_measurements(x_i, points.flow_px, points.uv1_px, self.camera, min_parallax_px=min_parallax,
                                      jacobians=self.jacobians)
                if not bool(m.valid.any()):
                    break
                upd = epipolar_update(m, sigma, parallax_inflation=u.parallax_inflation)
                # iterated EKF: linearised at x_i, applied to the prior (mean, cov)
                shift = (upd.H @ (mean - x_i).unsqueeze(-1)).squeeze(-1)
                result = ekf_update(mean, cov, innovation=upd.innovation - shift, H=upd.H,
                                    noise_cov=upd.noise_cov, gate=u.gate, sequential=u.sequential,
                                    normalize=normalize_quaternions)
                x_i = result.mean
            info = dict(kind="flow", name=self.name, candidates=M, points=len(points), valid=int(m.valid.sum()),
                        degenerate=m.n_degenerate, behind=m.n_behind, low_parallax=m.n_low_parallax)
            accepted = 0.0 if result is None else float(result.weight.detach().sum())
            if result is not None:
                chain.update(result, accepted=accepted, **info)
            else:
                chain.log.append({"t_s": chain.time_s, "accepted": 0.0, **info})
            self._recover(chain, valid=info["valid"], accepted=accepted)
        PoseAugmentation(self.time_s, u.sigma_p0, u.sigma_q0, mode=u.augmentation_mode).apply(chain)

    def _recover(self, chain: ChainBuilder, *, valid: int, accepted: float) -> None:
        """Count consecutive gated frames; after ``recovery.after_frames`` inflate (:class:`FlowRecovery`)."""
        r = self.update.recovery
        if r.after_frames == 0:
            return
        gated = chain.memory.get("flow_gated", 0) + 1 if r.gated(valid, accepted) else 0
        chain.memory["flow_gated"] = gated
        if gated >= r.after_frames:
            eye = torch.eye(chain.mean.shape[-1], dtype=chain.mean.dtype)
            chain.linear_predict(eye, r.inflation(chain.mean), kind="flow_inflate", name=self.name, frames=gated)
            chain.memory["flow_gated"] = 0
