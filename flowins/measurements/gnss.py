"""GNSS position measurement model.

    h(x) = p + C(q) ℓ        (antenna position in the local ENU frame, m)

with ``ℓ`` the antenna lever arm in the IMU frame (zero by default, as in the
paper), and noise ``R = s² diag(σ_h², σ_h², σ_v²)`` from the fix's reported
horizontal and vertical 1-σ accuracies, scaled by ``s`` (a tuning parameter, 1 by default).

GNSS errors are correlated in time (atmosphere, multipath, the receiver's own
filter: tens of seconds). A filter that takes them as white believes ``n`` fixes
average their errors down by ``n``. For a first-order Gauss-Markov error with
correlation time ``τ`` sampled every ``Δt`` (lag-one correlation ``ρ = exp(-Δt/τ)``)
the mean of ``n`` fixes has variance ``(σ²/n)(1 + ρ)/(1 - ρ)`` for large ``n``, so
:func:`correlation_inflation` scales each fix's ``R`` by that factor: the white-noise
filter then draws the information the fixes really hold (``τ = 0``: no change).
"""
from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Hashable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor
from torch.func import jacrev, vmap

from flowins.config import bounded, check_fields
from flowins.filter.chain import BatchChain, ChainBuilder, RowBatchEvent
from flowins.filter.ekf import Gate, chi2_quantile
from flowins.filter.updater import update, update_rows
from flowins.geometry import quaternion as quat
from flowins.measurements.gnss_heading import (
    HeadingAlignment,
    HeadingFit,
    fit_heading_batch,
    fit_record,
    heading_conditional_covariance,
    heading_jacobian,
    heading_noise,
    heading_transform,
)
from flowins.state import STATE, pose_slices, split


def gnss_position(x: Tensor, lever_arm_m: Tensor) -> Tensor:
    """``h(x)`` ``(..., 3)`` for states ``(..., D)`` and a lever arm ``(3,)``."""
    s = split(x)
    return s.p + quat.rotate(s.q, lever_arm_m.to(x.dtype).expand_as(s.p))


def gnss_jacobian(x: Tensor, lever_arm_m: Tensor) -> Tensor:
    """``∂h/∂x`` ``(..., 3, D)`` by ``torch.func.jacrev``."""
    jac = jacrev(gnss_position)
    if x.ndim == 1:
        return jac(x, lever_arm_m)
    flat = x.reshape(-1, x.shape[-1])
    return vmap(jac, in_dims=(0, None))(flat, lever_arm_m).reshape(*x.shape[:-1], 3, x.shape[-1])


def gnss_jacobian_analytic(x: Tensor, lever_arm_m: Tensor | None) -> Tensor:
    """Closed form of :func:`gnss_jacobian`: ``[I₃, 0, ∂(C(q)ℓ)/∂q, 0]`` ``(..., 3, D)``.

    ``lever_arm_m=None`` means a zero lever arm, whose ``∂/∂q`` block is zero.
    """
    H = x.new_zeros(*x.shape[:-1], 3, x.shape[-1])
    H[..., STATE.p] = torch.eye(3, dtype=x.dtype, device=x.device)
    if lever_arm_m is not None:
        H[..., STATE.q] = quat.rotate_jacobian(split(x).q, lever_arm_m.to(x.dtype).expand(*x.shape[:-1], 3))
    return H


def gnss_noise(h_acc_m: Tensor, v_acc_m: Tensor, scale: float | Tensor = 1.0) -> Tensor:
    """``R`` ``(..., 3, 3)`` from horizontal and vertical 1-σ accuracies ``(...)``, on their
    device (a learned ``scale`` on another device is moved there, with its gradient)."""
    if isinstance(scale, Tensor):
        scale = scale.to(device=h_acc_m.device)
    sigmas = torch.stack((h_acc_m, h_acc_m, v_acc_m), dim=-1) * scale
    return torch.diag_embed(sigmas * sigmas)


def correlation_inflation(t_s: Tensor, correlation_s: float | Tensor) -> Tensor:
    """Variance factor ``(1 + ρ) / (1 - ρ)`` ``(G,)`` per fix, ``ρ = exp(-Δt / τ)``.

    ``Δt`` is the time since the previous fix (for the first, to the next one);
    ``τ = correlation_s = 0`` gives ones.
    """
    t = torch.as_tensor(t_s, dtype=torch.float64)
    tau = torch.as_tensor(correlation_s, dtype=torch.float64)
    if bool((tau < 0).any()):
        raise ValueError(f"correlation_s (filter.gnss_correlation_s), the GNSS error correlation time, must be "
                         f">= 0 s, got {float(tau)}")
    if t.shape[0] < 2 or float(tau) == 0.0:
        return torch.ones_like(t)
    dt = torch.diff(t)
    dt = torch.cat((dt[:1], dt))
    rho = torch.exp(-dt / tau)
    return (1.0 + rho) / (1.0 - rho)


