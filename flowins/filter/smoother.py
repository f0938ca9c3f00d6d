"""Extended Rauch-Tung-Striebel smoother over the filter's node chain.

For nodes ``j = J-1, ..., 0`` with filtered ``(m_j, P_j)``, the next node's
prediction ``(m⁻_{j+1}, P⁻_{j+1})`` and the transition ``Φ_{j+1}`` between them
(product of EKF Jacobians, or ``A⋆`` for a pose forgetting):

    G_j   = P_j Φ_{j+1}ᵀ (P⁻_{j+1})⁻¹
    mˢ_j  = m_j + G_j (mˢ_{j+1} - m⁻_{j+1})
    Pˢ_j  = P_j + G_j (Pˢ_{j+1} - P⁻_{j+1}) G_jᵀ

(Särkkä 2013, Thm. 9.1 for the extended case). Updates at a node only change its
filtered Gaussian, so the recursion is exact through every update, prediction,
forgetting and augmentation step the filter recorded.
"""
from __future__ import annotations

import torch
from torch import Tensor

from flowins.filter.chain import FilterTrack, NodeTrack, marginal_frame_changes, to_final_frame
from flowins.state import normalize_quaternions, symmetrize


class SmoothedTrack(NodeTrack):
    """The smoothed nodes, all in the final frame."""


def rts_gains(track: FilterTrack) -> Tensor:
    """One-step smoother gains ``G_j`` ``(J-1, 26, 26)``, all at once (batched solve)."""
    P = track.node_cov[:-1]
    Phi = track.transition[1:]
    cross = Phi @ P  # Φ_{j+1} P_j = (P_j Φ_{j+1}ᵀ)ᵀ
    P_pred = symmetrize(track.pred_cov[1:])
    return torch.linalg.solve(P_pred, cross).transpose(-1, -2)


def _key_nodes(track: FilterTrack) -> Tensor:
    """Nodes whose filtered Gaussian differs from their prediction (an update acted), and the last."""
    changed = (track.node_mean != track.pred_mean).any(-1) | (track.node_cov != track.pred_cov).flatten(1).any(-1)
    changed[-1] = True
    return changed


def _transitions_to_next_key(transition: Tensor, next_key: Tensor) -> Tensor:
    """``Φ_{j→k(j)}`` ``(J-1, D, D)``: for each node ``j < J-1`` the transition to the first key
    node ``k(j) > j`` (``next_key`` ``(J-1,)``), the product ``Φ_k ⋯ Φ_{j+1}``.

    Built from the key nodes backwards, ``Φ_{j→k} = Φ_{j+1→k} Φ_{j+1}``: one batched product
    per distance from the key, for all runs of nodes at once (one product per node).
    """
    to_key = transition[1:].clone()  # distance 1: Φ_{j+1}
    distance = next_key - torch.arange(next_key.shape[0], device=next_key.device)
    for d in range(2, int(distance.max()) + 1 if distance.numel() else 0):
        j = torch.nonzero(distance == d).squeeze(-1)
        to_key.index_copy_(0, j, to_key[j + 1] @ transition[j + 1])
    return to_key


