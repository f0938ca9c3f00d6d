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
from typing import NamedTuple

import torch
from torch import Tensor

from flowins.filter.ekf import dynamics_jacobians
from flowins.geometry import quaternion as quat
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
from flowins.state import NOISE_DIM, STATE_DIM, State, join, split, symmetrize


class Propagated(NamedTuple):
    mean: Tensor  # (m, 26) state at each node
    cov: Tensor  # (m, 26, 26)
    transition: Tensor  # (m, 26, 26) Φ_j from the previous node (or the start) to node j


def _run_pieces(
    x0: Tensor, acc_mps2: Tensor, gyro_rps: Tensor, dt_s: Tensor, gravity_mps2: float | Tensor, scheme: str
) -> tuple[Tensor, StepPieces]:
    """Noise-free states after each of ``K`` steps ``(K, 26)`` and the steps' :class:`StepPieces`.

    With the noise at zero the biases and scale are constant over the run, so
    ``q_k = q_0 ⊙ 𝒬_1 ⊙ ... ⊙ 𝒬_k`` is a prefix product and ``v``, ``p`` are
    cumulative sums; the pieces (rotation increments, ``C(q_rot)``) are the ones the
    closed-form Jacobians reuse.
    """
    s = split(x0)
    dt = dt_s.unsqueeze(-1)
    theta = (gyro_rps - s.b_w) * dt
    E, E_rot = rotation_increments(theta, scheme)
    q = quat.multiply(s.q, quat.cumulative_product(E))
    q_before = torch.cat((s.q.unsqueeze(0), q[:-1]), dim=0)
    q_rot = q if scheme == "paper" else quat.multiply(q_before, E_rot)
    C = quat.to_matrix(q_rot)
    acc_unbiased = acc_mps2 - s.b_a
    a = s.T_a * acc_unbiased
    acc_world = (C @ a.unsqueeze(-1)).squeeze(-1) - gravity_vector(gravity_mps2, like=x0)
    v = s.v + torch.cumsum(acc_world * dt, dim=0)
    v_before = torch.cat((s.v.unsqueeze(0), v[:-1]), dim=0)
    v_step = v_before if scheme == "paper" else 0.5 * (v_before + v)
    p = s.p + torch.cumsum(v_step * dt, dim=0)
    K = dt_s.shape[0]
    means = join(
        State(
            p=p,
            v=v,
            q=q,
            b_a=s.b_a.expand(K, 3),
            b_w=s.b_w.expand(K, 3),
            T_a=s.T_a.expand(K, 3),
            p_prev=s.p_prev.expand(K, 3),
            q_prev=s.q_prev.expand(K, 4),
        )
    )
    pieces = StepPieces(q_before, theta, E, E_rot, q_rot, C, acc_unbiased, a, s.T_a.expand(K, 3), dt)
    return means, pieces


def propagate_mean(
    x0: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    dt_s: Tensor,
    gravity_mps2: float | Tensor,
    scheme: str = "midpoint",
) -> Tensor:
    """States after each of ``K`` steps ``(K, 26)`` from ``x0`` ``(26,)``, noise-free.

    Equal to ``K`` sequential :func:`mechanize` calls, computed with a log-depth
    quaternion scan and cumulative sums.
    """
    return _run_pieces(x0, acc_mps2, gyro_rps, dt_s, gravity_mps2, scheme)[0]


