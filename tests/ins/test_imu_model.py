"""IMU presets and the Kalibr reader (configs/imu, flowins.ins.imu_model)."""
from __future__ import annotations

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
