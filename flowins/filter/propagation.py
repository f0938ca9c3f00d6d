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

from typing import NamedTuple

import torch
from torch import Tensor

from flowins.filter.ekf import dynamics_jacobians
from flowins.geometry import quaternion as quat
from flowins.ins.jacobians import mechanization_jacobians
from flowins.ins.mechanization import ProcessNoise, check_scheme, gravity_vector, mechanize
from flowins.state import NOISE_DIM, STATE_DIM, State, join, split, symmetrize


class Propagated(NamedTuple):
    mean: Tensor  # (m, 26) state at each node
    cov: Tensor  # (m, 26, 26)
    transition: Tensor  # (m, 26, 26) Φ_j from the previous node (or the start) to node j


def propagate_mean(
    x0: Tensor,
    acc_mps2: Tensor,
    gyro_rps: Tensor,
    dt_s: Tensor,
    gravity_mps2: float | Tensor,
    scheme: str = "midpoint",
) -> Tensor:
    """States after each of ``K`` steps ``(K, 26)`` from ``x0`` ``(26,)``, noise-free.

    Equal to ``K`` sequential :func:`mechanize` calls: with the noise at zero the
    biases and scale are constant over the run, so ``q_k = q_0 ⊙ 𝒬_1 ⊙ ... ⊙ 𝒬_k``
    is a prefix product and ``v``, ``p`` are cumulative sums.
    """
    s = split(x0)
    dt = dt_s.unsqueeze(-1)
    check_scheme(scheme)
    theta = (gyro_rps - s.b_w) * dt
    q = quat.multiply(s.q, quat.cumulative_product(quat.from_rotation_vector(theta)))
    if scheme == "paper":
        q_rot = q
    else:
        q_before = torch.cat((s.q.unsqueeze(0), q[:-1]), dim=0)
        q_rot = quat.multiply(q_before, quat.from_rotation_vector(0.5 * theta))
    acc_world = quat.rotate(q_rot, s.T_a * (acc_mps2 - s.b_a)) - gravity_vector(gravity_mps2, like=x0)
    v = s.v + torch.cumsum(acc_world * dt, dim=0)
    v_before = torch.cat((s.v.unsqueeze(0), v[:-1]), dim=0)
    v_step = v_before if scheme == "paper" else 0.5 * (v_before + v)
    p = s.p + torch.cumsum(v_step * dt, dim=0)
    K = dt_s.shape[0]
    return join(
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


def _compose_pairs(F: Tensor, S: Tensor) -> tuple[Tensor, Tensor]:
    """Reduce ``(n, L, D, D)`` step transitions/noises to ``(n, D, D)`` by pairwise composition."""
    while F.shape[1] > 1:
        if F.shape[1] % 2:
            eye = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device).expand(F.shape[0], 1, *F.shape[-2:])
            F = torch.cat((F, eye), dim=1)
            S = torch.cat((S, torch.zeros_like(S[:, :1])), dim=1)
        F1, F2 = F[:, 0::2], F[:, 1::2]  # earlier, later
        S1, S2 = S[:, 0::2], S[:, 1::2]
        S = F2 @ S1 @ F2.transpose(-1, -2) + S2
        F = F2 @ F1
    return F[:, 0], S[:, 0]


def _check_nodes(node_steps: Tensor, num_steps: int) -> None:
    if node_steps.numel() == 0 or int(node_steps[-1]) != num_steps - 1:
        raise ValueError("node_steps must end with the last step index")
    if (node_steps[1:] <= node_steps[:-1]).any() or int(node_steps[0]) < 0:
        raise ValueError("node_steps must be strictly increasing step indices")


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
    _check_nodes(node_steps, K)
    means = propagate_mean(x0, acc_mps2, gyro_rps, dt_s, gravity_mps2, scheme)
    before = torch.cat((x0.unsqueeze(0), means[:-1]), dim=0)
    F, G = mechanization_jacobians(before, acc_mps2, gyro_rps, dt_s, scheme)
    W = (G * noise.variances(dt_s).unsqueeze(-2)) @ G.transpose(-1, -2)

    # group the steps into node intervals, padded with identity steps
    starts = torch.cat((node_steps.new_zeros(1), node_steps[:-1] + 1))
    lengths = node_steps - starts + 1
    L = int(lengths.max())
    offsets = torch.arange(L, device=node_steps.device)
    index = starts.unsqueeze(1) + offsets.unsqueeze(0)  # (m, L)
    valid = offsets.unsqueeze(0) < lengths.unsqueeze(1)
    index = torch.where(valid, index, torch.full_like(index, K))  # K -> padding element
    eye = torch.eye(STATE_DIM, dtype=x0.dtype, device=x0.device)
    F_pad = torch.cat((F, eye.unsqueeze(0)), dim=0)[index]
    W_pad = torch.cat((W, torch.zeros_like(eye).unsqueeze(0)), dim=0)[index]
    Phi, S = _compose_pairs(F_pad, W_pad)

    covs = []
    P = P0
    for j in range(node_steps.shape[0]):
        P = symmetrize(Phi[j] @ P @ Phi[j].T + S[j])
        covs.append(P)
    return Propagated(means[node_steps], torch.stack(covs), Phi)


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
