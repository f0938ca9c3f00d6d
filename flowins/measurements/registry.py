"""Measurement kinds by name: a sensor is one file in ``measurements/``, one config node, one registration.

A kind's file holds its measurement model (the events it builds: ``H``, residual and
``R`` handed to :func:`flowins.filter.updater.update`), a settings dataclass (the keys of
its config node ``filter.measurements.<name>``) and a function that turns its stream into
events; the file registers the kind when it is imported
(``register(MeasurementKind(name, settings, events))``).
:func:`flowins.navigation.prepare_navigation` adds the events of every stream in
``NavigationRun.streams`` by its kind's name, with the settings in
``NavigationConfig.measurements`` (built by :func:`measurement_settings`) or the kind's defaults.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

from flowins.config import build
from flowins.constants import STANDARD_GRAVITY_MPS2

if TYPE_CHECKING:
    from flowins.data.streams import ImuStream
    from flowins.geometry.geodesy import LocalTangentPlane


@dataclass(frozen=True)
class NavigationContext:
    """What a measurement kind may need from the run it is added to."""

    #: the filter's start (s): events before it are left out
    t_start_s: float
    #: the IMU's last sample (s): an event after it raises
    t_end_s: float
    #: the local ENU frame of the run (its origin at the first GNSS fix, or as given); None without one
    frame: LocalTangentPlane | None
    #: the filter's dtype
    dtype: torch.dtype
    #: the run's IMU readings (a kind whose model needs them, such as the vehicle constraint's lever arm)
    imu: ImuStream | None = None
    #: gravity's magnitude (m/s²) the run's filter takes
    gravity_mps2: float = STANDARD_GRAVITY_MPS2


@dataclass(frozen=True)
class MeasurementKind:
    """A sensor the filter can use, under the name of its stream and config node.

    ``events(stream, settings, context)`` returns the filter events of one ``stream``
    (objects with ``time_s``, ``name`` and ``apply(chain)``, :class:`flowins.filter.chain.Event`,
    each handing its ``H``, residual and ``R`` to :func:`flowins.filter.updater.update`) with
    ``settings``, an instance of ``settings``: a dataclass whose fields are the keys of
    ``filter.measurements.<name>``, each with a default.
    """

    name: str
    settings: type
    events: Callable[[Any, Any, NavigationContext], list]
    #: the stream a run gets when its settings say ``mode: on`` and the run has none (a kind
    #: whose measurements need no recorded data, such as a motion constraint); None: no such mode
    default_stream: Callable[[], Any] | None = None


#: the registered kinds by name
MEASUREMENTS: dict[str, MeasurementKind] = {}


def register(kind: MeasurementKind) -> MeasurementKind:
    """Add ``kind`` to :data:`MEASUREMENTS` (returned unchanged); ValueError for a name
    already registered or settings that are not a default-constructible dataclass."""
    if kind.name in MEASUREMENTS:
        raise ValueError(f"measurement kind {kind.name!r} is already registered ({MEASUREMENTS[kind.name].events!r})")
    if not (isinstance(kind.settings, type) and dataclasses.is_dataclass(kind.settings)):
        raise ValueError(f"measurement kind {kind.name!r}: settings={kind.settings!r}; expected a dataclass type")
    try:
        kind.settings()
    except TypeError as error:
        raise ValueError(f"measurement kind {kind.name!r}: {kind.settings.__name__}() fails ({error}); "
                         "every field needs a default") from None
    MEASUREMENTS[kind.name] = kind
    return kind


def measurement_kind(name: str) -> MeasurementKind:
    """The kind registered as ``name``; ValueError naming the registered kinds otherwise."""
    try:
        return MEASUREMENTS[name]
    except KeyError:
        known = ", ".join(sorted(MEASUREMENTS)) or "none"
        raise ValueError(f"unknown measurement kind {name!r}; registered kinds: {known}") from None


def measurement_settings(cfg_node: Mapping[str, Any]) -> dict[str, Any]:
    """The settings of each kind named in ``cfg_node`` (the config node ``filter.measurements``:
    name -> its keys; an empty or null node: the kind's defaults), built and checked by
    :func:`flowins.config.build`."""
    out: dict[str, Any] = {}
    for name, values in cfg_node.items():
        key = f"filter.measurements.{name}"
        try:
            kind = measurement_kind(name)
        except ValueError as error:
            raise ValueError(f"{key}: {error}") from None
        if values is not None and not isinstance(values, Mapping):
            raise ValueError(f"{key}={values!r}: expected a mapping of {kind.settings.__name__}'s keys")
        out[name] = build(kind.settings, values or {}, key)
    return out


def registered_events(streams: Mapping[str, Any], settings: Mapping[str, Any], context: NavigationContext) -> list:
    """The events of every registered kind: each of ``streams`` (name -> stream) by its kind,
    with its settings from ``settings`` (name -> settings; a kind not named there uses its
    defaults), and each kind switched on in ``settings`` (``mode: on``) that needs no recorded
    stream, on its default stream; events before ``context.t_start_s`` are left out."""
    streams = dict(streams)
    for name, chosen in settings.items():
        kind = measurement_kind(name)
        if name not in streams and kind.default_stream is not None and getattr(chosen, "mode", None) == "on":
            streams[name] = kind.default_stream()
    events = []
    for name, stream in streams.items():
        kind = measurement_kind(name)
        chosen = settings.get(name)
        chosen = kind.settings() if chosen is None else chosen
        events += [e for e in kind.events(stream, chosen, context) if e.time_s >= context.t_start_s]
    return events

