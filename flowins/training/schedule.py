"""The training schedule: learning rate per optimiser step and window length per epoch.

Pure functions of the step and epoch counters, so a run is reproducible and a test can
compare them with their closed forms:

* :func:`learning_rate`: a linear warm-up from ``lr / 10`` over the first ``warmup_steps``
  optimiser steps (Adam's first steps, with its moment estimates still empty, are the
  largest), then a cosine decay over the epochs from ``lr`` at the first epoch to
  ``lr_final`` at the last, so that the last epochs refine instead of jumping around;
* :func:`window_length`: the window curriculum. The truncated-backpropagation window of
  epoch ``e`` is ``curriculum[e]`` while the list lasts, then ``window_s``. Short windows
  first: from a badly tuned start a long window drifts far, and its loss, and gradient,
  are dominated by that drift.
"""
from __future__ import annotations

import math
from collections.abc import Sequence


def learning_rate(step: int, epoch: int, *, lr: float, lr_final: float, warmup_steps: int,
                  epochs: int | None) -> float:
    """Adam's learning rate at optimiser step ``step`` (0-based, counted over the whole
    run) in epoch ``epoch`` (0-based) of ``epochs`` (None or < 1: no decay).

        warm-up  w(s) = 0.1 + 0.9 min(1, (s + 1) / warmup_steps)   (1 without warm-up)
        decay    d(e) = lr_final + (lr - lr_final) (1 + cos(π e / (epochs - 1))) / 2
        rate     d(e) w(s)
    """
    if step < 0 or epoch < 0:
        raise ValueError(f"learning_rate: step and epoch must be >= 0, got {step}, {epoch}")
    warm = 1.0 if warmup_steps <= 0 else 0.1 + 0.9 * min(1.0, (step + 1) / warmup_steps)
    if epochs is None or epochs <= 1:
        return lr * warm
    phase = min(epoch, epochs - 1) / (epochs - 1)
    return (lr_final + (lr - lr_final) * 0.5 * (1.0 + math.cos(math.pi * phase))) * warm


def window_length(epoch: int, *, window_s: float, curriculum: Sequence[float] = ()) -> float:
    """The window (s) of epoch ``epoch`` (0-based): ``curriculum[epoch]`` while it lasts, then ``window_s``."""
    return float(curriculum[epoch]) if epoch < len(curriculum) else float(window_s)
