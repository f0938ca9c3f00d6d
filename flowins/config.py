"""Config values checked on their way into the package: every error names the key.

A Hydra override arrives as whatever its text parses to (``filter.acc_noise=abc`` is the
string ``'abc'``). :func:`build` makes a settings dataclass from a config node and checks
each value against the field's annotation first, so a wrong value stops with the key and
what was expected (``filter.acc_noise='abc': expected a number``) rather than deep in torch.
A field declared with :func:`bounded` also carries its range (and, for a list, that it
may not be empty), which :func:`build` checks with the same kind of message;
:func:`setting` does the same for one job key.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import os
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

import torch

T = TypeVar("T")

_KINDS = {float: "a number", int: "an integer", bool: "true or false", str: "a string"}
_PLURALS = {float: "numbers", int: "integers", str: "names"}


def _expected(tp: Any) -> str:
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        # a tensor stands where training learns a number: a config gives the number
        return " or ".join(dict.fromkeys("null" if a is type(None) else _expected(a) for a in args
                                         if a is not torch.Tensor))
    if typing.get_origin(tp) is tuple:
        if args and args[-1] is not Ellipsis:
            return f"a list of {len(args)} numbers"
        return f"a list of {_PLURALS.get(args[0] if args else float, 'items')}"
    if dataclasses.is_dataclass(tp) or typing.get_origin(tp) in (dict, Mapping):
        return "a group of keys"
    return _KINDS.get(tp, getattr(tp, "__name__", str(tp)))


def _scalar(value: Any, tp: Any, key: str) -> Any:
    """``value`` as ``tp`` (float, int, bool, str), or ValueError naming ``key``."""
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if not math.isfinite(value):
                raise ValueError(f"{key}={value!r}: expected a finite number")
            return float(value)
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif tp is str:
        if isinstance(value, str):
            return value
    else:
        raise TypeError(f"flowins.config: no check for {tp!r} ({key})")
    raise ValueError(f"{key}={value!r}: expected {_KINDS[tp]}")


def check_value(value: Any, tp: Any, key: str) -> Any:
    """``value`` checked against the annotation ``tp`` (and converted: ints to floats,
    lists to tuples, mappings to the dataclass); ValueError naming ``key`` otherwise."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        if isinstance(value, (str, os.PathLike)) and os.PathLike in options:
            return value
        if value is None:
            if type(None) in options:
                return None
            raise ValueError(f"{key}=null: expected {_expected(tp)}")
        if isinstance(value, torch.Tensor) and torch.Tensor in options:
            return value
        errors = []
        for option in options:
            if option in (type(None), torch.Tensor):
                continue
            try:
                return check_value(value, option, key)
            except ValueError as error:
                errors.append(error)
        if len(errors) == 1:
            raise errors[0]
        raise ValueError(f"{key}={value!r}: expected {_expected(tp)}")
    if origin is tuple:
        args = typing.get_args(tp)
        if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
            raise ValueError(f"{key}={value!r}: expected {_expected(tp)}")
        if args and args[-1] is not Ellipsis and len(value) != len(args):
            raise ValueError(f"{key}={list(value)!r}: expected {_expected(tp)}")
        items = args if args and args[-1] is not Ellipsis else (args[0] if args else float,) * len(value)
        return tuple(check_value(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, items)))
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise ValueError(f"{key}={value!r}: expected a group of keys")
        item = typing.get_args(tp)[1] if typing.get_args(tp) else typing.Any
        return {name: check_value(v, item, f"{key}.{name}") for name, v in value.items()}
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(f"{key}={value!r}: expected a group of keys ({', '.join(_fields(tp))})")
        return build(tp, value, key)
    if origin is typing.Literal:
        choices = typing.get_args(tp)
        if value in choices and not isinstance(value, bool):
            return value
        raise ValueError(f"{key}={value!r}: expected one of {', '.join(map(str, choices))}")
    if tp is os.PathLike:
        if isinstance(value, (str, os.PathLike)):
            return value
        raise ValueError(f"{key}={value!r}: expected a path")
    if tp is torch.device:
        return check_device(value, key)
    if tp is torch.dtype:
        if isinstance(value, torch.dtype):
            return value
        raise ValueError(f"{key}={value!r}: expected a torch dtype")
    if tp is typing.Any:
        return value
    return _scalar(value, tp, key)


