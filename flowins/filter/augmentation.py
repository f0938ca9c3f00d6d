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

A state with a window of ``N > 1`` cloned poses (``D = 19 + 7 N``, :mod:`flowins.state`)
shifts the window at each frame instead: clone ``k`` takes clone ``k - 1`` (``k = N-1 .. 1``),
clone 0 the current pose, and the oldest clone falls out, each with the nugget added
(:func:`copy_matrices`, the ``"limit"`` mode; the paper's forgetting and ``H⋆`` update
are written for the one clone of the 26-dim state only). :func:`with_window` extends a
26-dim prior to ``N`` clones.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from flowins.constants import cached_constant
from flowins.filter.chain import BatchChain, ChainBuilder
from flowins.filter.ekf import ekf_update, linear_predict
from flowins.state import CORE_DIM, STATE, STATE_DIM, normalize_quaternions, pose_slices, state_dim, symmetrize


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

    Not gated; quaternions are re-normalised afterwards like after every update. The 26-dim
    state only (``mean`` ``(..., 26)``).
    """
    _check_paper(mean.shape[-1])
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
    nugget_var: float | Tensor, *, dtype: torch.dtype, device=None, dim: int = STATE_DIM
) -> tuple[Tensor, Tensor]:
    """``(T, Q)`` of :func:`copy_pose` as a linear step ``x = T x + w``, ``w ~ N(0, Q)``, each
    ``(D, D)`` for a state of ``D = dim`` entries (``19 + 7 N``; 26, the default, for one clone).

    ``T`` is the identity on the core and shifts the window of cloned poses: clone ``k`` takes
    clone ``k - 1`` (``k = N-1 .. 1``), clone 0 (``p_prev``, ``q_prev``) the current pose ``(p, q)``;
    ``Q`` is ``nugget I`` on every clone. For a plain-number nugget the pair is built once per
    dtype, device and ``D`` (the filter asks for it every frame); callers must not modify it in
    place."""
    if isinstance(nugget_var, Tensor):
        return _copy_matrices(nugget_var, dtype, device, dim)
    return _cached_copy_matrices(float(nugget_var), dtype, None if device is None else torch.device(device), dim)


def _copy_matrices(nugget_var: float | Tensor, dtype: torch.dtype, device, dim: int = STATE_DIM) -> tuple[Tensor, Tensor]:
    T = torch.zeros(dim, dim, dtype=dtype, device=device)
    T[:CORE_DIM, :CORE_DIM] = torch.eye(CORE_DIM, dtype=dtype, device=device)
    poses = pose_slices(dim)  # (p, q), clone 0, clone 1, ...: each takes the one before it
    for (p_to, q_to), (p_from, q_from) in zip(poses[1:], poses[:-1]):
        T[p_to, p_from] = torch.eye(3, dtype=dtype, device=device)
        T[q_to, q_from] = torch.eye(4, dtype=dtype, device=device)
    nugget = torch.as_tensor(nugget_var, dtype=dtype, device=device)
    Q = torch.zeros_like(T)
    Q[CORE_DIM:, CORE_DIM:] = nugget * torch.eye(dim - CORE_DIM, dtype=dtype, device=device)
    return T, Q


_cached_copy_matrices = cached_constant(_copy_matrices)


@cached_constant
def copy_index(device: torch.device, dim: int = STATE_DIM) -> Tensor:
    """``(D,)``: the state entry each entry of :func:`copy_pose`'s result copies (its ``T`` is
    the identity's rows at these indices): itself on the core, the pose before it in the window
    for each clone (``p`` and ``q`` for clone 0), for a state of ``D = dim`` entries."""
    index = torch.arange(dim, device=device)
    poses = pose_slices(dim)
    for (p_to, q_to), (p_from, q_from) in zip(poses[1:], poses[:-1]):
        index[p_to] = torch.arange(p_from.start, p_from.stop, device=device)
        index[q_to] = torch.arange(q_from.start, q_from.stop, device=device)
    return index


def copy_pose(mean: Tensor, cov: Tensor, *, nugget_var: float | Tensor) -> tuple[Tensor, Tensor]:
    """The ``σ_{p,0}, σ_{q,0} → ∞`` limit of forgetting followed by augmentation.

    ``p_prev := p``, ``q_prev := q`` (and, with ``N > 1`` clones, each further clone := the one
    before it) with the covariance rows copied and the nugget added to the clones' own
    blocks; the core state is untouched. ``mean`` ``(..., D)``, ``cov`` ``(..., D, D)``.
    """
    T, Q = copy_matrices(nugget_var, dtype=mean.dtype, device=mean.device, dim=mean.shape[-1])
    new_mean, new_cov = linear_predict(mean, cov, T, Q)
    return normalize_quaternions(new_mean), symmetrize(new_cov)


def with_window(mean: Tensor, cov: Tensor, clones: int, *, nugget_var: float | Tensor = 0.0) -> tuple[Tensor, Tensor]:
    """A 26-dim prior ``mean`` ``(..., 26)``, ``cov`` ``(..., 26, 26)`` (clone 0 set) extended to a
    window of ``N = clones`` cloned poses: ``(..., D)``, ``(..., D, D)``, ``D = 19 + 7 N``.

    Each further clone is a copy of clone 0: its mean entries, and its covariance rows and
    columns (``x ↦ T x`` with ``T`` rows of the identity, so the covariance stays positive
    semi-definite), plus ``nugget_var`` on the diagonal of each further clone's own block
    (default 0: exact copies). ``N = 1`` returns the inputs themselves.

    Exact copies make the covariance singular until the first frame's :func:`copy_matrices`
    adds its nugget to every clone; the RTS smoother cannot invert a predicted covariance
    before that. When updates (zero velocity, GNSS) come before the first frame, give the
    prior's own nugget (:attr:`~flowins.ins.initialization.InitialUncertainty.augmentation_nugget_var`,
    what clone 0 has over ``(p, q)``): the core and clone 0 of the filter are the same either way.
    """
    if mean.shape[-1:] != (STATE_DIM,) or cov.shape[-2:] != (STATE_DIM, STATE_DIM):
        raise ValueError(f"with_window: the prior must be (..., {STATE_DIM}) and (..., {STATE_DIM}, {STATE_DIM}), "
                         f"got {tuple(mean.shape)} and {tuple(cov.shape)}")
    dim = state_dim(clones)  # N >= 1
    if clones == 1:
        return mean, cov
    index = _window_index(mean.device, clones)
    wide = cov[..., index, :][..., index]
    if isinstance(nugget_var, Tensor) or nugget_var != 0.0:
        nugget = torch.as_tensor(nugget_var, dtype=cov.dtype, device=cov.device)
        further = torch.arange(dim, device=cov.device) >= STATE_DIM
        wide = wide + torch.diag_embed(further.to(cov.dtype) * nugget)
    return mean[..., index], wide


@cached_constant
def _window_index(device: torch.device, clones: int) -> Tensor:
    """``(19 + 7 N,)``: the 26-dim state's entries, then clone 0's ``N - 1`` times (:func:`with_window`)."""
    clone0 = [torch.arange(sl.start, sl.stop) for sl in pose_slices(STATE_DIM)[1]]
    return torch.cat([torch.arange(STATE_DIM)] + clone0 * (clones - 1)).to(device)


def _check_paper(dim: int) -> None:
    """Mode ``"paper"`` (:func:`forgetting_matrices`, :func:`augment_pose`) takes the 26-dim state only."""
    if dim != STATE_DIM:
        raise ValueError(f"pose augmentation mode 'paper' (forgetting A⋆ and the H⋆ update) is written for the "
                         f"{STATE_DIM}-dim state with one cloned pose, got a state of {dim} entries (a window of "
                         f"cloned poses): use mode 'limit' (FlowUpdate.augmentation_mode), which shifts the window")


@dataclass(frozen=True)
class PoseAugmentation:
    """Pose forgetting then pose augmentation at ``time_s`` (the per-frame step of the paper).

    ``mode="paper"`` applies ``A⋆, Q⋆`` and the ``H⋆`` update literally;
    ``mode="limit"`` applies their ``σ → ∞`` limit (:func:`copy_pose`) as one
    linear step; it is the one mode for states with a window of ``N > 1`` cloned poses,
    whose window it shifts.
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
    """:class:`PoseAugmentation` on the rows ``rows`` of ``chain`` at once (mode ``"paper"``: the
    26-dim state only; ``"limit"``: any ``D = 19 + 7 N``, the window shifted)."""
    like = chain.mean
    dim = like.shape[-1]
    if mode == "paper":
        _check_paper(dim)
        A, Q = forgetting_matrices(sigma_p0, sigma_q0, dtype=like.dtype, device=like.device)
        chain.linear_predict_rows(rows, A.unsqueeze(0), Q.unsqueeze(0))
        chain.update_rows(rows, *augment_pose(*chain.newest(rows), nugget_var=nugget_var))
    elif mode == "limit":
        # one linear step, recorded as such so the smoother sees its transition
        T, Q = copy_matrices(nugget_var, dtype=like.dtype, device=like.device, dim=dim)
        chain.linear_predict_rows(rows, T.unsqueeze(0), Q.unsqueeze(0), select=copy_index(like.device, dim))
    else:
        raise ValueError(f"pose augmentation mode must be 'paper' or 'limit', got {mode!r}")