# ---------------------------------------------------------------------------
# The GNSS updater: a fix as a filter event, and what follows a run of rejected fixes
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class GnssRecovery:
    """What follows a run of GNSS fixes the gate rejected (config ``filter.gnss_recovery``).

    A filter that has drifted further than its covariance admits rejects every later
    fix, and never comes back. After ``after_rejections`` consecutive rejections the
    filter's position is reset to the latest fix, with that fix's covariance; with
    ``velocity`` its velocity too, to the mean velocity of the rejected run's fixes
    (σ² = (R_first + R_last) / Δt² + (½ ``acceleration_sigma_mps2`` Δt)²). The
    augmented previous-frame position moves with the position, so the flow's relative
    pose is kept. The reset is a linear step ``x ↦ A x + b`` with noise ``Q`` in the
    filter's chain, so the smoother sees it as a jump and does not smooth across it.
    0 switches recovery off.

    The innovations also tell an inconsistent filter that still passes the gate: when
    the NIS of the last ``nis_window`` accepted fixes sums above the χ²(3 ``nis_window``)
    quantile ``nis_probability``, the filter is reset the same way (0, the default: off;
    on the simulated walk, whose urban-canyon GNSS errors are correlated over seconds,
    a window of 10 fired on a consistent filter and made ``ins_gnss`` worse). A reset
    adds ``acc_bias_sigma_mps2`` and ``gyro_bias_sigma_rps`` to the biases' σ, so a
    filter that drifted off on biases it trusted too much can learn them again.
    """

    after_rejections: int = bounded(3, minimum=0)
    velocity: bool = True
    acceleration_sigma_mps2: float = bounded(1.0, minimum=0.0)
    #: added to the IMU biases' σ at a reset: a filter that drifted off has biases it trusts too much
    acc_bias_sigma_mps2: float = bounded(0.1, minimum=0.0)
    gyro_bias_sigma_rps: float = bounded(2e-3, minimum=0.0)
    nis_window: int = bounded(0, minimum=0)
    nis_probability: float = bounded(1 - 1e-6, above=0.0, below=1.0)

    def __post_init__(self) -> None:
        check_fields(self)


def reset_matrices(mean: Tensor, fixes: list[tuple[float, Tensor, Tensor]], recovery: GnssRecovery
                   ) -> tuple[Tensor, Tensor, Tensor, bool]:
    """``(A (D, D), b (D,), Q (D, D), velocity_reset)`` of the reset to the last of
    ``fixes`` ``[(t_s, z (3,), R (3, 3)), ...]`` (:class:`GnssRecovery`) for a state ``mean``
    ``(D,)`` (:func:`reset_rows` of one row)."""
    (t_first, z_first, R_first), (t_last, z, R) = fixes[0], fixes[-1]
    times = torch.tensor([[t_first], [t_last]], dtype=torch.float64, device=mean.device)
    A, b, Q, with_velocity = reset_rows(mean[None], times[0], z_first[None], R_first[None], times[1], z[None], R[None],
                                        recovery)
    return A[0], b[0], Q[0], bool(with_velocity[0])


