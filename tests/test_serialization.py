"""Files a user passes in are read as tensors and plain values: a pickle that runs code is
refused before it runs, by every loader, with an error naming the argument and the file."""
from __future__ import annotations

import os
import re
import zipfile

import numpy as np
import pytest
import torch

from flowins.flow.flownet2 import FlowNet2Provider, load_checkpoint
from flowins.flow.spynet import spynet_state_dict
from flowins.serialization import load_tensors
from flowins.training.parameters import NAMES, SIGNED, FilterParameters


class Payload:
    """Unpickling this calls ``os.mkdir(marker)``: a stand-in for any code a file might run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


def _malicious(tmp_path, name: str, wrap) -> tuple:
    """A file that holds ``wrap(payload)`` and the folder the payload would create."""
    marker = tmp_path / f"{name}-ran"
    path = tmp_path / name
    torch.save(wrap(Payload(marker)), path)
    return path, marker


def _parameters_checkpoint(payload) -> dict:
    params = FilterParameters({n: 0.5 if n == "dropout_p" else 0.0 if n in SIGNED else 1.0 for n in NAMES})
    return {"state_dict": {"params." + k: v for k, v in params.state_dict().items()}, "hyper_parameters": payload}


def test_the_payload_is_live_when_unpickled(tmp_path):
    """The test file really runs code under a plain unpickler (so the tests below can fail)."""
    path, marker = _malicious(tmp_path, "live.ckpt", _parameters_checkpoint)
    torch.load(path, weights_only=False)
    assert marker.is_dir()


@pytest.mark.parametrize(
    "load, argument",
    [
        (lambda p: FilterParameters.from_checkpoint(p), "model.checkpoint"),
        (lambda p: load_checkpoint(FlowNet2Provider.untrained("FlowNet2S", dropout_option=None).model, p),
         "flow.checkpoint (FlowNet2)"),
        (lambda p: spynet_state_dict(p), "flow.weights (SpyNet)"),
    ],
    ids=["train.py checkpoint", "FlowNet2", "SpyNet"],
)
def test_every_loader_refuses_code_and_leaves_no_trace(tmp_path, load, argument):
    path, marker = _malicious(tmp_path, "evil.pth", _parameters_checkpoint)
    with pytest.raises(ValueError) as info:
        load(path)
    message = str(info.value)
    assert message.startswith(f"{argument}: {path}")
    assert "posix.mkdir" in message or "os.mkdir" in message  # what the file asked for
    assert "weights_only=False" not in message  # no advice to load it unsafely
    assert not marker.exists()


def test_refusal_inside_a_nested_value_and_a_bare_object(tmp_path):
    for name, wrap in (("nested.ckpt", lambda p: {"a": [1, {"b": (torch.zeros(2), p)}]}), ("bare.ckpt", lambda p: p)):
        path, marker = _malicious(tmp_path, name, wrap)
        with pytest.raises(ValueError, match=re.escape(f"model.checkpoint: {path} asks to load the Python object")):
            load_tensors(path, argument="model.checkpoint", expected="a .ckpt")
        assert not marker.exists()


def test_plain_values_round_trip(tmp_path):
    value = {"state_dict": {"w": torch.arange(6.0).reshape(2, 3), "n": torch.tensor(3)}, "epoch": 4, "name": "x",
             "scores": [1.5, (2, None)], "best_EPE": np.float64(1.25), "step": np.int64(7), "flag": np.bool_(True)}
    path = tmp_path / "plain.pth"
    torch.save(value, path)
    got = load_tensors(path, argument="a", expected="b")
    assert torch.equal(got["state_dict"]["w"], value["state_dict"]["w"])
    assert got["epoch"] == 4 and got["name"] == "x" and got["scores"] == [1.5, (2, None)]
    assert got["best_EPE"] == 1.25 and got["best_EPE"].dtype == np.float64 and got["step"] == 7 and got["flag"]


def test_numpy_1_scalars_load(tmp_path):
    """A NumPy scalar pickled under NumPy 1 names ``numpy.core.multiarray.scalar``."""
    path = tmp_path / "np2.pth"
    torch.save({"best_EPE": np.float32(0.5)}, path)
    old = tmp_path / "np1.pth"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(old, "w") as dst:
        for name in src.namelist():
            data = src.read(name)
            if name.endswith("data.pkl"):
                data = re.sub(rb"cnumpy\._?core\.multiarray\nscalar", b"cnumpy.core.multiarray\nscalar", data)
                assert b"numpy.core.multiarray" in data
            dst.writestr(name, data)
    assert load_tensors(old, argument="a", expected="b")["best_EPE"] == np.float32(0.5)


@pytest.mark.parametrize("content, reason", [(b"", "the file ends early"), (b"\x00not a checkpoint" * 8, "Unsupported"),
                                             ("truncated", "PytorchStreamReader")])
def test_unreadable_files_name_the_argument_and_the_file(tmp_path, content, reason):
    path = tmp_path / "bad.ckpt"
    if content == "truncated":
        torch.save({"w": torch.zeros(1000)}, path)
        content = path.read_bytes()[:200]
    path.write_bytes(content)
    with pytest.raises(ValueError, match=rf"^model\.checkpoint: cannot read {re.escape(str(path))} as a PyTorch file "
                                         rf"\({reason}.*\); expected a \.ckpt written by train\.py$"):
        FilterParameters.from_checkpoint(path)
    with pytest.raises(ValueError, match=rf"^model\.checkpoint: {re.escape(str(tmp_path / 'nowhere.ckpt'))} is not a file"):
        FilterParameters.from_checkpoint(tmp_path / "nowhere.ckpt")
