"""Extended Kalman filter steps: prediction, Joseph-form update and innovation gating.

Pure functions on ``(mean, cov)`` with any leading batch dimensions. The
equations are the paper's (Sec. "Inertial Navigation" eq. prediction step, and
Sec. "Information Fusion" eq. update step):

    prediction   m⁻ = f(m, 0),   P⁻ = F_x P F_xᵀ + F_ε Q F_εᵀ
    update       v = z - h(m⁻)  (or v = 0 - h(m⁻, δ) for the implicit flow model)
                 S = H_x P⁻ H_xᵀ + H_r R H_rᵀ,  K = P⁻ H_xᵀ S⁻¹
                 m = m⁻ + K v,  P = D P⁻ Dᵀ + K H_r R H_rᵀ Kᵀ,  D = I - K H_x

followed by quaternion re-normalisation of the mean and symmetrisation of ``P``.

**No wait on the device.** Every factorisation is a ``cholesky_ex`` / ``solve_ex`` whose
error flag stays a tensor: an update returns ``failed`` (``(...,)`` bool: the covariance
could not be factorised even with the largest jitter, or a solve met a singular matrix) and
the caller decides when to read it (:meth:`flowins.filter.chain.BatchChain.check_failed`). On a GPU or under
``torch.compile`` the jitter ladder of :func:`_cholesky_psd` is one batched call, so an update
is one graph with no read-back; on the CPU in eager mode, where a read costs nothing, the
ladder stops at the first jitter every matrix takes (the same factors).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal, NamedTuple

import torch
from torch import Tensor
from torch.func import jacrev, vmap

from flowins.config import bounded, check_fields
from flowins.constants import cached_constant
from flowins.linalg import in_slices
from flowins.state import symmetrize

# --------------------------------------------------------------------------- prediction


def dynamics_jacobians(
    f: Callable[..., Tensor], mean: Tensor, noise_dim: int, *args: Tensor
) -> tuple[Tensor, Tensor]:
    """``(F_x, F_ε)`` of ``f(x, ε, *args)`` at ``(mean, 0)`` by reverse-mode autodiff.

    ``mean`` is ``(D,)`` or ``(B, D)`` (then ``args`` carry the same batch and
    ``torch.func.vmap`` maps over it). Returns ``(..., D, D)`` and ``(..., D, noise_dim)``.
    """
    jac = jacrev(f, argnums=(0, 1))
    if mean.ndim == 1:
        return jac(mean, mean.new_zeros(noise_dim), *args)
    if mean.ndim != 2:
        raise ValueError(f"mean must be (D,) or (B, D), got shape {tuple(mean.shape)}")
    zeros = mean.new_zeros(mean.shape[0], noise_dim)
    return vmap(jac)(mean, zeros, *args)


def propagate_covariance(cov: Tensor, F_x: Tensor, F_eps: Tensor, noise_cov: Tensor) -> Tensor:
    """``F_x P F_xᵀ + F_ε Q F_εᵀ``, symmetrised."""
    return symmetrize(F_x @ cov @ F_x.transpose(-1, -2) + F_eps @ noise_cov @ F_eps.transpose(-1, -2))


def predict(
    f: Callable[..., Tensor], mean: Tensor, cov: Tensor, noise_cov: Tensor, *args: Tensor
) -> tuple[Tensor, Tensor]:
    """The EKF prediction step with ``torch.func.jacrev`` Jacobians.

    Args:
        f: dynamics ``f(x, ε, *args) -> x'`` (pure).
        mean: ``(D,)`` or ``(B, D)``; cov: ``(..., D, D)``; noise_cov: ``Q`` ``(..., E, E)``.
    """
    F_x, F_eps = dynamics_jacobians(f, mean, noise_cov.shape[-1], *args)
    noise = mean.new_zeros(*mean.shape[:-1], noise_cov.shape[-1])
    return f(mean, noise, *args), propagate_covariance(cov, F_x, F_eps, noise_cov)


def linear_predict(mean: Tensor, cov: Tensor, A: Tensor, Q: Tensor, b: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Linear Kalman prediction ``m = A m + b``, ``P = A P Aᵀ + Q`` (symmetrised)."""
    m = (A @ mean.unsqueeze(-1)).squeeze(-1)
    return m if b is None else m + b, symmetrize(A @ cov @ A.transpose(-1, -2) + Q)