def _factor_predicted(cov: Tensor, t_s: Tensor) -> tuple[Tensor, Tensor]:
    """LU factors of predicted covariances ``(K, D, D)``. A covariance that is singular at
    the filter's precision (in float32 the pose copy's nugget is below the rounding of the
    position variances) is factorised with a jitter of ``ε·max(diag)``, raised by 10x until
    it factorises; one that still fails at ``1e-3·max(diag)`` raises, naming its time.

    A matrix whose pivots come out invalid (outside ``1 .. D``) is factorised again on its own:
    after a ``torch.set_num_threads`` call, the batched ``getrf`` of torch 2.13's MKL returns
    invalid pivots for some matrices of a batch of large ones (103 of 530 at 159 x 159, a
    window of 20 clones), and ``lu_solve`` would refuse them."""
    LU, pivots, info = torch.linalg.lu_factor_ex(cov)
    invalid = torch.nonzero(((pivots < 1) | (pivots > cov.shape[-1])).any(-1)).squeeze(-1)
    if invalid.numel():
        alone = zip(*(torch.linalg.lu_factor_ex(cov[i]) for i in invalid.tolist()))
        LU, pivots, info = (t.index_copy(0, invalid, torch.stack(parts)) for t, parts in zip((LU, pivots, info), alone))
    bad = torch.nonzero(info != 0).squeeze(-1)
    if bad.numel() == 0:
        return LU, pivots
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    scale = cov[bad].diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(torch.finfo(cov.dtype).tiny)[:, None, None]
    jitter = torch.finfo(cov.dtype).eps
    while jitter <= 1e-3:
        LU_b, piv_b, info_b = torch.linalg.lu_factor_ex(cov[bad] + jitter * scale * eye)
        if not bool((info_b != 0).any()):
            return LU.index_copy(0, bad, LU_b), pivots.index_copy(0, bad, piv_b)
        jitter *= 10.0
    t = float(t_s[bad[0]])
    raise ValueError(f"rts_smooth: the predicted covariance at t = {t:.3f} s is singular even with a jitter of "
                     f"1e-3 of its largest variance; run the filter in float64 (filter.dtype=float64)")


#: the most bytes of one (nodes, D, D) tensor the smoother's batched steps form at a time
_BLOCK_BYTES = 32 << 20


