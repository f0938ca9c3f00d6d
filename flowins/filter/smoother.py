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
from flowins.state import CORE_DIM, normalize_quaternions, symmetrize


class SmoothedTrack(NodeTrack):
    """The smoothed nodes, all in the final frame."""


def rts_gains(track: FilterTrack) -> Tensor:
    """One-step smoother gains ``G_j`` ``(J-1, 26, 26)``, all at once (batched solve)."""
    P = track.node_cov[:-1]
    Phi = track.transition[1:]
    cross = Phi @ P  # Φ_{j+1} P_j = (P_j Φ_{j+1}ᵀ)ᵀ
    P_pred = symmetrize(track.pred_cov[1:])
    return torch.linalg.solve(P_pred, cross).transpose(-1, -2)


#: a transition's kind (:func:`_transition_kinds`): the identity outside its leading
#: ``CORE_DIM x CORE_DIM`` block (a propagation's), rows of the identity (a pose copied or moved,
#: as a window's augmentation does), or neither
_CORE, _COPY, _DENSE = 0, 1, 2


def _transition_kinds(transition: Tensor) -> tuple[Tensor, Tensor]:
    """Each transition's kind ``(n,)`` and, for :data:`_COPY`, which entry each row copies ``(n, D)``
    (the whole of ``transition`` ``(n, D, D)`` read once, a third of it again)."""
    D = transition.shape[-1]
    eye = torch.eye(D, dtype=transition.dtype, device=transition.device)
    core = (transition[:, CORE_DIM:, :] == eye[CORE_DIM:]).flatten(1).all(1) & (
        transition[:, :CORE_DIM, CORE_DIM:] == 0).flatten(1).all(1)
    kind = torch.where(core, _CORE, _DENSE)
    rest = torch.nonzero(~core).squeeze(-1)
    if rest.numel():
        T = transition[rest]
        copy = ((T == 0) | (T == 1)).flatten(1).all(1) & (T.sum(-1) == 1).all(-1)
        kind = kind.index_copy(0, rest, torch.where(copy, _COPY, _DENSE))
    return kind, transition.argmax(-1)


def _apply(transition: Tensor, kinds: tuple[Tensor, Tensor], at: Tensor, Y: Tensor) -> Tensor:
    """``Φ_at Y`` ``(m, D, w)`` for the transitions ``transition[at]`` (``at`` ``(m,)``) of kinds
    ``kinds`` (:func:`_transition_kinds`): a core transition's leading block times ``Y``'s leading
    rows (``(CORE_DIM / D)²`` of the dense product), a copy's rows gathered, the others dense."""
    kind, row = kinds[0][at], kinds[1]
    out = Y.clone()
    for k in (_CORE, _COPY, _DENSE):
        i = torch.nonzero(kind == k).squeeze(-1)
        if not i.numel():
            continue
        t = at[i]
        if k == _CORE:
            part = torch.cat((transition[t, :CORE_DIM, :CORE_DIM] @ Y[i, :CORE_DIM], Y[i, CORE_DIM:]), 1)
        elif k == _COPY:
            part = Y[i].gather(1, row[t].unsqueeze(-1).expand(-1, -1, Y.shape[-1]))
        else:
            part = transition[t] @ Y[i]
        out.index_copy_(0, i, part)
    return out


def _to_next_key(transition: Tensor, kinds: tuple[Tensor, Tensor], cov: Tensor, distance: Tensor,
                 nodes: Tensor) -> Tensor:
    """``Φ_{j→k(j)} C_j`` ``(n, D, w)``: the columns ``C_j`` ``(n, D, w)`` of the nodes ``nodes``
    ``(n,)`` carried to their next key node ``k(j) = j + distance_j``, where ``transition[j]`` is
    ``Φ_j`` (into node ``j``) and ``kinds`` its :func:`_transition_kinds`.

    The transitions are applied one after another, ``Φ_{j→k} C = Φ_k ⋯ Φ_{j+1} C``: one batched
    application per distance from the node (:func:`_apply`), and no product of two
    transitions (which would cost ``D / w`` times as much).
    """
    out = _apply(transition, kinds, nodes + 1, cov)
    for d in range(2, int(distance.max()) + 1 if distance.numel() else 0):
        j = torch.nonzero(distance >= d).squeeze(-1)
        out.index_copy_(0, j, _apply(transition, kinds, nodes[j] + d, out[j]))
    return out


