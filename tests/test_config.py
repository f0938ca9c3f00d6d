"""flowins.config: a config value of the wrong kind or range stops with its key named.

Each case is an override a user could type; the expected message names the dotted key
and what was expected (the independent truth is the override itself: the key in it).
"""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.config import build, check_value, setting
from flowins.ins.imu_model import imu_model
from flowins.settings import evaluate_settings, navigation_config, train_settings
from flowins.navigation import NavigationConfig

CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


def _evaluate_config(*overrides: str) -> dict:
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=["output_dir=/tmp/unused", *overrides])
    return OmegaConf.to_container(cfg, resolve=True)


def _filter(*overrides: str) -> NavigationConfig:
    cfg = _evaluate_config(*overrides)
    return navigation_config(cfg["filter"], imu_model(cfg["imu"], recording=False))


def test_the_defaults_pass():
    assert isinstance(_filter(), NavigationConfig)
    evaluate_settings(_evaluate_config())


def test_filter_workers_auto_is_one_per_core_this_process_may_use():
    import os

    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    assert _filter().workers == _filter("filter.workers=auto").workers == cores
    assert _filter("filter.workers=3").workers == 3
    assert NavigationConfig().workers == 1  # the Python API: one process unless asked


@pytest.mark.parametrize("override, message", [
    ("filter.acc_noise=abc", r"filter\.acc_noise='abc': expected a number"),
    ("filter.acc_noise=-1", r"filter\.acc_noise=-1: expected a number >= 0"),
    ("filter.output_every=0", r"filter\.output_every=0: expected an integer >= 1"),
    ("filter.output_every=2.5", r"filter\.output_every=2\.5: expected an integer"),
    ("filter.scheme=rk4", r"filter\.scheme='rk4': expected one of midpoint, paper"),
    ("filter.jacobians=numeric", r"filter\.jacobians='numeric'"),
    ("filter.gravity_mps2=0", r"filter\.gravity_mps2=0: expected a number > 0"),
    ("filter.dtype=float32", r"filter\.dtype='float32'"),
    ("filter.device=gpu", r"filter\.device='gpu': expected cpu, cuda or cuda:N"),
    ("filter.workers=0", r"filter\.workers=0: expected an integer >= 1"),
    ("filter.workers=many", r"filter\.workers='many': expected an integer >= 1 or auto"),
    ("filter.init.mode=bogus", r"filter\.init\.mode='bogus'"),
    ("filter.init.still.min_s=x", r"filter\.init\.still\.min_s='x': expected a number"),
    ("filter.init.still.min_s=-1", r"filter\.init\.still\.min_s=-1: expected a number > 0"),
    ("filter.flow.recovery.max_accepted=1", r"filter\.flow\.recovery\.max_accepted=1: expected a number < 1"),
    ("filter.tracks.window=-1", r"filter\.tracks\.window=-1: expected an integer >= 0"),
    ("filter.tracks.sigma_px=0", r"filter\.tracks\.sigma_px=0: expected a number > 0"),
    ("filter.measurements.vehicle.mode=sometimes",
     r"filter\.measurements\.vehicle\.mode='sometimes': expected one of auto, on, off"),
    ("filter.measurements.vehicle.up_axis=x", r"filter\.measurements\.vehicle\.forward_axis='x' and up_axis='x' are the same"),
    ("filter.init.moving.velocity_mps=[1,2]", r"filter\.init\.moving\.velocity_mps=\[1, 2\]: expected a list of 3"),
    ("filter.initial.position_m=nan", r"filter\.initial\.position_m=nan: expected a finite number"),
    ("filter.gnss_gate.probability=2", r"filter\.gnss_gate\.probability=2: expected a number < 1"),
    ("filter.gnss_recovery.velocity=maybe", r"filter\.gnss_recovery\.velocity='maybe': expected true or false"),
    ("filter.gnss_recovery.after_rejections=-1", r"filter\.gnss_recovery\.after_rejections=-1: expected an integer >= 0"),
    ("filter.flow.n_points=abc", r"filter\.flow\.n_points='abc': expected an integer"),
    ("filter.flow.gate.mode=x", r"filter\.flow\.gate\.mode='x': expected one of hard, soft, off"),
    ("filter.flow.recovery.after_frames=x", r"filter\.flow\.recovery\.after_frames='x': expected an integer"),
    ("+filter.foo=1", r"filter\.foo: unknown key"),
    ("+filter.measurements.sonar.range_m=1", r"filter\.measurements\.sonar: unknown measurement kind 'sonar'"),
    ("+filter.init.still.foo=1", r"filter\.init\.still\.foo: unknown key; filter\.init\.still takes min_s"),
    ("imu=phone imu.inflation=abc", r"imu\.inflation='abc': expected a number"),
    ("imu=phone imu.acc_range_mps2=-3", r"imu\.acc_range_mps2 \(phone\) must be > 0"),
])
def test_a_bad_filter_or_imu_value_names_its_key(override, message):
    with pytest.raises(ValueError, match=message):
        _filter(*override.split())


