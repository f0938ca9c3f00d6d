"""A user's mistake ends a job with ``error: …`` and exit status 2, no traceback; the
job's log file holds the run's story (flowins.jobs.cli, configs/hydra/job_logging)."""
from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from flowins.jobs.cli import USER_ERRORS, user_errors

ROOT = Path(__file__).resolve().parents[2]


def _evaluate(tmp_path: Path, *overrides: str, env: dict | None = None) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"} | (env or {})
    return subprocess.run([sys.executable, "evaluate.py", f"hydra.run.dir={tmp_path}", *overrides], cwd=ROOT,
                          capture_output=True, text=True, env=environment, timeout=300)


def test_a_config_mistake_prints_error_and_exits_2_without_a_traceback(tmp_path):
    done = _evaluate(tmp_path, "combinations=[]")
    out = done.stdout + done.stderr
    assert done.returncode == 2, out
    assert "error: combinations=[]: expected a list of at least one of" in done.stderr  # on stderr
    assert "Traceback" not in out and "Error executing job" not in out
    log = (tmp_path / "evaluate.log").read_text()
    assert "combinations=[]" in log and "ERROR" in log  # the job's log holds it too


def test_hydra_full_error_shows_the_traceback(tmp_path):
    done = _evaluate(tmp_path, "filter.acc_noise=abc", env={"HYDRA_FULL_ERROR": "1"})
    out = done.stdout + done.stderr
    assert done.returncode != 0 and done.returncode != 2
    assert "Traceback" in out and "filter.acc_noise='abc': expected a number" in out


def test_a_missing_recording_is_a_user_error(tmp_path):
    done = _evaluate(tmp_path, f"sequence.path={tmp_path / 'nowhere'}")
    out = done.stdout + done.stderr
    assert done.returncode == 2 and "error: " in out and "nowhere" in out and "Traceback" not in out


def test_only_user_errors_are_caught(capsys):
    @user_errors
    def bad_value():
        raise ValueError("imu.csv line 3: ax is 'x'")

    @user_errors
    def bug():
        raise KeyError("a flowins bug")

    with pytest.raises(SystemExit) as stop:
        bad_value()
    assert stop.value.code == 2
    assert "error: imu.csv line 3: ax is 'x'" in capsys.readouterr().err
    with pytest.raises(KeyError):  # a bug keeps its traceback
        bug()
    assert ValueError in USER_ERRORS and OSError in USER_ERRORS and KeyError not in USER_ERRORS


def test_the_logger_reaches_the_console_when_nobody_set_up_logging(capsys):
    from flowins.jobs.cli import console_logging

    console_logging()
    logging.getLogger("flowins").info("a line of the run's story")
    assert "a line of the run's story" in capsys.readouterr().out


def test_help_is_short_and_says_where_the_full_config_is():
    done = subprocess.run([sys.executable, "evaluate.py", "--help"], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    lines = done.stdout.strip().splitlines()
    assert done.returncode == 0 and 10 <= len(lines) <= 40, done.stdout
    assert "sequence.path=DIR" in done.stdout and "--cfg job" in done.stdout
    assert "data.train" not in done.stdout  # no train-only group in evaluate's help
