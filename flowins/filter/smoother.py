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

from collections.abc import Sequence
from typing import NamedTuple

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


#: the most bytes of one (nodes, D, D) tensor the smoother's batched steps form at a time on a
#: CPU: well below glibc's largest threshold for mapping an allocation on its own (32 MiB), so
#: that each block's tensors reuse the heap's pages instead of mapping fresh ones, which the
#: kernel must zero at their first touch (``benchmarks/bench_walk_tracks.py --stages`` times the
#: smoother); on a GPU (no such cost, and each block is kernel launches) :data:`_CUDA_BLOCK_BYTES`
_BLOCK_BYTES = 8 << 20
_CUDA_BLOCK_BYTES = 32 << 20


def _node_blocks(keys: Tensor, J: int, D: int) -> list[tuple[int, int]]:
    """The nodes ``0 .. J-2`` as ranges ``[a, b)`` with ``b`` a key node (whole runs: the nodes
    whose next key is ``b`` or before, so each node's transition to its next key stays inside
    its block), each of about :data:`_BLOCK_BYTES` (:data:`_CUDA_BLOCK_BYTES` for keys on a GPU)
    of ``D x D`` float64 matrices (a single longer run is one block)."""
    per_block = max(1, (_CUDA_BLOCK_BYTES if keys.is_cuda else _BLOCK_BYTES) // (8 * D * D))
    blocks, a = [], 0
    for end in keys.tolist():  # the last key is J-1
        if end - a >= per_block or end == J - 1:
            if end > a:
                blocks.append((a, end))
            a = end
    return blocks


class _Prepared(NamedTuple):
    """One track's gains and key nodes, ready for the backward pass over its keys."""

    keys: Tensor  # (K,) the key nodes
    key_pred_cov: Tensor  # (K, D, D) their predicted covariances
    slot: Tensor  # (J-1,) each node's next key (an index into keys)
    blocks: list[tuple[int, int]]
    gains: list[Tensor]  # per block: 𝒢_j[:c] (nodes, c, D)
    key_gains: Tensor  # (K-1, D, D) the key nodes' whole gains


def _prepare(track: FilterTrack, c: int) -> _Prepared:
    """The gains of every node of ``track`` (``J > 1`` nodes) to its next key node."""
    J, D = track.node_mean.shape[-2:]
    node_cov = track.node_cov
    keys = torch.nonzero(track.key_nodes()).squeeze(-1)
    slot = torch.searchsorted(keys, torch.arange(J - 1, device=keys.device), right=True)  # each node's next key
    key_pred_cov = track.key_pred_cov()
    LU, pivots = _factor_predicted(symmetrize(key_pred_cov), track.t_s[keys.to(track.t_s.device)])
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
    return _Prepared(keys, key_pred_cov, slot, blocks, gains, torch.cat(key_gains))


#: the most bytes of one (tracks, keys, D, D) tensor the batched backward pass forms at a time
#: on a CPU; on a GPU a sixteenth of its memory (the pass holds about three such tensors, and
#: there each step of the recursion waits on kernel launches, so fewer, wider groups pay)
_BACKWARD_BYTES = 256 << 20


def _backward_bytes(device: torch.device) -> int:
    if device.type == "cuda":
        return torch.cuda.get_device_properties(device).total_memory // 16
    return _BACKWARD_BYTES


def _backward(tracks: Sequence[FilterTrack], prepared: Sequence[_Prepared]) -> list[tuple[Tensor, Tensor]]:
    """The residuals ``r_k = mˢ_k - m⁻_k`` ``(K, D)``, ``R_k = Pˢ_k - P⁻_k`` ``(K, D, D)`` at every
    key node of each track, by the backward recursion over the key nodes. The tracks go
    together, their keys aligned at their last one (a track with fewer keys is padded in
    front with zeros, which stay zero), in groups of about :func:`_backward_bytes`."""
    out: list[tuple[Tensor, Tensor]] = []
    if not tracks:
        return out
    D = tracks[0].node_mean.shape[-1]
    budget = _backward_bytes(tracks[0].node_mean.device)
    group: list[int] = []
    longest = 0  # the most keys of a track in the group
    for i in range(len(tracks)):
        keys = prepared[i].keys.shape[0]
        if group and (len(group) + 1) * max(longest, keys) * D * D * 8 > budget:
            out += _backward_group([tracks[j] for j in group], [prepared[j] for j in group])
            group, longest = [], 0
        group.append(i)
        longest = max(longest, keys)
    if group:
        out += _backward_group([tracks[j] for j in group], [prepared[j] for j in group])
    return out


def _backward_group(tracks: Sequence[FilterTrack], prepared: Sequence[_Prepared]) -> list[tuple[Tensor, Tensor]]:
    counts = [p.keys.shape[0] for p in prepared]
    K = max(counts)

    def aligned(parts: list[Tensor], length: int) -> Tensor:  # (R, length, ...), each part right-aligned
        if len(parts) == 1 and parts[0].shape[0] == length:
            return parts[0].unsqueeze(0)  # one track: no copy
        return torch.stack([part if part.shape[0] == length else
                            torch.cat((part.new_zeros(length - part.shape[0], *part.shape[1:]), part)) for part in parts])

    # what each key's update changed, m_k - m⁻_k and P_k - P⁻_k: the residuals follow
    # r_k = (m_k - m⁻_k) + G_k r_next, R_k = (P_k - P⁻_k) + G_k R_next G_kᵀ
    jump_mean = aligned([t.node_mean[p.keys] - t.pred_mean[p.keys] for t, p in zip(tracks, prepared)], K)
    # the keys' covariances gathered, then the prediction taken off in place: one (keys, D, D) tensor, not two
    jump_cov = aligned([t.node_cov[p.keys].sub_(p.key_pred_cov) for t, p in zip(tracks, prepared)], K)
    gains = aligned([p.key_gains for p in prepared], K - 1)  # key k's gain at k (the last key has none)
    residual_mean: list[Tensor] = [jump_mean[:, -1]]
    residual_cov: list[Tensor] = [jump_cov[:, -1]]
    for i in range(K - 2, -1, -1):
        G = gains[:, i]
        residual_mean.append(jump_mean[:, i] + (G @ residual_mean[-1].unsqueeze(-1)).squeeze(-1))
        residual_cov.append(jump_cov[:, i] + G @ residual_cov[-1] @ G.transpose(-1, -2))
    r_m = torch.stack(residual_mean[::-1], 1)
    r_P = torch.stack(residual_cov[::-1], 1)
    return [(r_m[i, K - n:], r_P[i, K - n:]) for i, n in enumerate(counts)]


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
    return rts_smooth_batch([track], normalize=normalize, marginal=marginal)[0]


def rts_smooth_batch(tracks: Sequence[FilterTrack], *, normalize: bool = True,
                     marginal: int | None = None) -> list[SmoothedTrack]:
    """:func:`rts_smooth` of each of ``tracks`` (of one state size), their backward recursions
    over the key nodes run together: one batched step per key of the longest track instead of
    one per key of every track (what a GPU waits on: each step is a few small kernels)."""
    sizes = {t.node_mean.shape[-1] for t in tracks}
    if len(sizes) > 1:
        raise ValueError(f"rts_smooth_batch: the tracks' states differ in size ({sorted(sizes)}); smooth them apart")
    out: list[SmoothedTrack | None] = [None] * len(tracks)
    long = [i for i, t in enumerate(tracks) if t.node_mean.shape[-2] > 1]
    D = sizes.pop() if sizes else 0
    c = D if marginal is None else marginal
    changes = [marginal_frame_changes(t.frame_changes, c, D, where=f"rts_smooth(marginal={marginal})") for t in tracks]
    for i, t in enumerate(tracks):
        if i not in long:
            out[i] = SmoothedTrack(t.t_s, t.node_mean[:, :c].clone(), t.node_cov[:, :c, :c].clone())
    prepared = [_prepare(tracks[i], c) for i in long]
    residuals = _backward([tracks[i] for i in long], prepared)
    for i, p, (r_m, r_P) in zip(long, prepared, residuals):
        track = tracks[i]
        node_mean, node_cov = track.node_mean, track.node_cov
        # every node j < J-1 from its next key's residuals, batched by block
        means, covs = [], []
        for (a, b), G in zip(p.blocks, p.gains):
            nodes = slice(a, b)
            means.append(node_mean[nodes, :c] + (G @ r_m[p.slot[nodes]].unsqueeze(-1)).squeeze(-1))
            covs.append(node_cov[nodes, :c, :c] + G @ r_P[p.slot[nodes]] @ G.transpose(-1, -2))
        mean = torch.cat((*means, node_mean[-1:, :c]))
        cov = torch.cat((*covs, node_cov[-1:, :c, :c]))
        mean, cov = to_final_frame(mean, cov, changes[i])
        if normalize:
            mean = normalize_quaternions(mean)
        out[i] = SmoothedTrack(track.t_s, mean, symmetrize(cov))
    return out


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