def _solve_by_key(LU: Tensor, pivots: Tensor, rhs: Tensor, key: Tensor) -> Tensor:
    """``(P⁻_k)⁻¹ B_j`` ``(n, D, w)`` for nodes ``j`` whose next key is ``key[j]`` ``(n,)`` (sorted,
    an index into the LU factors ``(k, D, D)``, ``pivots`` ``(k, D)``), ``B`` ``(n, D, w)``.

    The nodes of one key are solved as one system, their columns side by side (padded with
    zeros to the most nodes a key has), so that no node gathers a copy of its key's factors."""
    n, D, w = rhs.shape
    count = torch.bincount(key, minlength=LU.shape[0])
    position = torch.arange(n, device=key.device) - (count.cumsum(0) - count)[key]  # each node's place in its key's
    width = int(count.max())
    side = rhs.new_zeros(LU.shape[0], width, D, w)
    side[key, position] = rhs
    solved = torch.linalg.lu_solve(LU, pivots, side.transpose(1, 2).reshape(LU.shape[0], D, width * w))
    return solved.view(LU.shape[0], D, width, w)[key, :, position]


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

    keys: list[int]  # (K,) the key nodes
    key_pred_cov: list[Tensor]  # (K) their predicted covariances (D, D)
    slot: Tensor  # (J-1,) each node's next key (an index into keys)
    blocks: list[tuple[int, int]]
    gains: list[Tensor]  # per block: 𝒢_j[:c] (nodes, c, D)
    key_gains: list[Tensor]  # (K-1) the key nodes' whole gains (D, D)


def _prepare(track: FilterTrack, c: int) -> _Prepared:
    """The gains of every node of ``track`` (``J > 1`` nodes) to its next key node."""
    J, D = track.node_mean.shape[-2:]
    node_cov = track.node_cov
    keys = torch.nonzero(track.key_nodes()).squeeze(-1)
    slot = torch.searchsorted(keys, torch.arange(J - 1, device=keys.device), right=True)  # each node's next key
    distance = keys[slot] - torch.arange(J - 1, device=keys.device)
    # the keys' predicted covariances: the updated nodes', and the last node's filtered one
    # where no update acted there (views: no (K, D, D) tensor is formed)
    key_pred_cov = list(track.updated_pred_cov.unbind(0)) + ([] if bool(track.updated[-1]) else [node_cov[-1]])
    # the nodes in blocks of whole runs (each ends at a key node), so that the (nodes, D, ·)
    # tensors below stay small; a block [a, b) needs the keys (a, b] (its nodes' next keys,
    # and its own keys' next ones), which no other block needs: each is factorised there
    blocks = _node_blocks(keys, J, D)
    bounds = torch.tensor(blocks, device=keys.device).T.contiguous()  # (2, blocks): a, b
    first_slot, last_slot = slot[bounds[0]].tolist(), slot[bounds[1] - 1].tolist()
    inner_from, inner_to = torch.searchsorted(keys, bounds).tolist()  # the keys in [a, b)
    t_keys = track.t_s[keys.to(track.t_s.device)]
    # 𝒢_jᵀ[:, :c] = (P⁻_k)⁻¹ Φ_{j→k} P_j[:, :c] for every node; the key nodes' whole gains
    gains, key_gains = [], []
    for (a, b), s0, s1, k0, k1 in zip(blocks, first_slot, last_slot, inner_from, inner_to):
        nodes = slice(a, b)
        LU, pivots = _factor_predicted(symmetrize(torch.stack(key_pred_cov[s0 : s1 + 1])), t_keys[s0 : s1 + 1])
        transition = track.transition[a : b + 1]
        kinds = _transition_kinds(transition)
        local = torch.arange(b - a, device=keys.device)
        moved = _to_next_key(transition, kinds, node_cov[nodes, :, :c], distance[nodes], local)
        gains.append(_solve_by_key(LU, pivots, moved, slot[nodes] - s0).transpose(-1, -2))
        if k1 == k0:
            continue
        inner = keys[k0:k1]  # their next keys are k0 + 1 .. k1 (s1 = k1; s0 = k0 + 1 unless a is no key)
        if c == D:
            key_gains.append(gains[-1][inner - a])
        else:
            moved = _to_next_key(transition, kinds, node_cov[inner], distance[inner], inner - a)
            own = slice(k0 + 1 - s0, k1 + 1 - s0)
            key_gains.append(torch.linalg.lu_solve(LU[own], pivots[own], moved).transpose(-1, -2))
    return _Prepared(keys.tolist(), key_pred_cov, slot, blocks, gains,
                     [g for block in key_gains for g in block.unbind(0)])


#: the most bytes of one (tracks, keys, D, D) tensor the batched backward pass forms at a time
#: on a CPU; on a GPU a sixteenth of its memory (the pass holds about three such tensors, and
#: there each step of the recursion waits on kernel launches, so fewer, wider groups pay)
_BACKWARD_BYTES = 256 << 20


