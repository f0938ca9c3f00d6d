"""The filter's free parameters as one ``nn.Module``: each a start value times a bounded factor.

Each parameter ``θ`` has a start ``θ₀`` (the hand-tuned value, or ``model.start``), a bound
of ``b`` decades (``model.bound_decades``, per name ``model.bounds``) and one unconstrained
coordinate ``a`` (``raw.<name>``, 0 at the start), which the optimiser moves. With
``B = b ln 10``:

* a positive parameter is ``θ = θ₀ · exp(B · tanh(a / B))``, within
  ``[θ₀ · 10^-b, θ₀ · 10^b]`` whatever ``a`` is;
* the dropout rate is ``logit θ = logit θ₀ + B · tanh(a / B)``: its odds within
  ``10^±b`` of the start's, the rate in ``(0, 1)``.

An angle's 1-σ has an absolute ceiling ``c`` too (:data:`CEILINGS`: roll/pitch ``π/2``, yaw
``π``): above the start, ``B`` is replaced by ``B⁺ = min(B, ln(c / θ₀))``, so the value stays
below ``c`` (and at ``θ₀`` when it starts at or above it) with the same slope of 1 at the start.

A signed parameter (:data:`SIGNED`: the vehicle constraint's mounting angles and lever arm)
moves by a step ``u`` per unit of ``a`` within a largest magnitude ``W`` (its bound, in its
own units: ``model.bounds.<name>``, default :data:`SIGNED`'s):
``θ = W tanh(atanh(θ₀ / W) + u a / W)`` (written as ``θ₀`` plus a difference of tanh, so that it
is exactly ``θ₀`` at ``a = 0``), with a slope ``u`` at
``θ₀ = 0``, and ``|θ| < W`` whatever ``a`` is; it may start at 0 or below.

Near the start ``d ln θ / d a = sech²(a / B) ≈ 1``, so the learning rate is in units of
``ln θ`` (of ``logit θ`` for the dropout rate): ai-imu-dr's factor ``10^tanh(a)`` on its
learned covariances, widened to ``b`` decades and with a slope of 1 at the start. A bound
of ``None`` (``null``) is ``B = ∞``: ``θ = θ₀ · exp(a)``, plain log (logit) space without
a prior. A parameter that starts at 0 stays 0 (a random walk switched off): it cannot be
learned.

The start and the bound of each parameter are buffers (``center.<name>``,
``bound.<name>`` in decades, ``inf`` for none), so a checkpoint's ``state_dict`` alone gives
the values (:meth:`FilterParameters.from_checkpoint`). A checkpoint with ``raw.<name>``
only (no ``center.<name>``) holds each value's log (logit) and loads as those values.
:meth:`FilterParameters.apply` writes the current values (tensors with a gradient) into a
:class:`~flowins.navigation.NavigationConfig`; the filter then runs unchanged, and the
gradient of a loss on its output reaches every learned coordinate.

The parameters (units of the filter config, ``configs/filter/default.yaml``):

==========================  ==========================================================
``acc_noise``, ``gyro_noise``  IMU white-noise densities ``Σ_a``, ``Σ_ω`` (per √Hz)
``*_bias_walk``, ``acc_scale_walk``  random walks of the biases and the scale
``initial_*``               1-σ of the initial state (velocity, roll/pitch, biases, scale;
                            position and yaw too, frozen by default: at the start they are
                            unknown by construction, not a tuning choice)
``sigma_p0``, ``sigma_q0``  pose-forgetting variances (used by ``augmentation_mode: paper``)
``gnss_noise_scale``        multiplies each fix's reported accuracy
``flow_sigma_scale``,       flow noise ``σ = sqrt((scale σ_flow)² + floor²)``
``flow_sigma_floor_px``
``dropout_p``               Monte Carlo dropout rate of the flow network
``vehicle_*_sigma_mps``     σ of the vehicle constraint's sideways and vertical velocity
``vehicle_mount_*_rad``     the IMU's mounting turn from the vehicle's axes (pitch, yaw; signed)
``vehicle_lever_*_m``       the non-slipping point from the IMU (forward, left, up; signed)
``tracks_sigma_px``         1-σ of a tracked pixel in the multi-view track update
``*_gate_threshold``,       the χ² gates of the flow points and the GNSS fixes: soft
``*_gate_softness``         (``sigmoid((threshold - NIS) / softness)``) while training,
                            hard (``NIS <= threshold``) at inference
``tracks_gate_scale``,      the χ² gate of the multi-view tracks, whose degrees of freedom
``tracks_gate_softness``    differ by track: ``threshold = scale · χ²_dof(probability)``,
                            soft while training and hard at inference as above
==========================  ==========================================================
"""
from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import torch
from torch import Tensor, nn

from flowins.config import bounded
from flowins.filter.ekf import Gate
from flowins.ins.initialization import InitialUncertainty
from flowins.measurements.adaptive_noise import AdaptiveNoise
from flowins.measurements.vehicle import VehicleSettings
from flowins.navigation import NavigationConfig
from flowins.serialization import load_tensors

