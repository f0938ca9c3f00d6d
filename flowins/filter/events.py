"""Measurement events the filter runner applies at their times.

Each event is a small frozen dataclass with ``time_s``, ``name`` (used in error
messages and logs) and ``apply(chain)``; the maths lives in the pure functions of
:mod:`flowins.filter.ekf`, :mod:`flowins.filter.augmentation` and
:mod:`flowins.measurements`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from torch import Tensor

from flowins.filter.augmentation import augment_pose, copy_matrices, forgetting_matrices
from flowins.filter.ekf import Gate, ekf_update
from flowins.filter.runner import ChainBuilder

if TYPE_CHECKING:
    from flowins.measurements.flow import FlowCamera
from flowins.measurements.gnss import gnss_jacobian_analytic, gnss_position
from flowins.state import STATE


@dataclass(frozen=True)
class GnssFix:
    """A GNSS position fix ``z`` (local ENU, m) with noise ``R`` ``(3, 3)``."""

    time_s: float
    position_m: Tensor  # (3,)
    noise_cov: Tensor  # (3, 3)
    gate: Gate = field(default_factory=Gate)
    lever_arm_m: Tensor | None = None
    name: str = "GNSS fix"

    def apply(self, chain: ChainBuilder) -> None:
        mean, cov = chain.mean, chain.cov
        lever = None if self.lever_arm_m is None else self.lever_arm_m.to(mean)
        H = gnss_jacobian_analytic(mean, lever)
        predicted = mean[STATE.p] if lever is None else gnss_position(mean, lever)
        innovation = self.position_m.to(mean) - predicted
        result = ekf_update(
            mean,
            cov,
            innovation=innovation.reshape(1, 3),
            H=H.reshape(1, 3, -1),
            noise_cov=self.noise_cov.to(mean).reshape(1, 3, 3),
            gate=self.gate,
        )
        chain.update(
            result,
            kind="gnss",
            name=self.name,
            nis=float(result.nis[0]),
            accepted=float(result.weight[0]),
        )


def gnss_fixes(
    t_s: Tensor,
    position_m: Tensor,
    noise_cov: Tensor,
    *,
    gate: Gate | None = None,
    lever_arm_m: Tensor | None = None,
    name: str = "GNSS",
) -> list[GnssFix]:
    """One :class:`GnssFix` per row of ``t_s (G,)``, ``position_m (G, 3)``, ``noise_cov (G, 3, 3)``."""
    gate = gate or Gate()
    return [
        GnssFix(float(t_s[i]), position_m[i], noise_cov[i], gate, lever_arm_m, f"{name} row {i}")
        for i in range(t_s.shape[0])
    ]


@dataclass(frozen=True)
class PoseAugmentation:
    """Pose forgetting then pose augmentation at ``time_s`` (the per-frame step of the paper).

    ``mode="paper"`` applies ``A⋆, Q⋆`` and the ``H⋆`` update literally;
    ``mode="limit"`` applies their ``σ → ∞`` limit (:func:`copy_pose`) as one
    linear step.
    """

    time_s: float
    sigma_p0: float | Tensor = 1e3
    sigma_q0: float | Tensor = 1e2
    nugget_var: float | Tensor = 1e-9
    mode: str = "paper"
    name: str = "pose augmentation"

    def __post_init__(self) -> None:
        if self.mode not in ("paper", "limit"):
            raise ValueError(f"PoseAugmentation.mode must be 'paper' or 'limit', got {self.mode!r}")

    def apply(self, chain: ChainBuilder) -> None:
        mean = chain.mean
        if self.mode == "paper":
            A, Q = forgetting_matrices(self.sigma_p0, self.sigma_q0, dtype=mean.dtype, device=mean.device)
            chain.linear_predict(A, Q)
            chain.update(augment_pose(chain.mean, chain.cov, nugget_var=self.nugget_var))
        else:
            # one linear step, recorded as such so the smoother sees its transition
            T, Q = copy_matrices(self.nugget_var, dtype=mean.dtype, device=mean.device)
            chain.linear_predict(T, Q)


@dataclass(frozen=True)
class FlowFrame:
    """A camera frame: flow updates against the augmented previous frame's pose, then
    pose forgetting and augmentation (the paper's per-frame order).

    ``flow_px``, ``uv1_px``, ``sigma_px`` ``(M, 2)``: flow points from the previous
    frame to this one, their pixels in the previous frame and 1-σ. The update uses
    the epipolar component of each point (:func:`flowins.measurements.flow.epipolar_update`);
    degenerate points are skipped and counted in the log. ``M = 0`` (the first
    frame) only augments.
    """

    time_s: float
    flow_px: Tensor
    uv1_px: Tensor
    sigma_px: Tensor
    camera: "FlowCamera"
    gate: Gate = field(default_factory=Gate)
    sequential: bool = False
    augmentation: PoseAugmentation | None = None
    #: leave out points whose parallax is below this many flow σ (0: keep all)
    min_parallax_sigma: float = 0.0
    name: str = "flow frame"

    def apply(self, chain: ChainBuilder) -> None:
        from flowins.measurements.flow import epipolar_update, flow_measurements

        M = self.flow_px.shape[0]
        if M:
            mean, cov = chain.mean, chain.cov
            sigma = self.sigma_px.to(mean)
            m = flow_measurements(
                mean, self.flow_px.to(mean), self.uv1_px.to(mean), self.camera,
                min_parallax_px=self.min_parallax_sigma * sigma.norm(dim=-1) / 2**0.5,
            )
            info = dict(kind="flow", name=self.name, points=M, valid=int(m.valid.sum()),
                        degenerate=m.n_degenerate, behind=m.n_behind, low_parallax=m.n_low_parallax)
            if bool(m.valid.any()):
                upd = epipolar_update(m, sigma)
                result = ekf_update(
                    mean, cov, innovation=upd.innovation, H=upd.H, noise_cov=upd.noise_cov,
                    gate=self.gate, sequential=self.sequential,
                )
                chain.update(result, accepted=float(result.weight.sum()), **info)
            else:
                chain.log.append({"t_s": chain.time_s, "accepted": 0.0, **info})
        augmentation = self.augmentation or PoseAugmentation(self.time_s)
        augmentation.apply(chain)
