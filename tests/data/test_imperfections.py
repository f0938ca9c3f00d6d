"""The simulator's sensor imperfections against the recording without them (same seed)."""
from __future__ import annotations

import json
import math

import pytest
import torch

from flowins.data.simulate.drive import DriveConfig, drive_sequence
from flowins.data.synthetic import Imperfections, imperfect, imperfections_generator, synthetic_walk_recording

F64 = torch.float64
SEED = 4
ACC_BIAS, GYRO_BIAS = (0.1, -0.2, 0.35), (0.01, 0.02, -0.03)


def walk(imperfections: Imperfections | None = None):
    extra = {} if imperfections is None else {"imperfections": imperfections}
    return synthetic_walk_recording(duration_s=30.0, seed=SEED, **extra)


def drive(imperfections: Imperfections = Imperfections()):
    return drive_sequence(DriveConfig(duration_s=30.0, outage_s=0.0, seed=SEED, imperfections=imperfections))


@pytest.fixture(scope="module")
def plain_walk():
    return walk()


@pytest.fixture(scope="module")
def plain_drive():
    return drive()


def assert_same_gnss_and_truth(a, b):
    for field in ("t_s", "lat_deg", "lon_deg", "alt_m", "h_acc_m", "v_acc_m"):
        assert torch.equal(getattr(a.gnss, field), getattr(b.gnss, field)), field
    for field in ("t_s", "pos_m", "quat_wxyz"):
        assert torch.equal(getattr(a.truth, field), getattr(b.truth, field)), field


def rows_in(t_all, t_kept):
    """Rows of ``t_all`` that hold the times ``t_kept`` exactly (asserted)."""
    rows = torch.searchsorted(t_all, t_kept)
    assert torch.equal(t_all[rows], t_kept)
    return rows


def test_default_imperfections_change_nothing_and_draw_no_random_number(plain_walk, plain_drive):
    again = walk(Imperfections())
    for field in ("t_s", "acc_mps2", "gyro_rps"):
        assert torch.equal(getattr(again.imu, field), getattr(plain_walk.imu, field))
    assert_same_gnss_and_truth(again, plain_walk)
    assert all(torch.equal(again.imu_errors[k], plain_walk.imu_errors[k]) for k in plain_walk.imu_errors)
    sequence, _ = drive(Imperfections())
    assert torch.equal(sequence.imu.gyro_rps, plain_drive[0].imu.gyro_rps)
    gen = torch.Generator().manual_seed(0)
    state = gen.get_state()
    t, acc, gyro = plain_walk.imu.t_s, plain_walk.imu.acc_mps2, plain_walk.imu.gyro_rps
    out = imperfect(t, acc, gyro, Imperfections(), gen)
    assert out[0] is t and out[1] is acc and out[2] is gyro and torch.equal(out[3], torch.arange(len(t)))
    assert torch.equal(gen.get_state(), state)


def test_a_constant_bias_is_added_to_every_reading_and_to_the_truth(plain_walk, plain_drive):
    biased = walk(Imperfections(acc_bias_mps2=ACC_BIAS, gyro_bias_rps=GYRO_BIAS))
    acc_bias, gyro_bias = torch.tensor(ACC_BIAS, dtype=F64), torch.tensor(GYRO_BIAS, dtype=F64)
    assert torch.equal(biased.imu.t_s, plain_walk.imu.t_s)
    torch.testing.assert_close(biased.imu.acc_mps2 - plain_walk.imu.acc_mps2, acc_bias.expand(len(biased.imu.t_s), 3),
                               rtol=0, atol=1e-13)
    torch.testing.assert_close(biased.imu.gyro_rps - plain_walk.imu.gyro_rps, gyro_bias.expand(len(biased.imu.t_s), 3),
                               rtol=0, atol=1e-15)
    torch.testing.assert_close(biased.imu_errors["b_a"] - plain_walk.imu_errors["b_a"],
                               acc_bias.expand_as(biased.imu_errors["b_a"]), rtol=0, atol=1e-15)
    torch.testing.assert_close(biased.imu_errors["b_w"] - plain_walk.imu_errors["b_w"],
                               gyro_bias.expand_as(biased.imu_errors["b_w"]), rtol=0, atol=1e-15)
    assert torch.equal(biased.imu_errors["T_a"], plain_walk.imu_errors["T_a"])
    assert_same_gnss_and_truth(biased, plain_walk)
    sequence, truth = drive(Imperfections(gyro_bias_rps=GYRO_BIAS))
    torch.testing.assert_close(sequence.imu.gyro_rps - plain_drive[0].imu.gyro_rps,
                               gyro_bias.expand(len(sequence.imu), 3), rtol=0, atol=1e-15)
    torch.testing.assert_close(truth["b_w"] - plain_drive[1]["b_w"], gyro_bias.expand_as(truth["b_w"]), rtol=0, atol=1e-15)
    assert torch.equal(sequence.imu.acc_mps2, plain_drive[0].imu.acc_mps2)


