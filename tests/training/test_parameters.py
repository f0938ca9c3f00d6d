"""The learned filter parameters: unconstrained coordinates, writing them into the filter
config, reading the defaults, freezing, and the train.py checkpoint layout."""
import math
from pathlib import Path

import pytest
import torch

from flowins.filter.ekf import Gate
from flowins.measurements.flow_update import FlowUpdate
from flowins.ins.initialization import InitialUncertainty
from flowins.ins.mechanization import ProcessNoise
from flowins.navigation import NavigationConfig
from flowins.training.parameters import (
    FROZEN_BY_DEFAULT,
    NAMES,
    FilterParameters,
    starting_values,
)

#: χ²_dof(0.999) from scipy.stats.chi2.ppf (an independent implementation of the quantile)
CHI2_0999_DOF1 = 10.827566170662733
CHI2_0999_DOF3 = 16.26623619623813


def some_start() -> dict[str, float]:
    """A distinct positive value per name (so a mix-up of two fields shows), dropout_p in (0, 1)."""
    start = {name: 0.01 * (i + 1) * (1.7 ** i) for i, name in enumerate(NAMES)}
    start["dropout_p"] = 0.37
    return start


def test_values_round_trip_through_log_and_logit_space():
    start = some_start()
    params = FilterParameters(start)
    values = params.values()
    assert set(values) == set(NAMES)
    for name in NAMES:
        assert values[name] == pytest.approx(start[name], rel=1e-12), name
    # the stored coordinates are the log, and the logit for the dropout rate
    for name in NAMES:
        raw = float(params.raw[name].detach())
        expect = math.log(start[name] / (1 - start[name])) if name == "dropout_p" else math.log(start[name])
        assert raw == pytest.approx(expect, rel=1e-12, abs=1e-12), name
        assert params.raw[name].dtype == torch.float64
    # any raw value is valid: the dropout rate stays in (0, 1), the others positive
    with torch.no_grad():
        for name in NAMES:
            params.raw[name].fill_(-40.0)
    assert all(v > 0 for v in params.values().values())
    assert 0 < params.values()["dropout_p"] < 1e-15


@pytest.mark.parametrize("p", [1e-6, 0.2, 0.5, 0.93])
def test_dropout_rate_round_trips_anywhere_in_the_open_interval(p):
    start = some_start()
    start["dropout_p"] = p
    assert FilterParameters(start).values()["dropout_p"] == pytest.approx(p, rel=1e-12)


@pytest.mark.parametrize("p", [0.0, 1.0, -0.1])
def test_dropout_rate_outside_the_open_interval_raises(p):
    start = some_start()
    start["dropout_p"] = p
    with pytest.raises(ValueError, match="dropout_p must be in"):
        FilterParameters(start)


