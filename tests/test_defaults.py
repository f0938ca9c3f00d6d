"""Every default lives once: the YAML of configs/filter and configs/sequence against the
dataclasses the jobs build from them, key by key, recursively. A YAML value that differs
from its field's default, or a key with no field, fails here with its dotted name."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch
import yaml

from flowins.measurements.vehicle import VehicleSettings
from flowins.navigation import NavigationConfig
from flowins.settings import FILTER_KEYS, NOISE_KEYS, SequenceSettings, filter_keys

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
#: keys whose YAML value is resolved when the job starts, not a default to mirror
RESOLVED = {"filter.workers": "auto: one worker per core", "filter.device": "a string the job parses",
            "filter.dtype": "a string the job parses",
            "filter.compile": "YAML's false / true, which the job reads as 'false' / 'true' (tests/filter/test_compiling.py)"}


def _default(field: dataclasses.Field):
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


def _same(a, b) -> bool:
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b or a == b and type(a) is type(b)
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=1e-12, abs_tol=0.0)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def drift(node: dict, default, path: str) -> list[str]:
    """The keys of ``node`` whose value differs from ``default``'s field (a dataclass
    instance), or that it has no field for; nested mappings against nested dataclasses."""
    fields = {f.name: f for f in dataclasses.fields(default)}
    problems = []
    for key, value in node.items():
        name = FILTER_KEYS.get(key, key) if path == "filter" else key
        dotted = f"{path}.{key}"
        if dotted in RESOLVED:
            continue
        if name not in fields:
            problems.append(f"{dotted}: no field {type(default).__name__}.{name}")
            continue
        expected = getattr(default, name)
        if isinstance(value, dict) and dataclasses.is_dataclass(expected):
            problems += drift(value, expected, dotted)
        elif isinstance(value, dict) and isinstance(expected, dict):
            continue  # a mapping of registered settings: checked below
        elif not _same(value, expected):
            problems.append(f"{dotted}: YAML {value!r}, {type(default).__name__}.{name} = {expected!r}")
    return problems


def test_the_filter_yaml_is_the_dataclasses_defaults():
    node = yaml.safe_load((CONFIGS / "filter" / "default.yaml").read_text())
    noise = {k: node.pop(k) for k in NOISE_KEYS}
    vehicle = node["measurements"].pop("vehicle")
    default = NavigationConfig()
    problems = drift(node, default, "filter")
    problems += drift({k: v for k, v in noise.items() if v is not None}, default.noise, "filter")
    problems += drift(vehicle, VehicleSettings(), "filter.measurements.vehicle")
    assert not problems, "\n".join(problems)


def test_the_sequence_yaml_is_the_settings_defaults():
    node = yaml.safe_load((CONFIGS / "sequence" / "simulated_walk.yaml").read_text())
    node.pop("kind")  # which reader: not a setting of the sequence
    assert not (problems := drift(node, SequenceSettings(), "sequence")), "\n".join(problems)


def test_a_drifted_default_is_named():
    """The check itself: a changed value and an unknown key are both reported."""
    problems = drift({"gnss_noise_scale": 2.0, "no_such_key": 1, "flow": {"n_points": 128}}, NavigationConfig(),
                     "filter")
    assert any(p.startswith("filter.gnss_noise_scale: YAML 2.0") for p in problems)
    assert any(p.startswith("filter.no_such_key: no field") for p in problems)
    assert any(p.startswith("filter.flow.n_points: YAML 128") for p in problems)


@pytest.mark.parametrize("value, expected, same", [(0.035, 0.0349, False), (True, 1, False), (1, 1.0, True),
                                                   ([1, 2], (1, 2), True), (None, None, True)])
def test_values_compare_exactly_up_to_rounding_and_type(value, expected, same):
    assert _same(value, expected) is same


def test_the_dtype_and_device_keys_parse_to_the_defaults():
    node = yaml.safe_load((CONFIGS / "filter" / "default.yaml").read_text())
    assert getattr(torch, node["dtype"]) == NavigationConfig().dtype
    assert torch.device(node["device"]) == NavigationConfig().device


def test_the_filter_yaml_has_every_key_the_filter_takes_and_no_other():
    """The keys come from the dataclasses (settings.filter_keys): a new field without its YAML
    line, or a YAML line without its field, fails here."""
    node = yaml.safe_load((CONFIGS / "filter" / "default.yaml").read_text())
    assert sorted(node) == sorted(filter_keys())