@pytest.mark.parametrize("sensor, field, limit", [("acc_mps2", "acc_range_mps2", 11.0), ("gyro_rps", "gyro_range_rps", 0.2)])
def test_clipping_is_exactly_at_the_range_and_nowhere_else(plain_walk, sensor, field, limit):
    clipped = getattr(walk(Imperfections(**{field: limit})).imu, sensor)
    plain = getattr(plain_walk.imu, sensor)
    above, below, inside = plain > limit, plain < -limit, plain.abs() <= limit
    assert int(above.sum()) > 50 and int(below.sum() + above.sum()) < plain.numel() // 2  # the clip bites, not all
    assert bool((clipped[above] == limit).all()) and bool((clipped[below] == -limit).all())
    assert torch.equal(clipped[inside], plain[inside])


@pytest.mark.parametrize("fraction, run", [(0.1, 1), (0.05, 7), (0.3, 4)])
def test_dropped_rows_come_in_runs_inside_the_recording_and_the_rest_is_unchanged(plain_walk, fraction, run):
    dropped_walk = walk(Imperfections(drop_fraction=fraction, drop_run=run))
    n = len(plain_walk.imu.t_s)
    kept = rows_in(plain_walk.imu.t_s, dropped_walk.imu.t_s)
    assert abs((n - len(kept)) - round(fraction * n)) <= run
    assert int(kept[0]) == 0 and int(kept[-1]) == n - 1
    steps = torch.diff(kept)
    assert set(steps.tolist()) <= {1, run + 1}  # every gap is exactly one run, runs never meet
    assert torch.equal(dropped_walk.imu.acc_mps2, plain_walk.imu.acc_mps2[kept])
    assert torch.equal(dropped_walk.imu.gyro_rps, plain_walk.imu.gyro_rps[kept])
    for key in ("b_a", "b_w"):
        assert torch.equal(dropped_walk.imu_errors[key], plain_walk.imu_errors[key][kept])
    assert_same_gnss_and_truth(dropped_walk, plain_walk)
    again = walk(Imperfections(drop_fraction=fraction, drop_run=run))
    assert torch.equal(again.imu.t_s, dropped_walk.imu.t_s)  # deterministic in the seed


def test_dropped_runs_keep_both_ends_even_when_packed_tight():
    """Small recordings nearly full of runs, where a run at either end is likely if allowed."""
    for case in range(300):
        gen = torch.Generator().manual_seed(case)
        n, run = int(torch.randint(6, 40, (1,), generator=gen)), int(torch.randint(1, 4, (1,), generator=gen))
        fraction = 0.49 * run / (run + 1)  # the most that fits apart from each other and the ends
        t = torch.arange(n, dtype=F64)
        acc = torch.arange(3 * n, dtype=F64).reshape(n, 3)
        t_kept, acc_kept, _, kept = imperfect(t, acc, -acc, Imperfections(drop_fraction=fraction, drop_run=run), gen)
        assert int(kept[0]) == 0 and int(kept[-1]) == n - 1, (n, run, kept)
        assert set(torch.diff(kept).tolist()) <= {1, run + 1}, (n, run, kept)
        assert n - len(kept) == run * round(fraction * n / run)
        assert torch.equal(t_kept, t[kept]) and torch.equal(acc_kept, acc[kept])