def check_device(value: Any, key: str) -> torch.device:
    """``value`` as a :class:`torch.device` this machine has: ``cpu``, or ``cuda`` / ``cuda:N``
    with a CUDA GPU that torch sees; errors name ``key`` and what is there."""
    try:
        device = torch.device(value) if isinstance(value, (str, torch.device)) else None
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise ValueError(f"{key}={value!r}: expected cpu, cuda or cuda:N")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"{key}={value}: torch {torch.__version__} sees no CUDA GPU here "
                             f"(torch.cuda.is_available() is False); use {key}=cpu, or install torch's CUDA build")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"{key}={value}: there are {torch.cuda.device_count()} CUDA GPU(s) "
                             f"(cuda:0 to cuda:{torch.cuda.device_count() - 1})")
    return device


def _fields(cls: type) -> list[str]:
    return [f.name for f in dataclasses.fields(cls) if f.init]


def bounded(default: Any = dataclasses.MISSING, *, minimum: float | None = None, maximum: float | None = None,
            above: float | None = None, below: float | None = None, nonempty: bool = False, **kwargs: Any) -> Any:
    """A dataclass field whose value must lie in ``[minimum, maximum]``, exceed ``above`` and stay
    under ``below`` (each item's, for a tuple; every element's, finite, for a tensor); with ``nonempty`` an
    empty list is refused. :func:`build` checks it on a config's value and :func:`check_fields`
    (called from the dataclass's ``__post_init__``) on every instance."""
    if isinstance(default, (list, dict)):
        mutable, default = default, dataclasses.MISSING
        kwargs["default_factory"] = lambda: type(mutable)(mutable)
    return dataclasses.field(default=default, metadata={"minimum": minimum, "maximum": maximum, "above": above,
                                                        "below": below, "nonempty": nonempty}, **kwargs)


def _check_range(value: Any, raw: Any, tp: Any, key: str, minimum: float | None, maximum: float | None,
                 above: float | None = None, below: float | None = None) -> None:
    """ValueError naming ``key`` when ``value`` (a number, or a tensor's every element, which
    must be finite) is outside ``[minimum, maximum]``, not above ``above`` or not below ``below``."""
    if value is None:
        return
    v = value.detach() if isinstance(value, torch.Tensor) else value
    what = "numbers" if isinstance(value, torch.Tensor) else _expected(tp)
    if isinstance(v, torch.Tensor) and not bool(torch.isfinite(v).all()):
        raise ValueError(f"{key}={raw!r}: expected finite numbers")
    if below is not None and not bool((v < below).all() if isinstance(v, torch.Tensor) else v < below):
        raise ValueError(f"{key}={raw!r}: expected {what} < {below:g}")
    if above is not None and not bool((v > above).all() if isinstance(v, torch.Tensor) else v > above):
        raise ValueError(f"{key}={raw!r}: expected {what} > {above:g}")
    if minimum is not None and not bool((v >= minimum).all() if isinstance(v, torch.Tensor) else v >= minimum):
        raise ValueError(f"{key}={raw!r}: expected {what} >= {minimum:g}")
    if maximum is not None and not bool((v <= maximum).all() if isinstance(v, torch.Tensor) else v <= maximum):
        raise ValueError(f"{key}={raw!r}: expected {what} <= {maximum:g}")


