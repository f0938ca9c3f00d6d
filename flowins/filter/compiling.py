"""The filter's steps through ``torch.compile`` (``filter.compile``).

A step that is a pure function of tensors with no read-back (the flow frame's whole update,
:func:`~flowins.measurements.flow_update.flow_frame_step`; on CUDA also the IMU propagation
between events, :func:`~flowins.filter.propagation.propagate_batched`, and every other event's
gated update, :func:`~flowins.filter.updater.gated_update`) is captured as one graph
(``fullgraph=True``: a graph break is an error, not a silent fallback) and compiled:

* on a CPU by inductor, which writes C++ and needs a C++ compiler (``$CXX``, else ``g++`` or
  ``clang++`` on the path);
* on a CUDA device by inductor with ``mode="reduce-overhead"``: its kernels replayed as CUDA
  graphs, the launches of a frame in one.

``filter.compile``: ``false`` (the default: eager), ``true`` (compile, and stop with an error
where it cannot) or ``auto`` (compile where it can, eager elsewhere, saying which).
Compiling costs minutes per shape on a 2-core CPU (docs/performance.md), so a step's inputs
are padded to a few fixed shapes (:func:`bucket`) and each compiled function is kept for the
process: the cost is paid once per shape, and inductor's cache on disk
(``TORCHINDUCTOR_CACHE_DIR``) shortens it in a later process. A pass that carries a gradient
(a training step) runs its steps compiled too, forward and backward (AOT autograd traces the
backward with the forward), except on CUDA, where its steps run eagerly (CUDA graphs replayed
before a backward that still needs the previous replay's memory are not supported here).
"""
from __future__ import annotations

import functools
import logging
import os
import shutil
import time
import warnings
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

SETTINGS = ("false", "true", "auto")

log = logging.getLogger(__name__)


@dataclass
class Compiler:
    """How the steps run (:func:`compiler_for`) and what compiling them cost: ``backend`` None
    runs them eagerly; ``reason`` says why, for the job's log."""

    backend: str | None
    mode: str | None = None
    reason: str = ""
    #: whether every step runs compiled, not only the flow frames: the IMU propagation between
    #: events (``propagate_batched``) and every other event's gated update (``updater.step_rows``).
    #: On CUDA, where each one's tens to hundreds of kernel launches become one graph; not on a CPU,
    #: where inductor's code for them runs hardly faster than eager (docs/performance.md) and each
    #: shape costs a compile
    all_steps: bool = False
    #: seconds spent in calls that compiled (a new shape), and their count
    compile_s: float = 0.0
    compiles: int = 0
    #: calls that ran compiled (0: the pass had no step to compile, e.g. no flow frames)
    calls: int = 0

    @property
    def enabled(self) -> bool:
        return self.backend is not None

    def __call__(self, fn: Callable, *args: Any, **kwargs: Any) -> Any:
        """``fn(*args, **kwargs)``, compiled where this compiler is on (with CUDA graphs, only where
        nothing needs a gradient)."""
        if not self.enabled or (self.mode == "reduce-overhead" and torch.is_grad_enabled()
                                and _needs_grad(args, kwargs)):
            return fn(*args, **kwargs)
        args, kwargs = map_tensors(_fixed_layout, (args, kwargs))
        how = (fn, self.backend, self.mode)
        compiled = _COMPILED.get(how)
        if compiled is None:
            compiled = _COMPILED[how] = torch.compile(fn, fullgraph=True, dynamic=False, backend=self.backend,
                                                      mode=self.mode)
        self.calls += 1
        shapes, seen = _signature(args, kwargs), _SEEN.setdefault(compiled, set())
        if shapes not in seen:  # a step not met yet at these shapes: it compiles now, for minutes on a CPU
            seen.add(shapes)
            log.info("filter steps: compiling %s (shape %d of it in this process) with %s for %s (once per shape "
                     "in a process; minutes on a CPU)", _name(fn), len(seen), self.backend, _describe(shapes))
        graphs = _graphs()
        start = time.perf_counter()
        _quiet_inductor()
        with warnings.catch_warnings():
            _quiet_tracing()
            if self.mode == "reduce-overhead":  # CUDA graphs: a new step; its outputs live in the graph's
                torch.compiler.cudagraph_mark_step_begin()  # memory, which the next replay overwrites
                out = copied(compiled(*args, **kwargs))
            else:
                out = compiled(*args, **kwargs)
        compiled_now = _graphs() - graphs
        if compiled_now:  # a shape (or setting) not met yet in this process: this call compiled
            spent = time.perf_counter() - start
            self.compile_s += spent
            self.compiles += compiled_now
            log.info("filter steps: %s compiled in %.1f s%s", _name(fn), spent,
                     "; its backward compiles at the first backward pass" if _with_gradients(shapes) else "")
        return out

    def describe(self) -> str:
        """One line for the job's log: how the steps ran and, compiled, what that cost."""
        if not self.enabled:
            return f"filter steps: eager ({self.reason})"
        return (f"filter steps: compiled with {self.backend}{'' if self.mode is None else ', ' + self.mode} "
                f"({self.reason}); {self.compiles} shape(s) compiled in {self.compile_s:.1f} s")


#: each step's compiled function by (function, backend, mode), for the process: a later run
#: with the shapes met before compiles nothing
_COMPILED: dict[tuple, Callable] = {}


#: per compiled step, the inputs' shapes it has met (:func:`_signature`), to say when it compiles
_SEEN: weakref.WeakKeyDictionary[Callable, set[tuple]] = weakref.WeakKeyDictionary()


