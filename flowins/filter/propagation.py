"""Propagating the INS mean and covariance over a run of IMU samples.

Two interchangeable paths produce the same numbers (tests check 1e-9 in float64):

* :func:`propagate_reference` - the plain EKF: one ``mechanize`` call and one
  ``torch.func.jacrev`` per sample, in a Python loop.
* :func:`propagate_batched` - the fast path: between measurement updates the
  mean depends only on the inputs, so the whole run is computed at once
  (a log-depth quaternion scan and cumulative sums), the Jacobians of all
  samples come from the closed forms of :mod:`flowins.ins.jacobians` in one
  batched call, and the covariance transition between output nodes is a
  log-depth tree reduction of ``(F, S) -> (F₂F₁, F₂ S₁ F₂ᵀ + S₂)``.

Both return, for each output node ``j`` (an index into the steps), the state mean,
the covariance and the transition ``Φ_j`` from the previous node (the product of the
step Jacobians in between), which the RTS smoother needs.
"""
from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from flowins.filter.ekf import dynamics_jacobians
from flowins.geometry import quaternion as quat
from flowins.constants import cached_constant
from flowins.ins.jacobians import (
    StepPieces,
    core_jacobians_from_pieces,
    embed_core,
    pad_core,
    rotation_increments,
)
from flowins.ins.mechanization import (
    ProcessNoise,
    check_scheme,
    gravity_vector,
    mechanize,
)
from flowins.state import CORE_DIM, NOISE_DIM, STATE_DIM, State, join, split, symmetrize


class Propagated(NamedTuple):
    mean: Tensor  # (..., m, D) state at each node (D = 19 + 7 N, 26 for N = 1 cloned pose)
    cov: Tensor  # (..., m, D, D)
    transition: Tensor  # (..., m, D, D) Φ_j from the previous node (or the start) to node j


def _run_pieces(
    x0: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, dt_s: Tensor, gravity_mps2: float | Tensor, scheme: str
) -> tuple[Tensor, StepPieces]:
    """Noise-free states after each of ``K`` steps ``(..., K, D)`` from ``x0`` ``(..., D)``
    and the steps' :class:`StepPieces`.

    With the noise at zero the biases and scale are constant over the run, so
    ``q_k = q_0 ⊙ 𝒬_1 ⊙ ... ⊙ 𝒬_k`` is a prefix product and ``v``, ``p`` are
    cumulative sums; the pieces (rotation increments and their Jacobians, ``C(q_rot)``)
    are the ones the closed-form Jacobians reuse.
    """
    s = split(x0)
    dt = dt_s.unsqueeze(-1)  # (..., K, 1)
    theta = (gyro_rps - s.b_w.unsqueeze(-2)) * dt
    E, E_rot, dE, R_E = rotation_increments(theta, scheme)
    # q_k = q_{k-1} ⊙ 𝒬_k = R(𝒬_k) q_{k-1}: prefix products of the right-product matrices
    q = (_prefix_products(R_E[..., 0, :, :]) @ s.q.unsqueeze(-2).unsqueeze(-1)).squeeze(-1)  # (..., K, 4)
    q_before = torch.cat((s.q.unsqueeze(-2), q[..., :-1, :]), dim=-2)
    q_rot = q if scheme == "paper" else (R_E[..., 1, :, :] @ q_before.unsqueeze(-1)).squeeze(-1)
    C = quat.to_matrix(q_rot)
    acc_unbiased = acc_mps2 - s.b_a.unsqueeze(-2)
    T_a = s.T_a.unsqueeze(-2).expand_as(acc_unbiased)
    a = T_a * acc_unbiased
    acc_world = (C @ a.unsqueeze(-1)).squeeze(-1) - _gravity(gravity_mps2, x0)
    v_all = torch.cumsum(torch.cat((s.v.unsqueeze(-2), acc_world * dt), dim=-2), dim=-2)  # v_0 .. v_K
    v_before, v = v_all[..., :-1, :], v_all[..., 1:, :]
    v_step = v_before if scheme == "paper" else 0.5 * (v_before + v)
    p = torch.cumsum(torch.cat((s.p.unsqueeze(-2), v_step * dt), dim=-2), dim=-2)[..., 1:, :]
    shape = acc_unbiased.shape[:-1]
    means = join(
        State(
            p=p,
            v=v,
            q=q,
            b_a=s.b_a.unsqueeze(-2).expand(*shape, 3),
            b_w=s.b_w.unsqueeze(-2).expand(*shape, 3),
            T_a=T_a,
            p_prev=s.p_prev.unsqueeze(-2).expand(*shape, 3),
            q_prev=s.q_prev.unsqueeze(-2).expand(*shape, 4),
        )
    )
    if x0.shape[-1] != STATE_DIM:  # the further cloned poses are constant too
        means = torch.cat((means, x0[..., STATE_DIM:].unsqueeze(-2).expand(*shape, x0.shape[-1] - STATE_DIM)), -1)
    return means, StepPieces(q_before, theta, E, E_rot, dE, R_E, q_rot, C, acc_unbiased, a, T_a, dt)


