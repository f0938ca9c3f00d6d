"""Test-wide settings.

The filter's tensors are small (26 x 26): one intra-op thread is fastest, and it keeps
the suite's run time stable on a busy 2-core machine (oversubscribed threads made
small matrix products two orders of magnitude slower here).
"""
import os
import traceback
import typing
import weakref

import pytest
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

torch.set_num_threads(1)


def _where() -> str:
    """``file:line`` of the innermost frame in the flowins package on the stack."""
    import flowins

    root = os.path.dirname(flowins.__file__)
    return next((f"{os.path.relpath(f.filename, os.path.dirname(root))}:{f.lineno}"
                 for f in reversed(traceback.extract_stack()) if f.filename.startswith(root)), "?")


class MixedDtypes(TorchFunctionMode):
    """Records every torch op whose tensor arguments (of one dimension or more) hold two
    floating dtypes: a constant built in float64 (or the default dtype) meeting a float32
    state. On a GPU the same slip is a CPU tensor meeting a CUDA one (an error there);
    run a float32 filter under this mode with ``torch.set_default_dtype(torch.float64)``
    to see both kinds of slip on a CPU. Casts (``to``, ``copy_``, assignment) are allowed."""

    CASTS: typing.ClassVar[set] = {torch.Tensor.to, torch.Tensor.type_as, torch.Tensor.copy_, torch.Tensor.__setitem__,
                                   torch.as_tensor, torch.Tensor.double, torch.Tensor.float, torch.Tensor.type}

    def __init__(self):
        super().__init__()
        self.slips: dict[str, int] = {}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func not in self.CASTS:
            dtypes = {a.dtype for a in tree_flatten((args, kwargs))[0]
                      if isinstance(a, torch.Tensor) and a.ndim > 0 and a.is_floating_point()}
            if len(dtypes) > 1:
                key = f"{getattr(func, '__name__', func)} at {_where()}: {sorted(map(str, dtypes))}"
                self.slips[key] = self.slips.get(key, 0) + 1
        return func(*args, **kwargs)


@pytest.fixture
def mixed_dtypes():
    """``with mixed_dtypes() as mode:`` a :class:`MixedDtypes` mode with the default dtype
    float64 inside (restored after); ``mode.slips`` names each op, where and its dtypes."""
    import contextlib

    @contextlib.contextmanager
    def guard():
        previous = torch.get_default_dtype()
        torch.set_default_dtype(torch.float64)
        try:
            with MixedDtypes() as mode:
                yield mode
        finally:
            torch.set_default_dtype(previous)

    return guard


#: the fake device of :class:`FakeDevice`: tensors "on" it are CPU tensors it has tagged
FAKE_DEVICE = torch.device("meta")
_DEVICE = torch._C.TensorBase.__dict__["device"]  # the getset descriptor behind x.device


