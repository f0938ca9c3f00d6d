"""The one state layout of flowins: the paper's 26-dimensional INS state.

    x = (p, v, q, b_a, b_w, T_a, p_prev, q_prev)

=========  ====  ======  =====================================================
name       size  unit    meaning
=========  ====  ======  =====================================================
p          3     m       IMU position in the local world frame (ENU, z up)
v          3     m/s     IMU velocity in the world frame
q          4     -       orientation, unit quaternion (w, x, y, z), body->world
b_a        3     m/s^2   additive accelerometer bias
b_w        3     rad/s   additive gyroscope bias
T_a        3     -       diagonal multiplicative accelerometer scale
p_prev     3     m       augmented position of the previous camera frame
q_prev     4     -       augmented orientation of the previous camera frame
=========  ====  ======  =====================================================

Every other module addresses the state through the names defined here
(``STATE.p``, ``STATE.q_prev``, ...), never through index literals. The process
noise vector has its own layout, :data:`NOISE`.

A sliding window of ``N`` cloned camera poses (the multi-view track update,
:mod:`flowins.measurements.tracks`) extends the layout: the core, then clone 0
(``p_prev``, ``q_prev``: the previous camera frame), clone 1 (the frame before), ...,
clone ``N - 1``, 7 entries each, so a state has ``D = 19 + 7 N`` entries
(:func:`state_dim`, :func:`window_layout`); ``N = 1`` is the 26-dim layout above.
Functions that act on every pose of a state (:func:`normalize_quaternions`,
:func:`pose_slices`) read ``N`` from its last dimension.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import NamedTuple

import torch
from torch import Tensor


@cache
def _slices(sizes: tuple[tuple[str, int], ...]) -> dict[str, slice]:
    out, start = {}, 0
    for field, size in sizes:
        out[field] = slice(start, start + size)
        start += size
    return out


@dataclass(frozen=True)
class _Layout:
    """Named, contiguous slices of a flat vector."""

    sizes: tuple[tuple[str, int], ...]

    @property
    def dim(self) -> int:
        return sum(size for _, size in self.sizes)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.sizes)

    def slice(self, name: str) -> slice:
        found = _slices(self.sizes).get(name)
        if found is None:
            raise KeyError(f"no field {name!r} in layout; fields are {self.names}")
        return found

    def __getattr__(self, name: str) -> slice:
        if name.startswith("_") or name in ("sizes",):
            raise AttributeError(name)
        try:
            return self.slice(name)
        except KeyError as exc:
            raise AttributeError(str(exc)) from None

    def indices(self, *names: str) -> Tensor:
        """Integer indices of the named fields, concatenated in the given order."""
        return torch.cat([torch.arange(self.slice(n).start, self.slice(n).stop) for n in names])


#: The paper's state layout (Sec. "Inertial Navigation").
STATE = _Layout(
    (
        ("p", 3),
        ("v", 3),
        ("q", 4),
        ("b_a", 3),
        ("b_w", 3),
        ("T_a", 3),
        ("p_prev", 3),
        ("q_prev", 4),
    )
)
STATE_DIM: int = STATE.dim  # 26

#: The "core" (non-augmented) part, the first 19 entries: A_star keeps these, and
#: the IMU propagation touches nothing else (the augmented pose is constant).
CORE = _Layout(STATE.sizes[: STATE.names.index("T_a") + 1])
CORE_DIM: int = CORE.dim  # 19

#: Process noise layout: white accelerometer and gyroscope input noise (the
#: paper's epsilon^a, epsilon^omega) and optional random walks of the biases
#: and of the accelerometer scale (off by default, as in the paper).
NOISE = _Layout(
    (
        ("acc", 3),
        ("gyro", 3),
        ("b_a", 3),
        ("b_w", 3),
        ("T_a", 3),
    )
)
NOISE_DIM: int = NOISE.dim  # 15


def state_dim(clones: int) -> int:
    """``D = 19 + 7 N``: the state's size with a window of ``N >= 1`` cloned poses."""
    if not (isinstance(clones, int) and not isinstance(clones, bool) and clones >= 1):
        raise ValueError(f"a state has a window of N >= 1 cloned poses, got N = {clones!r}")
    return CORE_DIM + 7 * clones


def window_size(dim: int, *, where: str | None = None) -> int:
    """``N``, the number of cloned poses of a state of size ``dim`` (``19 + 7 N``); a ValueError
    otherwise, naming ``where`` (the caller and what it was given) when given."""
    clones, rest = divmod(dim - CORE_DIM, 7)
    if rest or clones < 1:
        prefix = "" if where is None else f"{where}: "
        raise ValueError(f"{prefix}a state has 19 + 7 N entries (N >= 1 cloned poses, {STATE_DIM} for N = 1), "
                         f"got {dim}")
    return clones


