"""Content keys: equal exactly when what they key is equal."""
from __future__ import annotations

import hashlib
import sys

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from flowins.cache import array_digest, content_key, file_digest, source_digest


def test_file_digest_is_the_sha256_of_the_bytes(tmp_path):
    path = tmp_path / "x.bin"
    data = bytes(range(256)) * 1000
    path.write_bytes(data)
    assert file_digest(path) == hashlib.sha256(data).hexdigest()


def test_array_digest_sees_values_dtype_and_shape():
    a = torch.arange(6, dtype=torch.float64)
    assert array_digest(a) == array_digest(a.clone()) == array_digest(a.numpy())
    assert array_digest(a) == array_digest(torch.arange(12, dtype=torch.float64)[::2] / 2)  # a strided view
    assert array_digest(a) != array_digest(a.float())
    assert array_digest(a) != array_digest(a.reshape(2, 3))
    b = a.clone()
    b[3] = np.nextafter(3.0, 4.0)  # one ulp
    assert array_digest(a) != array_digest(b)


def test_content_key_of_nested_settings_tensors_and_modules():
    settings = {"flow": {"p": 0.2, "passes": 10}, "step": 1, "size": (3, 4)}
    assert content_key(settings) == content_key({"step": 1, "size": [3, 4], "flow": {"passes": 10, "p": 0.2}})
    assert content_key(settings) == content_key(OmegaConf.create(settings))  # Hydra's configs key like dicts
    assert content_key(settings) != content_key({**settings, "step": 2})
    torch.manual_seed(0)
    net = torch.nn.Linear(3, 2)
    same = torch.nn.Linear(3, 2)
    same.load_state_dict(net.state_dict())
    assert content_key({"weights": net}) == content_key({"weights": same})
    with torch.no_grad():
        same.bias[1] += 1e-6  # one weight changed: another key
    assert content_key({"weights": net}) != content_key({"weights": same})
    with pytest.raises(TypeError, match="cannot key a object"):
        content_key({"x": object()})


def test_source_digest_follows_the_code(tmp_path, monkeypatch):
    package = tmp_path / "keyed_pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("X = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    before = source_digest("keyed_pkg")
    assert source_digest("keyed_pkg") == before
    (package / "a.py").write_text("X = 2\n")
    assert source_digest("keyed_pkg") != before
    (package / "a.py").write_text("X = 1\n")
    assert source_digest("keyed_pkg") == before
    (package / "b.py").write_text("")  # a new module counts
    assert source_digest("keyed_pkg") != before
    sys.modules.pop("keyed_pkg", None)