#: name -> (where in NavigationConfig, field); "gate:*" and "dropout" are handled apart
_FIELDS: dict[str, tuple[str, str]] = {
    "acc_noise": ("noise", "acc_noise"),
    "gyro_noise": ("noise", "gyro_noise"),
    "acc_bias_walk": ("noise", "acc_bias_walk"),
    "gyro_bias_walk": ("noise", "gyro_bias_walk"),
    "acc_scale_walk": ("noise", "acc_scale_walk"),
    "initial_position_m": ("initial", "position_m"),
    "initial_velocity_mps": ("initial", "velocity_mps"),
    "initial_roll_pitch_rad": ("initial", "roll_pitch_rad"),
    "initial_yaw_rad": ("initial", "yaw_rad"),
    "initial_acc_bias_mps2": ("initial", "acc_bias_mps2"),
    "initial_gyro_bias_rps": ("initial", "gyro_bias_rps"),
    "initial_acc_scale": ("initial", "acc_scale"),
    "sigma_p0": ("flow", "sigma_p0"),
    "sigma_q0": ("flow", "sigma_q0"),
    "gnss_noise_scale": ("config", "gnss_noise_scale"),
    "flow_sigma_scale": ("flow", "sigma_scale"),
    "flow_sigma_floor_px": ("flow", "sigma_floor_px"),
    "flow_gate_threshold": ("gate", "flow"),
    "flow_gate_softness": ("gate", "flow"),
    "gnss_gate_threshold": ("gate", "gnss"),
    "gnss_gate_softness": ("gate", "gnss"),
    "vehicle_lateral_sigma_mps": ("vehicle", "lateral_sigma_mps"),
    "vehicle_vertical_sigma_mps": ("vehicle", "vertical_sigma_mps"),
    "vehicle_mount_pitch_rad": ("vehicle", "mount_pitch_rad"),
    "vehicle_mount_yaw_rad": ("vehicle", "mount_yaw_rad"),
    "vehicle_lever_forward_m": ("vehicle", "lever_forward_m"),
    "vehicle_lever_left_m": ("vehicle", "lever_left_m"),
    "vehicle_lever_up_m": ("vehicle", "lever_up_m"),
    "tracks_sigma_px": ("tracks", "sigma_px"),
    "tracks_gate_scale": ("gate", "tracks"),
    "tracks_gate_softness": ("gate", "tracks"),
    "dropout_p": ("dropout", "p"),
}
#: names a checkpoint written before they existed lacks: it loads with their defaults
ADDED_NAMES: frozenset[str] = frozenset({"vehicle_lateral_sigma_mps", "vehicle_vertical_sigma_mps", "tracks_sigma_px",
                                         "tracks_gate_scale", "tracks_gate_softness", "vehicle_mount_pitch_rad",
                                         "vehicle_mount_yaw_rad", "vehicle_lever_forward_m", "vehicle_lever_left_m",
                                         "vehicle_lever_up_m"})
#: the measurement kinds whose σs a learned network may set (``model.adaptive``): kind -> its σs
ADAPTIVE_KINDS: dict[str, int] = {"vehicle": 2}
#: the kinds whose network may also set angles (``model.adaptive_angles_rad``): kind -> how many
#: (the vehicle constraint's mounting pitch and yaw at each update)
ADAPTIVE_ANGLES: dict[str, int] = {"vehicle": 2}
#: signed parameters: name -> (step u per unit of the coordinate, largest magnitude W), in the
#: parameter's units (the module docstring); W stays inside VehicleSettings' own limits
SIGNED: dict[str, tuple[float, float]] = {
    "vehicle_mount_pitch_rad": (0.01, 0.3), "vehicle_mount_yaw_rad": (0.01, 0.3),
    "vehicle_lever_forward_m": (0.1, 5.0), "vehicle_lever_left_m": (0.1, 5.0), "vehicle_lever_up_m": (0.1, 5.0),
}
NAMES: tuple[str, ...] = tuple(_FIELDS)
#: the noise parameters (what a "mis-tuned" start multiplies)
NOISE_NAMES: tuple[str, ...] = (
    "acc_noise", "gyro_noise", "acc_bias_walk", "gyro_bias_walk", "acc_scale_walk",
    "initial_velocity_mps", "initial_roll_pitch_rad", "initial_acc_bias_mps2", "initial_gyro_bias_rps",
    "initial_acc_scale", "gnss_noise_scale", "flow_sigma_scale", "flow_sigma_floor_px",
)  # fmt: skip
#: the noise levels one factor scales with the filter's estimates unchanged (``model.noise_level``):
#: the noise parameters and the other measurements' σs
LEVEL_NAMES: tuple[str, ...] = (*NOISE_NAMES, "vehicle_lateral_sigma_mps", "vehicle_vertical_sigma_mps",
                                "tracks_sigma_px")
#: frozen unless the config says otherwise
FROZEN_BY_DEFAULT = frozenset({"initial_position_m", "initial_yaw_rad", *SIGNED})
#: how far a learned value may go from its start, in decades each way (``model.bound_decades``)
DEFAULT_BOUND_DECADES = 2.0
#: absolute ceilings whatever the start and the bound: an angle's 1-σ beyond these means nothing
#: (a roll or pitch 1-σ past a right angle, a yaw 1-σ past half a turn)
CEILINGS: dict[str, float] = {"initial_roll_pitch_rad": math.pi / 2, "initial_yaw_rad": math.pi}


