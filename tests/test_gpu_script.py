"""``benchmarks/gpu.sh``'s own logic (the order of its sections, its time caps, a bad section
name), with a stand-in ``python`` on the PATH that logs its arguments and sleeps in
``train.py``, so that no section computes anything."""
import os
import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu.sh"

FAKE_PYTHON = """#!/usr/bin/env bash
echo "python $*" >>"$FAKE_LOG"
case "$*" in
  *train.py*) sleep 5 ;;
esac
cat >/dev/null 2>&1 </dev/null
exit 0
"""


def _run(tmp_path: Path, sections: str, *, fake: str = FAKE_PYTHON, **env: str) -> tuple[subprocess.CompletedProcess, list[str]]:
    if shutil.which("timeout") is None:
        pytest.skip("no timeout(1) on this machine")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    fake_path = bin_dir / "python"
    fake_path.write_text(fake)
    fake_path.chmod(0o755)
    log = tmp_path / "calls.log"
    log.write_text("")
    environ = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "FAKE_LOG": str(log),
               "GPU_SH_DEVICE": "cpu", "GPU_SH_SECTIONS": sections, "FLOWINS_GPU_CACHE": str(tmp_path / "cache"),
               **env}
    done = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True, env=environ, timeout=120)
    return done, log.read_text().splitlines()


def test_the_sections_run_in_the_order_given(tmp_path):
    done, calls = _run(tmp_path, "4 3 1")
    headers = [line.split("] ", 1)[1][:2] for line in done.stdout.splitlines() if line.startswith("== [")]
    assert headers[1:4] == ["4.", "3.", "1."], done.stdout
    scripts = [c for c in calls if "bench_flow_filter.py" in c or "evaluate.py" in c or "pytest" in c]
    assert ["bench_flow_filter.py" in scripts[0], "evaluate.py" in scripts[1], "pytest" in scripts[-1]] == [True] * 3


def test_a_capped_training_stops_at_its_limit_and_is_no_failure(tmp_path):
    done, _ = _run(tmp_path, "6", GPU_SH_TRAIN_S="1")
    assert "stopped at the limit of 1 s" in done.stdout, done.stdout
    assert done.returncode == 0, done.stdout
    uncapped, _ = _run(tmp_path, "6")
    assert "stopped at the limit" not in uncapped.stdout


def test_an_unknown_section_is_refused_before_any_work(tmp_path):
    done, calls = _run(tmp_path, "2 10")
    assert done.returncode == 1
    assert "error: GPU_SH_SECTIONS: no section 10 (1 to 9)" in done.stdout
    assert calls == []  # not even the machine's check


def test_the_benchmark_alone_on_the_short_walk_with_its_profile(tmp_path):
    """``GPU_SH_BENCH_QUICK=1`` runs section 4 on the 60 s walk, ``GPU_SH_PROFILE_S`` hands the
    profile's seconds to it; without them, the 300 s walk and no profile."""
    _, calls = _run(tmp_path, "4", GPU_SH_BENCH_QUICK="1", GPU_SH_PROFILE_S="10")
    (bench,) = [c for c in calls if "bench_flow_filter.py" in c]
    assert " --quick " in f"{bench} " and "--profile-s 10" in bench, bench
    _, calls = _run(tmp_path, "4")
    (bench,) = [c for c in calls if "bench_flow_filter.py" in c]
    assert "--quick" not in bench and "--profile-s 0" in bench, bench


def test_section_7_times_a_training_step_at_the_rows_asked_for_on_the_device(tmp_path):
    done, calls = _run(tmp_path, "7", GPU_SH_TRAIN_ROWS="2,64")
    assert done.returncode == 0, done.stdout
    step = [c for c in calls if "bench_train_ops.py" in c]
    assert len(step) == 1 and "--device cpu" in step[0] and "--rows 2,64" in step[0], calls



def test_a_failing_step_benchmark_fails_its_section(tmp_path):
    failing = FAKE_PYTHON.replace("exit 0", 'case "$*" in *bench_train_ops*) exit 3 ;; esac\nexit 0')
    done, _ = _run(tmp_path, "7", fake=failing)
    assert done.returncode == 1 and "error: section 7 failed" in done.stdout, done.stdout


def test_section_8_times_the_triangulation_at_both_sizes_on_the_device(tmp_path):
    done, calls = _run(tmp_path, "8")
    assert done.returncode == 0, done.stdout
    runs = [c for c in calls if "bench_triangulation.py" in c]
    assert len(runs) == 2 and all("--device cpu" in c for c in runs), calls
    assert ["--points 256" in runs[0], "--points 2048" in runs[1]] == [True, True], runs


def test_the_compile_section_runs_the_single_recording_eager_then_compiled(tmp_path):
    done, calls = _run(tmp_path, "9")
    assert done.returncode == 0, done.stdout
    runs = [c for c in calls if "bench_flow_filter.py" in c]
    assert [r.rsplit("filter.compile=", 1)[1] for r in runs] == ["false", "true"], runs
    assert all("--quick" in r and "--batch 0" in r for r in runs), runs