def _compose(later: tuple[Tensor, Tensor], earlier: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    """Step ``earlier`` then step ``later``: ``(F₂F₁, F₂ S₁ F₂ᵀ + S₂)``."""
    (F2, S2), (F1, S1) = later, earlier
    return F2 @ F1, F2 @ S1 @ F2.transpose(-1, -2) + S2


def _compose_pairs(F: Tensor, S: Tensor) -> tuple[Tensor, Tensor]:
    """Reduce ``(n, L, D, D)`` step transitions/noises to ``(n, D, D)`` by pairwise composition.

    A level of odd length sets its last (latest) element aside instead of padding
    the whole level; the set-aside elements are applied after the tree, latest last.
    """
    aside = []
    while F.shape[1] > 1:
        if F.shape[1] % 2:
            aside.append((F[:, -1], S[:, -1]))
            F, S = F[:, :-1], S[:, :-1]
        F, S = _compose((F[:, 1::2], S[:, 1::2]), (F[:, 0::2], S[:, 0::2]))
    out = (F[:, 0], S[:, 0])
    for later in reversed(aside):  # set aside at a deeper level = earlier in time
        out = _compose(later, out)
    return out


def _prefix_compose(F: Tensor, S: Tensor) -> tuple[Tensor, Tensor]:
    """Inclusive prefix compositions of ``m`` steps ``(m, D, D)`` (a log-depth scan):
    entry ``j`` maps the start to after step ``j``."""
    shift = 1
    m = F.shape[0]
    while shift < m:
        F_new, S_new = _compose((F[shift:], S[shift:]), (F[:-shift], S[:-shift]))
        F, S = torch.cat((F[:shift], F_new), dim=0), torch.cat((S[:shift], S_new), dim=0)
        shift *= 2
    return F, S


def _group_steps(F: Tensor, W: Tensor, node_steps: list[int]) -> tuple[Tensor, Tensor]:
    """The steps' transitions and noises ``(K, D, D)`` grouped into node intervals ``(m, L, D, D)``.

    Equal intervals are a free view; otherwise short intervals are padded with
    identity transitions and zero noise (one gather of each, its index built from the
    node steps as Python integers: fewer small tensor operations).
    """
    K = F.shape[0]
    m = len(node_steps)
    starts = [0] + [step + 1 for step in node_steps[:-1]]
    lengths = [step - start + 1 for step, start in zip(node_steps, starts)]
    if K % m == 0 and all(length == K // m for length in lengths):
        return F.reshape(m, K // m, *F.shape[1:]), W.reshape(m, K // m, *W.shape[1:])
    L = max(lengths)
    index = torch.tensor([[start + o if o < length else K for o in range(L)] for start, length in zip(starts, lengths)],
                         device=F.device)
    eye = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device).unsqueeze(0)
    return torch.cat((F, eye))[index], torch.cat((W, torch.zeros_like(eye)))[index]


def _check_nodes(node_steps: Tensor, num_steps: int) -> list[int]:
    """The node steps as Python integers, checked: strictly increasing, ending with the last step."""
    steps = node_steps.tolist()
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
    node_steps: Tensor,
    *,
    noise: ProcessNoise,
    gravity_mps2: float | Tensor,
    scheme: str = "midpoint",
) -> Propagated:
    """Fast path: propagate ``(x0, P0)`` over ``K`` steps, reporting at ``node_steps``.

    Args:
        x0 ``(26,)``, P0 ``(26, 26)``; acc/gyro ``(K, 3)``, dt ``(K,)``.
        node_steps: increasing step indices ``(m,)`` after which a node is reported;
            the last must be ``K - 1``.
    """
    K = dt_s.shape[0]
    steps = _check_nodes(node_steps, K)
    means, pieces = _run_pieces(x0, acc_mps2, gyro_rps, dt_s, gravity_mps2, scheme)
    F, G = core_jacobians_from_pieces(pieces, scheme)  # (K, 19, 19), (K, 19, 15)
    W = (G * noise.variances(dt_s).unsqueeze(-2)) @ G.transpose(-1, -2)
    Phi_core, S_core = _compose_pairs(*_group_steps(F, W, steps))  # over (m, L, 19, 19)
    Phi, S = embed_core(Phi_core)[0], pad_core(S_core)
    # covariance at every node at once: P_j = Φ_{0→j} P0 Φ_{0→j}ᵀ + S_{0→j}
    Phi_pre, S_pre = _prefix_compose(Phi, S)
    covs = symmetrize(Phi_pre @ P0 @ Phi_pre.transpose(-1, -2) + S_pre)
    return Propagated(means[node_steps], covs, Phi)


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
    """Reference path: the plain per-sample EKF prediction with ``jacrev`` Jacobians."""
    K = dt_s.shape[0]
    _check_nodes(node_steps, K)
    is_node = torch.zeros(K, dtype=torch.bool)
    is_node[node_steps.cpu()] = True
    Q = noise.covariance(dt_s)
    eye = torch.eye(STATE_DIM, dtype=x0.dtype, device=x0.device)
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
