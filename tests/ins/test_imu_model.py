"""IMU presets and the Kalibr reader (configs/imu, flowins.ins.imu_model)."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.ins.imu_model import imu_model, read_kalibr_imu

CONFIGS = str(Path(__file__).resolve().parents[2] / "configs")
KALIBR = """%YAML:1.0
imu0:
  accelerometer_noise_density: 0.0186
  accelerometer_random_walk: 0.000433
  gyroscope_noise_density: 0.00187
  gyroscope_random_walk: 2.66e-05
  rostopic: /imu0
  update_rate: 200.0
"""


def _imu(*overrides):
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        return OmegaConf.to_container(compose("evaluate", overrides=list(overrides)).imu, resolve=True)


@pytest.mark.parametrize("nested", [True, False])
def test_a_kalibr_file_is_read_flat_or_under_one_key(tmp_path, nested):
    text = KALIBR if nested else "\n".join(line[2:] if line.startswith("  ") else line for line in KALIBR.splitlines()
                                           if line != "imu0:")
    (tmp_path / "imu.yaml").write_text(text)
    model = imu_model(_imu("imu=kalibr", f"imu.path={tmp_path / 'imu.yaml'}"), recording=True)
    assert (model.acc_noise, model.gyro_noise, model.acc_bias_walk, model.gyro_bias_walk) == (
        0.0186, 0.00187, 0.000433, 2.66e-05)
    assert model.rate_hz == 200.0 and model.noise()["acc_noise"] == 0.0186  # Kalibr's values as they are


def test_a_kalibr_file_missing_a_key_names_it(tmp_path):
    (tmp_path / "imu.yaml").write_text(KALIBR.replace("  gyroscope_random_walk: 2.66e-05\n", ""))
    with pytest.raises(ValueError, match="missing gyroscope_random_walk"):
        read_kalibr_imu(tmp_path / "imu.yaml")


def test_auto_takes_the_recordings_own_sensor_else_phone_else_the_simulated_walk():
    cfg = _imu()
    assert imu_model(cfg, recording=True, sensor="adis16448").name == "adis16448"
    assert imu_model(cfg, recording=True).name == "phone"
    assert imu_model(cfg, recording=False).name == "simulated_walk"
    with pytest.raises(ValueError, match="'xsens'"):
        imu_model(cfg, recording=True, sensor="xsens")


def test_a_preset_inflates_its_densities_but_not_its_walks():
    model = imu_model(_imu("imu=adis16448"), recording=True)
    assert model.noise()["acc_noise"] == pytest.approx(2.0e-3 * model.inflation)
    assert model.noise()["gyro_bias_walk"] == model.gyro_bias_walk == 1.9393e-5


@pytest.mark.parametrize("text, message", [
    (KALIBR.replace("0.0186", "abc"), r"imu\.yaml: accelerometer_noise_density is 'abc'; expected a finite number"),
    (KALIBR.replace("0.00187", "-0.1"), r"imu\.yaml: gyroscope_noise_density is -0\.1; expected a finite number >= 0"),
    (KALIBR.replace("200.0", ".nan"), r"imu\.yaml: update_rate is nan"),
    ("- a list\n", r"imu\.yaml"),
    ("x: !!python/object/apply:os.system ['touch RAN']\n", r"imu\.yaml"),
])
def test_a_bad_kalibr_file_names_the_file_and_key_and_runs_nothing(tmp_path, monkeypatch, text, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "imu.yaml").write_text(text)
    with pytest.raises(ValueError, match=message):
        imu_model(_imu("imu=kalibr", f"imu.path={tmp_path / 'imu.yaml'}"), recording=True)
    assert not (tmp_path / "RAN").exists()


def test_a_missing_kalibr_file_or_path_is_named(tmp_path):
    with pytest.raises((ValueError, OSError), match=r"nowhere\.yaml"):
        imu_model(_imu("imu=kalibr", f"imu.path={tmp_path / 'nowhere.yaml'}"), recording=True)
    with pytest.raises(ValueError, match=r"imu=kalibr needs imu\.path=FILE"):
        imu_model(_imu("imu=kalibr"), recording=True)


# ---------------------------------------------------------------- noise from a still start
def _still_walk(acc_density: float = 0.003, gyro_density: float = 2e-4, *, still_s: float = 5.0, seed: int = 0):
    """A walk starting still for ``still_s``, its exact readings plus white noise of the given densities at 100 Hz."""
    import torch

    from flowins.data.streams import ImuStream
    from flowins.data.synthetic import Walk, WalkConfig

    t = torch.arange(0.0, 20.0, 0.01, dtype=torch.float64)
    acc, gyro = Walk(WalkConfig(duration_s=20.0, stationary_s=still_s, ramp_s=2.0)).imu(t)
    gen = torch.Generator().manual_seed(seed)
    acc = acc + acc_density / 0.1 * torch.randn(acc.shape, generator=gen, dtype=torch.float64)
    gyro = gyro + gyro_density / 0.1 * torch.randn(gyro.shape, generator=gen, dtype=torch.float64)
    return ImuStream(t, acc, gyro, name="walk/imu.csv")


def test_still_noise_densities_recover_white_noise_under_a_drift():
    """σ √Δt of white noise, with a linear drift and an offset per axis removed first."""
    import torch

    from flowins.ins.imu_model import still_noise_densities

    gen = torch.Generator().manual_seed(1)
    t = torch.arange(0.0, 10.0, 0.005, dtype=torch.float64)  # 200 Hz
    sigma = torch.tensor([0.02, 0.03, 0.025], dtype=torch.float64)
    acc = sigma * torch.randn(t.shape[0], 3, generator=gen, dtype=torch.float64) + 9.8 + 0.01 * t.unsqueeze(-1)
    gyro = 0.001 * torch.randn(t.shape[0], 3, generator=gen, dtype=torch.float64) + 1e-4 * t.unsqueeze(-1)
    m = still_noise_densities(t, acc, gyro, end=t.shape[0])
    assert m.acc_noise == pytest.approx(float(sigma.square().mean().sqrt()) * math.sqrt(0.005), rel=0.03)
    assert m.gyro_noise == pytest.approx(0.001 * math.sqrt(0.005), rel=0.03)
    assert (m.samples, m.start_s) == (t.shape[0], 0.0)
    with pytest.raises(ValueError, match="need at least 10"):
        still_noise_densities(t, acc, gyro, end=5)


def _auto_cfg(**overrides):
    from pathlib import Path

    import yaml

    root = Path(__file__).resolve().parents[2] / "configs" / "imu"
    cfg = {k: v for k, v in yaml.safe_load((root / "auto.yaml").read_text()).items() if k != "defaults"}
    for preset in ("phone", "simulated_walk"):
        cfg[preset] = yaml.safe_load((root / f"{preset}.yaml").read_text())
    return cfg | overrides


class _Rec:
    def __init__(self, imu, sensor=None):
        self.imu, self.sensor = imu, sensor


def test_a_recording_that_names_no_imu_gets_the_noise_of_its_still_start():
    from flowins.settings import resolve_imu

    imu = resolve_imu(_auto_cfg(), [_Rec(_still_walk())], recorded=True)
    phone = resolve_imu(_auto_cfg(still_noise=False), [_Rec(_still_walk())], recorded=True)
    assert phone.name == "phone"
    assert imu.name == "measured" and imu.inflation == 10.0
    assert imu.acc_noise == pytest.approx(0.003, rel=0.1) and imu.gyro_noise == pytest.approx(2e-4, rel=0.1)
    # what a still start can't measure stays the fallback preset's
    assert (imu.acc_bias_walk, imu.gyro_bias_walk, imu.gyro_range_rps) == (
        phone.acc_bias_walk, phone.gyro_bias_walk, phone.gyro_range_rps)
    assert "walk/imu.csv 0.00–" in imu.source and "× 10" in imu.source
    # two recordings: the RMS of their densities
    both = resolve_imu(_auto_cfg(), [_Rec(_still_walk()), _Rec(_still_walk(0.006, 4e-4, seed=3))], recorded=True)
    assert both.acc_noise == pytest.approx(math.sqrt((0.003**2 + 0.006**2) / 2), rel=0.1)


def test_a_short_still_start_a_named_sensor_or_the_simulated_walk_keep_their_presets():
    from flowins.settings import resolve_imu

    assert resolve_imu(_auto_cfg(), [_Rec(_still_walk(still_s=1.0))], recorded=True).name == "phone"
    assert resolve_imu(_auto_cfg(), [_Rec(_still_walk(), "simulated_walk")], recorded=True).name == "simulated_walk"
    assert resolve_imu(_auto_cfg(), [_Rec(_still_walk())], recorded=False).name == "simulated_walk"
    with pytest.raises(ValueError, match="imu.still_noise_inflation"):
        resolve_imu(_auto_cfg(still_noise_inflation=-1.0), [_Rec(_still_walk())], recorded=True)
