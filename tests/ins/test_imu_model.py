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
    """σ √Δt of white noise per axis, with a linear drift and an offset per axis removed
    first; the sensor's figure is the quietest axis's."""
    import torch

    from flowins.ins.imu_model import still_noise_densities

    gen = torch.Generator().manual_seed(1)
    t = torch.arange(0.0, 10.0, 0.005, dtype=torch.float64)  # 200 Hz
    sigma = torch.tensor([0.02, 0.03, 0.025], dtype=torch.float64)
    acc = sigma * torch.randn(t.shape[0], 3, generator=gen, dtype=torch.float64) + 9.8 + 0.01 * t.unsqueeze(-1)
    gyro = 0.001 * torch.randn(t.shape[0], 3, generator=gen, dtype=torch.float64) + 1e-4 * t.unsqueeze(-1)
    m = still_noise_densities(t, acc, gyro, end=t.shape[0])
    for got, want in zip(m.acc_axes, sigma * math.sqrt(0.005)):
        assert got == pytest.approx(float(want), rel=0.1)
    # the quietest axis by its one-σ upper bound: thousands of bins, a few per cent above its floor
    assert min(m.acc_axes) < m.acc_noise < 1.05 * min(m.acc_axes)
    assert m.gyro_noise == pytest.approx(0.001 * math.sqrt(0.005), rel=0.1)
    assert m.trusted and (m.samples, m.start_s) == (t.shape[0], 0.0)
    # with white noise only, all of the variance is white: the raw figure agrees
    assert m.gyro_raw == pytest.approx(0.001 * math.sqrt(0.005), rel=0.06)
    with pytest.raises(ValueError, match="need at least 10"):
        still_noise_densities(t, acc, gyro, end=5)


@pytest.mark.parametrize("rate_hz", [100.0, 200.0])
@pytest.mark.parametrize("vibration_mps2", [0.2, 0.5, 0.8])
def test_vibration_on_the_still_start_does_not_pass_for_white_noise(vibration_mps2, rate_hz):
    """A simulated walk at 100 or 200 Hz whose still start vibrates (rotor-like tones,
    accelerometer std 0.2-0.8 m/s²): the raw variance reads several times the simulator's true
    white noise, the floor stays within 2× of it at 200 Hz. At 100 Hz the tones, sampled at
    jittered times, alias into a broadband, white-like part that no spectrum can tell from the
    sensor's: there the floor is never below half the truth (the one-σ upper bound keeps a
    floor that rests on a few bins from reading low) and stays below the raw figure."""
    from flowins.data.synthetic import ImuErrors, Vibration, WalkConfig, synthetic_walk_recording
    from flowins.ins.imu_model import still_noise_densities

    truth = ImuErrors()
    for seed in (0, 1):
        imu = synthetic_walk_recording(duration_s=20.0, seed=seed, imu_rate_hz=rate_hz, walk=WalkConfig(duration_s=20.0),
                                       vibration=Vibration(vibration_mps2, vibration_mps2 / 20, until_s=5.0)).imu
        m = still_noise_densities(imu.t_s, imu.acc_mps2, imu.gyro_rps, round(4.9 * rate_hz))  # all of it vibrating
        assert m.acc_raw > 3 * truth.acc_noise and m.gyro_raw > 2.5 * truth.gyro_noise
        high = 2.0 if rate_hz == 200.0 else m.acc_raw / truth.acc_noise
        assert 0.5 < m.acc_noise / truth.acc_noise < high and 0.5 < m.gyro_noise / truth.gyro_noise < 2.0


