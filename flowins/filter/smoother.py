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

from flowins.filter.chain import FilterTrack, NodeTrack, to_final_frame
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


def _transitions_to_next_key(transition: Tensor, key: Tensor) -> tuple[Tensor, Tensor]:
    """For each node ``j < J-1``: ``Φ_{j→k(j)}`` ``(J-1, D, D)``, the transition from node
    ``j`` to the first key node ``k(j) > j``, and ``k(j)`` ``(J-1,)``.

    A segmented suffix product ``Φ_{k} ⋯ Φ_{j+1}`` computed as a log-depth scan:
    ``X_j = Φ_{j+1}``, extended by ``X_{j+d}`` while node ``j+d`` is not a key.
    """
    J = key.shape[0]
    X = transition[1:]  # X_j = Φ_{j+1}
    reach = torch.arange(1, J, device=key.device)  # node X_j currently reaches
    open_ = ~key[1:]  # X_j still has to be extended beyond reach_j
    shift = 1
    while bool(open_.any()):
        if shift >= J - 1:
            raise RuntimeError("smoother: a run of nodes has no key node after it")  # the last node is a key
        later = torch.cat((X[shift:], X[-1:].expand(shift, *X.shape[1:])))
        later_open = torch.cat((open_[shift:], open_.new_zeros(shift)))
        later_reach = torch.cat((reach[shift:], reach[-1:].expand(shift)))
        X = torch.where(open_[:, None, None], later @ X, X)
        reach = torch.where(open_, later_reach, reach)
        open_ = open_ & later_open
        shift *= 2
    return X, reach


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


def rts_smooth(track: FilterTrack, *, normalize: bool = True) -> SmoothedTrack:
    """Smoothed means and covariances at every node of ``track``.

    Between updates the RTS gains compose: for a run of prediction-only nodes
    ending at the next updated ("key") node ``k``,
    ``G_j G_{j+1} ⋯ G_{k-1} = P_j Φ_{j→k}ᵀ (P⁻_k)⁻¹``, so

        mˢ_j = m_j + P_j Φ_{j→k}ᵀ (P⁻_k)⁻¹ (mˢ_k - m⁻_k)
        Pˢ_j = P_j + 𝒢_j (Pˢ_k - P⁻_k) 𝒢_jᵀ

    The backward recursion therefore runs only over the key nodes; every other
    node follows in one batched step. The result is the same as the node-by-node
    recursion (:func:`rts_smooth_sequential`, tests check 1e-9).

    ``normalize`` re-normalises the quaternions of the smoothed means (the
    covariances are left as the recursion gives them).
    """
    J = track.t_s.shape[0]
    if J == 1:
        return SmoothedTrack(track.t_s, track.node_mean.clone(), track.node_cov.clone())
    key = _key_nodes(track)
    Phi_to_key, k_of = _transitions_to_next_key(track.transition, key)
    P = track.node_cov[:-1]
    keys = torch.nonzero(key).squeeze(-1)
    LU, pivots = _factor_predicted(symmetrize(track.pred_cov[keys]), track.t_s[keys.to(track.t_s.device)])
    slot = torch.searchsorted(keys, k_of)  # which key's factor each node needs
    # 𝒢_jᵀ = (P⁻_k)⁻¹ Φ_{j→k} P_j
    gains = torch.linalg.lu_solve(LU[slot], pivots[slot], Phi_to_key @ P).transpose(-1, -2)

    # backward over the key nodes only: r_k = mˢ_k - m⁻_k, R_k = Pˢ_k - P⁻_k
    mean_s = track.node_mean.clone()
    cov_s = track.node_cov.clone()
    key_list = keys.tolist()
    residual_mean: dict[int, Tensor] = {}
    residual_cov: dict[int, Tensor] = {}
    k_next = key_list[-1]
    residual_mean[k_next] = mean_s[k_next] - track.pred_mean[k_next]
    residual_cov[k_next] = cov_s[k_next] - track.pred_cov[k_next]
    node_mean, node_cov = track.node_mean, track.node_cov
    for k in reversed(key_list[:-1]):
        G = gains[k]
        m_k = node_mean[k] + G @ residual_mean[k_next]
        P_k = node_cov[k] + G @ residual_cov[k_next] @ G.T
        residual_mean[k] = m_k - track.pred_mean[k]
        residual_cov[k] = P_k - track.pred_cov[k]
        k_next = k
    # every node j < J-1 from its next key's residuals, batched
    r_m = torch.stack([residual_mean[k] for k in key_list])[slot]
    r_P = torch.stack([residual_cov[k] for k in key_list])[slot]
    mean = torch.cat((node_mean[:-1] + (gains @ r_m.unsqueeze(-1)).squeeze(-1), node_mean[-1:]))
    cov = torch.cat((P + gains @ r_P @ gains.transpose(-1, -2), node_cov[-1:]))
    mean, cov = to_final_frame(mean, cov, track.frame_changes)
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