def test_apply_while_training_writes_tensors_with_a_gradient_into_every_field():
    start = some_start()
    params = FilterParameters(start)
    base = NavigationConfig()
    config = params.apply(base, training=True)
    fields = {
        "acc_noise": config.noise.acc_noise,
        "gyro_noise": config.noise.gyro_noise,
        "acc_bias_walk": config.noise.acc_bias_walk,
        "gyro_bias_walk": config.noise.gyro_bias_walk,
        "acc_scale_walk": config.noise.acc_scale_walk,
        "initial_velocity_mps": config.initial.velocity_mps,
        "initial_roll_pitch_rad": config.initial.roll_pitch_rad,
        "initial_acc_bias_mps2": config.initial.acc_bias_mps2,
        "initial_gyro_bias_rps": config.initial.gyro_bias_rps,
        "initial_acc_scale": config.initial.acc_scale,
        "gnss_noise_scale": config.gnss_noise_scale,
        "flow_sigma_scale": config.flow_update.sigma_scale,
        "flow_sigma_floor_px": config.flow_update.sigma_floor_px,
        "sigma_p0": config.flow_update.sigma_p0,
        "sigma_q0": config.flow_update.sigma_q0,
        "flow_gate_threshold": config.flow_update.gate.threshold,
        "flow_gate_softness": config.flow_update.gate.softness,
        "gnss_gate_threshold": config.gnss_gate.threshold,
        "gnss_gate_softness": config.gnss_gate.softness,
    }
    for name, value in fields.items():
        assert isinstance(value, torch.Tensor) and value.requires_grad, name
        assert float(value.detach()) == pytest.approx(start[name], rel=1e-12), name
    # the gradient of a field reaches its own raw parameter only: d value / d raw = value (log space)
    fields["acc_noise"].backward()
    assert float(params.raw["acc_noise"].grad) == pytest.approx(start["acc_noise"], rel=1e-12)
    assert all(params.raw[n].grad is None for n in NAMES if n != "acc_noise")
    # frozen by default: the value is written but carries no gradient
    for name, value in (("initial_position_m", config.initial.position_m), ("initial_yaw_rad", config.initial.yaw_rad)):
        assert isinstance(value, torch.Tensor) and not value.requires_grad, name
        assert float(value) == pytest.approx(start[name], rel=1e-12), name
    assert config.flow_update.gate.mode == "soft" and config.gnss_gate.mode == "soft"
    # everything that is not learned is the base's
    assert config.flow_update.n_points == base.flow_update.n_points
    assert config.flow_update.augmentation_mode == base.flow_update.augmentation_mode
    assert config.noise.discretization == base.noise.discretization
    assert config.start == base.start and config.output_every == base.output_every


def test_apply_for_inference_writes_floats_and_hard_gates_at_the_learned_threshold():
    start = some_start()
    config = FilterParameters(start).apply(NavigationConfig(), training=False)
    assert type(config.noise.acc_noise) is float and config.noise.acc_noise == pytest.approx(start["acc_noise"], rel=1e-12)
    assert type(config.flow_update.sigma_scale) is float
    assert type(config.gnss_noise_scale) is float
    assert type(config.initial.velocity_mps) is float
    for gate, kind in ((config.flow_update.gate, "flow"), (config.gnss_gate, "gnss")):
        assert gate.mode == "hard"
        assert type(gate.threshold) is float
        assert gate.threshold == pytest.approx(start[f"{kind}_gate_threshold"], rel=1e-12)
        # the hard gate decides at the learned threshold, not at the χ² quantile of its probability
        t = gate.threshold
        w = gate.weights(torch.tensor([0.99 * t, 1.01 * t], dtype=torch.float64), dof=1)
        assert w.tolist() == [1.0, 0.0]


def test_a_gate_switched_off_stays_off():
    base = NavigationConfig(gnss_gate=Gate(mode="off"), flow_update=FlowUpdate(gate=Gate(mode="off")))
    for training in (True, False):
        config = FilterParameters(some_start()).apply(base, training=training)
        assert config.gnss_gate.mode == "off" and config.flow_update.gate.mode == "off"


def test_starting_values_read_the_config():
    values = starting_values(NavigationConfig())
    assert set(values) == set(NAMES)
    approx = lambda x: pytest.approx(x, rel=1e-6)
    assert values["acc_noise"] == approx(3e-3) and values["gyro_noise"] == approx(2e-4)
    assert values["acc_bias_walk"] == 0.0
    assert values["initial_velocity_mps"] == approx(0.05) and values["initial_yaw_rad"] == approx(math.pi)
    assert values["flow_sigma_floor_px"] == approx(0.25) and values["sigma_p0"] == approx(1e3)
    assert values["sigma_q0"] == approx(1e2)
    assert values["flow_gate_threshold"] == approx(CHI2_0999_DOF1)
    assert values["gnss_gate_threshold"] == approx(CHI2_0999_DOF3)
    assert values["flow_gate_softness"] == 1.0 and values["dropout_p"] == approx(0.2)
    # a changed config is read, including an explicit gate threshold and a tensor value
    config = NavigationConfig(
        noise=ProcessNoise(acc_noise=torch.tensor(7e-3, dtype=torch.float64), gyro_bias_walk=1e-5),
        initial=InitialUncertainty(acc_scale=0.03),
        gnss_noise_scale=2.5,
        gnss_gate=Gate(probability=0.99, softness=3.0),
        flow_update=FlowUpdate(sigma_scale=1.5, gate=Gate(threshold=4.0)),
    )
    values = starting_values(config, dropout_p=0.1)
    assert values["acc_noise"] == approx(7e-3) and values["gyro_bias_walk"] == approx(1e-5)
    assert values["initial_acc_scale"] == approx(0.03) and values["gnss_noise_scale"] == 2.5
    assert values["flow_sigma_scale"] == 1.5 and values["flow_gate_threshold"] == 4.0
    assert values["gnss_gate_threshold"] == approx(11.344866730144373)  # χ²_3(0.99), scipy
    assert values["gnss_gate_softness"] == 3.0 and values["dropout_p"] == approx(0.1)
    # the defaults, written back, are the config the values came from
    tuned = FilterParameters({**starting_values(NavigationConfig()), "acc_bias_walk": 1e-4, "gyro_bias_walk": 1e-5,
                              "acc_scale_walk": 1e-5})
    back = tuned.apply(NavigationConfig(), training=False)
    assert back.noise.acc_noise == approx(3e-3)
    assert back.flow_update.gate.threshold == approx(CHI2_0999_DOF1)


