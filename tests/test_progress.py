"""flowins.progress: off a terminal, one log line per tenth of the work, not one per item."""
from __future__ import annotations

import logging

from flowins.progress import Progress, progress


def test_off_a_terminal_progress_logs_each_tenth_once(caplog):
    caplog.set_level(logging.INFO, logger="flowins")
    items = list(progress(range(2384), description="simulate frames", unit="frame", terminal=False,
                              min_seconds=0.0))
    assert items == list(range(2384))  # every item comes through, in order
    lines = [r.getMessage() for r in caplog.records if r.name == "flowins"]
    assert len(lines) == 10
    percents = [int(line.split(": ")[1].split("%")[0]) for line in lines]
    assert percents == [10, 20, 30, 40, 50, 60, 70, 80, 90, 100]
    assert lines[-1].startswith("simulate frames: 100% (2384/2384 frames, ")


def test_a_batch_update_that_crosses_several_tenths_reports_once(caplog):
    caplog.set_level(logging.INFO, logger="flowins")
    bar = Progress(total=10, description="dense flow", unit="pair", terminal=False, min_seconds=0.0)
    bar.update(4)
    bar.update(6)
    bar.close()
    assert [r.getMessage().split(" (")[0] for r in caplog.records] == ["dense flow: 40%", "dense flow: 100%"]


def test_disabled_or_empty_progress_says_nothing(caplog):
    caplog.set_level(logging.INFO, logger="flowins")
    assert list(progress([1, 2], description="x", enabled=False, terminal=False)) == [1, 2]
    assert list(progress([], description="y", terminal=False)) == []
    assert caplog.records == []


def test_work_done_before_min_seconds_says_nothing_and_later_tenths_do(caplog, monkeypatch):
    import flowins.progress as module

    clock = iter([0.0, 1.0, 2.0, 7.0, 8.0])  # start, then one reading per update
    monkeypatch.setattr(module.time, "perf_counter", lambda: next(clock))
    caplog.set_level(logging.INFO, logger="flowins")
    bar = Progress(total=4, description="filter", unit="update", terminal=False, min_seconds=5.0)
    for _ in range(4):
        bar.update(1)
    assert [r.getMessage().split(" (")[0] for r in caplog.records] == ["filter: 75%", "filter: 100%"]