def reset_rows(mean: Tensor, t_first: Tensor, z_first: Tensor, R_first: Tensor, t_last: Tensor, z: Tensor, R: Tensor,
               recovery: GnssRecovery) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(A (r, D, D), b (r, D), Q (r, D, D), velocity_reset (r,))`` of the resets of ``r`` rows
    (:class:`GnssRecovery`), each to its last fix ``(t_last (r,) float64, z (r, 3), R (r, 3, 3))``
    from the first of its run ``(t_first, z_first, R_first)``, for the states ``mean`` ``(r, D)``:
    ``p := z`` and every cloned pose's position moves with it (``p_k := p_k - p + z``), so the
    relative poses the flow measures are kept; with ``recovery.velocity`` and fixes apart in
    time, ``v := (z - z_first) / Δt``. Nothing is read back from the device."""
    r, dim = mean.shape
    like = {"dtype": mean.dtype, "device": mean.device}
    eye3 = torch.eye(3, **like)
    A = torch.eye(dim, **like).repeat(r, 1, 1)
    b = mean.new_zeros(r, dim)
    Q = mean.new_zeros(r, dim, dim)
    z, R, z_first, R_first = (t.to(mean) for t in (z, R, z_first, R_first))
    positions = [p for p, _ in pose_slices(dim)]  # p, then each clone's
    A[:, STATE.p, STATE.p] = 0.0
    for clone in positions[1:]:
        A[:, clone, STATE.p] = -eye3
    for rows in positions:
        b[:, rows] = z
        for cols in positions:
            Q[:, rows, cols] = R
    span64 = t_last - t_first
    with_velocity = (span64 > 0) & recovery.velocity
    span = torch.where(with_velocity, span64, 1.0).to(mean.dtype)[:, None, None]
    off = with_velocity.to(mean.dtype)[:, None, None]
    A[:, STATE.v, STATE.v] = (1.0 - off) * eye3
    b[:, STATE.v] = off[:, 0] * (z - z_first) / span[:, 0]
    Q[:, STATE.v, STATE.v] = off * ((R + R_first) / span**2 + (0.5 * recovery.acceleration_sigma_mps2 * span) ** 2 * eye3)
    Q[:, STATE.b_a, STATE.b_a] = recovery.acc_bias_sigma_mps2**2 * eye3
    Q[:, STATE.b_w, STATE.b_w] = recovery.gyro_bias_sigma_rps**2 * eye3
    return A, b, Q, with_velocity


@dataclass(frozen=True)
class GnssFix(RowBatchEvent):
    """A GNSS position fix ``z`` (local ENU, m) with noise ``R`` ``(3, 3)``.

    With ``heading`` enabled, a fix that finds the filter's yaw unknown is held back
    until the held fixes can set it (:mod:`flowins.measurements.gnss_heading`); the fixes that
    set it are not applied again as position updates.
    """

    time_s: float
    position_m: Tensor  # (3,)
    noise_cov: Tensor  # (3, 3)
    gate: Gate = field(default_factory=Gate)
    lever_arm_m: Tensor | None = None
    name: str = "GNSS fix"
    heading: HeadingAlignment | None = None
    recovery: GnssRecovery | None = None
    #: ``time_s`` as a float64 tensor on the filter's device (:meth:`place`; None: made when needed)
    time_t: Tensor | None = None

    def batch_key(self) -> Hashable:
        """Fixes with the same gate, heading alignment, recovery and lever arm act together (a
        run's fixes share them, as do the runs of one navigation config)."""
        return (GnssFix, id(self.gate), id(self.heading), id(self.recovery), id(self.lever_arm_m))

    @classmethod
    def place(cls, fixes: list[GnssFix], like: Tensor) -> list[GnssFix]:
        """The fixes with their positions and noises in ``like``'s dtype and device and their
        times there in float64: one copy for each, each fix's a view of it."""
        if all(f.time_t is not None and f.position_m.dtype == like.dtype and f.position_m.device == like.device
               for f in fixes):
            return list(fixes)
        z = torch.stack([f.position_m for f in fixes]).to(like)
        R = torch.stack([f.noise_cov for f in fixes]).to(like)
        t = torch.tensor([f.time_s for f in fixes], dtype=torch.float64).to(like.device)
        return [dataclasses.replace(f, position_m=z[i], noise_cov=R[i], time_t=t[i]) for i, f in enumerate(fixes)]

    @classmethod
    def apply_batch(cls, chain: BatchChain, rows: Sequence[int], fixes: Sequence[GnssFix]) -> None:
        """The fixes ``fixes[i]`` (one gate, heading alignment, recovery) on the rows ``rows[i]``:
        those held for the heading are held (:func:`_hold_for_heading`), the others update as one."""
        heading = fixes[0].heading
        applied = list(range(len(rows)))
        if heading is not None and heading.enabled:
            applied = _hold_for_heading(chain, rows, fixes, heading)
        if applied:
            _update_rows(chain, [rows[i] for i in applied], [fixes[i] for i in applied])

    def _recover(self, chain: ChainBuilder, *, rejected: bool, nis: float) -> None:
        """Reset after ``after_rejections`` consecutive rejections, or when the last
        ``nis_window`` fixes' NIS say the filter is inconsistent (:class:`GnssRecovery`)."""
        r = self.recovery
        if r is None:
            return
        fix = (self.time_s, self.position_m, self.noise_cov)  # moved to the filter's device at a reset
        run = chain.memory.setdefault("gnss_rejected", [])
        recent = chain.memory.setdefault("gnss_recent", [])
        run[:] = run + [fix] if rejected else []
        if not rejected:
            recent[:] = (recent + [(fix, nis)])[-r.nis_window:] if r.nis_window else []
        if r.after_rejections and len(run) >= r.after_rejections:
            self._reset(chain, run, why="rejected", rejected=len(run))
        elif r.nis_window and len(recent) == r.nis_window and sum(n for _, n in recent) > chi2_quantile(
                r.nis_probability, 3 * r.nis_window):
            self._reset(chain, [f for f, _ in recent], why="inconsistent",
                        mean_nis=sum(n for _, n in recent) / r.nis_window)
        else:
            return
        run.clear()
        recent.clear()

    def _reset(self, chain: ChainBuilder, fixes: list, *, why: str, **facts) -> None:
        mean = chain.mean
        fixes = [(t, z.to(mean), R.to(mean)) for t, z, R in fixes]
        offset = float(torch.linalg.vector_norm(fixes[-1][1] - mean[STATE.p]).detach())
        A, b, Q, with_velocity = reset_matrices(mean, fixes, self.recovery)
        chain.linear_predict(A, Q, b, kind="gnss_reset", name=self.name, why=why, offset_m=offset,
                             velocity=with_velocity, **facts)


def _update_rows(chain: BatchChain, rows: list[int], fixes: list[GnssFix]) -> None:
    """The position updates of ``fixes[i]`` on the rows ``rows[i]`` as one update, then each
    row's recovery (:class:`GnssRecovery`) from its fix's NIS and gate."""
    first = fixes[0]
    mean, _ = chain.newest(rows)
    lever = None if first.lever_arm_m is None else first.lever_arm_m.to(mean)
    H = gnss_jacobian_analytic(mean, lever)
    predicted = mean[:, STATE.p] if lever is None else gnss_position(mean, lever)
    z = torch.stack([fix.position_m for fix in fixes]).to(mean)
    R = torch.stack([fix.noise_cov for fix in fixes]).to(mean)
    result = update_rows(chain, rows, H=H.unsqueeze(1), residual=(z - predicted).unsqueeze(1),
                         noise_cov=R.unsqueeze(1), gate=first.gate, infos=[{"kind": "gnss", "name": fix.name} for fix in fixes])
    recovery = first.recovery
    if recovery is None:
        return
    if recovery.nis_window:  # the window's NIS sums decide on the host: one read per fix
        for row, fix in zip(rows, fixes):
            entry = chain.logs[row][-1]
            fix._recover(chain.row(row), rejected=entry["accepted"] < 0.5, nis=entry["nis"])
    elif recovery.after_rejections:
        _reset_after_rejections(chain, rows, fixes, z, R, rejected=result.weight[:, 0] < 0.5)


def _reset_after_rejections(chain: BatchChain, rows: list[int], fixes: list[GnssFix], z: Tensor, R: Tensor, *,
                            rejected: Tensor) -> None:
    """Each row's run of rejected fixes, counted on the device, and its reset where the run reaches
    ``after_rejections`` (:class:`GnssRecovery`): a node at the fix's time on every row, the reset
    where a row resets and the identity elsewhere (:func:`reset_rows`; the smoother's recursion
    through an identity node is the one without it), its ``gnss_reset`` log entry kept where it
    reset. Nothing is read back from the device."""
    recovery = fixes[0].recovery
    mean, _ = chain.newest(rows)
    t = torch.stack([fix.time_t if fix.time_t is not None else
                     torch.tensor(fix.time_s, dtype=torch.float64, device=mean.device) for fix in fixes])
    count = chain.row_state("gnss_rejected", rows)
    state = {name: chain.row_state(f"gnss_rejected_{name}", rows, shape=shape, dtype=dtype)
             for name, shape, dtype in (("t", (), torch.float64), ("z", (3,), mean.dtype), ("R", (3, 3), mean.dtype))}
    starts = rejected & (count == 0)  # a run's first fix: the reset's velocity spans the run
    state = {name: torch.where(starts.view(-1, *[1] * (now.ndim - 1)), now, state[name])
             for name, now in (("t", t), ("z", z), ("R", R))}
    count = torch.where(rejected, count + 1, 0)
    reset = count >= recovery.after_rejections
    A, b, Q, with_velocity = reset_rows(mean, state["t"], state["z"], state["R"], t, z, R, recovery)
    eye = torch.eye(mean.shape[-1], dtype=mean.dtype, device=mean.device)
    where = reset[:, None, None]
    chain.linear_predict_rows(rows, torch.where(where, A, eye), torch.where(where, Q, 0.0), torch.where(reset[:, None], b, 0.0),
                              [{"kind": "gnss_reset", "name": fix.name, "why": "rejected"} for fix in fixes],
                              values={"offset_m": torch.linalg.vector_norm(z - mean[:, STATE.p], dim=-1),
                                      "velocity": with_velocity, "rejected": count}, keep=reset)
    chain.set_row_state("gnss_rejected", rows, torch.where(reset, 0, count))
    for name, values in state.items():
        chain.set_row_state(f"gnss_rejected_{name}", rows, values)


def _hold_for_heading(chain: BatchChain, rows: Sequence[int], fixes: Sequence[GnssFix],
                      a: HeadingAlignment) -> list[int]:
    """Hold each fix while its row's yaw is unknown; align a row when its held fixes allow.
    Returns the indices ``i`` whose fix is applied as a position update.

    The filter's track is worth waiting for only while it drifts less than a fix is
    off: once its position variance (given its yaw) has grown since the first held
    fix by more than this fix's variance, it aligns with what it holds or, if that
    cannot set the heading, gives up and applies fixes as they come from then on. The
    rows' variances, and the fits of the rows that may align, are computed together.
    """
    applied, waiting = [], []
    for i, row in enumerate(rows):
        (applied if chain.memories[row].get("heading") in ("known", "given up") else waiting).append(i)
    if not waiting:
        return applied
    mean, cov = chain.newest([rows[i] for i in waiting])
    xy = slice(STATE.p.start, STATE.p.start + 2)
    h = heading_jacobian(mean)
    yaw_var = (h * (cov @ h.unsqueeze(-1)).squeeze(-1)).sum(-1)
    filter_var = torch.diagonal(heading_conditional_covariance(mean, cov, xy), dim1=-2, dim2=-1).mean(-1)
    noise = torch.stack([fixes[i].noise_cov for i in waiting]).to(mean)
    fix_var = torch.diagonal(noise[:, :2, :2], dim1=-2, dim2=-1).mean(-1)
    values = torch.stack((yaw_var, filter_var, fix_var), -1).detach().tolist()
    holding, drifted = [], {}
    for k, i in enumerate(waiting):
        memory, fix = chain.memories[rows[i]], fixes[i]
        held = memory.setdefault("heading_fixes", [])
        yaw, f_var, x_var = values[k]
        if not held and yaw <= a.unknown_yaw_sigma_rad**2:
            memory["heading"] = "known"
            applied.append(i)
            continue
        x, y = fix.position_m[:2].tolist()
        if not held:
            memory["heading_first"] = (f_var, x, y)
            memory["heading_baseline_m"] = 0.0
        first_var, x0, y0 = memory["heading_first"]
        drifted[i] = max(f_var - first_var, 0.0) > x_var
        memory["heading_baseline_m"] = max(memory["heading_baseline_m"], math.hypot(x - x0, y - y0))
        held.append((mean[k, xy], fix.position_m[:2], filter_var[k], fix_var[k]))  # the fix where it is
        holding.append(i)
    fits, sigmas = _fit_held(chain, rows, [i for i in holding
                                           if len(chain.memories[rows[i]]["heading_fixes"]) >= a.min_fixes
                                           and chain.memories[rows[i]]["heading_baseline_m"] >= a.baseline_m], a,
                             drifted=drifted)
    for i in holding:
        chain_row, fix = chain.row(rows[i]), fixes[i]
        fit = fits.get(i)
        if fit is not None:
            _align(chain_row, fit, fix, a)
        elif drifted[i]:
            # the fixes held so far are in the past and are not applied; this one and
            # every later one are, as they come
            chain_row.memory["heading"] = "given up"
            fitted = "" if i not in sigmas else (
                f", their fit's σ {sigmas[i]:.3f} rad > filter.gnss_heading.drifted_max_sigma_rad="
                f"{a.drifted_limit_rad:g}")
            chain_row.log.append({"t_s": chain_row.time_s, "kind": "heading", "name": fix.name, "status": "given up",
                                  "fixes": len(chain_row.memory["heading_fixes"]) - 1,
                                  **({"fit_sigma_rad": sigmas[i]} if i in sigmas else {}),
                                  "reason": "the track drifted more than a fix before the held fixes could set the "
                                  f"heading{fitted}; they are left out, this fix and the later ones are applied as "
                                  "they come"})
            applied.append(i)
        else:
            chain_row.log.append({"t_s": chain_row.time_s, "kind": "gnss", "name": fix.name, "accepted": 0.0,
                                  "status": "held for heading"})
    return sorted(applied)


def _fit_held(chain: BatchChain, rows: Sequence[int], which: list[int], a: HeadingAlignment, *,
              drifted: dict[int, bool]) -> tuple[dict[int, HeadingFit], dict[int, float]]:
    """The heading fits of the held fixes of the rows ``rows[i]``, ``i`` in ``which``, fitted
    together, and every fit's σ_ψ; only the fits whose σ_ψ is at most ``max_sigma_rad`` are
    returned, or at most ``drifted_max_sigma_rad`` for a row whose track has drifted
    (``drifted[i]``)."""
    if not which:
        return {}, {}
    held = [chain.memories[rows[i]]["heading_fixes"] for i in which]
    counts = [len(h) for h in held]
    N, pad = max(counts), sum(counts)
    starts = [0, *itertools.accumulate(counts[:-1])]  # each row's first entry in the flat stack
    index = torch.tensor([[start + j if j < c else pad for j in range(N)] for start, c in zip(starts, counts)])

    def padded(part: int) -> Tensor:
        """Entry ``part`` of every row's held fixes, ``(R, N, ...)``, a row's missing ones set to
        one: one stack for all rows (not one per row: on a GPU each is a kernel)."""
        flat = torch.stack([entry[part] for h in held for entry in h])
        flat = torch.cat((flat, flat.new_ones(1, *flat.shape[1:])))
        return flat[index.to(flat.device)]

    filter_xy = padded(0)
    fix_xy = padded(1).to(filter_xy)
    var = padded(2) + padded(3).to(filter_xy)
    fit = fit_heading_batch(filter_xy, fix_xy, var, counts, outlier_probability=a.outlier_probability)
    sigma = fit.sigma_rad.detach().tolist()
    fits = {i: HeadingFit(*(part[k] for part in fit[:-1]), fit.used[k, : counts[k]])
            for k, i in enumerate(which)
            if sigma[k] <= (a.drifted_limit_rad if drifted[i] else a.max_sigma_rad)}
    return fits, dict(zip(which, sigma))


def _align(chain: ChainBuilder, fit: HeadingFit, fix: GnssFix, a: HeadingAlignment) -> None:
    """Set the row's heading from ``fit``: 1. condition on the filter's own heading; 2. rotate
    into the fixes' frame (:mod:`flowins.measurements.gnss_heading`)."""
    mean = chain.mean
    h = heading_jacobian(mean).reshape(1, 1, -1)
    sigma_c = torch.as_tensor(a.condition_sigma_rad, dtype=mean.dtype, device=mean.device)
    update(chain, H=h, residual=mean.new_zeros(1, 1), noise_cov=(sigma_c**2).reshape(1, 1, 1), likelihood=False)
    A, b = heading_transform(fit, dtype=mean.dtype, dim=mean.shape[-1])
    Q = heading_noise(A @ chain.mean + b, fit)
    record = fit_record(fit)
    chain.change_frame(A, Q, b, kind="heading", name=fix.name, status="aligned",
                       **{k: record[k] for k in ("yaw_rad", "sigma_rad", "fixes", "outliers")}, fit=record)
    chain.memory["heading"] = "known"
    chain.log.append({"t_s": chain.time_s, "kind": "gnss", "name": fix.name, "accepted": 0.0,
                      "status": "set the heading"})


def gnss_fixes(
    t_s: Tensor,
    position_m: Tensor,
    noise_cov: Tensor,
    *,
    gate: Gate | None = None,
    lever_arm_m: Tensor | None = None,
    name: str = "GNSS",
    heading: HeadingAlignment | None = None,
    recovery: GnssRecovery | None = None,
) -> list[GnssFix]:
    """One :class:`GnssFix` per row of ``t_s (G,)``, ``position_m (G, 3)``, ``noise_cov (G, 3, 3)``."""
    gate = gate or Gate()
    return [
        GnssFix(float(t_s[i]), position_m[i], noise_cov[i], gate, lever_arm_m, f"{name} row {i}", heading, recovery)
        for i in range(t_s.shape[0])
    ]