@pytest.mark.parametrize("seed", [1, 3, 4])
def test_white_floor_fits_a_known_spectrum(seed):
    """White noise plus a random walk's increments, whose spectrum rises as f² (the model), and
    a strong tone: the floor is the white part."""
    import torch

    from flowins.ins.imu_model import white_floor

    gen = torch.Generator().manual_seed(seed)
    dt = 0.005
    t = torch.arange(0.0, 20.0, dt, dtype=torch.float64)
    white = 0.02 * torch.randn(t.shape[0], 1, generator=gen, dtype=torch.float64)
    # first differences of white noise: a bounded integral, spectrum ∝ sin²(π f Δt) (the model)
    bounded = torch.diff(0.1 * torch.randn(t.shape[0] + 1, 1, generator=gen, dtype=torch.float64), dim=0)
    tone = 1.0 * torch.sin(2 * math.pi * 37.0 * t).unsqueeze(-1)
    floors, covered, bins = white_floor(t, torch.cat((white, white + bounded, white + tone), -1))
    for floor in floors:
        assert floor == pytest.approx(0.02 * math.sqrt(dt), rel=0.2)
    assert floors[1] < 0.3 * float((white + bounded).std()) * math.sqrt(dt)  # the raw figure is far off
    assert covered == [False, False, False]
    # white noise rests on every bin kept; the rising column on fewer
    assert bins[0] > 0.9 * (t.shape[0] // 2 - 3) and bins[1] < bins[0]


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
    from flowins.sensor import resolve_imu

    imu = resolve_imu(_auto_cfg(), [_Rec(_still_walk())], recorded=True)
    phone = resolve_imu(_auto_cfg(still_noise=False), [_Rec(_still_walk())], recorded=True)
    assert phone.name == "phone"
    # a sensor as quiet as the preset's inflated figures: the preset's densities stand
    assert imu.name == "measured" and imu.inflation == 1.0
    assert (imu.acc_noise, imu.gyro_noise) == (phone.acc_noise * phone.inflation, phone.gyro_noise * phone.inflation)
    assert "phone's, above the measured" in imu.source
    # a noisier sensor: its measured floor × imu.still_noise_inflation, above the preset's
    noisy = resolve_imu(_auto_cfg(), [_Rec(_still_walk(0.03, 2e-3))], recorded=True)
    assert noisy.acc_noise == pytest.approx(0.3, rel=0.1) and noisy.gyro_noise == pytest.approx(0.02, rel=0.1)
    # what a still start can't measure stays the fallback preset's
    assert (imu.acc_bias_walk, imu.gyro_bias_walk, imu.gyro_range_rps) == (
        phone.acc_bias_walk, phone.gyro_bias_walk, phone.gyro_range_rps)
    assert "walk/imu.csv 0.00–" in imu.source and "× 10" in imu.source
    # two recordings: the RMS of their densities
    both = resolve_imu(_auto_cfg(), [_Rec(_still_walk(0.03, 2e-3)), _Rec(_still_walk(0.02, 1.5e-3, seed=3))],
                       recorded=True)
    assert both.acc_noise == pytest.approx(10 * math.sqrt((0.03**2 + 0.02**2) / 2), rel=0.1)
    # one without a still start long enough: left out, and named
    one = resolve_imu(_auto_cfg(), [_Rec(_still_walk(0.03, 2e-3)), _Rec(_still_walk(0.06, 4e-3, still_s=1.0))],
                      recorded=True)
    assert one.acc_noise == pytest.approx(0.3, rel=0.1) and "not measured on walk/imu.csv: still for" in one.source


def test_a_short_still_start_a_named_sensor_or_the_simulated_walk_keep_their_presets():
    from flowins.sensor import resolve_imu

    short = resolve_imu(_auto_cfg(), [_Rec(_still_walk(still_s=1.0))], recorded=True)
    assert short.name == "phone" and "the still start's noise is not measured (walk/imu.csv: still for" in short.source
    assert resolve_imu(_auto_cfg(), [_Rec(_still_walk(), "simulated_walk")], recorded=True).name == "simulated_walk"
    assert resolve_imu(_auto_cfg(), [_Rec(_still_walk())], recorded=False).name == "simulated_walk"
    with pytest.raises(ValueError, match="imu.still_noise_inflation"):
        resolve_imu(_auto_cfg(still_noise_inflation=-1.0), [_Rec(_still_walk())], recorded=True)