def test_all_imperfections_together_bias_then_clip_then_drop_in_the_drive(plain_drive):
    imperfections = Imperfections(acc_bias_mps2=ACC_BIAS, gyro_bias_rps=GYRO_BIAS, acc_range_mps2=9.9,
                                  gyro_range_rps=0.05, drop_fraction=0.2, drop_run=3)
    (sequence, truth), (plain, plain_truth) = drive(imperfections), plain_drive
    kept = rows_in(plain.imu.t_s, sequence.imu.t_s)
    acc_bias, gyro_bias = torch.tensor(ACC_BIAS, dtype=F64), torch.tensor(GYRO_BIAS, dtype=F64)
    torch.testing.assert_close(sequence.imu.acc_mps2, (plain.imu.acc_mps2 + acc_bias).clamp(-9.9, 9.9)[kept], rtol=0, atol=1e-13)
    torch.testing.assert_close(sequence.imu.gyro_rps, (plain.imu.gyro_rps + gyro_bias).clamp(-0.05, 0.05)[kept],
                               rtol=0, atol=1e-15)
    assert float(sequence.imu.acc_mps2[:, 2].max()) == 9.9 and float(sequence.imu.gyro_rps.abs().max()) == 0.05
    torch.testing.assert_close(truth["b_w"], (plain_truth["b_w"] + gyro_bias)[kept], rtol=0, atol=1e-15)
    torch.testing.assert_close(truth["b_a"], (plain_truth["b_a"] + acc_bias)[kept], rtol=0, atol=1e-15)
    assert torch.equal(sequence.gnss.lat_deg, plain.gnss.lat_deg)
    # the same rows as imperfect() itself keeps, from the generator the simulator names
    t, acc, gyro = plain.imu.t_s, plain.imu.acc_mps2, plain.imu.gyro_rps
    assert torch.equal(imperfect(t, acc, gyro, imperfections, imperfections_generator(SEED))[3], kept)


def test_the_drive_config_carries_its_imperfections_as_json():
    config = DriveConfig(imperfections=Imperfections(gyro_bias_rps=(0.01, 0, 0), gyro_range_rps=4.0, drop_fraction=0.01))
    plain = json.loads(json.dumps(config.as_plain()))
    assert plain["imperfections"] == {"gyro_bias_rps": [0.01, 0.0, 0.0], "acc_bias_mps2": [0.0, 0.0, 0.0],
                                      "acc_range_mps2": None, "gyro_range_rps": 4.0, "drop_fraction": 0.01,
                                      "drop_run": 1}
    assert config.key() != DriveConfig().key()


@pytest.mark.parametrize("field, value", [
    ("gyro_bias_rps", (0.0, 0.0)), ("gyro_bias_rps", (0.0, math.nan, 0.0)), ("acc_bias_mps2", (0.0, 0.0, math.inf)),
    ("acc_bias_mps2", 0.1), ("acc_range_mps2", 0.0), ("gyro_range_rps", -1.0), ("gyro_range_rps", math.inf),
    ("drop_fraction", 0.5), ("drop_fraction", -0.01), ("drop_fraction", math.nan), ("drop_run", 0), ("drop_run", 2.0),
])
def test_a_bad_field_is_refused_by_name(field, value):
    with pytest.raises(ValueError, match=f"Imperfections.{field}="):
        Imperfections(**{field: value})


def test_runs_that_cannot_fit_are_refused_and_a_plain_dict_is_no_imperfections():
    t = torch.arange(4, dtype=F64)
    with pytest.raises(ValueError, match="drop_run=3"):
        imperfect(t, torch.zeros(4, 3), torch.zeros(4, 3), Imperfections(drop_fraction=0.45, drop_run=3),
                  torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="DriveConfig.imperfections"):
        DriveConfig(imperfections={"drop_fraction": 0.1})