@dataclass(frozen=True)
class ModelSettings:
    """The ``model`` config group (``configs/model/filter.yaml``): the loss, the optimiser's
    schedule and which parameters start where and are learned.

    Attributes:
        lr, lr_final, warmup_steps: Adam's learning rate (units of log(parameter) near the
            start), the end of its cosine decay, and the linear warm-up's optimiser steps.
        accumulate_windows: window groups whose gradients are summed into one step.
        average_epochs: the parameters after every optimiser step of the last this many epochs
            averaged (in the optimiser's coordinates) into one more candidate, validated after
            the last epoch (:meth:`~flowins.training.module.FilterLearner.use_average`); 0: none.
        gradient_clip: the gradient-norm clip of each step.
        nll_weight: weight of the Gaussian negative log-likelihood of the position errors.
        innovation_weight: weight of the innovation negative log-likelihood per scalar
            measurement (metres per nat; :func:`~flowins.training.unroll.window_loss`).
        innovation_learns: parameters learned from the innovation negative log-likelihood
            per scalar measurement alone, the rest from the window loss
            (:func:`~flowins.training.unroll.split_gradient`). The likelihood fixes absolute
            noise levels, which the window loss sees only as ratios; () for none.
        noise_level: ``loss``: every parameter from the loss; ``likelihood``: the learned
            parameters of :data:`LEVEL_NAMES` keep their ratios from the loss and take their
            common level from the innovation likelihood per scalar measurement
            (:func:`~flowins.training.unroll.level_gradient`).
        orientation_weight_m_per_rad: weight of the orientation RMSE (rad) in the loss.
        loss: ``window`` (the position RMSE after each window's yaw alignment), ``segments``
            (relative errors over segments of ``segment_s``) or ``start`` (the position RMSE after
            one alignment per sequence, at its start; :func:`~flowins.training.unroll.window_loss`).
        segment_s: the segment durations (s) of ``loss=segments``.
        mistune: every noise parameter's start multiplied by this.
        start: starting values replacing the filter config's, by parameter name (>= 0, any
            sign for those of :data:`SIGNED`).
        learn, freeze: the names learned (None: all but the frozen-by-default ones) and kept.
        bound_decades: how far a learned value may go from its start, in decades each way
            (the module docstring); None: unbounded.
        bounds: ``bound_decades`` replaced for these names (a number > 0, or None); for those
            of :data:`SIGNED` their largest magnitude in their units (None or left out:
            :data:`SIGNED`'s).
        adaptive: measurement kinds whose σs a learned network sets at each update
            (:data:`ADAPTIVE_KINDS`; :class:`~flowins.measurements.adaptive_noise.AdaptiveNoise`).
        adaptive_decades: each of its factors within ``10^±adaptive_decades`` of the σ.
        adaptive_angles_rad: > 0: the vehicle network also sets the mounting's pitch and yaw at
            each update (the car's pitch under acceleration, its slip in a turn), each within
            ``±adaptive_angles_rad`` of the mounting (:data:`ADAPTIVE_ANGLES`); 0: σs only.
        adaptive_compensate_gravity: the angles read the car's acceleration, the specific force
            less gravity by the filter's attitude at each update, not the specific force, in
            which a slope looks like an acceleration (needs ``adaptive_angles_rad > 0``).
        adaptive_lr: the networks' weights' learning rate at the start, on ``lr``'s schedule
            (warm-up and decay alike).
        checkpoint: a ``train.py`` checkpoint whose learned values the filter uses.
        select_flow_gate: probabilities ``p`` whose χ²₁ quantiles compete, after training, as
            the flow gate's threshold of the chosen validation's parameters (each one more
            validation; :meth:`~flowins.training.module.FilterLearner.gate_variants`); () for none.
        recheck_while_training: the flow recheck (``filter.flow.recheck``) soft in the training
            steps; False: off there (one update per frame), as configured in every validation.
    """

    lr: float = bounded(0.1, minimum=1e-12)
    lr_final: float | None = bounded(None, minimum=1e-12)
    warmup_steps: int = bounded(0, minimum=0)
    accumulate_windows: int = bounded(1, minimum=1)
    average_epochs: int = bounded(0, minimum=0)
    gradient_clip: float = bounded(1.0, minimum=1e-12)
    nll_weight: float = bounded(0.0, minimum=0.0)
    innovation_weight: float = bounded(0.0, minimum=0.0)
    innovation_learns: tuple[str, ...] = ()
    noise_level: Literal["loss", "likelihood"] = "loss"
    orientation_weight_m_per_rad: float = bounded(0.0, minimum=0.0)
    loss: Literal["window", "segments", "start"] = "window"
    segment_s: tuple[float, ...] = bounded((10.0, 20.0, 40.0), minimum=1e-3, nonempty=True)
    mistune: float = bounded(1.0, minimum=1e-12)
    start: dict[str, float] = bounded({})
    learn: tuple[str, ...] | None = None
    freeze: tuple[str, ...] = ()
    bound_decades: float | None = bounded(DEFAULT_BOUND_DECADES, minimum=1e-12)
    bounds: dict[str, float | None] = bounded({})
    adaptive: tuple[str, ...] = ()
    adaptive_decades: float = bounded(1.0, above=0.0)
    adaptive_angles_rad: float = bounded(0.0, minimum=0.0, maximum=0.5)
    adaptive_compensate_gravity: bool = False
    adaptive_lr: float = bounded(0.01, minimum=1e-12)
    checkpoint: str | None = None
    select_flow_gate: tuple[float, ...] = bounded((), above=0.0, below=1.0)
    recheck_while_training: bool = True

    def __post_init__(self) -> None:
        if unknown := sorted(set(self.adaptive) - set(ADAPTIVE_KINDS)):
            raise ValueError(f"model.adaptive: {unknown}; expected kinds from {list(ADAPTIVE_KINDS)}")
        if self.adaptive_compensate_gravity and not (self.adaptive_angles_rad > 0
                                                     and set(self.adaptive) & set(ADAPTIVE_ANGLES)):
            raise ValueError("model.adaptive_compensate_gravity=true: it acts on the angles; expected "
                             f"model.adaptive with one of {list(ADAPTIVE_ANGLES)} and model.adaptive_angles_rad > 0")
        for name, value in self.start.items():
            if name not in NAMES:
                raise ValueError(f"model.start.{name}: unknown parameter; expected names from {', '.join(NAMES)}")
            if name in SIGNED:
                if not abs(value) < SIGNED[name][1]:
                    raise ValueError(f"model.start.{name}={value!r}: expected a number of magnitude < "
                                     f"{SIGNED[name][1]:g}")
            elif not value >= 0.0:
                raise ValueError(f"model.start.{name}={value!r}: expected a number >= 0")
        for key in ("learn", "freeze", "innovation_learns"):
            for name in getattr(self, key) or ():
                if name not in NAMES:
                    raise ValueError(f"model.{key}: unknown parameter {name!r}; expected names from {', '.join(NAMES)}")
        if self.learn is not None:  # checked here, before any sequence is loaded, where the names are given
            self.level_group(set(self.learn) - set(self.freeze), source="model.learn")
        for name, decades in self.bounds.items():
            if name not in NAMES:
                raise ValueError(f"model.bounds.{name}: unknown parameter; expected names from {', '.join(NAMES)}")
            if decades is not None and not decades > 0.0:
                raise ValueError(f"model.bounds.{name}={decades!r}: expected a number > 0 or null (unbounded)")

    def level_group(self, learned: Iterable[str], *, source: str = "the learned parameters") -> frozenset[str]:
        """The parameters of ``learned`` whose common level comes from the likelihood (those of
        :data:`LEVEL_NAMES` outside ``innovation_learns``; none unless ``noise_level=likelihood``).
        Raises where that mode has fewer than two of them (``source`` names where ``learned`` came from)."""
        if self.noise_level != "likelihood":
            return frozenset()
        group = (frozenset(learned) & frozenset(LEVEL_NAMES)) - frozenset(self.innovation_learns)
        if len(group) < 2:
            raise ValueError(f"model.noise_level=likelihood: needs at least two learned noise parameters of "
                             f"{', '.join(LEVEL_NAMES)} outside model.innovation_learns; {source} gives "
                             f"{sorted(group) or 'none'}")
        return group

    def parameter_bounds(self) -> dict[str, float | None]:
        """Every parameter's bound in decades (None: unbounded): ``bounds``, else ``bound_decades``;
        a signed one's largest magnitude from ``bounds``, else None (:data:`SIGNED`'s)."""
        return {n: self.bounds.get(n, None if n in SIGNED else self.bound_decades) for n in NAMES}


