"""Content keys: equal exactly when what they key is equal; the lock that lets processes take turns at one folder."""
from __future__ import annotations

import hashlib
import sys

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from flowins.cache import array_digest, content_key, file_digest, folder_lock, source_digest


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


def _hold_and_write(folder, log, held, hold_s):
    import time

    with folder_lock(folder):
        held.set()
        with open(log, "a") as f:
            f.write("first in\n")
        time.sleep(hold_s)
        with open(log, "a") as f:
            f.write("first out\n")


def test_a_second_process_waits_for_the_folder_lock(tmp_path):
    """One process holds the lock for 0.5 s; another that asks for it meanwhile writes only
    after the first has let go (without the lock its line lands between the two)."""
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    folder, log = tmp_path / "sim", tmp_path / "log.txt"
    held = context.Event()
    first = context.Process(target=_hold_and_write, args=(folder, log, held, 0.5))
    first.start()
    assert held.wait(60.0)
    with folder_lock(folder):
        with open(log, "a") as f:
            f.write("second\n")
    first.join(60.0)
    assert first.exitcode == 0
    assert log.read_text().splitlines() == ["first in", "first out", "second"]
    assert (tmp_path / "sim.lock").exists() and not folder.exists()  # the lock is a file beside the folder