def _prefix_products(M: Tensor) -> Tensor:
    """``M_k ⋯ M_1`` for ``M`` ``(..., K, D, D)`` (inclusive prefix products, later factors on
    the left; a log-depth scan)."""
    K = M.shape[-3]
    shift = 1
    while shift < K:
        M = torch.cat((M[..., :shift, :, :], M[..., shift:, :, :] @ M[..., :-shift, :, :]), dim=-3)
        shift *= 2
    return M


def _gravity(gravity_mps2: float | Tensor, like: Tensor) -> Tensor:
    """``(0, 0, g0)`` (built once per value, dtype and device for a plain number)."""
    if isinstance(gravity_mps2, Tensor):
        return gravity_vector(gravity_mps2, like=like)
    return _cached_gravity(float(gravity_mps2), like.dtype, like.device)


@cached_constant
def _cached_gravity(gravity_mps2: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    return gravity_vector(gravity_mps2, like=torch.zeros((), dtype=dtype, device=device))


def propagate_mean(
    x0: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    dt_s: Tensor,
    gravity_mps2: float | Tensor,
    scheme: str = "midpoint",
) -> Tensor:
    """States after each of ``K`` steps ``(..., K, D)`` from ``x0`` ``(..., D)``, noise-free.

    Equal to ``K`` sequential :func:`mechanize` calls, computed with a log-depth
    quaternion scan and cumulative sums.
    """
    return _run_pieces(x0, acc_mps2, gyro_rps, dt_s, gravity_mps2, scheme)[0]


def _compose(later: tuple[Tensor, Tensor], earlier: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    """Step ``earlier`` then step ``later``: ``(F₂F₁, F₂ S₁ F₂ᵀ + S₂)``."""
    (F2, S2), (F1, S1) = later, earlier
    return F2 @ F1, F2 @ S1 @ F2.transpose(-1, -2) + S2


def _interval_compose(F: Tensor, W: Tensor) -> tuple[Tensor, Tensor]:
    """Transition and noise over intervals of ``L`` steps ``(..., L, D, D)`` -> ``(..., D, D)``:
    ``Φ = F_L ⋯ F_1`` and ``S = Σ_k T_k W_k T_kᵀ`` with the suffix products
    ``T_k = F_L ⋯ F_{k+1}`` (a log-depth scan over the interval)."""
    T = _suffix_products(F)  # T_k = F_L ⋯ F_k, maps the state before step k to the end
    T_after = torch.cat((T[..., 1:, :, :], _eye_like(F)), dim=-3)  # F_L ⋯ F_{k+1}
    return T[..., 0, :, :], (T_after @ W @ T_after.transpose(-1, -2)).sum(-3)


def _suffix_products(F: Tensor) -> Tensor:
    """``T_k = F_{L-1} ⋯ F_k`` for ``F`` ``(..., L, D, D)`` (inclusive suffix products, log depth)."""
    L = F.shape[-3]
    shift = 1
    while shift < L:
        F = torch.cat((F[..., shift:, :, :] @ F[..., :-shift, :, :], F[..., L - shift:, :, :]), dim=-3)
        shift *= 2
    return F


def _eye_like(F: Tensor) -> Tensor:
    """An identity ``(..., 1, D, D)`` matching ``F`` ``(..., L, D, D)``."""
    return _identity_step(F.dtype, F.device)[:, 0].expand(*F.shape[:-3], 1, *F.shape[-2:])


def _prefix_compose(F: Tensor, S: Tensor) -> tuple[Tensor, Tensor]:
    """Inclusive prefix compositions of ``m`` steps ``(..., m, D, D)`` (a log-depth scan):
    entry ``j`` maps the start to after step ``j``."""
    shift = 1
    m = F.shape[-3]
    while shift < m:
        F_new, S_new = _compose((F[..., shift:, :, :], S[..., shift:, :, :]), (F[..., :-shift, :, :], S[..., :-shift, :, :]))
        F = torch.cat((F[..., :shift, :, :], F_new), dim=-3)
        S = torch.cat((S[..., :shift, :, :], S_new), dim=-3)
        shift *= 2
    return F, S


class NodePlan(NamedTuple):
    """Where a batch of runs reports nodes (:func:`plan_nodes`)."""

    group: Tensor  # (B, m, L) step of each node interval's slots, B K for an identity padding slot
    node_step: Tensor  # (B, m) the step after which each node lies, -1 for a padding node (the start)
    real: list[list[bool]]  # (B, m) whether each node is one of the row's own nodes


def plan_nodes(node_steps: Sequence[Sequence[int]], num_steps: int, *, device=None) -> NodePlan:
    """The node intervals of ``B`` rows of ``K = num_steps`` steps, padded to one shape.

    Row ``b`` reports its nodes after the steps ``node_steps[b]`` (strictly increasing,
    the last ``K - 1``; empty for a row with nothing to report). Rows with fewer than
    ``m`` nodes get padding nodes first (no steps: the start state, an identity
    transition); every interval is padded to ``L`` slots, the longest interval, with
    identity steps after its own.
    """
    rows = [_check_nodes(steps, num_steps, allow_empty=True) for steps in node_steps]
    if len(rows) > 4:  # array arithmetic: the lists below cost Python work per row and slot
        return _plan_arrays(rows, num_steps, device)
    m = max(len(steps) for steps in rows)
    intervals, node_step, real = [], [], []
    for steps in rows:
        pad = m - len(steps)
        starts = [0] + [step + 1 for step in steps[:-1]]
        intervals.append([[]] * pad + [list(range(start, step + 1)) for start, step in zip(starts, steps)])
        node_step.append([-1] * pad + list(steps))
        real.append([False] * pad + [True] * len(steps))
    L = max(1, max(len(i) for row in intervals for i in row))
    sentinel = len(rows) * num_steps
    group = [[[b * num_steps + k for k in i] + [sentinel] * (L - len(i)) for i in row] for b, row in enumerate(intervals)]
    # one tensor for both (each tensor made from Python numbers is two operations)
    both = torch.tensor([[g + [step] for g, step in zip(rows, steps)] for rows, steps in zip(group, node_step)],
                        device=device)
    return NodePlan(both[..., :L], both[..., L], real)


def pad_plan(plan: NodePlan, *, nodes: int, slots: int, sentinel: int) -> NodePlan:
    """``plan`` grown to ``nodes`` nodes per row (padding nodes first: the start state, an
    identity transition) and ``slots`` slots per interval (identity steps, index ``sentinel``:
    the ``B K`` of :func:`plan_nodes`), for a step of fixed shape."""
    _, m, L = plan.group.shape
    if nodes < m or slots < L:
        raise ValueError(f"pad_plan: the plan has {m} nodes of {L} slots, more than {nodes} of {slots}")
    group = torch.nn.functional.pad(plan.group, (0, slots - L, nodes - m, 0), value=sentinel)
    node_step = torch.nn.functional.pad(plan.node_step, (nodes - m, 0), value=-1)
    return NodePlan(group, node_step, [[False] * (nodes - m) + list(flags) for flags in plan.real])


def _plan_arrays(rows: list[list[int]], num_steps: int, device) -> NodePlan:
    """:func:`plan_nodes` of checked ``rows`` in NumPy array arithmetic (the same plan)."""
    B = len(rows)
    counts = np.fromiter((len(steps) for steps in rows), dtype=np.int64, count=B)
    m = int(counts.max())
    steps = np.fromiter(itertools.chain.from_iterable(rows), dtype=np.int64, count=int(counts.sum()))
    row = np.repeat(np.arange(B), counts)  # each node's row
    ends = np.cumsum(counts)
    first = np.zeros(steps.shape[0], dtype=bool)  # a row's first node: its interval starts at step 0
    first[(ends - counts)[counts > 0]] = True
    starts = np.where(first, 0, np.concatenate(([0], steps[:-1] + 1)))
    lengths = steps - starts + 1
    L = max(1, int(lengths.max(initial=0)))
    slot = (m - counts)[row] + np.arange(steps.shape[0]) - (ends - counts)[row]  # padding nodes first
    sentinel = B * num_steps
    both = np.full((B, m, L + 1), sentinel, dtype=np.int64)
    both[:, :, L] = -1
    both[row, slot, L] = steps
    k = np.arange(L)
    both[row, slot, :L] = np.where(k < lengths[:, None], row[:, None] * num_steps + starts[:, None] + k, sentinel)
    real = (np.arange(m) >= (m - counts)[:, None]).tolist()
    both = torch.from_numpy(both).to(device)
    return NodePlan(both[..., :L], both[..., L], real)


def _check_nodes(node_steps: Sequence[int] | Tensor, num_steps: int, *, allow_empty: bool = False) -> list[int]:
    """The node steps as Python integers, checked: strictly increasing, ending with the last
    step (or, with ``allow_empty``, none at all)."""
    steps = node_steps.tolist() if isinstance(node_steps, Tensor) else list(node_steps)
    if not steps and allow_empty:
        return steps
    if not steps or steps[-1] != num_steps - 1:
        raise ValueError("node_steps must end with the last step index")
    if steps[0] < 0 or any(b <= a for a, b in itertools.pairwise(steps)):
        raise ValueError("node_steps must be strictly increasing step indices")
    return steps


def propagate_batched(
    x0: Tensor,
    P0: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    dt_s: Tensor,
    node_steps: Tensor | NodePlan,
    *,
    noise: ProcessNoise | Sequence[ProcessNoise] | None = None,
    gravity_mps2: float | Tensor,
    scheme: str = "midpoint",
    variances: Tensor | None = None,
) -> Propagated:
    """Fast path: propagate ``(x0, P0)`` over ``K`` steps, reporting at the nodes.

    Args:
        x0 ``(D,)``, P0 ``(D, D)`` (``D = 19 + 7 N``, 26 for the paper's one cloned pose; the
            cloned poses are constant, an identity transition); acc/gyro ``(K, 3)``, dt ``(K,)``;
            node_steps: increasing step indices ``(m,)`` after which a node is reported, the last
            ``K - 1``. Or a batch of ``B`` runs: x0 ``(B, D)``, P0 ``(B, D, D)``,
            acc/gyro ``(B, K, 3)``, dt ``(B, K)`` and node_steps a :class:`NodePlan`
            (:func:`plan_nodes`); a row's steps with ``Δt = 0`` are identities (padding).
        noise: one for all rows, or one per row; or ``variances`` ``(K, 15)`` or ``(B, K, 15)``,
            the steps' noise variances (:meth:`ProcessNoise.variances`) computed beforehand.
    Returns: ``(m, ...)`` outputs, or ``(B, m, ...)`` with each row's padding nodes first.
    """
    if not isinstance(node_steps, NodePlan):
        _check_nodes(node_steps, dt_s.shape[-1])
        plan = plan_nodes([node_steps], dt_s.shape[-1], device=dt_s.device)
        out = propagate_batched(x0.unsqueeze(0), P0.unsqueeze(0), acc_mps2.unsqueeze(0), gyro_rps.unsqueeze(0),
                                dt_s.unsqueeze(0), plan, noise=noise, gravity_mps2=gravity_mps2, scheme=scheme,
                                variances=None if variances is None else variances.unsqueeze(0))
        return Propagated(*(t[0] for t in out))
    plan = node_steps
    B, K = dt_s.shape
    dim = x0.shape[-1]
    means, pieces = _run_pieces(x0, acc_mps2, gyro_rps, dt_s, gravity_mps2, scheme)  # (B, K, D)
    F, G = core_jacobians_from_pieces(pieces, scheme)  # (B, K, 19, 19), (B, K, 19, 15)
    if (noise is None) == (variances is None):
        raise ValueError("propagate_batched: give the process noise or the steps' variances, one of them")
    W = (G * (_variances(noise, dt_s) if variances is None else variances).unsqueeze(-2)) @ G.transpose(-1, -2)
    # each node interval's steps, padded with identity steps (one gather of F and W together)
    steps = torch.cat((torch.stack((F, W), dim=-3).reshape(B * K, 2, CORE_DIM, CORE_DIM), _identity_step(F.dtype, F.device)))
    grouped = steps[plan.group.reshape(-1)].unflatten(0, plan.group.shape)  # (B, m, L, 2, 19, 19)
    # unbound, not indexed: the backward of one unbind stacks both gradients, where each index's
    # would fill a zero tensor of the whole gather
    Phi_core, S_core = _interval_compose(*grouped.unbind(-3))
    Phi, S = embed_core(Phi_core, dim=dim)[0], pad_core(S_core, dim=dim)  # (B, m, D, D)
    covs = _node_covariances(P0, Phi, S)
    # node means: the state after each node's step, the start for a padding node (step -1)
    node_mean = torch.cat((x0.unsqueeze(-2), means), dim=-2).gather(
        -2, (plan.node_step + 1).unsqueeze(-1).expand(*plan.node_step.shape, dim))
    return Propagated(node_mean, covs, Phi)


def _node_covariances(P0: Tensor, Phi: Tensor, S: Tensor) -> Tensor:
    """``P_j`` at the ``m`` nodes ``(..., m, D, D)`` from ``P0`` ``(..., D, D)`` and the node
    intervals' transitions and noises: node by node for ``m <= 2`` (fewer operations),
    otherwise all at once, ``P_j = Φ_{0→j} P0 Φ_{0→j}ᵀ + S_{0→j}`` with prefix compositions."""
    m = Phi.shape[-3]
    if m <= 2:
        covs, P = [], P0
        for j in range(m):
            F = Phi[..., j, :, :]
            P = F @ P @ F.transpose(-1, -2) + S[..., j, :, :]
            covs.append(P)
        return symmetrize(covs[0].unsqueeze(-3) if m == 1 else torch.stack(covs, dim=-3))
    Phi_pre, S_pre = _prefix_compose(Phi, S)
    return symmetrize(Phi_pre @ P0.unsqueeze(-3) @ Phi_pre.transpose(-1, -2) + S_pre)


def _variances(noise: ProcessNoise | Sequence[ProcessNoise], dt_s: Tensor) -> Tensor:
    """The steps' noise variances ``(B, K, 15)`` for one noise model or one per row."""
    if isinstance(noise, ProcessNoise):
        return noise.variances(dt_s)
    if all(n is noise[0] for n in noise):
        return noise[0].variances(dt_s)
    return torch.stack([n.variances(dt) for n, dt in zip(noise, dt_s.unbind(0))])


@cached_constant
def _identity_step(dtype: torch.dtype, device: torch.device) -> Tensor:
    """The padding step ``(1, 2, 19, 19)``: identity transition and zero noise."""
    eye = torch.eye(CORE_DIM, dtype=dtype, device=device)
    return torch.stack((eye, torch.zeros_like(eye))).unsqueeze(0)


def propagate_reference(
    x0: Tensor,
    P0: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    dt_s: Tensor,
    node_steps: Tensor,
    *,
    noise: ProcessNoise,
    gravity_mps2: float | Tensor,
    scheme: str = "midpoint",
) -> Propagated:
    """Reference path: the plain per-sample EKF prediction with ``jacrev`` Jacobians (states of any
    ``D = 19 + 7 N``, as :func:`propagate_batched`)."""
    K = dt_s.shape[0]
    _check_nodes(node_steps, K)
    is_node = torch.zeros(K, dtype=torch.bool)
    is_node[node_steps.cpu()] = True
    Q = noise.covariance(dt_s)
    eye = torch.eye(x0.shape[-1], dtype=x0.dtype, device=x0.device)
    x, P, Phi = x0, P0, eye
    means, covs, transitions = [], [], []
    zeros = x0.new_zeros(NOISE_DIM)
    check_scheme(scheme)

    def f(x: Tensor, eps: Tensor, acc: Tensor, gyro: Tensor, dt: Tensor) -> Tensor:
        return mechanize(x, eps, acc, gyro, dt, gravity_mps2, scheme)

    for k in range(K):
        args = (acc_mps2[k], gyro_rps[k], dt_s[k])
        F_x, F_eps = dynamics_jacobians(f, x, NOISE_DIM, *args)
        x = f(x, zeros, *args)
        P = symmetrize(F_x @ P @ F_x.T + F_eps @ Q[k] @ F_eps.T)
        Phi = F_x @ Phi
        if is_node[k]:
            means.append(x)
            covs.append(P)
            transitions.append(Phi)
            Phi = eye
    return Propagated(torch.stack(means), torch.stack(covs), torch.stack(transitions))