class FakeDevice(TorchFunctionMode):
    """A second device on a CPU: tensors made with ``device=meta`` (or moved there) are CPU
    tensors tagged as on it; every op on a tagged tensor tags its results; ``x.device`` of a
    tagged tensor is ``meta``. An op that meets a tagged tensor and an untagged one (of one
    dimension or more) is recorded as a slip: on a GPU it is a CPU tensor meeting a CUDA one.
    Indexing is allowed one way only, as on a GPU: a tensor on the device by CPU indices.
    Every read of a tagged tensor's values by the host (``tolist``, ``item``, ``bool``,
    ``nonzero``, ``cpu``, ...) is recorded in :attr:`reads` by where it happened, and every copy
    of host data to the device (``to`` of a CPU tensor, ``tensor`` / ``as_tensor`` made on the
    device) in :attr:`copies`: on a GPU each read waits for the device's queue, and so does each
    copy from pageable memory."""

    ALLOWED: typing.ClassVar[set] = {torch.Tensor.copy_, torch.Tensor.__setitem__, torch.Tensor.__getitem__, torch.Tensor.to,
               torch.Tensor.cpu, torch.as_tensor, torch.Tensor.index_select, torch.Tensor.tolist}

    #: id -> weak reference of every tensor on the fake device, shared by all modes (cached
    #: constants built for it outlive a mode); tensors compare by value, so no WeakSet
    tagged: typing.ClassVar[dict] = {}

    #: the calls that read a tensor's values into the host
    READS: typing.ClassVar[set] = {torch.Tensor.tolist, torch.Tensor.item, torch.Tensor.__bool__, torch.Tensor.__int__,
                                   torch.Tensor.__float__, torch.Tensor.__index__, torch.nonzero, torch.Tensor.nonzero,
                                   torch.Tensor.cpu, torch.Tensor.numpy, torch.equal}

    def __init__(self):
        super().__init__()
        self.slips = {}
        self.reads = {}
        self.copies = {}

    @classmethod
    def place(cls, *modules) -> None:
        """Count the parameters and buffers of ``modules`` as on the device (``module.to(cuda)``)."""
        for module in modules:
            for t in (*module.parameters(), *module.buffers()):
                cls._tag(t)

    @classmethod
    def _tag(cls, t: torch.Tensor) -> None:
        key = id(t)
        cls.tagged[key] = weakref.ref(t, lambda _: cls.tagged.pop(key, None))

    def _is(self, t):
        ref = self.tagged.get(id(t)) if isinstance(t, torch.Tensor) else None
        return ref is not None and ref() is t

    def _slip(self, what):
        key = f"{what} at {_where()}"
        self.slips[key] = self.slips.get(key, 0) + 1

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        if getattr(func, "__self__", None) is _DEVICE:
            return FAKE_DEVICE if self._is(args[0]) else func(*args)
        flat, _ = tree_flatten((args, kwargs))
        tensors = [t for t in flat if isinstance(t, torch.Tensor)]
        on = [t for t in tensors if self._is(t)]
        target = None  # where the result goes: True tagged, False untagged, None: follow the inputs
        dev = kwargs.get("device")
        if dev is not None and torch.device(dev) == FAKE_DEVICE:
            kwargs["device"] = "cpu"
            target = True
        elif dev is not None:
            target = False
        if func is torch.Tensor.to:
            rest = list(args[1:])
            for i, a in enumerate(rest):
                if isinstance(a, (str, torch.device)):
                    if torch.device(a) == FAKE_DEVICE:
                        rest[i], target = "cpu", True
                    else:
                        target = False
                elif isinstance(a, torch.Tensor):
                    target = self._is(a)
            args = (args[0], *rest)
        if func is torch.Tensor.cpu:
            target = False
        if func is torch.Tensor.numpy and on:
            self._slip("numpy() of a tensor on the device")
        if func in self.READS and on:
            key = f"{func.__name__} at {_where()}"
            self.reads[key] = self.reads.get(key, 0) + 1
        if target and func in (torch.tensor, torch.as_tensor, torch.Tensor.to) and not (args and self._is(args[0])):
            key = f"{func.__name__} at {_where()}"
            self.copies[key] = self.copies.get(key, 0) + 1
        if func in (torch.Tensor.__getitem__, torch.Tensor.index_select) and on and not self._is(args[0]):
            self._slip(f"{func.__name__}: a CPU tensor {tuple(args[0].shape)} indexed by indices on the device")
        if on and func not in self.ALLOWED and target is None:
            plain = [t for t in tensors if not self._is(t) and t.ndim > 0]
            if plain:
                self._slip(f"{getattr(func, '__name__', func)}: {len(plain)} CPU tensor(s) {[tuple(t.shape) for t in plain]}")
        out = func(*args, **kwargs)
        if target is not None and any(out is t and self._is(t) != target for t in tensors):
            out = out.clone()  # a move between devices is a new tensor (``to`` returns its input when nothing changes)
        tag = bool(on) if target is None else target
        for t in tree_flatten(out)[0]:
            if isinstance(t, torch.Tensor):
                if tag:
                    self._tag(t)
                elif target is False and self._is(t) and t is not (args[0] if args else None):
                    del self.tagged[id(t)]
        return out


@pytest.fixture
def fake_device():
    """``with fake_device() as mode:`` a :class:`FakeDevice` mode; ``mode.slips`` names each op
    that met a tensor on the fake device and a CPU one, where, and the CPU tensors' shapes;
    ``mode.place(*modules)`` puts modules' parameters and buffers on the device."""
    return FakeDevice


@pytest.fixture
def wrong_heading_walk():
    """A factory ``(seed, duration_s, second_pass) -> (recording, run, config)``: INS + GNSS on a
    synthetic walk with a good IMU, the filter's yaw 2 rad off with σ = π, so the held GNSS
    fixes set its heading (``baseline_m=15``, ``max_sigma_rad=0.5``)."""
    from flowins.data.synthetic import ImuErrors, synthetic_walk_recording
    from flowins.geometry.geodesy import LocalTangentPlane
    from flowins.ins.initialization import InitialUncertainty
    from flowins.ins.mechanization import ProcessNoise
    from flowins.measurements.gnss_heading import HeadingAlignment
    from flowins.navigation import NavigationConfig, NavigationRun
    from flowins.start import StartSettings

    def make(seed: int, duration_s: float = 90.0, second_pass: bool = False):
        origin = (60.1699, 24.9384, 20.0)
        rec = synthetic_walk_recording(duration_s=duration_s, seed=seed, origin=origin, imu_errors=ImuErrors(
            acc_noise=2e-4, gyro_noise=1e-5, acc_bias_std=0.002, gyro_bias_std=2e-5, acc_bias_walk=0.0,
            gyro_bias_walk=0.0, acc_scale_std=0.0))
        config = NavigationConfig(noise=ProcessNoise(acc_noise=2e-4, gyro_noise=1e-5),
                                  initial=InitialUncertainty(acc_bias_mps2=0.005, gyro_bias_rps=1e-4, acc_scale=1e-3),
                                  start=StartSettings(yaw_rad=2.0),
                                  gnss_heading=HeadingAlignment(baseline_m=15.0, max_sigma_rad=0.5, second_pass=second_pass))
        return rec, NavigationRun(rec.imu, rec.gnss, frame=LocalTangentPlane(*origin)), config

    return make


@pytest.fixture
def repo_module():
    """``load(relative_path)``: a file of the repository (a benchmark, another test file) loaded
    as a module, for tests of code that is not in the package."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]

    def load(relative: str):
        path = root / relative
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