def test_starting_values_keep_float64_precision():
    values = starting_values(NavigationConfig())
    assert values["acc_noise"] == 3e-3
    assert values["flow_gate_threshold"] == pytest.approx(CHI2_0999_DOF1, rel=1e-12)


def test_learning_a_parameter_that_starts_at_zero_raises_and_names_it():
    start = starting_values(NavigationConfig())  # the random walks are 0 there
    with pytest.raises(ValueError, match="acc_bias_walk starts at 0"):
        FilterParameters(start)
    # frozen, a zero is fine and stays exactly zero
    params = FilterParameters(start, learn=[n for n in NAMES if not n.endswith("_walk")])
    assert params.values()["gyro_bias_walk"] == 0.0
    assert params.apply(NavigationConfig(), training=False).noise.acc_scale_walk == 0.0


def test_unknown_names_raise():
    with pytest.raises(ValueError, match=r"cannot learn unknown parameters \['acc_nosie'\]"):
        FilterParameters(some_start(), learn=["acc_noise", "acc_nosie"])
    with pytest.raises(ValueError, match=r"unknown names \['bogus'\]"):
        FilterParameters({**some_start(), "bogus": 1.0})
    start = some_start()
    del start["sigma_q0"]
    with pytest.raises(ValueError, match=r"missing values for \['sigma_q0'\]"):
        FilterParameters(start)


def test_frozen_parameters_have_no_gradient_and_the_default_freezes_position_and_yaw():
    default = FilterParameters(some_start())
    assert FROZEN_BY_DEFAULT == {"initial_position_m", "initial_yaw_rad"}
    for name in NAMES:
        assert default.raw[name].requires_grad == (name not in FROZEN_BY_DEFAULT), name
    assert set(default.learned) == set(NAMES) - FROZEN_BY_DEFAULT
    chosen = FilterParameters(some_start(), learn=["acc_noise", "dropout_p"])
    assert chosen.learned == ["acc_noise", "dropout_p"]
    assert [p.requires_grad for p in chosen.parameters()].count(True) == 2
    none = FilterParameters(some_start(), learn=())
    assert none.learned == []


def test_from_checkpoint_round_trips_the_lightning_layout(tmp_path):
    params = FilterParameters(some_start())
    with torch.no_grad():  # values away from the start, as after training
        params.raw["acc_noise"].add_(0.3)
        params.raw["dropout_p"].sub_(0.7)
    path = tmp_path / "best.ckpt"
    torch.save({"epoch": 3, "state_dict": {"params." + k: v for k, v in params.state_dict().items()}}, path)
    loaded = FilterParameters.from_checkpoint(path)
    for name in NAMES:
        assert float(loaded.raw[name]) == float(params.raw[name].detach()), name
    assert loaded.values() == params.values()
    assert loaded.learned == []  # a checkpoint gives values, not a training setup
    # the module the training job writes has exactly this layout
    from flowins.training.module import FilterLearner

    learner = FilterLearner(params, NavigationConfig(), methods=["ins_gnss"])
    path2 = tmp_path / "learner.ckpt"
    torch.save({"state_dict": learner.state_dict()}, path2)
    assert FilterParameters.from_checkpoint(path2).values() == params.values()


