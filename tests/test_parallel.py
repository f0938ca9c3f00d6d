"""flowins.parallel: an even split of the work (against the best split, found by brute force), and
calls in worker processes that return what the calls return here, in order, with their errors and
log records."""
import functools
import itertools
import logging
import os
import random

import pytest

from flowins import progress
from flowins.parallel import run_in_processes, run_parts, split_by_load


def best_split(loads, parts):
    """The least possible largest group load, over every assignment of the loads to ``parts`` groups."""
    best = float("inf")
    for assignment in itertools.product(range(parts), repeat=len(loads)):
        totals = [0.0] * parts
        for load, group in zip(loads, assignment):
            totals[group] += load
        best = min(best, max(totals))
    return best


@pytest.mark.parametrize("seed", range(12))
def test_split_by_load_uses_every_index_once_within_graham_s_bound_of_the_best_split(seed):
    rng = random.Random(seed)
    n, parts = rng.randint(1, 7), rng.randint(1, 3)
    loads = [rng.choice([rng.uniform(0, 10), float(rng.randint(1, 4))]) for _ in range(n)]
    groups = split_by_load(loads, parts)
    assert len(groups) == min(parts, n) and all(groups)
    assert sorted(i for group in groups for i in group) == list(range(n))
    assert all(group == sorted(group) for group in groups)
    assert [group[0] for group in groups] == sorted(group[0] for group in groups)
    largest = max(sum(loads[i] for i in group) for group in groups)
    m = len(groups)
    assert largest <= (4 / 3 - 1 / (3 * m)) * best_split(loads, m) + 1e-9


def test_split_by_load_of_equal_loads_deals_them_out_evenly_and_checks_its_arguments():
    assert split_by_load([5.0] * 8, 2) == [[0, 2, 4, 6], [1, 3, 5, 7]]
    assert split_by_load([1.0, 9.0, 1.0], 5) == [[0], [1], [2]]
    with pytest.raises(ValueError, match="parts must be >= 1"):
        split_by_load([1.0], 0)
    with pytest.raises(ValueError, match="loads must be numbers >= 0"):
        split_by_load([1.0, float("nan")], 2)


@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_calls_in_workers_return_what_they_return_here_in_order(method):
    # a flowins function, so that a spawned worker imports it as this process does
    parts = [([4.0, 1.0, 3.0, 2.0], 2), ([1.0] * 5, 3), ([7.0], 4)]
    assert run_in_processes(split_by_load, parts, method=method) == [split_by_load(*args) for args in parts]


def _sums_and_process(xs, ys):
    return [(x * 10 + y, os.getpid()) for x, y in zip(xs, ys)]


def test_parts_run_in_workers_come_back_in_the_items_order_and_a_short_part_is_an_error():
    xs, ys = list(range(7)), list(range(7, 0, -1))
    parts = split_by_load([float(y) for y in ys], 3)  # not contiguous: each part gathers from the whole list
    assert any(part != list(range(part[0], part[-1] + 1)) for part in parts)
    got = run_parts(_sums_and_process, parts, xs, ys, method="fork")
    assert [value for value, _ in got] == [x * 10 + y for x, y in zip(xs, ys)]
    assert os.getpid() not in {pid for _, pid in got}  # in workers (a quick one may take two parts)
    with pytest.raises(ValueError, match="gave 1 results for a part of 2 items"):
        run_parts(_first_only, [[0, 1], [2]], xs, method="fork")


def _first_only(xs):
    return xs[:1]


def test_an_error_in_a_worker_is_raised_here_with_its_message():
    with pytest.raises(ValueError, match="split_by_load: parts must be >= 1, got 0"):
        run_in_processes(split_by_load, [([1.0], 1), ([1.0], 0)], method="fork")


def _killed(seconds: float) -> float:
    """Kills its worker process (as the system's out-of-memory killer does) after ``seconds``."""
    import os
    import signal
    import time

    time.sleep(seconds)
    if seconds > 0:
        os.kill(os.getpid(), signal.SIGKILL)
    return seconds


def test_a_killed_worker_raises_here_instead_of_leaving_the_caller_waiting():
    """A pool that lost a worker to SIGKILL would wait for its result for ever; here the call
    ends with a ChildProcessError (an OSError: the jobs print it as ``error: ...``). An alarm
    turns such a wait into a failure of this test after 60 s."""
    import signal

    def waited(signum, frame):
        raise TimeoutError("run_in_processes still waits for a killed worker after 60 s")

    previous = signal.signal(signal.SIGALRM, waited)
    signal.alarm(60)
    try:
        with pytest.raises(ChildProcessError, match="ended without returning its result: killed"):
            run_in_processes(_killed, [(0.0,), (0.2,)], method="fork")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert run_in_processes(_killed, [(0.0,), (0.0,)], method="fork") == [0.0, 0.0]


def _report(name: str, count: int) -> int:
    logging.getLogger("flowins.test_parallel").warning("warning: %s done", name)
    for _ in progress.progress(range(count), description="counting", unit="step", min_seconds=0.0):
        pass
    return count


def test_a_worker_s_log_records_and_progress_lines_reach_this_process(caplog):
    with caplog.at_level(logging.INFO, logger="flowins"):
        assert run_in_processes(_report, [("first", 2), ("second", 3)], method="fork") == [2, 3]
    messages = [r.getMessage() for r in caplog.records]
    assert "warning: first done" in messages and "warning: second done" in messages
    # progress in a worker is logged under its name, never drawn as a bar
    assert any(m.startswith("worker 1/2: counting: 100%") for m in messages)
    assert any(m.startswith("worker 2/2: counting: 100%") for m in messages)


def test_a_worker_runs_one_thread():
    import torch

    # a forked worker starts with one thread anyway (torch sets it so after a fork); a spawned one would not
    assert run_in_processes(functools.partial(torch.get_num_threads), [(), ()], method="spawn") == [1, 1]


def _nested_batch(count: int) -> str:
    """In a worker process: a batch asked to use workers runs in the worker itself."""
    from flowins.data.synthetic import synthetic_walk_recording
    from flowins.navigation import NavigationConfig, NavigationRun, navigate_batch
    from flowins.parallel import can_start_workers

    recs = [synthetic_walk_recording(duration_s=4.0, seed=s) for s in range(count)]
    results = navigate_batch([NavigationRun(r.imu, r.gnss) for r in recs], config=NavigationConfig(workers=2))
    return f"{can_start_workers()} {len(results)}"


def test_a_daemonic_worker_runs_its_batch_itself_instead_of_starting_workers(caplog):
    from flowins.parallel import can_start_workers

    assert can_start_workers()
    with caplog.at_level(logging.INFO, logger="flowins"):
        assert run_in_processes(_nested_batch, [(2,)], method="fork") == ["False 2"]
    assert any("2 runs in this process: it is a worker process itself" in r.getMessage() for r in caplog.records)
