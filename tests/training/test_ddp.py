"""Two training processes (``trainer=ddp``, gloo on the CPU), really run: each takes one of the
two training sequences per step and validates its share of the held-out runs, and after the
run their parameters and validations equal those of one process that takes both sequences
per step and validates every run.

The two-process run is ``python train.py trainer=ddp ...`` in a subprocess (Lightning's DDP
launches the second process by running the same command again, which must not be pytest).
The runs use INS + GNSS with every fix applied as it comes, so that no flow is computed and
every parameter of the GNSS and IMU noise gets a gradient.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.jobs.train import run
from flowins.training.parameters import NAMES, FilterParameters

ROOT = Path(__file__).resolve().parents[2]

COMMON = ["methods=[ins_gnss]", "filter.gnss_heading.enabled=false", "progress=false", "logger=csv",
          "data.train=[{seed: 1, duration_s: 12.0},{seed: 2, duration_s: 12.0}]",
          "data.val=[{seed: 3, duration_s: 12.0}]",
          "data.select=[{seed: 4, duration_s: 12.0},{seed: 5, duration_s: 10.0}]", "window_s=4.0", "curriculum_window_s=[]",
          "trainer.max_epochs=2", "model.warmup_steps=2"]


@pytest.mark.slow
def test_two_processes_take_the_steps_of_one_process_with_both_sequences(tmp_path):
    cache = f"cache_dir={tmp_path / 'cache'}"
    ddp_dir = tmp_path / "ddp"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, str(ROOT / "train.py"), "trainer=ddp", "data.batch_size=1",
                           f"hydra.run.dir={ddp_dir}", cache, *COMMON],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "GLOBAL_RANK: 1" in done.stdout + done.stderr or "Initializing distributed: GLOBAL_RANK: 0, MEMBER: 1/2" in \
        done.stdout + done.stderr, done.stderr[-2000:]

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=[f"output_dir={tmp_path / 'one'}", cache, "data.batch_size=2", *COMMON])
    one = run(OmegaConf.to_container(cfg, resolve=True))

    # the same steps: the last epoch's parameters agree to rounding
    ddp_last = FilterParameters.from_checkpoint(ddp_dir / "checkpoints" / "last.ckpt")
    one_last = FilterParameters.from_checkpoint(tmp_path / "one" / "checkpoints" / "last.ckpt")
    start = one["start"]
    moved = [n for n in NAMES if abs(float(one_last.raw[n]) - float(FilterParameters(start, learn=()).raw[n])) > 1e-6]
    assert {"acc_noise", "gyro_noise", "gnss_noise_scale"} <= set(moved), moved  # learning did happen
    for name in NAMES:
        assert float(ddp_last.raw[name]) == pytest.approx(float(one_last.raw[name]), rel=1e-9, abs=1e-12), name
    # and the same validations (each process runs its share of the held-out runs, every value
    # summed from the one that ran it), so the same choice of checkpoint
    ddp_selection = json.loads((ddp_dir / "selection.json").read_text())
    assert ddp_selection["chosen"] == one["chosen"]
    for key in ("score", "select_score"):
        assert [e[key] for e in ddp_selection["history"]] == pytest.approx([e[key] for e in one["history"]],
                                                                          rel=1e-9), key
    for a, b in zip(ddp_selection["history"], one["history"], strict=True):
        assert a["select_rmse_m"] == {m: pytest.approx(v, rel=1e-9) for m, v in b["select_rmse_m"].items()}