def _check_start(name: str, value: float) -> float:
    """``value`` as the start of ``name``: in (0, 1) for the dropout rate, finite and >= 0 otherwise."""
    if name == "dropout_p":
        if not 0.0 < value < 1.0:
            raise ValueError(f"dropout_p must be in (0, 1), got {value}")
    elif name in SIGNED:
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value}")
    elif not value >= 0.0 or not math.isfinite(value):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return value


def _check_bound(name: str, decades: float | None) -> float:
    """The bound of ``name`` in decades, ``inf`` for None (unbounded)."""
    if decades is None:
        return math.inf
    decades = float(decades)
    if not decades > 0.0:  # NaN too
        raise ValueError(f"FilterParameters: the bound of {name} must be a number of decades > 0 or None, "
                         f"got {decades}")
    return decades


def _bounded_value(name: str, a: Tensor, center: Tensor, bound_decades: Tensor,
                   ceiling: Tensor | float = math.inf) -> Tensor:
    """The value of parameter ``name`` at the coordinate ``a`` around the start ``center``
    within ``bound_decades`` (``inf``: unbounded) and below ``ceiling`` (``inf``: none): the
    module docstring's maps, for tensors of any (broadcast) shape. Exactly ``center`` at
    ``a = 0``; free of NaN for every ``a``."""
    unbounded = torch.isinf(bound_decades)
    if name in SIGNED:  # bound_decades holds the largest magnitude W here
        W = bound_decades
        c = torch.atanh(center / W)  # θ₀ + W (tanh(c + u a / W) - tanh c): θ₀ exactly at a = 0
        return center + W * (torch.tanh(c + SIGNED[name][0] * a / W) - torch.tanh(c))
    scale = torch.where(unbounded, torch.ones_like(bound_decades), bound_decades * math.log(10.0))
    s = torch.where(unbounded, a, scale * torch.tanh(a / scale))  # B tanh(a / B); a itself for B = ∞
    if name != "dropout_p":
        ceiling = torch.as_tensor(ceiling, dtype=center.dtype, device=center.device)
        if bool(torch.isfinite(ceiling).any()):
            # above the start: B⁺ = min(B, ln(c / θ₀)) >= 0 (a floor keeps a / B⁺ finite)
            room = torch.log(ceiling / center.clamp_min(1e-300)).clamp_min(0.0)
            up = torch.minimum(torch.where(unbounded, torch.full_like(room, math.inf), scale), room).clamp_min(1e-12)
            s = torch.where(a > 0, torch.where(room > 0, up * torch.tanh(a / up), torch.zeros_like(s)), s)
        return center * torch.exp(s)
    # sigmoid(logit p0 + s), in the form without overflow for either sign of s and = p0 at s = 0
    p0, q0 = center, 1.0 - center
    up, down = torch.exp(-s.clamp(min=0.0)), torch.exp(s.clamp(max=0.0))
    return torch.where(s >= 0, p0 / (p0 + q0 * up), p0 * down / (p0 * down + q0))


