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

from collections.abc import Callable, Sequence
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


def _transition_kinds(transition: Tensor) -> tuple[Tensor, Tensor | None]:
    """Each transition's kind ``(n,)`` and, for :data:`_COPY`, which entry each row copies ``(n, D)``
    (the whole of ``transition`` ``(n, D, D)`` read once, a third of it again). Below
    ``D = 2 CORE_DIM`` (the paper's 26 entries) all are taken as dense, with None for the
    copies: there the core is over half of the product, and the kinds would cost more
    operations than they save."""
    D = transition.shape[-1]
    if D < 2 * CORE_DIM:
        return torch.full(transition.shape[:1], _DENSE, device=transition.device), None
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


def _apply(transition: Tensor, kinds: tuple[Tensor, Tensor | None], at: Tensor | slice, Y: Tensor) -> Tensor:
    """``Φ_at Y`` ``(m, D, w)`` for the transitions ``transition[at]`` (``at``: ``m`` indices or a
    slice) of kinds ``kinds`` (:func:`_transition_kinds`): a core transition's leading block times
    ``Y``'s leading rows (``(CORE_DIM / D)²`` of the dense product), a copy's rows gathered, the
    others dense."""
    kind, row = kinds[0][at], kinds[1]

    def applied(k: int, t: Tensor | slice, y: Tensor) -> Tensor:
        if k == _CORE:
            return torch.cat((transition[t, :CORE_DIM, :CORE_DIM] @ y[:, :CORE_DIM], y[:, CORE_DIM:]), 1)
        if k == _COPY:
            return y.gather(1, row[t].unsqueeze(-1).expand(-1, -1, y.shape[-1]))
        return transition[t] @ y

    present = [k for k, n in enumerate(torch.bincount(kind, minlength=3).tolist()) if n]
    if len(present) == 1:  # one kind: no gathers of Y
        return applied(present[0], at, Y)
    at = torch.arange(at.start, at.stop, device=Y.device) if isinstance(at, slice) else at
    out = Y.clone()
    for k in present:
        i = torch.nonzero(kind == k).squeeze(-1)
        out.index_copy_(0, i, applied(k, at[i], Y[i]))
    return out


def _to_next_key(transition: Tensor, kinds: tuple[Tensor, Tensor | None], cov: Tensor, distance: Tensor,
                 nodes: Tensor | None = None) -> Tensor:
    """``Φ_{j→k(j)} C_j`` ``(n, D, w)``: the columns ``C_j`` ``(n, D, w)`` of the nodes ``nodes``
    ``(n,)`` (None: ``0 .. n-1``) carried to their next key node ``k(j) = j + distance_j``, where
    ``transition[j]`` is ``Φ_j`` (into node ``j``) and ``kinds`` its :func:`_transition_kinds`.

    The transitions are applied one after another, ``Φ_{j→k} C = Φ_k ⋯ Φ_{j+1} C``: one batched
    application per distance from the node (:func:`_apply`), and no product of two
    transitions (which would cost ``D / w`` times as much). That is ``Σ_j distance_j``
    applications: where the keys lie far apart (a run without updates: every node's distance to
    the one key at its end) it grows with the square of the nodes, and the nodes' whole
    transitions to their key are formed instead, each from its successor's
    (:func:`_to_key_products`), one product per node.
    """
    n, D, w = cov.shape
    if nodes is None and n and float(distance.sum()) * w > _PRODUCTS_ABOVE * n * (D + w):
        return _to_key_products(transition, distance) @ cov
    out = _apply(transition, kinds, slice(1, cov.shape[0] + 1) if nodes is None else nodes + 1, cov)
    for d in range(2, int(distance.max()) + 1 if distance.numel() else 0):
        j = torch.nonzero(distance >= d).squeeze(-1)
        out.index_copy_(0, j, _apply(transition, kinds, (j if nodes is None else nodes[j]) + d, out[j]))
    return out


#: :func:`_to_next_key` forms the transitions' products where the applications would cost more
#: than this times as much (``benchmarks/bench_smoother_gaps.py`` sets it to inf for the reference)
_PRODUCTS_ABOVE = 1.0