def test_a_checkpoint_runs_spynet_dropout_in_closed_form_at_the_learned_rate(tmp_path):
    """evaluate.py with a checkpoint (:func:`flowins.settings.filter_setup`): SpyNet's dropout at
    the learned rate in closed form (the mode training uses, whose mean flow does not depend on
    the rate); a provider without a rate is left as it is."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from flowins.settings import filter_setup

    configs = Path(__file__).resolve().parents[2] / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        cfg = OmegaConf.to_container(compose(config_name="evaluate", overrides=["output_dir=/tmp/unused"]), resolve=True)

    params = FilterParameters(some_start())
    path = tmp_path / "best.ckpt"
    torch.save({"state_dict": {"params." + k: v for k, v in params.state_dict().items()}}, path)
    spynet = {"_target_": "flowins.flow.spynet.SpyNetProvider", "mc_passes": 10, "p": 0.2}
    setup = filter_setup({**cfg, "flow": spynet}, [], recorded=False, checkpoint=str(path))
    assert setup.flow == {**spynet, "p": pytest.approx(0.37, rel=1e-12), "mc_mode": "moments"}
    assert spynet["p"] == 0.2 and "mc_mode" not in spynet  # the caller's config is not changed
    assert setup.navigation.flow_update.sigma_scale == pytest.approx(params.values()["flow_sigma_scale"], rel=1e-12)
    assert setup.learned == pytest.approx(params.values(), rel=1e-12)
    dis = {"_target_": "flowins.flow.classical.DisProvider"}
    assert filter_setup({**cfg, "flow": dis}, [], recorded=False, checkpoint=str(path)).flow == dis
    assert filter_setup({**cfg, "flow": spynet}, [], recorded=False).flow == spynet  # no checkpoint: as configured


def test_from_checkpoint_names_missing_keys_and_missing_files(tmp_path):
    params = FilterParameters(some_start())
    state = {"params." + k: v for k, v in params.state_dict().items() if not k.endswith(("sigma_p0", "dropout_p"))}
    path = tmp_path / "partial.ckpt"
    torch.save({"state_dict": state}, path)
    with pytest.raises(ValueError, match=r"missing \['sigma_p0', 'dropout_p'\]"):
        FilterParameters.from_checkpoint(path)
    with pytest.raises(ValueError, match="is not a file"):
        FilterParameters.from_checkpoint(tmp_path / "nowhere.ckpt")
    path3 = tmp_path / "list.ckpt"
    torch.save([1, 2, 3], path3)
    with pytest.raises(ValueError, match="no state_dict"):
        FilterParameters.from_checkpoint(path3)


def test_from_checkpoint_refuses_values_that_are_not_single_numbers(tmp_path):
    params = FilterParameters(some_start())
    state = {"params." + k: v.detach().clone() for k, v in params.state_dict().items()}
    for name, bad in (("acc_noise", torch.tensor(float("nan"))), ("gyro_noise", torch.tensor(float("inf"))),
                      ("sigma_p0", torch.zeros(2)), ("dropout_p", torch.tensor(1))):
        path = tmp_path / f"{name}.ckpt"
        torch.save({"state_dict": {**state, "params.raw." + name: bad}}, path)
        with pytest.raises(ValueError, match=rf"model\.checkpoint: .*{name}\.ckpt: the parameters \['{name}'\] are not"):
            FilterParameters.from_checkpoint(path)
    # -inf in log space is a value of 0 (a random walk switched off): accepted
    path = tmp_path / "zero.ckpt"
    torch.save({"state_dict": {**state, "params.raw.acc_scale_walk": torch.tensor(float("-inf"), dtype=torch.float64)}}, path)
    assert FilterParameters.from_checkpoint(path).values()["acc_scale_walk"] == 0.0
