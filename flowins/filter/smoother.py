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

from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.filter.runner import FilterTrack, _NodeOutputs
from flowins.state import normalize_quaternions, symmetrize


@dataclass
class SmoothedTrack(_NodeOutputs):
    t_s: Tensor  # (J,) node times
    node_mean: Tensor  # (J, 26)
    node_cov: Tensor  # (J, 26, 26)


def rts_gains(track: FilterTrack) -> Tensor:
    """Smoother gains ``G_j`` ``(J-1, 26, 26)``, all at once (batched solve)."""
    P = track.node_cov[:-1]
    Phi = track.transition[1:]
    cross = Phi @ P  # Φ_{j+1} P_j = (P_j Φ_{j+1}ᵀ)ᵀ
    P_pred = symmetrize(track.pred_cov[1:])
    return torch.linalg.solve(P_pred, cross).transpose(-1, -2)


def rts_smooth(track: FilterTrack, *, normalize: bool = True) -> SmoothedTrack:
    """Smoothed means and covariances at every node of ``track``.

    ``normalize`` re-normalises the quaternions of the smoothed means (the
    covariances are left as the recursion gives them).
    """
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
    mean = torch.stack(means[::-1])
    if normalize:
        mean = normalize_quaternions(mean)
    # the recursion keeps P symmetric up to rounding; symmetrise the outputs once
    return SmoothedTrack(track.t_s, mean, symmetrize(torch.stack(covs[::-1])))
