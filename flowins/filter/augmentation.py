"""Pose forgetting and pose augmentation, as the paper writes them (Sec. "Information Fusion").

Forgetting (a linear Kalman prediction):

    A⋆ = blkdiag(I₁₉, 0₇),   Q⋆ = blkdiag(0₁₉, σ²_{p,0} I₃, σ²_{q,0} I₄)

Augmentation (a linear Kalman update "measuring" ``H⋆ x = 0``, i.e. ``p_prev = p``
and ``q_prev = q``, with a small nugget noise):

    H⋆ = [[I₃, 0, 0, …, -I₃, 0], [0, 0, I₄, …, 0, -I₄]]   (7 x 26)

The forgetting step sets the mean of the old pose to zero and gives it the
variances ``σ²_{p,0}``, ``σ²_{q,0}``; the augmentation then pulls it onto the current
pose. With finite ``σ`` this shrinks the current pose towards the origin by a
relative ``P_pp / σ²_{p,0}`` per frame; :func:`copy_pose` is the exact
``σ → ∞`` limit, where the old pose becomes the current one plus the nugget noise.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.constants import cached_constant
from flowins.filter.chain import BatchChain, ChainBuilder
from flowins.filter.ekf import ekf_update, linear_predict
from flowins.state import CORE_DIM, STATE, STATE_DIM, normalize_quaternions, symmetrize


def forgetting_matrices(
    sigma_p0: float | Tensor, sigma_q0: float | Tensor, *, dtype: torch.dtype, device=None
) -> tuple[Tensor, Tensor]:
    """``(A⋆, Q⋆)``, each ``(26, 26)``."""
    A = torch.zeros(STATE_DIM, STATE_DIM, dtype=dtype, device=device)
    A[:CORE_DIM, :CORE_DIM] = torch.eye(CORE_DIM, dtype=dtype, device=device)
    sp = torch.as_tensor(sigma_p0, dtype=dtype, device=device)
    sq = torch.as_tensor(sigma_q0, dtype=dtype, device=device)
    diag = torch.cat(
        (
            torch.zeros(CORE_DIM, dtype=dtype, device=device),
            (sp * sp).expand(3),
            (sq * sq).expand(4),
        )
    )
    return A, torch.diag(diag)


def augmentation_matrix(*, dtype: torch.dtype, device=None) -> Tensor:
    """``H⋆`` ``(7, 26)``."""
    H = torch.zeros(7, STATE_DIM, dtype=dtype, device=device)
    eye3 = torch.eye(3, dtype=dtype, device=device)
    eye4 = torch.eye(4, dtype=dtype, device=device)
    H[0:3, STATE.p] = eye3
    H[0:3, STATE.p_prev] = -eye3
    H[3:7, STATE.q] = eye4
    H[3:7, STATE.q_prev] = -eye4
    return H


def augment_pose(mean: Tensor, cov: Tensor, *, nugget_var: float | Tensor) -> tuple[Tensor, Tensor]:
    """The pose augmentation step: linear update with ``H⋆``, ``z = 0``, ``R = nugget I₇``.

    Not gated; quaternions are re-normalised afterwards like after every update.
    """
    H = augmentation_matrix(dtype=mean.dtype, device=mean.device)
    innovation = -(H @ mean.unsqueeze(-1)).squeeze(-1)
    R = torch.as_tensor(nugget_var, dtype=mean.dtype, device=mean.device) * torch.eye(
        7, dtype=mean.dtype, device=mean.device
    )
    batch = mean.shape[:-1]
    result = ekf_update(
        mean,
        cov,
        innovation=innovation.reshape(*batch, 1, 7),
        H=H.expand(*batch, 1, 7, STATE_DIM),
        noise_cov=R.expand(*batch, 1, 7, 7),
        normalize=normalize_quaternions,
    )
    return result.mean, result.cov


def copy_matrices(
    nugget_var: float | Tensor, *, dtype: torch.dtype, device=None
) -> tuple[Tensor, Tensor]:
    """``(T, Q)`` of :func:`copy_pose` as a linear step ``x = T x + w``, ``w ~ N(0, Q)``.

    For a plain-number nugget the pair is built once per dtype and device (the filter
    asks for it every frame); callers must not modify it in place."""
    if isinstance(nugget_var, Tensor):
        return _copy_matrices(nugget_var, dtype, device)
    return _cached_copy_matrices(float(nugget_var), dtype, None if device is None else torch.device(device))


def _copy_matrices(nugget_var: float | Tensor, dtype: torch.dtype, device) -> tuple[Tensor, Tensor]:
    T = torch.zeros(STATE_DIM, STATE_DIM, dtype=dtype, device=device)
    T[:CORE_DIM, :CORE_DIM] = torch.eye(CORE_DIM, dtype=dtype, device=device)
    T[STATE.p_prev, STATE.p] = torch.eye(3, dtype=dtype, device=device)
    T[STATE.q_prev, STATE.q] = torch.eye(4, dtype=dtype, device=device)
    nugget = torch.as_tensor(nugget_var, dtype=dtype, device=device)
    Q = torch.zeros_like(T)
    Q[CORE_DIM:, CORE_DIM:] = nugget * torch.eye(STATE_DIM - CORE_DIM, dtype=dtype, device=device)
    return T, Q


_cached_copy_matrices = cached_constant(_copy_matrices)


@cached_constant
def copy_index(device: torch.device) -> Tensor:
    """``(26,)``: the state entry each entry of :func:`copy_pose`'s result copies (its ``T`` is
    the identity's rows at these indices): itself on the core, ``p`` and ``q`` for the old pose."""
    index = torch.arange(STATE_DIM, device=device)
    index[STATE.p_prev] = torch.arange(STATE.p.start, STATE.p.stop, device=device)
    index[STATE.q_prev] = torch.arange(STATE.q.start, STATE.q.stop, device=device)
    return index