def _backward_bytes(device: torch.device) -> int:
    if device.type == "cuda":
        return torch.cuda.get_device_properties(device).total_memory // 16
    return _BACKWARD_BYTES


def _backward(tracks: Sequence[FilterTrack], prepared: Sequence[_Prepared]) -> list[tuple[Tensor, list[Tensor]]]:
    """The residuals ``r_k = mˢ_k - m⁻_k`` ``(K, D)`` and ``R_k = Pˢ_k - P⁻_k`` (``K`` tensors
    ``(D, D)``) at every key node of each track, by the backward recursion over the key nodes.
    The tracks go together, their keys aligned at their last one (a track with fewer keys is
    padded in front with zeros, which stay zero), in groups of about :func:`_backward_bytes`."""
    out: list[tuple[Tensor, list[Tensor]]] = []
    if not tracks:
        return out
    D = tracks[0].node_mean.shape[-1]
    budget = _backward_bytes(tracks[0].node_mean.device)
    group: list[int] = []
    longest = 0  # the most keys of a track in the group
    for i in range(len(tracks)):
        keys = len(prepared[i].keys)
        if group and (len(group) + 1) * max(longest, keys) * D * D * 8 > budget:
            out += _backward_group([tracks[j] for j in group], [prepared[j] for j in group])
            group, longest = [], 0
        group.append(i)
        longest = max(longest, keys)
    if group:
        out += _backward_group([tracks[j] for j in group], [prepared[j] for j in group])
    return out


def _rows(parts: list[Tensor]) -> Tensor:
    """``parts`` stacked (one part: a view, no copy)."""
    return parts[0].unsqueeze(0) if len(parts) == 1 else torch.stack(parts)


def _backward_group(tracks: Sequence[FilterTrack], prepared: Sequence[_Prepared]) -> list[tuple[Tensor, list[Tensor]]]:
    counts = [len(p.keys) for p in prepared]
    K = max(counts)
    zero = tracks[0].node_cov.new_zeros(tracks[0].node_cov.shape[-2:])

    def aligned(parts: list[Tensor], length: int) -> Tensor:  # (R, length, ...), each part right-aligned
        if len(parts) == 1 and parts[0].shape[0] == length:
            return parts[0].unsqueeze(0)  # one track: no copy
        return torch.stack([part if part.shape[0] == length else
                            torch.cat((part.new_zeros(length - part.shape[0], *part.shape[1:]), part)) for part in parts])

    def key_step(i: int) -> tuple[Tensor, Tensor]:
        """What the aligned key ``i`` of each track changed, ``P_k - P⁻_k``, and its gain (zeros
        for a track's padding); key by key, each ``(R, D, D)``, so that no ``(R, K, D, D)``
        tensor is gathered."""
        jumps, gains = [], []
        for t, p, n in zip(tracks, prepared, counts):
            k = i - (K - n)
            jumps.append(t.node_cov[p.keys[k]] - p.key_pred_cov[k] if k >= 0 else zero)
            gains.append(p.key_gains[k] if 0 <= k < n - 1 else zero)
        return _rows(jumps), _rows(gains)

    # r_k = (m_k - m⁻_k) + G_k r_next, R_k = (P_k - P⁻_k) + G_k R_next G_kᵀ
    jump_mean = aligned([t.node_mean[p.keys] - t.pred_mean[p.keys] for t, p in zip(tracks, prepared)], K)
    residual_mean: list[Tensor] = [jump_mean[:, -1]]
    residual_cov: list[Tensor] = [key_step(K - 1)[0]]
    for i in range(K - 2, -1, -1):
        jump_cov, G = key_step(i)
        residual_mean.append(jump_mean[:, i] + (G @ residual_mean[-1].unsqueeze(-1)).squeeze(-1))
        residual_cov.append(jump_cov + G @ residual_cov[-1] @ G.transpose(-1, -2))
    r_m = torch.stack(residual_mean[::-1], 1)
    residual_cov.reverse()
    return [(r_m[i, K - n:], [R[i] for R in residual_cov[K - n:]]) for i, n in enumerate(counts)]


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
        slot = p.slot.tolist()
        for (a, b), G in zip(p.blocks, p.gains):
            nodes = slice(a, b)
            means.append(node_mean[nodes, :c] + (G @ r_m[p.slot[nodes]].unsqueeze(-1)).squeeze(-1))
            covs.append(node_cov[nodes, :c, :c] + G @ torch.stack([r_P[k] for k in slot[a:b]]) @ G.transpose(-1, -2))
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