@pytest.mark.parametrize("override, message", [
    ("combinations=[]", r"combinations=\[\]: expected a list of at least one of ins, ins_gnss"),
    ("combinations=[ins_flow]", r"combinations: unknown combination 'ins_flow'"),
    ("flow_pairs.step=0", r"flow_pairs\.step=0: expected an integer >= 1"),
    ("flow_pairs.input_scale=2", r"flow_pairs\.input_scale=2: expected a number <= 1"),
    ("flow_pairs.batch_size=abc", r"flow_pairs\.batch_size='abc': expected an integer"),
    ("flow_panels=-1", r"flow_panels=-1: expected an integer >= 0"),
    ("plots=maybe", r"plots='maybe': expected true or false"),
    ("sequence.max_imu_gap_s=0", r"sequence\.max_imu_gap_s=0"),
    ("sequence.crop=yes", r"sequence\.crop='yes': expected true or false"),
    ("sequence.duration_s=abc", r"sequence\.duration_s='abc': expected a number"),
])
def test_a_bad_job_value_names_its_key(override, message):
    with pytest.raises(ValueError, match=message):
        evaluate_settings(_evaluate_config(override))


@pytest.mark.skipif(torch.cuda.is_available(), reason="the refusal of a machine without CUDA")
@pytest.mark.parametrize("override, message", [
    ("filter.device=cuda", r"filter\.device=cuda: torch .* sees no CUDA GPU here"),
    ("flow.device=cuda:1", r"flow\.device=cuda:1: torch .* sees no CUDA GPU here"),
])
def test_a_cuda_device_without_cuda_is_refused_before_any_work(override, message):
    with pytest.raises(ValueError, match=message):
        evaluate_settings(_evaluate_config(override))
    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = OmegaConf.to_container(compose(config_name="train", overrides=["output_dir=/tmp/unused", "trainer=gpu"]),
                                     resolve=True)
    with pytest.raises(ValueError, match=r"trainer\.accelerator=gpu \(trainer=gpu\): torch .* sees no CUDA GPU"):
        train_settings(cfg)


def test_check_value_converts_and_refuses():
    assert check_value(3, float, "k") == 3.0 and isinstance(check_value(3, float, "k"), float)
    assert check_value(4.0, int, "k") == 4
    assert check_value([1, 2, 3], tuple[float, float, float], "k") == (1.0, 2.0, 3.0)
    assert check_value(None, float | None, "k") is None
    for value, tp in ((True, float), (True, int), (1, bool), ("1", float), (4.5, int), (float("inf"), float)):
        with pytest.raises(ValueError, match=r"^k="):
            check_value(value, tp, "k")


def test_setting_range_and_missing_key():
    cfg = {"a": {"b": 5}}
    assert setting(cfg, "a.b", int, minimum=1, maximum=5) == 5
    with pytest.raises(ValueError, match=r"a\.b=5: expected an integer <= 4"):
        setting(cfg, "a.b", int, maximum=4)
    with pytest.raises(ValueError, match=r"a\.c: missing from the config"):
        setting(cfg, "a.c", int)
    assert setting(cfg, "a.c", int, default=7) == 7


def test_build_names_the_nested_key_of_a_dataclass_refusal():
    from flowins.filter.ekf import Gate

    with pytest.raises(ValueError, match=r"^x\.gate\.probability=1\.5: expected a number < 1$"):
        build(Gate, {"probability": 1.5}, "x.gate")