def _node_blocks(keys: Tensor, J: int, D: int) -> list[tuple[int, int]]:
    """The nodes ``0 .. J-2`` as ranges ``[a, b)`` with ``b`` a key node (whole runs: the nodes
    whose next key is ``b`` or before, so each node's transition to its next key stays inside
    its block), each of about :data:`_BLOCK_BYTES` of ``D x D`` float64 matrices (a single
    longer run is one block)."""
    per_block = max(1, _BLOCK_BYTES // (8 * D * D))
    blocks, a = [], 0
    for end in keys.tolist():  # the last key is J-1
        if end - a >= per_block or end == J - 1:
            if end > a:
                blocks.append((a, end))
            a = end
    return blocks


def rts_smooth(track: FilterTrack, *, normalize: bool = True, marginal: int | None = None) -> SmoothedTrack:
    """Smoothed means and covariances at every node of ``track``.

    Between updates the RTS gains compose: for a run of prediction-only nodes
    ending at the next updated ("key") node ``k``,
    ``G_j G_{j+1} ⋯ G_{k-1} = P_j Φ_{j→k}ᵀ (P⁻_k)⁻¹``, so

        mˢ_j = m_j + P_j Φ_{j→k}ᵀ (P⁻_k)⁻¹ (mˢ_k - m⁻_k)
        Pˢ_j = P_j + 𝒢_j (Pˢ_k - P⁻_k) 𝒢_jᵀ

    The backward recursion therefore runs only over the key nodes; every other
    node follows in one batched step. The result is the same as the node-by-node
    recursion (:func:`rts_smooth_sequential`, tests check 1e-9).

    ``marginal``: the smoothed Gaussians of the first ``marginal`` state entries only,
    ``(J, marginal)`` and ``(J, marginal, marginal)`` (None: the whole state). The recursion
    still carries the whole state at the key nodes, but every node's output needs only the
    rows ``𝒢_j[:marginal]`` of its gain: with a window of cloned poses (``D = 19 + 7 N``) and
    ``marginal = 26`` that is about ``26 / D`` of the work and memory there.

    ``normalize`` re-normalises the quaternions of the smoothed means (the
    covariances are left as the recursion gives them).
    """
    J, D = track.node_mean.shape[-2:]
    c = D if marginal is None else marginal
    frame_changes = marginal_frame_changes(track.frame_changes, c, D, where=f"rts_smooth(marginal={marginal})")
    node_mean, node_cov = track.node_mean, track.node_cov
    if J == 1:
        return SmoothedTrack(track.t_s, node_mean[:, :c].clone(), node_cov[:, :c, :c].clone())
    keys = torch.nonzero(_key_nodes(track)).squeeze(-1)
    slot = torch.searchsorted(keys, torch.arange(J - 1, device=keys.device), right=True)  # each node's next key
    LU, pivots = _factor_predicted(symmetrize(track.pred_cov[keys]), track.t_s[keys.to(track.t_s.device)])
    # the nodes in blocks of whole runs (each ends at a key node), so that the (nodes, D, D)
    # products below stay small
    blocks = _node_blocks(keys, J, D)
    # 𝒢_jᵀ[:, :c] = (P⁻_k)⁻¹ Φ_{j→k} P_j[:, :c] for every node; the key nodes' whole gains
    gains, key_gains = [], []
    for a, b in blocks:
        nodes = slice(a, b)
        to_key = _transitions_to_next_key(track.transition[a : b + 1], keys[slot[nodes]] - a)
        gains.append(torch.linalg.lu_solve(LU[slot[nodes]], pivots[slot[nodes]],
                                           to_key @ node_cov[nodes, :, :c]).transpose(-1, -2))
        inner = keys[(keys >= a) & (keys < b)]
        if c == D:
            key_gains.append(gains[-1][inner - a])
        else:
            key_slot = slot[inner]
            key_gains.append(torch.linalg.lu_solve(LU[key_slot], pivots[key_slot],
                                                   to_key[inner - a] @ node_cov[inner]).transpose(-1, -2))
    key_gains = torch.cat(key_gains)

    # backward over the key nodes only: r_k = mˢ_k - m⁻_k, R_k = Pˢ_k - P⁻_k
    key_list = keys.tolist()
    residual_mean: list[Tensor] = [node_mean[key_list[-1]] - track.pred_mean[key_list[-1]]]
    residual_cov: list[Tensor] = [node_cov[key_list[-1]] - track.pred_cov[key_list[-1]]]
    for i in range(len(key_list) - 2, -1, -1):
        k, G = key_list[i], key_gains[i]
        m_k = node_mean[k] + G @ residual_mean[-1]
        P_k = node_cov[k] + G @ residual_cov[-1] @ G.T
        residual_mean.append(m_k - track.pred_mean[k])
        residual_cov.append(P_k - track.pred_cov[k])
    r_m = torch.stack(residual_mean[::-1])
    r_P = torch.stack(residual_cov[::-1])
    # every node j < J-1 from its next key's residuals, batched by block
    means, covs = [], []
    for (a, b), G in zip(blocks, gains):
        nodes = slice(a, b)
        means.append(node_mean[nodes, :c] + (G @ r_m[slot[nodes]].unsqueeze(-1)).squeeze(-1))
        covs.append(node_cov[nodes, :c, :c] + G @ r_P[slot[nodes]] @ G.transpose(-1, -2))
    mean = torch.cat((*means, node_mean[-1:, :c]))
    cov = torch.cat((*covs, node_cov[-1:, :c, :c]))
    mean, cov = to_final_frame(mean, cov, frame_changes)
    if normalize:
        mean = normalize_quaternions(mean)
    return SmoothedTrack(track.t_s, mean, symmetrize(cov))


def rts_smooth_sequential(track: FilterTrack, *, normalize: bool = True) -> SmoothedTrack:
    """The plain node-by-node RTS recursion (reference for :func:`rts_smooth`)."""
    J = track.t_s.shape[0]
    means = [track.node_mean[-1]]
    covs = [track.node_cov[-1]]
    if J > 1:
        gains = rts_gains(track).unbind(0)
        node_mean, node_cov = track.node_mean.unbind(0), track.node_cov.unbind(0)
        pred_mean, pred_cov = track.pred_mean.unbind(0), track.pred_cov.unbind(0)
        m_s, P_s = means[0], covs[0]
        for j in range(J - 2, -1, -1):
            G = gains[j]
            m_s = node_mean[j] + G @ (m_s - pred_mean[j + 1])
            P_s = node_cov[j] + G @ (P_s - pred_cov[j + 1]) @ G.T
            means.append(m_s)
            covs.append(P_s)
    mean, cov = to_final_frame(torch.stack(means[::-1]), torch.stack(covs[::-1]), track.frame_changes)
    if normalize:
        mean = normalize_quaternions(mean)
    # the recursion keeps P symmetric up to rounding; symmetrise the outputs once
    return SmoothedTrack(track.t_s, mean, symmetrize(cov))