def _signature(args: tuple, kwargs: dict) -> tuple:
    """The shape, dtype, device and gradient of every tensor in a step's inputs, in order, and
    whether gradients are on: what makes a compiled step compile again (its settings aside)."""
    found: list = []
    map_tensors(lambda t: found.append((tuple(t.shape), t.dtype, t.device.type, t.requires_grad)) or t, (args, kwargs))
    return torch.is_grad_enabled(), tuple(found)


def _describe(signature: tuple) -> str:
    """The largest of a step's input shapes (its batch and point counts show there), for the log."""
    largest = max(signature[1], key=lambda t: (len(t[0]), t[0]), default=((), None, "", False))[0]
    return f"inputs up to {tuple(largest)}" + (", with gradients" if _with_gradients(signature) else "")


def _with_gradients(signature: tuple) -> bool:
    """Whether a call of that :func:`_signature` carries a gradient (gradients on, an input needing one)."""
    grad, tensors = signature
    return grad and any(t[3] for t in tensors)


def _name(fn: Callable) -> str:
    return getattr(fn, "__qualname__", getattr(fn, "__name__", repr(fn)))


def _quiet_tracing() -> None:
    """Silence what tracing a step says about torch itself, not about the step, once per cached
    function and per internal call it meets (dozens of lines on a job's output): that dynamo traces
    through a ``functools`` cache (flowins caches only constants that are pure functions of their
    hashable arguments, :func:`~flowins.constants.cached_constant`, so tracing the function is
    exact)."""
    warnings.filterwarnings("ignore", message="Dynamo detected a call to a `functools.lru_cache`", category=UserWarning)


@functools.cache
def _quiet_inductor() -> None:
    """Silence inductor's own deprecation warnings for the process, once: a step's backward
    compiles in a backward pass, outside the step's call."""
    warnings.filterwarnings("ignore", category=FutureWarning, module=r"torch\._inductor")


def _graphs() -> int:
    """Graphs dynamo has compiled in this process (its own count)."""
    return torch._dynamo.utils.counters["stats"]["unique_graphs"]


def map_tensors(fn: Callable[[torch.Tensor], torch.Tensor], value: Any) -> Any:
    """``value`` with ``fn`` applied to every tensor in it, through tuples (named ones too), lists
    and dicts; everything else as it is."""
    if isinstance(value, torch.Tensor):
        return fn(value)
    if isinstance(value, tuple):
        items = [map_tensors(fn, v) for v in value]
        return type(value)(*items) if hasattr(value, "_fields") else tuple(items)
    if isinstance(value, list):
        return [map_tensors(fn, v) for v in value]
    if isinstance(value, dict):
        return {k: map_tensors(fn, v) for k, v in value.items()}
    return value


def copied(value: Any) -> Any:
    """``value`` with every tensor in it cloned (:func:`map_tensors`): what a caller keeps of a
    CUDA graph's outputs after its next replay."""
    return map_tensors(torch.Tensor.clone, value)


def _fixed_layout(t: torch.Tensor) -> torch.Tensor:
    """``t``, or a contiguous copy where its strides are not a fresh tensor's: a compiled shape
    guards on strides, those of size-1 dimensions too, and a view into the chain (its newest node)
    has strides that change from call to call."""
    stride, expected = t.stride(), []
    step = 1
    for size in reversed(t.shape):
        expected.append(step)
        step *= size
    return t if tuple(reversed(expected)) == stride else t.clone(memory_format=torch.contiguous_format)


def _needs_grad(args: tuple, kwargs: dict) -> bool:
    return any(isinstance(t, torch.Tensor) and t.requires_grad for t in (*args, *kwargs.values()))


def cpp_compiler() -> str | None:
    """The C++ compiler inductor would call on a CPU (``$CXX``, ``g++``, ``clang++``), None if none is found."""
    names = [os.environ["CXX"]] if os.environ.get("CXX") else ["g++", "clang++"]
    for name in names:
        path = shutil.which(name)
        if path:
            return path
    return None


def compiler_for(setting: str, device: torch.device) -> Compiler:
    """The :class:`Compiler` of ``filter.compile`` (``false`` | ``true`` | ``auto``) on ``device``."""
    if setting not in SETTINGS:
        raise ValueError(f"filter.compile={setting!r}: expected one of {', '.join(SETTINGS)}")
    if setting == "false":
        return Compiler(None, reason="filter.compile=false")
    if device.type == "cuda":
        return Compiler("inductor", "reduce-overhead", f"filter.compile={setting}, {device}: CUDA graphs",
                        all_steps=True)
    if device.type != "cpu":
        if setting == "true":
            raise ValueError(f"filter.compile=true: compiling on {device} is not supported; use cpu or cuda")
        return Compiler(None, reason=f"filter.compile=auto: nothing to compile with on {device}")
    cxx = cpp_compiler()
    if cxx is None:
        if setting == "true":
            raise ValueError("filter.compile=true: no C++ compiler found (set CXX, or install g++ or clang++), "
                             "which inductor needs on a CPU; filter.compile=auto runs eagerly without one")
        return Compiler(None, reason="filter.compile=auto: no C++ compiler found (CXX, g++, clang++)")
    return Compiler("inductor", None, f"filter.compile={setting}, C++ compiler {cxx}")


def bucket(n: int, *, smallest: int = 64) -> int:
    """The padded size of ``n`` items: the next power of two at or above ``n``, at least
    ``smallest``, so that a pass meets a handful of shapes, not one per count."""
    size = smallest
    while size < n:
        size *= 2
    return size