# --------------------------------------------------------------------------- gating


@lru_cache(maxsize=256)
def chi2_quantile(probability: float, dof: int) -> float:
    """``x`` with ``P(χ²_dof <= x) = probability`` (bisection on the regularised gamma)."""
    if not 0.0 < probability < 1.0:
        raise ValueError(f"gate probability must be in (0, 1), got {probability}")
    if dof < 1:
        raise ValueError(f"chi-square degrees of freedom must be >= 1, got {dof}")
    k = torch.tensor(dof / 2.0, dtype=torch.float64)

    def cdf(x: float) -> float:
        return float(torch.special.gammainc(k, torch.tensor(x / 2.0, dtype=torch.float64)))

    lo, hi = 0.0, float(dof)
    while cdf(hi) < probability:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if cdf(mid) < probability:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * max(1.0, hi):
            break
    return 0.5 * (lo + hi)


@dataclass(frozen=True)
class Gate:
    """Innovation gate on the normalised innovation squared ``NIS = vᵀ S⁻¹ v``.

    Attributes:
        mode: ``"hard"`` accepts a measurement iff ``NIS <= threshold`` (inference);
            ``"soft"`` weighs it by ``sigmoid((threshold - NIS) / softness)``, a smooth,
            differentiable version of the same test (training); ``"off"`` accepts all.
        probability: acceptance probability of the χ² test under the model; sets the
            threshold ``χ²_dof(probability)`` unless ``threshold`` is given.
        threshold: explicit NIS threshold (float or a learnable tensor); overrides
            ``probability``.
        softness: width of the soft gate in NIS units (float or tensor).
        scale: multiplies the threshold ``χ²_dof(probability)`` (float or a learnable tensor):
            one learnable factor for blocks of differing degrees of freedom (the sparse
            tracks' ``2m - 3``), where one threshold would not fit them all. Not used with
            an explicit ``threshold``.

    A weight ``w`` multiplies the measurement's innovation rows and Jacobian rows,
    which is exactly an update with noise ``R / w²``: ``w = 0`` adds no information
    and no division happens anywhere.
    """

    mode: Literal["hard", "soft", "off"] = "hard"
    probability: float = bounded(0.999, above=0.0, below=1.0)
    threshold: float | Tensor | None = None
    softness: float | Tensor = 1.0
    scale: float | Tensor = 1.0

    def __post_init__(self) -> None:
        check_fields(self)

    def threshold_for(self, dof: int | Tensor, *, max_dof: int | None = None) -> float | Tensor:
        """The NIS threshold for ``dof`` degrees of freedom: an int, or a tensor of them (one per
        block, the thresholds then a tensor of its shape), looked up in a table of the quantiles
        for ``1 .. max_dof`` (the blocks' dimension; None: ``dof``'s largest, a read from its device)."""
        if self.threshold is not None:
            return self.threshold
        if isinstance(dof, Tensor):
            top = int(dof.max()) if max_dof is None else max_dof
            table = _quantiles(self.probability, max(top, 1), dof.device)
            quantile = table[(dof.long() - 1).clamp(0, table.shape[0] - 1)]
        else:
            quantile = chi2_quantile(self.probability, dof)
        return quantile * self.scale

    def weights(self, nis: Tensor, dof: int | Tensor, *, max_dof: int | None = None) -> Tensor:
        """Weights in ``[0, 1]`` with the shape of ``nis`` (``dof`` an int, or one per block, each
        at most ``max_dof``: :meth:`threshold_for`)."""
        if self.mode == "off":
            return torch.ones_like(nis)
        threshold = self.threshold_for(dof, max_dof=max_dof)
        if isinstance(threshold, Tensor) and threshold.dtype != nis.dtype:
            threshold = threshold.to(nis.dtype)
        if self.mode == "hard":
            return (nis <= threshold).to(nis.dtype)
        return torch.sigmoid((threshold - nis) / self.softness)