def _plain_number(x: object) -> bool:
    """A one-element floating tensor that is not NaN (a ceiling: ``inf`` for none)."""
    return isinstance(x, Tensor) and x.numel() == 1 and x.is_floating_point() and not bool(torch.isnan(x).any())


def _vehicle(config: NavigationConfig) -> VehicleSettings:
    """The vehicle constraint's settings in ``config`` (the defaults when it names none)."""
    return config.measurements.get("vehicle") or VehicleSettings()


def starting_values(config: NavigationConfig, *, dropout_p: float = 0.2) -> dict[str, float]:
    """Every parameter's value in ``config`` (the hand-tuned defaults when ``config`` is the default)."""
    out: dict[str, float] = {}
    for name, (where, field) in _FIELDS.items():
        if where == "noise":
            value = getattr(config.noise, field)
        elif where == "initial":
            value = getattr(config.initial, field)
        elif where == "flow":
            value = getattr(config.flow_update, field)
        elif where == "config":
            value = getattr(config, field)
        elif where == "vehicle":
            value = getattr(_vehicle(config), field)
        elif where == "tracks":
            value = getattr(config.tracks, field)
        elif where == "gate":
            gate = {"flow": config.flow_update.gate, "gnss": config.gnss_gate, "tracks": config.tracks.gate}[field]
            dof = 1 if field == "flow" else 3  # one epipolar scalar per point; a 3-D fix
            value = (gate.threshold_for(dof) if name.endswith("threshold")
                     else gate.scale if name.endswith("scale") else gate.softness)
        else:
            value = dropout_p
        out[name] = float(torch.as_tensor(value, dtype=torch.float64).detach())
    return out


class _Tensors(nn.Module):
    """Named buffers (``<attribute>.<name>`` in the owner's ``state_dict``)."""

    def __init__(self, values: Mapping[str, Tensor]) -> None:
        super().__init__()
        for name, value in values.items():
            self.register_buffer(name, value)

    def __getitem__(self, name: str) -> Tensor:
        return getattr(self, name)


