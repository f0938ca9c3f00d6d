"""The filter's free parameters as one ``nn.Module``, in unconstrained coordinates.

Every positive quantity is stored as its logarithm and the dropout rate as its
logit, so any step of the optimiser keeps them valid. :meth:`FilterParameters.apply`
writes the current values (tensors with a gradient) into a
:class:`~flowins.navigation.NavigationConfig`; the filter then runs unchanged, and
the gradient of a loss on its output reaches every parameter.

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
``*_gate_threshold``,       the χ² gates of the flow points and the GNSS fixes: soft
``*_gate_softness``         (``sigmoid((threshold - NIS) / softness)``) while training,
                            hard (``NIS <= threshold``) at inference
==========================  ==========================================================
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor, nn

from flowins.config import bounded
from flowins.filter.ekf import Gate
from flowins.ins.initialization import InitialUncertainty
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
    "dropout_p": ("dropout", "p"),
}
NAMES: tuple[str, ...] = tuple(_FIELDS)
#: the noise parameters (what a "mis-tuned" start multiplies)
NOISE_NAMES: tuple[str, ...] = (
    "acc_noise", "gyro_noise", "acc_bias_walk", "gyro_bias_walk", "acc_scale_walk",
    "initial_velocity_mps", "initial_roll_pitch_rad", "initial_acc_bias_mps2", "initial_gyro_bias_rps",
    "initial_acc_scale", "gnss_noise_scale", "flow_sigma_scale", "flow_sigma_floor_px",
)  # fmt: skip
#: frozen unless the config says otherwise
FROZEN_BY_DEFAULT = frozenset({"initial_position_m", "initial_yaw_rad"})


@dataclass(frozen=True)
class ModelSettings:
    """The ``model`` config group (``configs/model/filter.yaml``): the loss, the optimiser's
    schedule and which parameters start where and are learned.

    Attributes:
        lr, lr_final, warmup_steps: Adam's learning rate (log-parameter units), the end of its
            cosine decay, and the linear warm-up's optimiser steps.
        accumulate_windows: window groups whose gradients are summed into one step.
        gradient_clip: the gradient-norm clip of each step.
        nll_weight: weight of the Gaussian negative log-likelihood of the position errors.
        innovation_weight: weight of the innovation negative log-likelihood per scalar
            measurement (metres per nat; :func:`~flowins.training.unroll.window_loss`).
        orientation_weight_m_per_rad: weight of the orientation RMSE (rad) in the loss.
        mistune: every noise parameter's start multiplied by this.
        start: starting values replacing the filter config's, by parameter name.
        learn, freeze: the names learned (None: all but the frozen-by-default ones) and kept.
        checkpoint: a ``train.py`` checkpoint whose learned values the filter uses.
    """

    lr: float = bounded(0.1, minimum=1e-12)
    lr_final: float | None = bounded(None, minimum=1e-12)
    warmup_steps: int = bounded(0, minimum=0)
    accumulate_windows: int = bounded(1, minimum=1)
    gradient_clip: float = bounded(1.0, minimum=1e-12)
    nll_weight: float = bounded(0.0, minimum=0.0)
    innovation_weight: float = bounded(0.0, minimum=0.0)
    orientation_weight_m_per_rad: float = bounded(0.0, minimum=0.0)
    mistune: float = bounded(1.0, minimum=1e-12)
    start: dict[str, float] = bounded({})
    learn: tuple[str, ...] | None = None
    freeze: tuple[str, ...] = ()
    checkpoint: str | None = None

    def __post_init__(self) -> None:
        for name, value in self.start.items():
            if name not in NAMES:
                raise ValueError(f"model.start.{name}: unknown parameter; expected names from {', '.join(NAMES)}")
            if not value >= 0.0:
                raise ValueError(f"model.start.{name}={value!r}: expected a number >= 0")
        for key in ("learn", "freeze"):
            for name in getattr(self, key) or ():
                if name not in NAMES:
                    raise ValueError(f"model.{key}: unknown parameter {name!r}; expected names from {', '.join(NAMES)}")


def _to_raw(name: str, value: float) -> float:
    if name == "dropout_p":
        if not 0.0 < value < 1.0:
            raise ValueError(f"dropout_p must be in (0, 1), got {value}")
        return math.log(value) - math.log1p(-value)
    if not value >= 0.0 or not math.isfinite(value):
        raise ValueError(f"{name} must be finite and >= 0, got {value}")
    return math.log(value) if value > 0 else -math.inf


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
        elif where == "gate":
            gate = config.flow_update.gate if field == "flow" else config.gnss_gate
            dof = 1 if field == "flow" else 3  # one epipolar scalar per point; a 3-D fix
            value = gate.threshold_for(dof) if name.endswith("threshold") else gate.softness
        else:
            value = dropout_p
        out[name] = float(torch.as_tensor(value, dtype=torch.float64).detach())
    return out


class FilterParameters(nn.Module):
    """The learnable filter parameters (see the module docstring).

    Args:
        start: a value for every name of :data:`NAMES` (e.g. :func:`starting_values`).
        learn: the names to learn; the others are kept at their start (default: all
            but :data:`FROZEN_BY_DEFAULT`). A parameter that starts at 0 (a random
            walk switched off) can't move in log space: learning it raises.
    """

    def __init__(self, start: Mapping[str, float], learn: Iterable[str] | None = None) -> None:
        super().__init__()
        missing = [n for n in NAMES if n not in start]
        unknown = [n for n in start if n not in _FIELDS]
        if missing or unknown:
            raise ValueError(f"FilterParameters: missing values for {missing}, unknown names {unknown}; expected {list(NAMES)}")
        learn = set(NAMES) - FROZEN_BY_DEFAULT if learn is None else set(learn)
        if unknown := sorted(learn - set(NAMES)):
            raise ValueError(f"FilterParameters: cannot learn unknown parameters {unknown}; expected names from {list(NAMES)}")
        self.raw = nn.ParameterDict()
        for name in NAMES:
            value = float(start[name])
            if name in learn and value == 0.0 and name != "dropout_p":
                raise ValueError(
                    f"FilterParameters: {name} starts at 0 and is learned in log space, where 0 is out of reach; "
                    f"give it a positive start (model.params.{name}.start) or freeze it"
                )
            self.raw[name] = nn.Parameter(
                torch.tensor(_to_raw(name, value), dtype=torch.float64), requires_grad=name in learn
            )

    @property
    def learned(self) -> list[str]:
        return [n for n in NAMES if self.raw[n].requires_grad]

    def value(self, name: str) -> Tensor:
        """The parameter in its own units (a 0-dim float64 tensor with a gradient)."""
        raw = self.raw[name]
        return torch.sigmoid(raw) if name == "dropout_p" else torch.exp(raw)

    def values(self) -> dict[str, float]:
        return {n: float(self.value(n).detach()) for n in NAMES}

    def apply(self, config: NavigationConfig, *, training: bool) -> NavigationConfig:
        """``config`` with this module's values: tensors with a gradient; the gates soft
        while ``training``, hard (at the learned threshold) otherwise."""
        v = {n: self.value(n) for n in NAMES}
        if not training:
            v = {n: float(x.detach()) for n, x in v.items()}
        noise = replace(config.noise, **{f: v[n] for n, (w, f) in _FIELDS.items() if w == "noise"})
        initial = InitialUncertainty(**{**config.initial.__dict__,
                                        **{f: v[n] for n, (w, f) in _FIELDS.items() if w == "initial"}})

        def gate(kind: str, base: Gate) -> Gate:
            if base.mode == "off":
                return base
            return Gate(mode="soft" if training else "hard", probability=base.probability,
                        threshold=v[f"{kind}_gate_threshold"], softness=v[f"{kind}_gate_softness"])

        flow = replace(config.flow_update, sigma_scale=v["flow_sigma_scale"], sigma_floor_px=v["flow_sigma_floor_px"],
                       sigma_p0=v["sigma_p0"], sigma_q0=v["sigma_q0"], gate=gate("flow", config.flow_update.gate))
        return replace(config, noise=noise, initial=initial, gnss_noise_scale=v["gnss_noise_scale"],
                       gnss_gate=gate("gnss", config.gnss_gate), flow_update=flow)

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> FilterParameters:
        """The parameters of a ``train.py`` checkpoint (a Lightning ``.ckpt``)."""
        expected = "a .ckpt written by train.py"
        ckpt = load_tensors(path, argument="model.checkpoint", expected=expected)
        state = ckpt.get("state_dict", ckpt) if isinstance(ckpt, dict) else None
        if not isinstance(state, dict):
            raise ValueError(f"model.checkpoint: {path} is not a train.py checkpoint (no state_dict); expected {expected}")
        raw = {k.rsplit("raw.", 1)[1]: v for k, v in state.items() if "raw." in k}
        missing = [n for n in NAMES if n not in raw]
        if missing:
            raise ValueError(f"model.checkpoint: {path} is not a train.py checkpoint of the filter parameters; "
                             f"missing {missing}")

        def plausible(x: object) -> bool:  # one float; -inf in log space is a value of 0 (a switched-off walk)
            return (isinstance(x, Tensor) and x.numel() == 1 and x.is_floating_point()
                    and not bool(torch.isnan(x).any() or torch.isposinf(x).any()))

        if bad := [n for n in NAMES if not plausible(raw[n])]:
            raise ValueError(f"model.checkpoint: {path}: the parameters {bad} are not single finite numbers "
                             "(stored in log space; -inf stands for 0)")
        return cls.from_raw({n: raw[n].reshape(()) for n in NAMES})

    @classmethod
    def from_raw(cls, raw: Mapping[str, float | Tensor]) -> FilterParameters:
        """Frozen parameters with these unconstrained values (log, or logit for ``dropout_p``), one per name."""
        module = cls({n: 0.5 if n == "dropout_p" else 1.0 for n in NAMES}, learn=())
        with torch.no_grad():
            for n in NAMES:
                module.raw[n].copy_(torch.as_tensor(raw[n], dtype=torch.float64))
        return module

    def extra_repr(self) -> str:
        return ", ".join(f"{n}={v:.4g}" for n, v in self.values().items())