#: the gate of an update given none (built once: a step traced by ``torch.compile`` builds no dataclass)
_NO_GATE = Gate(mode="off")


@cached_constant
def _quantiles(probability: float, max_dof: int, device: torch.device) -> Tensor:
    """``(max_dof,)`` float64: :func:`chi2_quantile` of ``probability`` for ``1 .. max_dof`` degrees of freedom."""
    return torch.tensor([chi2_quantile(probability, d) for d in range(1, max_dof + 1)], dtype=torch.float64,
                        device=device)


# --------------------------------------------------------------------------- update


class UpdateResult(NamedTuple):
    mean: Tensor  # (..., D)
    cov: Tensor  # (..., D, D)
    nis: Tensor  # (..., M) normalised innovation squared of each measurement block
    weight: Tensor  # (..., M) gate weight (1 accepted, 0 rejected)
    #: (..., M) each block's innovation negative log-likelihood ``½ (NIS + log det S)`` (without
    #: the constant ``½ d log 2π``), before the gate; None unless asked for (``likelihood=True``)
    nll: Tensor | None = None
    #: (...,) bool: a factorisation failed (see the module doc); None: nothing was factorised
    failed: Tensor | None = None


class Posterior(NamedTuple):
    """An update's Gaussian and whether a factorisation failed on the way (``(...,)`` bool)."""

    mean: Tensor  # (..., D)
    cov: Tensor  # (..., D, D)
    failed: Tensor  # (...,)


def waits_cost(t: Tensor) -> bool:
    """Whether reading a flag back from ``t``'s device would cost: on any device but the CPU (a GPU
    waits for its queue), or under ``torch.compile`` (a read breaks the graph)."""
    return t.device.type != "cpu" or torch.compiler.is_compiling()


def joseph_update(
    mean: Tensor, cov: Tensor, innovation: Tensor, H: Tensor, noise_cov: Tensor
) -> Posterior:
    """One Kalman update in Joseph form for a stacked measurement of dimension ``n``.

    Args:
        mean ``(..., D)``, cov ``(..., D, D)``, innovation ``v`` ``(..., n)``,
        H ``(..., n, D)``, noise_cov ``H_r R H_rᵀ`` ``(..., n, n)``.

    The Joseph form ``D P Dᵀ + K R Kᵀ`` is the exact posterior covariance for the
    gain used, so it stays symmetric positive semi-definite in floating point.
    """
    Ht = H.transpose(-1, -2)
    PHt = cov @ Ht
    S = symmetrize(H @ PHt + noise_cov)
    K, info = torch.linalg.solve_ex(S, PHt.transpose(-1, -2))
    K = K.transpose(-1, -2)
    eye = _eye(cov.shape[-1], cov.dtype, cov.device)
    D = eye - K @ H
    new_cov = D @ cov @ D.transpose(-1, -2) + K @ noise_cov @ K.transpose(-1, -2)
    new_mean = mean + (K @ innovation.unsqueeze(-1)).squeeze(-1)
    return Posterior(new_mean, symmetrize(new_cov), info != 0)


#: the jitters, as fractions of the largest variance, a covariance's factorisation tries in turn
_JITTERS = (1e-16, 1e-14, 1e-12, 1e-10, 1e-8, 1e-6)