def _to_key_products(transition: Tensor, distance: Tensor) -> Tensor:
    """``Φ_{j→k(j)}`` ``(n, D, D)`` for the nodes ``j = 0 .. n-1`` at ``distance`` ``(n,)`` from their
    next key, ``transition[j]`` being ``Φ_j``: ``Φ_{j+1}`` at distance 1, and
    ``Φ_{j→k} = Φ_{j+1→k} Φ_{j+1}`` further, the nodes of one distance in one batched product
    after those one closer (node ``j + 1`` is one closer than ``j`` to the same key)."""
    n = distance.shape[0]
    out = transition[1 : n + 1].clone()
    order = torch.argsort(distance, stable=True)
    counts = torch.bincount(distance, minlength=2).tolist()
    groups = order.split(counts)
    for j in groups[2:]:
        out[j] = out[j + 1] @ transition[j + 1]
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
    key_pred_cov: Tensor  # (U, D, D) the predicted covariances of the keys but the last where no update acted there
    slot: Tensor  # (J-1,) each node's next key (an index into keys)
    blocks: list[tuple[int, int]]
    block_keys: list[tuple[int, int]]  # per block [a, b): the first and last of its nodes' next keys (slots)
    gains: list[Tensor]  # per block: 𝒢_j[:c] (nodes, c, D)
    key_gains: list[Tensor]  # per block: its key nodes' whole gains (keys, D, D), K - 1 in all


def _prepare(track: FilterTrack, c: int) -> _Prepared:
    """The gains of every node of ``track`` (``J > 1`` nodes) to its next key node."""
    J, D = track.node_mean.shape[-2:]
    node_cov = track.node_cov
    keys = torch.nonzero(track.key_nodes()).squeeze(-1)
    slot = torch.searchsorted(keys, torch.arange(J - 1, device=keys.device), right=True)  # each node's next key
    distance = keys[slot] - torch.arange(J - 1, device=keys.device)
    # the keys' predicted covariances: the updated nodes', and the last node's filtered one
    # where no update acted there (taken block by block: no (K, D, D) tensor is formed)
    key_pred_cov = track.updated_pred_cov
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
        predicted = key_pred_cov[s0 : s1 + 1]
        if s1 >= key_pred_cov.shape[0]:
            predicted = torch.cat((predicted, node_cov[-1:]))
        LU, pivots = _factor_predicted(symmetrize(predicted), t_keys[s0 : s1 + 1])
        transition = track.transition[a : b + 1]
        kinds = _transition_kinds(transition)
        moved = _to_next_key(transition, kinds, node_cov[nodes, :, :c], distance[nodes])
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
    return _Prepared(keys.tolist(), key_pred_cov, slot, blocks, list(zip(first_slot, last_slot)), gains, key_gains)


def _rows(parts: list[Tensor]) -> Tensor:
    """``parts`` stacked (one part: a view, no copy)."""
    return parts[0].unsqueeze(0) if len(parts) == 1 else torch.stack(parts)


#: ``emit(track, block, residuals)``: a block's residuals ``(r_k, R_k)`` at its keys ``s0 .. s1``
Emit = Callable[[int, int, list[tuple[Tensor, Tensor]]], None]


#: the most bytes of the ``(tracks, keys, D, D)`` tensors of the keys' jumps and gains that the
#: backward pass gathers at once on a CPU (on a GPU a sixteenth of its memory); above it each key's
#: are taken as the recursion reaches it, a few operations per track and key instead of one
_STACKED_BYTES = 512 << 20


def _stacked_bytes(device: torch.device) -> int:
    if device.type == "cuda":
        return torch.cuda.get_device_properties(device).total_memory // 16
    return _STACKED_BYTES


