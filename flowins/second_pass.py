"""The smoother's second filter pass, for runs whose GNSS fixes set the heading.

The first pass holds the fixes back until they set the heading, and they never update it;
a second pass from the same start, knowing the heading from its first sample, applies every
fix, so the RTS smoother runs on a track that used them all (``filter.gnss_heading.second_pass``).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, Protocol

from flowins.filter.augmentation import with_window
from flowins.filter.chain import FilterTrack
from flowins.filter.compiling import Compiler
from flowins.filter.runner import FilterInput, run_filters
from flowins.filter.smoother import rts_smooth_batch
from flowins.measurements.gnss_heading import aligned_prior_covariance, fit_from_record
from flowins.state import STATE_DIM, window_size


class PassConfig(Protocol):
    """What the second pass reads of a :class:`~flowins.navigation.NavigationConfig`."""

    gnss_heading: Any  # HeadingAlignment: second_pass, condition_sigma_rad

    def filter_settings(self) -> dict: ...


def heading_fit_record(track: FilterTrack) -> dict[str, Any] | None:
    """The fit of the GNSS heading alignment that set ``track``'s heading (its log entry's
    ``fit``), or None where no fix set it."""
    for entry in track.log:
        if entry.get("kind") == "heading" and entry.get("status") == "aligned" and "fit" in entry:
            return entry["fit"]
    return None


def smoother_tracks(inputs: Sequence[FilterInput], tracks: Sequence[FilterTrack], config: PassConfig, *,
                    progress: bool = False, compiler: Compiler | None = None
                    ) -> tuple[list[FilterTrack], list[dict[str, Any] | None]]:
    """The filter tracks the RTS smoother runs on, one per run of ``inputs`` (filtered into
    ``tracks``), and for each run what was chosen (None: nothing to choose). A run's track is its
    own, or, for a run whose GNSS fixes set its heading (``filter.gnss_heading.second_pass``),
    a second filter pass from the same start. The first pass holds the fixes back until they set
    the heading, and they never update it; the second knows the heading from its first sample
    and applies every fix, so the smoother uses them all.

    The second pass starts at the first pass's smoothed mean at the start (the smoother carries
    the alignment back through the held stretch, where the filter's yaw moved while it was
    unknown, so the fit's rotation alone does not give the start's heading), with the run's own
    prior covariance aligned by the fit (:func:`~flowins.measurements.gnss_heading.aligned_prior_covariance`):
    it claims no more certainty than the prior and the fit (the smoothed covariance would count
    every measurement twice). A second pass that had to reset to the fixes more
    often than the first (``filter.gnss_recovery``: it drifted off them) is not used: the
    smoother runs on the first. All such runs go as one batch; the start carries no gradient
    through the first pass. ``progress``: report the second pass's progress; ``compiler``: how
    its events run their pure steps, as the first pass's (``filter.compile``).
    """
    out, which = list(tracks), [None] * len(tracks)
    if not config.gnss_heading.second_pass:
        return out, which
    again = [(i, record) for i, record in enumerate(heading_fit_record(t) for t in tracks) if record is not None]
    if not again:
        return out, which
    rows = []
    first = rts_smooth_batch([tracks[i] for i, _ in again], marginal=STATE_DIM)
    for (i, record), smoothed in zip(again, first):
        run = inputs[i]
        fit = fit_from_record(record, dtype=run.mean0.dtype, device=run.mean0.device)
        smoothed = smoothed.mean[0].detach()
        mean0 = with_window(smoothed, run.cov0[:STATE_DIM, :STATE_DIM], window_size(run.mean0.shape[-1]))[0]
        cov0 = aligned_prior_covariance(run.mean0, run.cov0, mean0, fit,
                                        condition_sigma_rad=config.gnss_heading.condition_sigma_rad)
        rows.append(dataclasses.replace(run, mean0=mean0, cov0=cov0))
    passes = run_filters(rows, **config.filter_settings(), progress=progress, description="smoother's second pass",
                         compiler=compiler)
    for (i, _), track in zip(again, passes):
        resets_first, resets_second = _resets(tracks[i]), _resets(track)
        if resets_second > resets_first:
            which[i] = {"pass": "first", "reason": f"the second pass reset to the fixes {_times(resets_second)}, the "
                        f"first {_times(resets_first)} (filter.gnss_recovery)"}
        else:
            out[i] = track
            which[i] = {"pass": "second", "reason": "the held fixes set the heading; the smoother's pass knows it "
                        "from the start and applies every fix"}
    return out, which


def _times(n: int) -> str:
    return {0: "never", 1: "once", 2: "twice"}.get(n, f"{n} times")


def _resets(track: FilterTrack) -> int:
    return sum(1 for e in track.log if e.get("kind") == "gnss_reset")