def _cholesky_psd(cov: Tensor) -> tuple[Tensor, Tensor]:
    """``(F, failed)``: a Cholesky factor of a positive semi-definite ``cov`` ``(..., D, D)``
    with the first jitter of :data:`_JITTERS` (times the largest variance) its factorisation
    takes (``P`` is singular right after the pose copy, up to its nugget), each matrix of a
    batch the jitter it alone would get; ``failed`` ``(...,)`` where none does (``F`` then
    from the largest). Where a read-back costs (:func:`waits_cost`) all jitters are factorised
    in one batched call; elsewhere the ladder stops at the first jitter every matrix takes."""
    eyes = _jittered_eyes(cov.shape[-1], cov.dtype, cov.device)  # (J, D, D): jitter · I, one per level
    scale = cov.diagonal(dim1=-2, dim2=-1).amax(-1, keepdim=True).unsqueeze(-1).detach().clamp_min(torch.finfo(cov.dtype).tiny)
    if waits_cost(cov):
        levels = eyes.view(eyes.shape[0], *([1] * (cov.ndim - 2)), *eyes.shape[1:])
        factors, info = torch.linalg.cholesky_ex(cov.unsqueeze(0) + scale.unsqueeze(0) * levels)  # (J, ..., D, D)
        ok = info == 0
        first = torch.where(ok.any(0), ok.to(torch.uint8).argmax(0), len(_JITTERS) - 1)
        F = torch.take_along_dim(factors, first[None, ..., None, None], 0)[0]
        # in the column-major layout LAPACK's factor has: the products that follow round alike
        return F.mT.contiguous().mT, ~ok.any(0)
    F, info = torch.linalg.cholesky_ex(cov + scale * eyes[0])
    for level in range(1, len(_JITTERS)):
        if not bool(info.any()):
            break
        failed = info != 0
        retry, info_retry = torch.linalg.cholesky_ex(cov + scale * eyes[level])
        F = torch.where(failed[..., None, None], retry, F)
        info = torch.where(failed, info_retry, info)
    return F, info != 0


