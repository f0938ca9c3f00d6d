"""The INS pipeline from validated streams to filtered and smoothed tracks.

``data (streams) -> measurements (GNSS fixes) -> filter (EKF, RTS)``; the flow
updates of the paper join here as further events in a later release.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from flowins.data.streams import GnssStream, ImuStream
from flowins.filter.ekf import Gate
from flowins.filter.events import gnss_fixes
from flowins.filter.runner import FilterTrack, run_filter
from flowins.filter.smoother import SmoothedTrack, rts_smooth
from flowins.geometry.geodesy import LocalTangentPlane, gnss_to_enu
from flowins.ins.initialization import InitialUncertainty, stationary_initialization
from flowins.ins.mechanization import STANDARD_GRAVITY_MPS2, ProcessNoise
from flowins.measurements.gnss import gnss_noise


@dataclass(frozen=True)
class NavigationConfig:
    """Everything the INS(+GNSS) filter needs besides the data."""

    noise: ProcessNoise = field(default_factory=ProcessNoise)
    initial: InitialUncertainty = field(default_factory=InitialUncertainty)
    stationary_s: float = 5.0
    initial_yaw_rad: float = 0.0
    gnss_gate: Gate = field(default_factory=Gate)
    gnss_noise_scale: float = 1.0
    output_every: int = 10
    scheme: str = "midpoint"
    gravity_mps2: float = STANDARD_GRAVITY_MPS2
    jacobians: str = "analytic"
    dtype: torch.dtype = torch.float64


@dataclass
class NavigationResult:
    filter: FilterTrack
    smoother: SmoothedTrack
    frame: LocalTangentPlane | None
    gnss_t_s: Tensor | None
    gnss_enu_m: Tensor | None
    gnss_h_acc_m: Tensor | None

    @property
    def gnss_accepted(self) -> Tensor | None:
        """Gate decision (1 accepted, 0 rejected) of each GNSS fix, in order."""
        flags = [entry["accepted"] for entry in self.filter.log if entry.get("kind") == "gnss"]
        return torch.tensor(flags) if flags else None


def navigate(
    imu: ImuStream,
    gnss: GnssStream | None = None,
    *,
    config: NavigationConfig = NavigationConfig(),
    frame: LocalTangentPlane | None = None,
    progress: bool = False,
) -> NavigationResult:
    """Run the EKF and the RTS smoother on an IMU stream, with GNSS fixes if given.

    The filter starts at the first IMU sample from a stationary initialisation
    over ``config.stationary_s``; with GNSS the local ENU frame has its origin at
    the first fix (or ``frame``) and the initial position is that fix's, with
    its accuracy as uncertainty. GNSS fixes outside the IMU time span raise.
    """
    initial = config.initial
    events = []
    enu = cov = None
    if gnss is not None:
        enu, _, frame = gnss_to_enu(gnss, origin=frame)
        cov = gnss_noise(gnss.h_acc_m, gnss.v_acc_m, config.gnss_noise_scale)
        events = gnss_fixes(gnss.t_s, enu, cov, gate=config.gnss_gate, name=gnss.name)
        initial = InitialUncertainty(
            **{**initial.__dict__, "position_m": float(max(gnss.h_acc_m[0], gnss.v_acc_m[0]))}
        )
    mean0, cov0 = stationary_initialization(
        t_s=imu.t_s,
        acc_mps2=imu.acc_mps2,
        gyro_rps=imu.gyro_rps,
        duration_s=config.stationary_s,
        yaw_rad=config.initial_yaw_rad,
        position_m=None,
        uncertainty=initial,
        dtype=config.dtype,
        name=imu.name,
    )
    track = run_filter(
        t_s=imu.t_s,
        acc_mps2=imu.acc_mps2,
        gyro_rps=imu.gyro_rps,
        mean0=mean0,
        cov0=cov0,
        noise=config.noise,
        events=events,
        output_every=config.output_every,
        gravity_mps2=config.gravity_mps2,
        jacobians=config.jacobians,
        scheme=config.scheme,
        progress=progress,
    )
    return NavigationResult(
        filter=track,
        smoother=rts_smooth(track),
        frame=frame,
        gnss_t_s=None if gnss is None else gnss.t_s,
        gnss_enu_m=enu,
        gnss_h_acc_m=None if gnss is None else gnss.h_acc_m,
    )