def copy_pose(mean: Tensor, cov: Tensor, *, nugget_var: float | Tensor) -> tuple[Tensor, Tensor]:
    """The ``σ_{p,0}, σ_{q,0} → ∞`` limit of forgetting followed by augmentation.

    ``p_prev := p``, ``q_prev := q`` with the covariance rows copied and the nugget
    added to the old pose's own block; the core state is untouched.
    """
    T, Q = copy_matrices(nugget_var, dtype=mean.dtype, device=mean.device)
    new_mean, new_cov = linear_predict(mean, cov, T, Q)
    return normalize_quaternions(new_mean), symmetrize(new_cov)


@dataclass(frozen=True)
class PoseAugmentation:
    """Pose forgetting then pose augmentation at ``time_s`` (the per-frame step of the paper).

    ``mode="paper"`` applies ``A⋆, Q⋆`` and the ``H⋆`` update literally;
    ``mode="limit"`` applies their ``σ → ∞`` limit (:func:`copy_pose`) as one
    linear step.
    """

    time_s: float
    sigma_p0: float | Tensor = 1e3
    sigma_q0: float | Tensor = 1e2
    nugget_var: float | Tensor = 1e-9
    mode: str = "paper"
    name: str = "pose augmentation"

    def __post_init__(self) -> None:
        if self.mode not in ("paper", "limit"):
            raise ValueError(f"PoseAugmentation.mode must be 'paper' or 'limit', got {self.mode!r}")

    def apply(self, chain: ChainBuilder) -> None:
        augment_pose_rows(chain.batch, [chain.row], sigma_p0=self.sigma_p0, sigma_q0=self.sigma_q0,
                          nugget_var=self.nugget_var, mode=self.mode)


def augment_pose_rows(chain: BatchChain, rows: list[int], *, sigma_p0: float | Tensor = 1e3,
                      sigma_q0: float | Tensor = 1e2, nugget_var: float | Tensor = 1e-9, mode: str = "paper") -> None:
    """:class:`PoseAugmentation` on the rows ``rows`` of ``chain`` at once."""
    like = chain.mean
    if mode == "paper":
        A, Q = forgetting_matrices(sigma_p0, sigma_q0, dtype=like.dtype, device=like.device)
        chain.linear_predict_rows(rows, A.unsqueeze(0), Q.unsqueeze(0))
        chain.update_rows(rows, *augment_pose(*chain.newest(rows), nugget_var=nugget_var))
    elif mode == "limit":
        # one linear step, recorded as such so the smoother sees its transition
        T, Q = copy_matrices(nugget_var, dtype=like.dtype, device=like.device)
        chain.linear_predict_rows(rows, T.unsqueeze(0), Q.unsqueeze(0), select=copy_index(like.device))
    else:
        raise ValueError(f"pose augmentation mode must be 'paper' or 'limit', got {mode!r}")