class FilterParameters(nn.Module):
    """The learnable filter parameters (see the module docstring).

    Args:
        start: a value for every name of :data:`NAMES` (e.g. :func:`starting_values`): the
            values at ``a = 0`` and the centres of the bounds.
        learn: the names to learn; the others are kept at their start (default: all
            but :data:`FROZEN_BY_DEFAULT`). A parameter that starts at 0 (a random
            walk switched off) can't move from it: learning it raises.
        bounds: decades each way from the start by name (None: unbounded;
            :meth:`ModelSettings.parameter_bounds`); names left out take
            :data:`DEFAULT_BOUND_DECADES`.
        ceilings: absolute ceilings by name (default :data:`CEILINGS`; ``{}``: none).
        adaptive: the measurement kinds whose σs a learned network sets at each update
            (:data:`ADAPTIVE_KINDS`; :class:`~flowins.measurements.adaptive_noise.AdaptiveNoise`),
            within ``adaptive_decades`` of the σs above; learned unless ``learn_adaptive`` is False.
        adaptive_angles_rad: > 0: the networks of :data:`ADAPTIVE_ANGLES`' kinds also set angles
            within ``±adaptive_angles_rad`` (rad); a kind -> bound mapping sets it per kind.
        adaptive_compensate_gravity: those angles read the car's acceleration, not the specific
            force (:class:`~flowins.measurements.adaptive_noise.AdaptiveNoise`); a collection of
            kinds sets it per kind.

    Attributes:
        raw: the coordinates ``a``, one 0-dim float64 ``nn.Parameter`` each (0 at the start).
        center, bound, ceiling: the starts, the bounds (decades, ``inf`` for none) and the
            ceilings (``inf`` for none), as buffers.
        adaptive: the networks by kind (an ``nn.ModuleDict``, empty without them).
    """

    def __init__(self, start: Mapping[str, float], learn: Iterable[str] | None = None, *,
                 bounds: Mapping[str, float | None] | None = None,
                 ceilings: Mapping[str, float] | None = None, adaptive: Iterable[str] = (),
                 adaptive_decades: float = 1.0, adaptive_angles_rad: float | Mapping[str, float] = 0.0,
                 adaptive_compensate_gravity: bool | Collection[str] = False, learn_adaptive: bool = True) -> None:
        super().__init__()
        if unknown := sorted(set(adaptive) - set(ADAPTIVE_KINDS)):
            raise ValueError(f"FilterParameters: adaptive noise for {unknown}; expected kinds from {list(ADAPTIVE_KINDS)}")
        angles = (adaptive_angles_rad if isinstance(adaptive_angles_rad, Mapping)
                  else {kind: float(adaptive_angles_rad) for kind in ADAPTIVE_ANGLES})

        def network(kind: str) -> AdaptiveNoise:
            bound = float(angles.get(kind, 0.0))
            if bound and kind not in ADAPTIVE_ANGLES:
                raise ValueError(f"FilterParameters: angles for {kind}; expected kinds from {list(ADAPTIVE_ANGLES)}")
            compensate = (kind in adaptive_compensate_gravity if not isinstance(adaptive_compensate_gravity, bool)
                          else adaptive_compensate_gravity and bool(bound))
            return AdaptiveNoise(ADAPTIVE_KINDS[kind], decades=adaptive_decades,
                                 angles=ADAPTIVE_ANGLES[kind] if bound else 0, angle_bound_rad=bound or 0.05,
                                 compensate_gravity=compensate)

        self.adaptive = nn.ModuleDict({kind: network(kind) for kind in sorted(set(adaptive))})
        self.adaptive.requires_grad_(learn_adaptive)
        bounds = dict(bounds or {})
        missing = [n for n in NAMES if n not in start]
        unknown = [n for n in start if n not in _FIELDS]
        if missing or unknown:
            raise ValueError(f"FilterParameters: missing values for {missing}, unknown names {unknown}; expected {list(NAMES)}")
        if unknown := [n for n in bounds if n not in _FIELDS]:
            raise ValueError(f"FilterParameters: bounds for unknown parameters {unknown}; expected names from {list(NAMES)}")
        learn = set(NAMES) - FROZEN_BY_DEFAULT if learn is None else set(learn)
        if unknown := sorted(learn - set(NAMES)):
            raise ValueError(f"FilterParameters: cannot learn unknown parameters {unknown}; expected names from {list(NAMES)}")
        f64 = {"dtype": torch.float64}
        centers, decades = {}, {}
        self.raw = nn.ParameterDict()
        for name in NAMES:
            value = _check_start(name, float(start[name]))
            if name in SIGNED:  # always bounded: None (or left out) is its default largest magnitude
                width = bounds.get(name) or SIGNED[name][1]
                if not abs(value) < float(width):
                    raise ValueError(f"FilterParameters: {name} starts at {value}, which its largest magnitude "
                                     f"{width} (model.bounds.{name}) must exceed")
            elif name in learn and value == 0.0:
                raise ValueError(
                    f"FilterParameters: {name} starts at 0, which a factor on its start cannot leave; "
                    f"give it a positive start (model.start.{name}) or freeze it"
                )
            centers[name] = torch.tensor(value, **f64)
            bound = (width if name in SIGNED else bounds.get(name, DEFAULT_BOUND_DECADES))
            decades[name] = torch.tensor(_check_bound(name, bound), **f64)
            self.raw[name] = nn.Parameter(torch.zeros((), **f64), requires_grad=name in learn)
        self.center = _Tensors(centers)
        self.bound = _Tensors(decades)
        ceilings = CEILINGS if ceilings is None else ceilings
        self.ceiling = _Tensors({n: torch.tensor(float(ceilings.get(n, math.inf)), **f64) for n in NAMES})

    @property
    def learned(self) -> list[str]:
        return [n for n in NAMES if self.raw[n].requires_grad]

    def value(self, name: str) -> Tensor:
        """The parameter in its own units (a 0-dim float64 tensor with a gradient)."""
        return _bounded_value(name, self.raw[name], self.center[name], self.bound[name], self.ceiling[name])

    def values(self) -> dict[str, float]:
        return {n: float(self.value(n).detach()) for n in NAMES}

    def coordinate(self, name: str, value: float) -> float:
        """The optimiser's coordinate at which parameter ``name`` (positive, not the dropout rate)
        is ``value``: :meth:`value`'s inverse. ValueError where its bound or ceiling keeps it
        from ``value``."""
        if name in SIGNED or name == "dropout_p":
            raise ValueError(f"FilterParameters.coordinate: {name} is not a positive parameter")
        center, decades = float(self.center[name]), float(self.bound[name])
        ceiling = float(self.ceiling[name])
        s = math.log(value / center) if value > 0 else -math.inf
        width = math.inf if math.isinf(decades) else decades * math.log(10.0)
        if s > 0 and math.isfinite(ceiling):
            width = min(width, max(math.log(ceiling / center), 0.0))
        if not abs(s) < width:
            raise ValueError(f"FilterParameters: {name}={value:g} lies outside its bound (start {center:g}, "
                             f"{decades:g} decades, ceiling {ceiling:g})")
        return s if math.isinf(width) else width * math.atanh(s / width)

    def bounds(self) -> dict[str, float | None]:
        """Each parameter's bound in decades (None: unbounded); a signed one's largest magnitude."""
        return {n: None if math.isinf(b := float(self.bound[n])) else b for n in NAMES}

    def apply(self, config: NavigationConfig, *, training: bool,
              device: torch.device | str | None = None, recheck: bool = True) -> NavigationConfig:
        """``config`` with this module's values: tensors with a gradient; the gates soft
        while ``training``, hard (at the learned threshold) otherwise. ``device``: where the
        filter runs (default: ``config.device``, i.e. ``filter.device``). ``recheck=False``:
        the flow recheck off."""
        v = {n: self.value(n) for n in NAMES}
        if not training:
            v = {n: float(x.detach()) for n, x in v.items()}
        # a signed parameter kept at its start is a plain number: a plain 0 leaves its term out
        v.update({n: float(v[n].detach()) for n in SIGNED if training and not self.raw[n].requires_grad})
        noise = replace(config.noise, **{f: v[n] for n, (w, f) in _FIELDS.items() if w == "noise"})
        initial = InitialUncertainty(**{**config.initial.__dict__,
                                        **{f: v[n] for n, (w, f) in _FIELDS.items() if w == "initial"}})

        def gate(kind: str, base: Gate) -> Gate:
            if base.mode == "off":
                return base
            # the flow and GNSS gates learn their threshold; the tracks', whose dof differ, a factor on χ²_dof(p)
            return Gate(mode="soft" if training else "hard", probability=base.probability,
                        threshold=v.get(f"{kind}_gate_threshold"), scale=v.get(f"{kind}_gate_scale", 1.0),
                        softness=v[f"{kind}_gate_softness"])

        def rechecked(base: Gate) -> Gate:  # its probability kept; soft as the flow gate while training
            if not recheck:
                return Gate(mode="off")
            return base if base.mode == "off" else Gate(mode="soft" if training else "hard",
                                                        probability=base.probability,
                                                        softness=v["flow_gate_softness"])

        flow = replace(config.flow_update, sigma_scale=v["flow_sigma_scale"], sigma_floor_px=v["flow_sigma_floor_px"],
                       sigma_p0=v["sigma_p0"], sigma_q0=v["sigma_q0"], gate=gate("flow", config.flow_update.gate),
                       recheck=rechecked(config.flow_update.recheck))
        vehicle = replace(_vehicle(config), **{f: v[n] for n, (w, f) in _FIELDS.items() if w == "vehicle"},
                          noise_model=self.adaptive["vehicle"] if "vehicle" in self.adaptive else None)
        return replace(config, noise=noise, initial=initial, gnss_noise_scale=v["gnss_noise_scale"],
                       device=config.device if device is None else device,
                       gnss_gate=gate("gnss", config.gnss_gate), flow_update=flow,
                       tracks=replace(config.tracks, sigma_px=v["tracks_sigma_px"],
                                      gate=gate("tracks", config.tracks.gate)),
                       measurements={**config.measurements, "vehicle": vehicle})

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> FilterParameters:
        """The parameters of a ``train.py`` checkpoint (a Lightning ``.ckpt``), frozen at its
        values: ``raw``, ``center`` and ``bound`` of each name, or ``raw`` alone (each
        value's log, logit for the dropout rate; :meth:`from_raw`)."""
        expected = "a .ckpt written by train.py"
        ckpt = load_tensors(path, argument="model.checkpoint", expected=expected)
        state = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
        if not isinstance(state, dict):
            raise ValueError(f"model.checkpoint: {path} is not a train.py checkpoint (no state_dict); expected {expected}")
        found: dict[str, dict[str, object]] = {"raw": {}, "center": {}, "bound": {}, "ceiling": {}}
        networks: dict[str, dict[str, Tensor]] = {}  # "params.adaptive.vehicle.head.bias": kind "vehicle"
        for key, tensor in state.items():
            parts = str(key).split(".")
            if "adaptive" in parts[:-2] and isinstance(tensor, Tensor):
                at = parts.index("adaptive")
                networks.setdefault(parts[at + 1], {})[".".join(parts[at + 2:])] = tensor
        for key, tensor in state.items():  # "params.raw.acc_noise": kind "raw", name "acc_noise"
            *_, kind, name = ("." + str(key)).split(".")
            if kind in found and name in _FIELDS:
                found[kind][name] = tensor
        raw = found["raw"]
        layouts = [kind for kind in ("center", "bound") if found[kind]]
        if any(n not in raw for n in ADDED_NAMES) and all(n in raw for n in NAMES if n not in ADDED_NAMES):
            # written before these parameters existed: they load at their defaults, not learned
            for n in ADDED_NAMES - set(raw):
                default = float(starting_values(NavigationConfig())[n])
                if "center" in layouts:  # at its start: a = 0
                    found["center"][n] = torch.tensor(default, dtype=torch.float64)
                    found["bound"][n] = torch.tensor(SIGNED[n][1] if n in SIGNED else DEFAULT_BOUND_DECADES,
                                                     dtype=torch.float64)
                    raw[n] = torch.zeros((), dtype=torch.float64)
                else:  # log space; a signed parameter as itself
                    raw[n] = torch.tensor(default if n in SIGNED else math.log(default), dtype=torch.float64)
        missing = {kind: [n for n in NAMES if n not in found[kind]] for kind in ("raw", *layouts)}
        if missing := {kind: names for kind, names in missing.items() if names}:
            what = "; ".join(f"missing {names}" if kind == "raw" else f"missing the {kind} of {names}"
                             for kind, names in missing.items())
            raise ValueError(f"model.checkpoint: {path} is not a train.py checkpoint of the filter parameters; {what}")

        def plausible(x: object, *, low: float = -math.inf) -> bool:  # one float, no NaN, no +inf, >= low
            return (isinstance(x, Tensor) and x.numel() == 1 and x.is_floating_point()
                    and not bool(torch.isnan(x).any() or torch.isposinf(x).any()) and float(x) >= low)

        if bad := [n for n in NAMES if not plausible(raw[n])]:
            raise ValueError(f"model.checkpoint: {path}: the parameters {bad} are not single finite numbers "
                             "(stored in log space; -inf stands for 0)")
        if not layouts:
            return cls.from_raw({n: raw[n].reshape(()) for n in NAMES})
        if unknown := sorted(set(networks) - set(ADAPTIVE_KINDS)):
            raise ValueError(f"model.checkpoint: {path}: adaptive noise for {unknown}; expected kinds from "
                             f"{list(ADAPTIVE_KINDS)}")
        center, bound = found["center"], found["bound"]
        bad = [f"center.{n}" for n in NAMES if not plausible(center[n], low=-math.inf if n in SIGNED else 0.0)
               or not math.isfinite(float(center[n]))]
        bad += [f"bound.{n}" for n in NAMES if not (isinstance(bound[n], Tensor) and bound[n].numel() == 1
                                                    and bound[n].is_floating_point() and float(bound[n]) > 0)]
        if bad:
            raise ValueError(f"model.checkpoint: {path}: {bad} are not single numbers (a start >= 0; "
                             "a bound > 0 decades, inf for none)")
        # a checkpoint without ceilings was learned without them: its values stay as they were
        ceiling = {n: float(found["ceiling"][n]) for n in NAMES if _plain_number(found["ceiling"].get(n))}
        angles = {}  # a network that sets angles keeps their bound as a buffer
        for kind, weights in networks.items():
            bound_rad = weights.get("angle_bound_rad")
            if bound_rad is not None:
                if not (plausible(bound_rad) and 0 < float(bound_rad) <= 0.5):
                    raise ValueError(f"model.checkpoint: {path}: the adaptive network for {kind} has angle_bound_rad="
                                     f"{bound_rad!r}; expected one number in (0, 0.5] rad")
                angles[kind] = float(bound_rad)
            elif "compensate_gravity" in weights:
                raise ValueError(f"model.checkpoint: {path}: the adaptive network for {kind} reads the car's "
                                 "acceleration (compensate_gravity) but sets no angles (no angle_bound_rad)")
        module = cls({n: float(center[n]) for n in NAMES}, learn=(),
                     bounds={n: None if math.isinf(float(bound[n])) else float(bound[n]) for n in NAMES},
                     ceilings=ceiling, adaptive=networks, adaptive_angles_rad=angles, learn_adaptive=False,
                     adaptive_compensate_gravity={kind for kind, w in networks.items() if "compensate_gravity" in w})
        with torch.no_grad():
            for n in NAMES:
                module.raw[n].copy_(raw[n].reshape(()))
        for kind, weights in networks.items():
            try:
                module.adaptive[kind].load_state_dict(weights)
            except RuntimeError as error:  # a layout this code does not build
                first = str(error).strip().splitlines()[0]
                raise ValueError(f"model.checkpoint: {path}: the adaptive noise network for {kind} does not load: "
                                 f"{first}") from None
        return module

    @classmethod
    def from_raw(cls, raw: Mapping[str, float | Tensor]) -> FilterParameters:
        """Frozen parameters at the values whose log (logit for ``dropout_p``; the value itself
        for those of :data:`SIGNED`) is ``raw``, one per name (-inf: a value of 0): the layout of
        checkpoints and ``selection.json`` histories without start values and bounds."""
        values = {}
        for n in NAMES:
            x = torch.as_tensor(raw[n], dtype=torch.float64)
            values[n] = float(x if n in SIGNED else torch.sigmoid(x) if n == "dropout_p" else torch.exp(x))
        return cls(values, learn=(), bounds={n: SIGNED[n][1] if n in SIGNED else None for n in NAMES}, ceilings={})

    def adaptive_state(self) -> dict[str, dict[str, Tensor]]:
        """A copy of each network's weights by kind (what a validation records to restore)."""
        return {k: {n: t.detach().clone() for n, t in m.state_dict().items()} for k, m in self.adaptive.items()}

    def extra_repr(self) -> str:
        return ", ".join(f"{n}={v:.4g}" for n, v in self.values().items())