@cache
def window_layout(clones: int) -> _Layout:
    """The layout with ``N = clones`` cloned poses: :data:`STATE`'s fields (clone 0 is
    ``p_prev``, ``q_prev``), then ``p_clone1``, ``q_clone1``, ..., ``p_clone{N-1}``, ``q_clone{N-1}``."""
    extra = tuple(item for k in range(1, clones) for item in ((f"p_clone{k}", 3), (f"q_clone{k}", 4)))
    state_dim(clones)  # checks N
    return _Layout(STATE.sizes + extra)


def pose_slices(dim: int) -> tuple[tuple[slice, slice], ...]:
    """``((p, q), (p_prev, q_prev), (p_clone1, q_clone1), ...)``: the slices of the current pose
    and of each cloned pose, newest first, of a state of size ``dim``."""
    layout = window_layout(window_size(dim))
    names = ("p", "q"), ("p_prev", "q_prev"), *((f"p_clone{k}", f"q_clone{k}") for k in range(1, window_size(dim)))
    return tuple((layout.slice(p), layout.slice(q)) for p, q in names)


class State(NamedTuple):
    """The state split into named parts (each with the leading batch shape)."""

    p: Tensor
    v: Tensor
    q: Tensor
    b_a: Tensor
    b_w: Tensor
    T_a: Tensor
    p_prev: Tensor
    q_prev: Tensor


def split(x: Tensor) -> State:
    """Split ``x`` of shape ``(..., 26)`` into a :class:`State` of views; a state with a window
    of ``N > 1`` clones ``(..., 19 + 7 N)`` gives its core and clone 0 (``p_prev``, ``q_prev``)."""
    window_size(x.shape[-1], where=f"split: a state of shape {tuple(x.shape)}")
    return State(*(x[..., STATE.slice(name)] for name in STATE.names))


def join(state: State) -> Tensor:
    """Inverse of :func:`split`: concatenate the parts into ``(..., 26)``."""
    parts = [getattr(state, name) for name in STATE.names]
    leading = {p.shape[:-1] for p in parts}
    if len(leading) == 1:  # common case: no broadcasting needed
        return torch.cat(parts, dim=-1)
    shape = torch.broadcast_shapes(*leading)
    return torch.cat([p.expand(*shape, p.shape[-1]) for p in parts], dim=-1)


def make_state(
    *,
    p: Tensor,
    v: Tensor,
    q: Tensor,
    b_a: Tensor | None = None,
    b_w: Tensor | None = None,
    T_a: Tensor | None = None,
    p_prev: Tensor | None = None,
    q_prev: Tensor | None = None,
) -> Tensor:
    """Build a state vector; biases default to 0, scale to 1, the augmented pose to (p, q)."""
    zeros = torch.zeros_like(p)
    return join(
        State(
            p=p,
            v=v,
            q=q,
            b_a=zeros if b_a is None else b_a,
            b_w=zeros if b_w is None else b_w,
            T_a=torch.ones_like(p) if T_a is None else T_a,
            p_prev=p if p_prev is None else p_prev,
            q_prev=q if q_prev is None else q_prev,
        )
    )


def normalize_quaternions(x: Tensor) -> Tensor:
    """Re-normalise the quaternions ``q``, ``q_prev`` (and those of the further clones) of
    ``x`` ``(..., 19 + 7 N)``.

    Out of place and differentiable; a zero quaternion is left at zero instead of
    producing NaN (the norm is clamped away from zero).
    """
    clones = window_size(x.shape[-1], where=f"normalize_quaternions: a state of shape {tuple(x.shape)}")
    index = _quaternion_index(x.device, clones)
    q = x[..., index].unflatten(-1, (1 + clones, 4))
    norm = torch.linalg.vector_norm(q, dim=-1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny ** 0.5)
    return x.index_copy(-1, index, (q / norm).flatten(-2))


@cache
def _quaternion_index(device: torch.device, clones: int = 1) -> Tensor:
    """Indices of ``q``, ``q_prev``, ... in a state with ``clones`` cloned poses ``(4 + 4 N,)``
    (an integer tensor: no gradient, so the cache is safe in and out of inference mode)."""
    with torch.inference_mode(False):
        quaternions = [q for _, q in pose_slices(state_dim(clones))]
        return torch.cat([torch.arange(q.start, q.stop) for q in quaternions]).to(device)


def symmetrize(cov: Tensor) -> Tensor:
    """``(P + P^T) / 2`` over the last two dimensions (the half in place on the sum: one new tensor,
    not two, the same numbers)."""
    return (cov + cov.transpose(-1, -2)).mul_(0.5)