def _backward(tracks: Sequence[FilterTrack], prepared: Sequence[_Prepared], emit: Emit) -> None:
    """The residuals ``r_k = mˢ_k - m⁻_k`` ``(D,)`` and ``R_k = Pˢ_k - P⁻_k`` ``(D, D)`` at the key
    nodes of each track, by the backward recursion over the key nodes, handed to ``emit`` block
    by block as soon as a block's keys are done (the residuals of the keys no block still
    needs are let go). The tracks go together, their keys aligned at their last one (a track
    with fewer keys is padded in front with zeros, which stay zero): one batched step per key
    of the longest track."""
    if not tracks:
        return
    counts = [len(p.keys) for p in prepared]
    K, R = max(counts), len(tracks)
    D = tracks[0].node_mean.shape[-1]
    zero = tracks[0].node_cov.new_zeros(D, D)
    # the keys' jumps, m_k - m⁻_k and P_k - P⁻_k, and gains G_k, aligned: (R, K, ...)
    if R * K * D * D * 8 * 2 <= _stacked_bytes(zero.device):
        def aligned(parts: list[Tensor], length: int) -> Tensor:  # each part right-aligned
            return _rows([part if part.shape[0] == length else
                          torch.cat((part.new_zeros(length - part.shape[0], *part.shape[1:]), part)) for part in parts])

        index = [torch.tensor(p.keys, device=zero.device) for p in prepared]
        jump_mean = aligned([t.node_mean[k] - t.pred_mean[k] for t, k in zip(tracks, index)], K)
        jumps = []
        for t, p, k in zip(tracks, prepared, index):
            jump = t.node_cov[k]
            jump[: p.key_pred_cov.shape[0]] -= p.key_pred_cov
            jump[p.key_pred_cov.shape[0]:] = 0.0  # the last node's, where no update acted: its filtered covariance
            jumps.append(jump)
        jump_cov = aligned(jumps, K)
        gains = aligned([torch.cat(p.key_gains) if p.key_gains else zero.new_zeros(0, D, D) for p in prepared], K - 1)

        def key_step(i: int) -> tuple[Tensor, Tensor, Tensor | None]:
            return jump_mean[:, i], jump_cov[:, i], gains[:, i] if i < K - 1 else None
    else:
        key_gains = [[g for block in p.key_gains for g in block.unbind(0)] for p in prepared]

        def key_step(i: int) -> tuple[Tensor, Tensor, Tensor | None]:
            jumps_m, jumps_P, G = [], [], []
            for t, p, n, gains in zip(tracks, prepared, counts, key_gains):
                k = i - (K - n)
                node = p.keys[k] if k >= 0 else 0
                jumps_m.append(t.node_mean[node] - t.pred_mean[node] if k >= 0 else zero[0])
                jumps_P.append(t.node_cov[node] - p.key_pred_cov[k] if 0 <= k < p.key_pred_cov.shape[0] else zero)
                G.append(gains[k] if 0 <= k < n - 1 else zero)
            return _rows(jumps_m), _rows(jumps_P), _rows(G) if i < K - 1 else None

    # where each block is handed over: at the aligned step of its first key
    hand_over: dict[int, list[tuple[int, int]]] = {}
    for t, (p, n) in enumerate(zip(prepared, counts)):
        for block, (first, _) in enumerate(p.block_keys):
            hand_over.setdefault(first + K - n, []).append((t, block))
    held: dict[int, tuple[Tensor, Tensor]] = {}  # aligned step -> (r_m, r_P) of every track
    pending = [len(p.blocks) - 1 for p in prepared]  # each track's next block to hand over (they go back in order)
    # r_k = (m_k - m⁻_k) + G_k r_next, R_k = (P_k - P⁻_k) + G_k R_next G_kᵀ
    r_m = r_P = None
    for i in range(K - 1, -1, -1):
        m, P, G = key_step(i)
        r_m, r_P = (m, P) if G is None else (m + (G @ r_m.unsqueeze(-1)).squeeze(-1), P + G @ r_P @ G.transpose(-1, -2))
        held[i] = (r_m, r_P)
        if i not in hand_over:
            continue
        for t, block in hand_over[i]:
            first, last = prepared[t].block_keys[block]
            shift = K - counts[t]
            emit(t, block, [(held[k + shift][0][t], held[k + shift][1][t]) for k in range(first, last + 1)])
            pending[t] = block - 1
        # let go of the steps above every block still to be handed over
        horizon = max((prepared[t].block_keys[b][1] + K - counts[t] for t, b in enumerate(pending) if b >= 0), default=-1)
        for step in [k for k in held if k > horizon]:
            del held[step]


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
    means: list[list[Tensor | None]] = [[None] * len(p.blocks) for p in prepared]
    covs: list[list[Tensor | None]] = [[None] * len(p.blocks) for p in prepared]

    def emit(t: int, block: int, residuals: list[tuple[Tensor, Tensor]]) -> None:
        """The nodes of ``block`` of track ``long[t]`` from their next keys' residuals."""
        p, track = prepared[t], tracks[long[t]]
        (a, b), G = p.blocks[block], p.gains[block]
        key = (p.slot[a:b] - p.block_keys[block][0]).tolist()
        r_m = torch.stack([residuals[k][0] for k in key])
        r_P = torch.stack([residuals[k][1] for k in key])
        means[t][block] = track.node_mean[a:b, :c] + (G @ r_m.unsqueeze(-1)).squeeze(-1)
        covs[t][block] = track.node_cov[a:b, :c, :c] + G @ r_P @ G.transpose(-1, -2)

    _backward([tracks[i] for i in long], prepared, emit)
    for t, i in enumerate(long):
        track = tracks[i]
        mean = torch.cat((*means[t], track.node_mean[-1:, :c]))
        cov = torch.cat((*covs[t], track.node_cov[-1:, :c, :c]))
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
