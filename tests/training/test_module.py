"""The learner's selection of the best validation: the start competes with every epoch."""
import math

import pytest

from flowins.navigation import NavigationConfig
from flowins.training.module import FilterLearner
from flowins.training.parameters import NAMES, FilterParameters


def _entry(label, score, raw):
    return {"label": label, "step": 0, "rmse_m": {"ins_gnss": score}, "score": score, "raw": raw}


def test_select_best_loads_the_lowest_validation_and_prefers_the_earliest_on_a_tie():
    params = FilterParameters({n: 0.3 if n == "dropout_p" else 0.5 + i for i, n in enumerate(NAMES)})
    learner = FilterLearner(params, NavigationConfig(), methods=["ins_gnss"])
    with pytest.raises(ValueError, match="no validation"):
        learner.select_best()
    start = {n: float(params.raw[n].detach()) for n in NAMES}
    moved = {n: v + 0.5 for n, v in start.items()}
    other = {n: v - 0.25 for n, v in start.items()}
    learner.history = [_entry("start", 1.0, start), _entry("epoch 1", math.inf, moved),
                       _entry("epoch 2", 0.5, other), _entry("epoch 3", 0.5, moved)]
    chosen = learner.select_best()
    assert chosen["label"] == "epoch 2"
    assert {n: float(params.raw[n].detach()) for n in NAMES} == other
    # an epoch no better than the start leaves the start
    learner.history = [_entry("start", 0.7, start), _entry("epoch 1", 0.7, moved), _entry("epoch 2", 0.9, other)]
    assert learner.select_best()["label"] == "start"
    assert {n: float(params.raw[n].detach()) for n in NAMES} == start
