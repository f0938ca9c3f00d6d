"""The update helper every measurement hands its linearisation to.

A measurement model builds, at the filter's newest mean ``m``, ``M`` blocks of dimension
``d``: the Jacobian ``H (..., M, d, D)``, the residual ``v = z - h(m)`` ``(..., M, d)`` (or
``-h(m, δ)`` for an implicit model) and the noise ``R = H_r R H_rᵀ`` ``(..., M, d, d)`` (or
whitened blocks, ``R = I``, with the ``½ log det`` of the noise they were whitened by), and
calls :func:`update` (one run, a :class:`~flowins.filter.chain.ChainBuilder`) or
:func:`update_rows` (rows of a :class:`~flowins.filter.chain.BatchChain`), as OpenVINS'
updaters hand theirs to ``StateHelper::EKFUpdate``. The helper owns the rest:

* the gated update of the newest node (:func:`flowins.filter.ekf.ekf_update`, each block
  gated on its NIS, the quaternions re-normalised after it);
* the innovation likelihood, when the chain keeps one
  (:attr:`~flowins.filter.chain.BatchChain.likelihood`): ``Σ_i w_i ½ (v_iᵀ S_i⁻¹ v_i +
  log det S_i)`` over the valid blocks, the gate weights ``w_i`` held constant, without
  the constant ``½ d log 2π`` (:func:`flowins.filter.ekf.block_nll`), over ``d Σ_i w_i``
  scalar measurements;
* writing the node with a log entry: the caller's facts plus ``nis`` (summed over the
  valid blocks, before the gate) and ``accepted`` (the gate weights summed over them).

A block that ``valid`` marks invalid carries no measurement (its rows of ``H`` and ``v``
are zero); it counts neither as accepted nor in the likelihood, and a row without a
valid block keeps its node (its log entry is still written). An iterated update
relinearises and calls :func:`step_rows` once per iteration, then :func:`commit_rows`.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from flowins.filter.chain import BatchChain, ChainBuilder
from flowins.filter.compiling import Compiler, bucket
from flowins.filter.ekf import Gate, UpdateResult, ekf_update
from flowins.state import normalize_quaternions


def update(
    chain: ChainBuilder,
    *,
    H: Tensor,
    residual: Tensor,
    noise_cov: Tensor | None,
    gate: Gate | None = None,
    sequential: bool = False,
    valid: Tensor | None = None,
    likelihood: bool = True,
    dof: Tensor | None = None,
    noise_logdet: Tensor | None = None,
    **info: Any,
) -> UpdateResult:
    """Update one run's newest node with ``M`` measurement blocks of dimension ``d``.

    Args:
        chain: the run's chain; its newest node ``(D,)``, ``(D, D)`` is the prior.
        H ``(M, d, D)``, residual ``(M, d)``, noise_cov ``(M, d, d)``: the blocks,
            linearised at the prior mean; noise_cov None: whitened blocks (``R = I``), with
            ``noise_logdet`` ``(M,)`` the ``½ log det`` of each one's noise before the whitening
            (:func:`~flowins.filter.ekf.ekf_update`).
        gate: the innovation gate of each block (default: none).
        sequential: the blocks one after another (:func:`~flowins.filter.ekf.ekf_update`).
        valid ``(M,)`` bool: the blocks that carry a measurement (default: all).
        likelihood: whether the update adds its innovation likelihood when the chain keeps
            one; False for a pseudo-measurement, whose residual is no data.
        dof ``(M,)``: each block's degrees of freedom when fewer than ``d`` (a block padded with
            rows that carry nothing); they set its gate and its count of scalar measurements.
        info: the log entry's facts (``kind``, ``name``, ...); none: no log entry.

    Returns the :class:`~flowins.filter.ekf.UpdateResult`, its ``weight`` zero on invalid
    blocks.
    """
    if residual.ndim != 2:
        raise ValueError(f"update: residual must be (M, d) for one run, got {tuple(residual.shape)} "
                         "(update_rows updates rows of a batch)")
    result = update_rows(chain.batch, [chain.row], H=H.unsqueeze(0), residual=residual.unsqueeze(0),
                         noise_cov=None if noise_cov is None else noise_cov.unsqueeze(0), gate=gate,
                         sequential=sequential, valid=None if valid is None else valid.unsqueeze(0),
                         likelihood=likelihood, infos=[info] if info else None,
                         dof=None if dof is None else dof.unsqueeze(0),
                         noise_logdet=None if noise_logdet is None else noise_logdet.unsqueeze(0))
    return UpdateResult(*(None if t is None else t[0] for t in result))


def update_rows(
    chain: BatchChain,
    rows: Sequence[int],
    *,
    H: Tensor,
    residual: Tensor,
    noise_cov: Tensor | None,
    gate: Gate | None = None,
    sequential: bool = False,
    valid: Tensor | None = None,
    likelihood: bool = True,
    infos: Sequence[dict[str, Any]] | None = None,
    dof: Tensor | None = None,
    noise_logdet: Tensor | None = None,
    values: dict[str, Tensor] | None = None,
) -> UpdateResult:
    """:func:`update` of the rows ``rows`` of ``chain`` at once (``r`` of them).

    Shapes carry the rows first: H ``(r, M, d, D)``, residual ``(r, M, d)``, noise_cov
    ``(r, M, d, d)`` (or None, with noise_logdet ``(r, M)``: whitened blocks, as in :func:`update`),
    valid and dof ``(r, M)``; ``infos[i]`` is row ``rows[i]``'s log entry, completed by the
    update's NIS and accepted weight and by ``values`` (``(r,)`` tensors by name) when the logs are
    read (:meth:`~flowins.filter.chain.BatchChain.log_rows`). A row without a valid block keeps
    its node's Gaussian. Where a read costs (a GPU, ``torch.compile``) nothing is read back.
    """
    result = step_rows(chain, rows, H=H, residual=residual, noise_cov=noise_cov, gate=gate, sequential=sequential,
                       valid=valid, likelihood=likelihood, dof=dof, noise_logdet=noise_logdet)
    if infos is not None:
        values = {**(values or {}), **dict(zip(("nis", "accepted"), _summary(result, valid).unbind(-1)))}
    commit_rows(chain, rows, result.mean, result.cov, infos, updated=None if valid is None else valid.any(-1),
                values=values)
    return result


def step_rows(
    chain: BatchChain,
    rows: Sequence[int],
    *,
    H: Tensor,
    residual: Tensor,
    noise_cov: Tensor | None,
    gate: Gate | None = None,
    sequential: bool = False,
    valid: Tensor | None = None,
    likelihood: bool = True,
    prior: tuple[Tensor, Tensor] | None = None,
    dof: Tensor | None = None,
    noise_logdet: Tensor | None = None,
) -> UpdateResult:
    """The update of :func:`update_rows` without writing the chain: one step of an
    iterated update, whose result the caller writes with :func:`commit_rows`.

    ``prior``: the rows' newest mean ``(r, D)`` and covariance ``(r, D, D)`` when the caller
    holds them already (default: read from ``chain``); with ``likelihood`` (and the chain
    keeping one) the step adds its innovation likelihood to the chain.
    """
    if residual.ndim != 3 or residual.shape[0] != len(rows):
        raise ValueError(f"update_rows: residual must be (r, M, d) for the r = {len(rows)} rows, "
                         f"got {tuple(residual.shape)}")
    mean, cov = chain.newest(rows) if prior is None else prior
    keep = likelihood and chain.likelihood
    blocks = dict(H=H, residual=residual, noise_cov=noise_cov, valid=valid, dof=dof, noise_logdet=noise_logdet)
    if chain.compiler.enabled and chain.compiler.all_steps:
        result = _compiled_update(chain.compiler, mean, cov, rows=chain.rows, gate=gate, sequential=sequential,
                                  likelihood=keep, **blocks)
    else:
        result = gated_update(mean, cov, gate=gate, sequential=sequential, likelihood=keep, **blocks)
    chain.check_failed(result.failed, "update", rows)
    if keep:
        chain.add_likelihood(rows, *likelihood_sums(result, residual.shape[-1] if dof is None else dof))
    return result


def commit_rows(
    chain: BatchChain,
    rows: Sequence[int],
    mean: Tensor,
    cov: Tensor,
    infos: Sequence[dict[str, Any]] | None,
    *,
    updated: Tensor | None = None,
    values: dict[str, Tensor] | None = None,
) -> None:
    """Write the updated Gaussians ``mean`` ``(r, D)``, ``cov`` ``(r, D, D)`` as the newest
    nodes of the rows ``rows``, with their log entries ``infos`` and the entries' values still on
    the device (``values``, :meth:`~flowins.filter.chain.BatchChain.log_rows`). A row with
    ``updated[i]`` False ``(r,)`` keeps its node's Gaussian (it is written back as it was: the
    pass reads no flag)."""
    if updated is not None:
        prior_mean, prior_cov = chain.newest(rows)
        mean = torch.where(updated[:, None], mean, prior_mean)
        cov = torch.where(updated[:, None, None], cov, prior_cov)
    chain.update_rows(rows, mean, cov, infos, values=values)


def gated_update(mean: Tensor, cov: Tensor, *, H: Tensor, residual: Tensor, noise_cov: Tensor | None,
                 gate: Gate | None, sequential: bool, valid: Tensor | None, likelihood: bool,
                 dof: Tensor | None = None, noise_logdet: Tensor | None = None) -> UpdateResult:
    """The gated update of the prior ``(mean, cov)`` with the state's quaternions re-normalised,
    the weight of invalid blocks set to zero: a pure function of tensors (no chain, nothing
    read back; its ``failed`` flags for the caller to read)."""
    if valid is not None and valid.shape != residual.shape[:-1]:
        raise ValueError(f"update: valid must be {tuple(residual.shape[:-1])} (one flag per block of the "
                         f"residual {tuple(residual.shape)}), got {tuple(valid.shape)}")
    result = ekf_update(mean, cov, innovation=residual, H=H, noise_cov=noise_cov, gate=gate, sequential=sequential,
                        normalize=normalize_quaternions, likelihood=likelihood, dof=dof, noise_logdet=noise_logdet)
    if valid is None:
        return result
    # built field by field: torch 2.11's dynamo cannot trace a named tuple's _replace
    return UpdateResult(result.mean, result.cov, result.nis, result.weight * valid, result.nll, result.failed)


def _compiled_update(compiler: Compiler, mean: Tensor, cov: Tensor, *, rows: int, H: Tensor, residual: Tensor,
                     noise_cov: Tensor | None, valid: Tensor | None, dof: Tensor | None, noise_logdet: Tensor | None,
                     **options: Any) -> UpdateResult:
    """:func:`gated_update` through ``compiler`` at a fixed shape: the ``r`` rows grown to the
    chain's ``rows`` (copies of the first, every block invalid) and the ``M`` blocks to a power of
    two (zero Jacobian and residual, unit noise, invalid: an exact no-op); the result cut back to
    ``(r, M)``."""
    r, M, d = residual.shape
    grown_rows, grown_blocks = max(rows, r) - r, bucket(M, smallest=1) - M
    if valid is None:
        valid = torch.ones(r, M, dtype=torch.bool, device=residual.device)
    eye = torch.eye(d, dtype=residual.dtype, device=residual.device)

    def grow(t: Tensor | None, block: Tensor | float | bool) -> Tensor | None:
        """``t`` ``(r, M, ...)`` grown to ``(r + grown_rows, M + grown_blocks, ...)``."""
        if t is None:
            return None
        if grown_blocks:
            fill = torch.as_tensor(block, dtype=t.dtype, device=t.device).expand(r, grown_blocks, *t.shape[2:])
            t = torch.cat((t, fill), 1)
        return rows_of(t)

    def rows_of(t: Tensor) -> Tensor:
        return torch.cat((t, t[:1].expand(grown_rows, *t.shape[1:])), 0) if grown_rows else t

    valid = grow(valid, False)
    if grown_rows:
        valid[r:] = False
    out = compiler(gated_update, rows_of(mean), rows_of(cov), H=grow(H, 0.0), residual=grow(residual, 0.0),
                   noise_cov=grow(noise_cov, eye), valid=valid, dof=grow(dof, d),
                   noise_logdet=grow(noise_logdet, 0.0), **options)
    return UpdateResult(out.mean[:r], out.cov[:r], out.nis[:r, :M], out.weight[:r, :M],
                        None if out.nll is None else out.nll[:r, :M], None if out.failed is None else out.failed[:r])


def likelihood_sums(result: UpdateResult, dim: int | Tensor) -> tuple[Tensor, Tensor]:
    """``(nll, count)`` ``(...)``: the gate-weighted block likelihoods and scalar measurements
    (``dim`` the blocks' dimension, or each block's degrees of freedom ``(..., M)``)."""
    kept = result.weight.detach()
    count = (dim * kept).sum(-1) if isinstance(dim, Tensor) else dim * kept.sum(-1)
    return (kept * result.nll).sum(-1), count


def _summary(result: UpdateResult, valid: Tensor | None) -> Tensor:
    """``(..., 2)``: the NIS summed over the valid blocks and the accepted weight."""
    nis = result.nis if valid is None else torch.where(valid, result.nis, 0.0)
    return torch.stack((nis.sum(-1), result.weight.sum(-1)), -1).detach()