def _check_field(field: dataclasses.Field, value: Any, raw: Any, tp: Any, key: str) -> None:
    """The range and non-emptiness a :func:`bounded` field declares."""
    meta = field.metadata
    if not meta:
        return
    bounds = meta.get("minimum"), meta.get("maximum"), meta.get("above"), meta.get("below")
    if isinstance(value, tuple):
        items = [a for a in typing.get_args(tp) if a is not type(None)] if typing.get_origin(tp) is not tuple else [tp]
        if meta.get("nonempty") and not value:
            raise ValueError(f"{key}=[]: expected {_expected(items[0])}, not an empty one")
        args = typing.get_args(items[0]) if items else ()
        for i, (item, raw_item) in enumerate(zip(value, raw)):
            _check_range(item, raw_item, args[0] if args else float, f"{key}[{i}]", *bounds)
    else:
        _check_range(value, raw, tp, key, *bounds)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def check_fields(obj: Any) -> None:
    """Every field of the dataclass instance ``obj`` that declares a :func:`bounded` range or
    a ``Literal`` of choices: a value of its annotation's kind (a tensor, which training may put in a number's
    place, is checked for its range only) within that range; ValueError naming
    ``ClassName.field`` (which :func:`build` turns into the config's key) otherwise. The one
    range check of every settings dataclass: call it from ``__post_init__``."""
    hints = _hints(type(obj))
    for field in dataclasses.fields(obj):
        if not field.metadata and typing.get_origin(hints[field.name]) is not typing.Literal:
            continue
        value = getattr(obj, field.name)
        key = f"{type(obj).__name__}.{field.name}"
        if not isinstance(value, torch.Tensor):
            value = check_value(value, hints[field.name], key)
        _check_field(field, value, getattr(obj, field.name), hints[field.name], key)


def build(cls: type[T], values: Mapping[str, Any], key: str, **ready: Any) -> T:
    """``cls(**values, **ready)`` for a dataclass ``cls``, each of ``values`` checked
    against its field's annotation (nested dataclasses from nested mappings). ``key`` is
    the config node's dotted name; an unknown key, a value of the wrong kind, or a value
    the dataclass itself refuses raises ValueError naming ``key.field``. ``ready`` holds
    values already built (not checked)."""
    hints = typing.get_type_hints(cls)
    names = _fields(cls)
    declared = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: dict[str, Any] = {}
    for name, value in values.items():
        dotted = f"{key}.{name}" if key else name
        if name not in names:
            raise ValueError(f"{dotted}: unknown key; {key or 'the job'} takes {', '.join(names)}")
        kwargs[name] = check_value(value, hints[name], dotted)
        _check_field(declared[name], kwargs[name], value, hints[name], dotted)
    kwargs.update(ready)
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as error:
        message = str(error).replace(f"{cls.__name__}.", f"{key}.")
        raise ValueError(message if key in message else f"{key}: {message}") from None


def setting(cfg: Mapping[str, Any], key: str, tp: type[T], *, minimum: float | None = None,
            maximum: float | None = None, default: Any = dataclasses.MISSING) -> T:
    """The value at dotted ``key`` of ``cfg`` as ``tp`` within ``[minimum, maximum]``;
    ValueError naming ``key`` and what was expected otherwise."""
    node: Any = cfg
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            if default is not dataclasses.MISSING:
                return default
            raise ValueError(f"{key}: missing from the config")
        node = node[part]
    value = check_value(node, tp, key)
    _check_range(value, node, tp, key, minimum, maximum)
    return value


def instantiate(node: Mapping[str, Any], key: str, **extra: Any) -> Any:
    """``hydra.utils.instantiate(node, **extra)`` with each value of ``node`` checked first
    against the annotation of its ``_target_``'s parameter (where flowins can check that
    kind), and any ValueError or TypeError of the constructor prefixed with ``key``."""
    from hydra.utils import instantiate as hydra_instantiate

    check_target(node, key)
    try:
        return hydra_instantiate(node, **extra)
    except (ValueError, TypeError) as error:
        message = str(error)
        raise ValueError(message if key in message else f"{key}: {message}") from None


def check_target(node: Mapping[str, Any], key: str) -> None:
    """Each value of a ``_target_`` node checked against the annotation of the target's
    parameter of that name (kinds flowins can check; others are left to the target)."""
    from hydra.utils import get_object

    target = node.get("_target_")
    if target is not None:
        try:
            made = get_object(target)
            hints = typing.get_type_hints(made.__init__ if isinstance(made, type) else made)
        except Exception:  # an object flowins does not own (Lightning's): its own errors speak
            hints = {}
        for name, value in node.items():
            if name in hints and not name.startswith("_"):
                try:
                    check_value(value, hints[name], f"{key}.{name}")
                except TypeError:  # a kind flowins has no check for
                    pass