@cached_constant
def _eye(n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.eye(n, dtype=dtype, device=device)


@cached_constant
def _jittered_eyes(n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(J, n, n)``: each jitter of :data:`_JITTERS` times the identity (both ladders add the same
    terms, so the CPU's and a GPU's factors agree to the bit)."""
    return torch.tensor(_JITTERS, dtype=dtype, device=device)[:, None, None] * torch.eye(n, dtype=dtype, device=device)


def scalar_update(
    mean: Tensor, cov: Tensor, innovation: Tensor, H: Tensor, noise_var: Tensor
) -> Posterior:
    """The stacked update of ``M`` independent scalar measurements, in ``D x D`` algebra.

    Args:
        mean ``(..., D)``, cov ``(..., D, D)``, innovation ``(..., M)``, H ``(..., M, D)``,
        noise_var ``(..., M)`` (``R = diag(noise_var)``).

    The same posterior as :func:`joseph_update` with a diagonal ``R``, without the
    ``M x M`` innovation covariance: with ``G = Hᵀ R⁻¹ H`` the push-through identity
    gives the gain from one ``D x D`` solve,

        K = P Hᵀ (H P Hᵀ + R)⁻¹ = (I + P G)⁻¹ P Hᵀ R⁻¹,

    computed symmetrically with a square root ``P = F Fᵀ`` as
    ``K = F (I + Fᵀ G F)⁻¹ Fᵀ Hᵀ R⁻¹`` (a Cholesky solve of a matrix whose eigenvalues are
    ``>= 1``; the non-symmetric ``I + P G`` loses digits when ``P`` is near singular). The
    covariance is the Joseph form ``D P Dᵀ + K R Kᵀ`` (``D = I - K H``) with that gain, so
    rounding in ``K`` enters ``P⁺`` only at second order and ``P⁺`` stays symmetric positive
    semi-definite.
    """
    Ht_Rinv = (H / noise_var.unsqueeze(-1)).transpose(-1, -2)  # (..., D, M)
    eye = _eye(cov.shape[-1], cov.dtype, cov.device)
    F, failed = _cholesky_psd(cov)
    FtHtR = F.transpose(-1, -2) @ Ht_Rinv  # (..., D, M)
    W, info = torch.linalg.cholesky_ex(eye + FtHtR @ (H @ F))  # eigenvalues >= 1: fails only on NaN
    gain = F @ torch.cholesky_solve(FtHtR, W)  # (..., D, M)
    D = eye - gain @ H
    new_cov = D @ cov @ D.transpose(-1, -2) + (gain * noise_var.unsqueeze(-2)) @ gain.transpose(-1, -2)
    new_mean = mean + (gain @ innovation.unsqueeze(-1)).squeeze(-1)
    return Posterior(new_mean, symmetrize(new_cov), failed | (info != 0))


def information_update(mean: Tensor, cov: Tensor, information: Tensor, projected: Tensor) -> Posterior:
    """The update of measurements given by their information ``G = Σᵢ Hᵢᵀ Rᵢ⁻¹ Hᵢ`` ``(..., D, D)``
    and ``b = Σᵢ Hᵢᵀ Rᵢ⁻¹ vᵢ`` ``(..., D)``, in ``D x D`` algebra (:func:`scalar_update` for
    blocks of any size and full noise).

    With a square root ``P = F Fᵀ`` and ``W = I + Fᵀ G F = L Lᵀ`` (eigenvalues ``>= 1``), the
    posterior covariance is ``A = F W⁻¹ Fᵀ = (P⁻¹ + G)⁻¹``, formed as the Gram matrix ``B Bᵀ``
    of ``B = F L⁻ᵀ`` (one triangular solve), so it is symmetric positive semi-definite by
    construction, as the Joseph form's would be, with three ``D x D`` products and one
    triangular solve where the Joseph form takes seven and two; the gain
    satisfies ``K v = A b``, so the mean moves by ``B (Bᵀ b)``. Where ``G`` is zero (every
    block rejected) the covariance stays ``P`` exactly (``B Bᵀ`` would give it back rounded).
    """
    eye = _eye(cov.shape[-1], cov.dtype, cov.device)
    F, failed = _cholesky_psd(cov)
    Ft = F.transpose(-1, -2)
    L, info = torch.linalg.cholesky_ex(symmetrize(eye + Ft @ information @ F))  # eigenvalues >= 1
    Bt = torch.linalg.solve_triangular(L, Ft, upper=False)  # Bᵀ = L⁻¹ Fᵀ
    B = Bt.transpose(-1, -2)
    new_mean = mean + (B @ (Bt @ projected.unsqueeze(-1))).squeeze(-1)
    nothing = (information == 0).flatten(-2).all(-1)
    return Posterior(new_mean, torch.where(nothing[..., None, None], cov, symmetrize(B @ Bt)), failed | (info != 0))


def block_information(innovation: Tensor, H: Tensor, noise_cov: Tensor | None) -> tuple[Tensor, Tensor]:
    """``G = Σᵢ Hᵢᵀ Rᵢ⁻¹ Hᵢ`` ``(..., D, D)`` and ``b = Σᵢ Hᵢᵀ Rᵢ⁻¹ vᵢ`` ``(..., D)`` of ``M`` blocks
    (innovation ``(..., M, d)``, H ``(..., M, d, D)``, noise_cov ``(..., M, d, d)``, or None for
    whitened blocks, ``R = I``), each block's ``R⁻¹`` from its Cholesky factor (a batched
    ``cholesky_solve`` with ``D`` right-hand sides is two orders of magnitude slower on the CPU
    than the ``d x d`` inverse and a product)."""
    if noise_cov is None:
        Rinv_H = H.flatten(-3, -2)
    else:
        Rinv = torch.cholesky_inverse(torch.linalg.cholesky_ex(symmetrize(noise_cov))[0])
        Rinv_H = (Rinv @ H).flatten(-3, -2)  # (..., M d, D): the sums over blocks are one product each
    G = H.flatten(-3, -2).transpose(-1, -2) @ Rinv_H
    return G, (Rinv_H.transpose(-1, -2) @ innovation.flatten(-2).unsqueeze(-1)).squeeze(-1)


def block_nis(cov: Tensor, innovation: Tensor, H: Tensor, noise_cov: Tensor | None) -> Tensor:
    """NIS ``v_iᵀ S_i⁻¹ v_i`` of each of ``M`` measurement blocks.

    innovation ``(..., M, d)``, H ``(..., M, d, D)``, noise_cov ``(..., M, d, d)`` (None:
    whitened, ``R = I``), cov ``(..., D, D)`` -> ``(..., M)``.
    """
    if innovation.shape[-1] == 1:  # scalars: S_i = h_i P h_iᵀ + r_i without M tiny solves
        return innovation[..., 0] ** 2 / _scalar_innovation_variance(cov, H, noise_cov)
    S = _block_innovation_cov(cov, H, noise_cov)
    return (innovation * torch.linalg.solve_ex(S, innovation.unsqueeze(-1))[0].squeeze(-1)).sum(-1)


def block_nll(cov: Tensor, innovation: Tensor, H: Tensor, noise_cov: Tensor | None) -> tuple[Tensor, Tensor]:
    """NIS and innovation negative log-likelihood of each of ``M`` measurement blocks.

    Shapes as for :func:`block_nis`; returns ``(nis, nll)``, both ``(..., M)``, with
    ``nll_i = ½ (v_iᵀ S_i⁻¹ v_i + log det S_i)``, ``S_i = H_i P H_iᵀ + R_i``: the negative
    log-density of the block's innovation under the filter's prediction, without the
    constant ``½ d log 2π``. Summed over the updates of a run, one block per update, it is
    the negative log-likelihood of all the measurements (the prediction-error
    decomposition). With whitened blocks (``noise_cov`` None) ``log det S`` is that of the
    whitened rows: the caller adds the whitening's own ``½ log det R`` (:func:`ekf_update`'s
    ``noise_logdet``).
    """
    if innovation.shape[-1] == 1:
        S = _scalar_innovation_variance(cov, H, noise_cov)
        nis = innovation[..., 0] ** 2 / S
        return nis, 0.5 * (nis + torch.log(S))
    S = _block_innovation_cov(cov, H, noise_cov)
    L = in_slices(torch.linalg.cholesky_ex, S, batch_dims=S.ndim - 2)[0]
    white = torch.linalg.solve_triangular(L, innovation.unsqueeze(-1), upper=False).squeeze(-1)
    nis = (white * white).sum(-1)
    return nis, 0.5 * nis + torch.log(L.diagonal(dim1=-2, dim2=-1)).sum(-1)


def _block_innovation_cov(cov: Tensor, H: Tensor, noise_cov: Tensor | None) -> Tensor:
    """``S_i = H_i P H_iᵀ + R_i`` ``(..., M, d, d)`` of each block, symmetrised (``R_i = I`` for
    ``noise_cov`` None)."""
    M, d = H.shape[-3:-1]
    HP = (H.flatten(-3, -2) @ cov).unflatten(-2, (M, d))  # one product per covariance, not one per block
    R = _eye(d, cov.dtype, cov.device) if noise_cov is None else noise_cov
    return symmetrize(HP @ H.transpose(-1, -2) + R)


def _scalar_innovation_variance(cov: Tensor, H: Tensor, noise_cov: Tensor | None) -> Tensor:
    """``S_i = h_i P h_iᵀ + r_i`` ``(..., M)`` of scalar blocks (``d = 1``; ``r_i = 1`` for
    ``noise_cov`` None)."""
    h = H[..., 0, :]
    return torch.linalg.vecdot(h @ cov, h) + (1.0 if noise_cov is None else noise_cov[..., 0, 0])


def left_out_nis(innovation: Tensor, H: Tensor, noise_var: Tensor, weight: Tensor, prior_mean: Tensor,
                 mean: Tensor, cov: Tensor) -> Tensor:
    """``(..., M)``: the NIS of each of ``M`` independent scalar measurements against the
    posterior of the others (its leave-one-out or deleted residual), from the posterior
    ``(mean, cov)`` that an update of ``prior_mean`` with all of them gave.

    Args:
        innovation ``(..., M)`` at ``prior_mean`` ``(..., D)``, H ``(..., M, D)``, noise_var
        ``(..., M)`` (``r``), weight ``(..., M)``: each measurement's gate weight ``w`` in that
        update (it entered with noise ``r / w²``; 0: not at all), mean ``(..., D)`` and cov
        ``(..., D, D)`` the posterior.

    With the posterior residual ``e = v - h (m⁺ - m)`` and ``a = h P⁺ hᵀ``, taking measurement
    ``i`` out of a linear update gives the residual ``e r / (r - w² a)`` and its predicted
    variance ``r + a r / (r - w² a)``, so

        NIS₋ᵢ = e² r / ((r - w² a) (r - w² a + a)),

    χ²₁ under the model: ``e² / (r - a)`` for a measurement that entered (``w = 1``),
    ``e² / (r + a)`` for one that did not (``w = 0``). No ``M x M`` matrix is formed: one
    ``(M, D) x (D, D)`` product. ``r - w² a > 0`` in exact arithmetic; it is kept above
    ``1e-12 r`` against rounding.
    """
    e = innovation - (H @ (mean - prior_mean).unsqueeze(-1)).squeeze(-1)
    a = torch.linalg.vecdot(H @ cov, H)
    left = torch.maximum(noise_var - weight.square() * a, 1e-12 * noise_var)
    return e.square() * noise_var / (left * (left + a))


def _block_diagonal(blocks: Tensor) -> Tensor:
    """``(..., M, d, d)`` -> block-diagonal ``(..., M d, M d)``."""
    *batch, M, d, _ = blocks.shape
    eye = torch.eye(M, dtype=blocks.dtype, device=blocks.device)
    full = blocks.unsqueeze(-2) * eye.view(M, 1, M, 1)  # (..., M, d, M, d)
    return full.reshape(*batch, M * d, M * d)


def ekf_update(
    mean: Tensor,
    cov: Tensor,
    *,
    innovation: Tensor,
    H: Tensor,
    noise_cov: Tensor | None,
    gate: Gate | None = None,
    sequential: bool = False,
    normalize: Callable[[Tensor], Tensor] | None = None,
    likelihood: bool = False,
    dof: Tensor | None = None,
    noise_logdet: Tensor | None = None,
) -> UpdateResult:
    """Gated EKF update with ``M`` independent measurement blocks of dimension ``d``.

    Args:
        mean ``(..., D)``, cov ``(..., D, D)``.
        innovation: ``(..., M, d)`` (``z - h(m)``, or ``-h(m, δ)`` for implicit models).
        H: ``(..., M, d, D)`` Jacobians of the measurement function at ``m``.
        noise_cov: ``(..., M, d, d)`` noise in measurement space, ``H_r R H_rᵀ``; None: the
            blocks are whitened (``R = I``: each block's innovation and ``H`` already
            multiplied by ``L⁻¹`` of its noise ``L Lᵀ``), which spares the ``d x d`` inverses.
        gate: innovation gate applied per block (default: none).
        sequential: process the blocks one after another (the paper's per-point
            update, each gated against the covariance updated so far) instead of
            one stacked update. With linear measurements and all blocks accepted the
            two are the same posterior.
        normalize: applied to the updated mean, the caller's hook for a state with
            constraints (the flowins layout passes :func:`flowins.state.normalize_quaternions`);
            None: the mean as the update gives it.
        likelihood: also return each block's innovation negative log-likelihood
            (:attr:`UpdateResult.nll`, :func:`block_nll`; with ``sequential`` each block's
            against the covariance updated by the blocks before it).
        dof: ``(..., M)`` the degrees of freedom each block's gate tests (default ``d``): a
            block padded to ``d`` with rows that carry nothing (zero innovation and ``H``,
            noise uncorrelated with its real rows) has fewer.
        noise_logdet: ``(..., M)`` with whitened blocks, ``½ log det`` of each block's noise
            before the whitening, added to its negative log-likelihood (which is then that of
            the measurement as it was; default 0).

    Stacked blocks with ``M d > D`` (many blocks of several rows, such as the multi-view
    track update) update in information form (:func:`information_update`), ``D x D`` algebra
    instead of an ``M d x M d`` innovation covariance.
    """
    if innovation.ndim < 2 or H.shape[:-1] != innovation.shape or (
            noise_cov is not None and noise_cov.shape[-2:] != innovation.shape[-1:] * 2):
        raise ValueError(
            "ekf_update expects innovation (..., M, d), H (..., M, d, D), noise_cov (..., M, d, d) or None; got "
            f"{tuple(innovation.shape)}, {tuple(H.shape)}, {None if noise_cov is None else tuple(noise_cov.shape)}"
        )
    gate = gate or _NO_GATE
    dof = innovation.shape[-1] if dof is None else dof
    failed = None
    if sequential:
        nis_list, weight_list, nll_list = [], [], []
        prior_mean = mean
        for i in range(innovation.shape[-2]):
            Hi, Ri = H[..., i : i + 1, :, :], None if noise_cov is None else noise_cov[..., i : i + 1, :, :]
            # the innovation was formed at the prior mean; move it to the current one
            # (first order: v_i - H_i (m - m_prior), exact for linear measurements)
            shift = (Hi[..., 0, :, :] @ (mean - prior_mean).unsqueeze(-1)).squeeze(-1)
            v = innovation[..., i : i + 1, :] - shift.unsqueeze(-2)
            dof_i = dof if not isinstance(dof, Tensor) else dof[..., i : i + 1]
            result = ekf_update(mean, cov, innovation=v, H=Hi, noise_cov=Ri, gate=gate, likelihood=likelihood, dof=dof_i)
            mean, cov = result.mean, result.cov
            failed = result.failed if failed is None else failed | result.failed
            nis_list.append(result.nis)
            weight_list.append(result.weight)
            nll_list.append(result.nll)
        nis, weight = torch.cat(nis_list, -1), torch.cat(weight_list, -1)
        nll = torch.cat(nll_list, -1) if likelihood else None
    else:
        nis, nll = block_nll(cov, innovation, H, noise_cov) if likelihood else (block_nis(cov, innovation, H, noise_cov), None)
        weight = gate.weights(nis, dof, max_dof=innovation.shape[-1])
        w = weight.unsqueeze(-1)
        *batch, M, d = innovation.shape
        if d == 1:  # independent scalars (the epipolar flow update): D x D algebra
            mean, cov, failed = scalar_update(mean, cov, (w * innovation)[..., 0], (w.unsqueeze(-1) * H)[..., 0, :],
                                              torch.ones_like(innovation[..., 0]) if noise_cov is None
                                              else noise_cov[..., 0, 0])
        elif M * d > H.shape[-1]:
            mean, cov, failed = information_update(mean, cov,
                                                   *block_information(w * innovation, w.unsqueeze(-1) * H, noise_cov))
        else:
            mean, cov, failed = joseph_update(
                mean,
                cov,
                (w * innovation).reshape(*batch, M * d),
                (w.unsqueeze(-1) * H).reshape(*batch, M * d, H.shape[-1]),
                _eye(M * d, cov.dtype, cov.device).expand(*batch, M * d, M * d) if noise_cov is None
                else _block_diagonal(noise_cov),
            )
    if nll is not None and noise_logdet is not None:
        nll = nll + noise_logdet
    if normalize is not None:
        mean = normalize(mean)
    return UpdateResult(mean, cov, nis, weight, nll, failed)  # each branch's covariance is already symmetrised
