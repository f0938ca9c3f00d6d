"""The learned filter parameters: unconstrained coordinates, writing them into the filter
config, reading the defaults, freezing, and the train.py checkpoint layout."""
import math
import re
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
    SIGNED,
    starting_values,
)

#: χ²_dof(0.999) from scipy.stats.chi2.ppf (an independent implementation of the quantile)
CHI2_0999_DOF1 = 10.827566170662733
CHI2_0999_DOF3 = 16.26623619623813


def some_start() -> dict[str, float]:
    """A distinct positive value per name (so a mix-up of two fields shows), dropout_p in (0, 1),
    the signed ones small and of both signs."""
    start = {name: 0.01 * (i + 1) * (1.7 ** i) for i, name in enumerate(NAMES)}
    start["dropout_p"] = 0.37
    start.update({name: (-1) ** i * 0.01 * (i + 1) for i, name in enumerate(SIGNED)})
    return start


def test_values_are_the_start_exactly_at_zero_coordinates():
    start = some_start()
    params = FilterParameters(start)
    assert set(params.values()) == set(NAMES)
    assert params.values() == start  # exactly: start · exp(0), and the dropout rate's form at s = 0
    for name in NAMES:
        assert float(params.raw[name].detach()) == 0.0, name
        assert params.raw[name].dtype == torch.float64
        bound = SIGNED[name][1] if name in SIGNED else 2.0  # a signed one's largest magnitude
        assert float(params.center[name]) == start[name] and float(params.bound[name]) == bound, name
    assert params.bounds() == {n: SIGNED[n][1] if n in SIGNED else 2.0 for n in NAMES}


@pytest.mark.parametrize("p", [1e-6, 0.2, 0.37, 0.5, 0.93, 1 - 1e-9])
def test_dropout_rate_is_its_start_exactly_anywhere_in_the_open_interval(p):
    start = some_start()
    start["dropout_p"] = p
    assert FilterParameters(start).values()["dropout_p"] == p
    assert FilterParameters(start, bounds={"dropout_p": None}).values()["dropout_p"] == p


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
    # the gradient of a field reaches its own raw parameter only: d value / d a = value at a = 0
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
    assert FROZEN_BY_DEFAULT == {"initial_position_m", "initial_yaw_rad", *SIGNED}  # a vehicle's mounting too
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


def test_a_checkpoint_keeps_the_configured_flow_and_takes_only_a_learned_rate(tmp_path):
    """evaluate.py with a checkpoint (:func:`flowins.settings.filter_setup`): the flow provider
    runs as configured, so a run with the checkpoint and one without compute the same flow;
    a dropout rate the checkpoint learned away from the configured one replaces it, one it
    kept (its float round trip) does not; ``flow.mc_mode=moments`` still gives closed form."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from flowins.settings import describe_flow, filter_setup

    configs = Path(__file__).resolve().parents[2] / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        cfg = OmegaConf.to_container(compose(config_name="evaluate", overrides=["output_dir=/tmp/unused"]), resolve=True)
    spynet = {"_target_": "flowins.flow.spynet.SpyNetProvider", "mc_passes": 10, "p": 0.2}

    def checkpoint(start: dict[str, float], name: str) -> str:
        params = FilterParameters(start)
        path = tmp_path / name
        torch.save({"state_dict": {"params." + k: v for k, v in params.state_dict().items()}}, path)
        return str(path)

    learned = checkpoint(some_start(), "learned.ckpt")  # dropout_p 0.37
    setup = filter_setup({**cfg, "flow": spynet}, [], recorded=False, checkpoint=learned)
    assert setup.flow == {**spynet, "p": pytest.approx(0.37, rel=1e-12)} and "mc_mode" not in setup.flow
    assert spynet["p"] == 0.2  # the caller's config is not changed
    assert "differs from the configured flow: p 0.2 -> 0.37" in describe_flow(setup.flow, spynet)
    assert setup.navigation.flow_update.sigma_scale == pytest.approx(FilterParameters(some_start()).values()[
        "flow_sigma_scale"], rel=1e-12)
    kept = checkpoint({**some_start(), "dropout_p": 0.2}, "kept.ckpt")
    same = filter_setup({**cfg, "flow": spynet}, [], recorded=False, checkpoint=kept)
    assert same.flow == spynet and "(the configured flow)" in describe_flow(same.flow, spynet)
    moments = {**spynet, "mc_mode": "moments"}
    assert filter_setup({**cfg, "flow": moments}, [], recorded=False, checkpoint=kept).flow == moments
    # a provider with no dropout keeps its config; the target is one that builds
    from flowins.config import instantiate
    from flowins.flow.classical import DISProvider

    dis = {"_target_": "flowins.flow.classical.DISProvider"}
    assert isinstance(instantiate(dis, "flow"), DISProvider)
    assert filter_setup({**cfg, "flow": dis}, [], recorded=False, checkpoint=learned).flow == dis


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
    # a = -inf is the lower limit of the bound
    minus_inf = torch.tensor(float("-inf"), dtype=torch.float64)
    path = tmp_path / "low.ckpt"
    torch.save({"state_dict": {**state, "params.raw.acc_scale_walk": minus_inf}}, path)
    assert FilterParameters.from_checkpoint(path).values()["acc_scale_walk"] == pytest.approx(
        some_start()["acc_scale_walk"] * 1e-2, rel=1e-12)
    # in the layout with raw values only, -inf in log space is a value of 0 (a random walk switched off)
    legacy = {"params.raw." + n: torch.tensor(v if n in SIGNED else math.log(v), dtype=torch.float64)
              for n, v in some_start().items() if n != "dropout_p"}
    legacy["params.raw.dropout_p"] = torch.tensor(0.0, dtype=torch.float64)
    path = tmp_path / "zero.ckpt"
    torch.save({"state_dict": {**legacy, "params.raw.acc_scale_walk": minus_inf}}, path)
    assert FilterParameters.from_checkpoint(path).values()["acc_scale_walk"] == 0.0
    # starts and bounds that are not numbers of their kind
    for key, bad in (("center.acc_noise", torch.tensor(-1.0, dtype=torch.float64)),
                     ("center.gyro_noise", torch.tensor(float("inf"), dtype=torch.float64)),
                     ("bound.sigma_p0", torch.tensor(0.0, dtype=torch.float64))):
        path = tmp_path / "bad.ckpt"
        torch.save({"state_dict": {**state, "params." + key: bad}}, path)
        with pytest.raises(ValueError, match=rf"model\.checkpoint: .*bad\.ckpt: \['{re.escape(key)}'\] are not"):
            FilterParameters.from_checkpoint(path)


# ---------------------------------------------------------------------------
# the prior: each value is its start times a bounded factor
# ---------------------------------------------------------------------------

POSITIVE = [n for n in NAMES if n != "dropout_p" and n not in SIGNED]


def _at(params: FilterParameters, a: dict[str, float]) -> FilterParameters:
    with torch.no_grad():
        for name, value in a.items():
            params.raw[name].fill_(value)
    return params


def _logit(p: float) -> float:
    return math.log(p) - math.log1p(-p)


@pytest.mark.parametrize("decades", [0.5, 2.0, 3.0])
def test_values_stay_within_the_bound_and_approach_its_limits(decades):
    start = some_start()
    params = FilterParameters(start, bounds={n: decades for n in NAMES}, ceilings={})
    for a, factor in ((1e3, 10.0 ** decades), (-1e3, 10.0 ** -decades)):
        values = _at(params, {n: a for n in NAMES}).values()
        for name in POSITIVE:
            assert start[name] * 10.0 ** -decades <= values[name] * (1 + 1e-15), name
            assert values[name] <= start[name] * 10.0 ** decades * (1 + 1e-15), name
            assert values[name] == pytest.approx(start[name] * factor, rel=1e-12), name  # the limit is reached
        # the dropout rate: in (0, 1), its logit within ±B of the start's, the limit reached
        p = values["dropout_p"]
        assert 0.0 < p < 1.0
        assert _logit(p) == pytest.approx(_logit(start["dropout_p"]) + math.copysign(decades * math.log(10), a),
                                          rel=1e-9)
    # inside: start · exp(B tanh(a / B)), an independent evaluation in plain floats
    scale = decades * math.log(10)
    for a in (-7.0, -0.3, 0.25, 1.5, 9.0):
        values = _at(params, {n: a for n in NAMES}).values()
        for name in POSITIVE:
            assert values[name] == pytest.approx(start[name] * math.exp(scale * math.tanh(a / scale)), rel=1e-13)
        expected = 1 / (1 + math.exp(-(_logit(start["dropout_p"]) + scale * math.tanh(a / scale))))
        assert values["dropout_p"] == pytest.approx(expected, rel=1e-13)


@pytest.mark.parametrize("name", ["acc_noise", "initial_roll_pitch_rad", "flow_gate_threshold", "dropout_p"])
@pytest.mark.parametrize("decades", [1.0, 2.0, None])
def test_the_gradient_is_the_closed_form_and_the_finite_difference(name, decades):
    """d value / d a: value · sech²(a / B) for a positive parameter (value for B = ∞), and
    p (1 - p) sech²(a / B) for the dropout rate, by autograd and by central differences."""
    params = FilterParameters(some_start(), bounds={name: decades}, ceilings={})
    scale = math.inf if decades is None else decades * math.log(10)
    for a in (-6.0, -1.0, 0.0, 0.4, 3.0, 8.0):
        _at(params, {name: a})
        value = params.value(name)
        (grad,) = torch.autograd.grad(value, params.raw[name])
        v = float(value.detach())
        sech2 = 1.0 if math.isinf(scale) else 1.0 / math.cosh(a / scale) ** 2
        closed = (v * (1 - v) if name == "dropout_p" else v) * sech2
        assert float(grad) == pytest.approx(closed, rel=1e-12, abs=1e-300), (a, decades)
        h = 1e-6
        with torch.no_grad():
            difference = (float(_at(params, {name: a + h}).value(name)) - float(_at(params, {name: a - h}).value(name)))
        assert float(grad) == pytest.approx(difference / (2 * h), rel=1e-7, abs=1e-9), (a, decades)


def test_unbounded_is_log_and_logit_space():
    """``bound_decades: null``: start · exp(a), sigmoid(logit p0 + a): the log-space
    parameters ``log start + a`` of an unbounded module, for any a."""
    start = some_start()
    params = FilterParameters(start, bounds={n: None for n in NAMES}, ceilings={})
    # a signed parameter is always bounded: None is its default largest magnitude
    assert params.bounds() == {n: SIGNED[n][1] if n in SIGNED else None for n in NAMES}
    for a in (-40.0, -2.5, 0.7, 30.0):
        values = _at(params, {n: a for n in NAMES}).values()
        for name in POSITIVE:
            assert values[name] == pytest.approx(math.exp(math.log(start[name]) + a), rel=1e-12), (name, a)
        expected = 1 / (1 + math.exp(-(_logit(start["dropout_p"]) + a)))
        assert values["dropout_p"] == pytest.approx(expected, rel=1e-12, abs=1e-300), a
    # far out the dropout rate saturates without NaN, in value and gradient
    for a in (-1e3, 1e3):
        _at(params, {"dropout_p": a})
        p = params.value("dropout_p")
        (grad,) = torch.autograd.grad(p, params.raw["dropout_p"])
        assert float(p.detach()) == (0.0 if a < 0 else 1.0) and float(grad) == 0.0


def test_unbounded_training_takes_the_steps_of_log_space_parameters():
    """The same Adam steps on a loss of the values give the same values as parameters
    stored as their logarithm and logit (the layout without a prior), to rounding."""
    start = some_start()
    learn = ["acc_noise", "gyro_noise", "flow_sigma_scale", "initial_roll_pitch_rad", "dropout_p"]
    target = {n: start[n] * 3.0 if n != "dropout_p" else 0.8 for n in learn}
    params = FilterParameters(start, learn, bounds={n: None for n in NAMES}, ceilings={})
    logs = {n: torch.tensor(_logit(start[n]) if n == "dropout_p" else math.log(start[n]), dtype=torch.float64,
                            requires_grad=True) for n in learn}

    def loss(value) -> torch.Tensor:
        return sum((torch.log(value(n)) - math.log(target[n])) ** 2 for n in learn)

    ours = torch.optim.Adam([params.raw[n] for n in learn], lr=0.2)
    theirs = torch.optim.Adam(list(logs.values()), lr=0.2)
    for _ in range(25):
        for opt, value in ((ours, params.value),
                           (theirs, lambda n: torch.sigmoid(logs[n]) if n == "dropout_p" else torch.exp(logs[n]))):
            opt.zero_grad()
            loss(value).backward()
            opt.step()
    values = params.values()
    for n in learn:
        reference = float((torch.sigmoid(logs[n]) if n == "dropout_p" else torch.exp(logs[n])).detach())
        assert values[n] == pytest.approx(reference, rel=1e-12), n
        assert values[n] != pytest.approx(start[n], rel=1e-3), n  # the steps moved it


def test_model_bounds_override_bound_decades_by_name():
    from flowins.config import build
    from flowins.settings import parameter_sets
    from flowins.training.parameters import ModelSettings

    walks = {"acc_bias_walk": 1e-4, "gyro_bias_walk": 1e-5, "acc_scale_walk": 1e-5}  # configs/model/filter.yaml
    model = build(ModelSettings, {"bound_decades": 1.0, "bounds": {"acc_noise": 0.5, "gyro_noise": None},
                                  "start": walks}, "model")
    bounds = model.parameter_bounds()
    assert bounds == {n: {"acc_noise": 0.5, "gyro_noise": None}.get(n, None if n in SIGNED else 1.0) for n in NAMES}
    assert ModelSettings().parameter_bounds() == {n: None if n in SIGNED else 2.0 for n in NAMES}
    assert build(ModelSettings, {"bound_decades": None}, "model").parameter_bounds() == {n: None for n in NAMES}
    sets = parameter_sets({"model": model, "flow": {}}, NavigationConfig())
    assert sets.bounds == bounds
    _, start, learn = sets  # unpacks as it did
    params = FilterParameters(start, learn, bounds=sets.bounds)
    values = _at(params, {"acc_noise": 1e3, "gyro_noise": 50.0, "initial_velocity_mps": 1e3}).values()
    assert values["acc_noise"] == pytest.approx(start["acc_noise"] * 10 ** 0.5, rel=1e-12)
    assert values["gyro_noise"] == pytest.approx(start["gyro_noise"] * math.exp(50.0), rel=1e-12)  # unbounded
    assert values["initial_velocity_mps"] == pytest.approx(start["initial_velocity_mps"] * 10.0, rel=1e-12)


@pytest.mark.parametrize(("key", "value", "message"), [
    ("bound_decades", 0, r"model\.bound_decades=0: expected a number or null >= 1e-12"),
    ("bound_decades", -1, r"model\.bound_decades=-1: expected"),
    ("bound_decades", "abc", r"model\.bound_decades='abc': expected a number"),
    ("bounds", {"acc_nosie": 1.0}, r"model\.bounds\.acc_nosie: unknown parameter"),
    ("bounds", {"acc_noise": 0.0}, r"model\.bounds\.acc_noise=0\.0: expected a number > 0 or null"),
    ("bounds", {"acc_noise": "abc"}, r"model\.bounds\.acc_noise='abc': expected a number"),
    ("innovation_learns", ["flow_sigma_scal"], r"model\.innovation_learns: unknown parameter 'flow_sigma_scal'"),
    ("select_flow_gate", [0.95, 1.0], r"model\.select_flow_gate\[1\]=1\.0: expected a number < 1"),
    ("select_flow_gate", [0.0], r"model\.select_flow_gate\[0\]=0\.0: expected a number > 0"),
])
def test_a_bad_bound_raises_naming_its_key(key, value, message):
    from flowins.config import build
    from flowins.training.parameters import ModelSettings

    with pytest.raises(ValueError, match=message):
        build(ModelSettings, {key: value}, "model")


def test_bad_bounds_of_the_module_raise():
    with pytest.raises(ValueError, match=r"bounds for unknown parameters \['acc_nosie'\]"):
        FilterParameters(some_start(), bounds={"acc_nosie": 1.0})
    with pytest.raises(ValueError, match=r"the bound of acc_noise must be a number of decades > 0 or None, got -1"):
        FilterParameters(some_start(), bounds={"acc_noise": -1.0})


@pytest.mark.parametrize("decades", [2.0, None])
def test_a_checkpoint_round_trip_keeps_the_values_and_the_bounds(tmp_path, decades):
    from flowins.training.module import FilterLearner

    bounds = {n: decades for n in NAMES} | {"acc_noise": 0.7}
    params = FilterParameters(some_start(), bounds=bounds)
    _at(params, {n: 0.37 * (i - 10) for i, n in enumerate(NAMES) if n not in FROZEN_BY_DEFAULT})
    learner = FilterLearner(params, NavigationConfig(), methods=["ins_gnss"])
    path = tmp_path / "learner.ckpt"
    torch.save({"state_dict": learner.state_dict()}, path)
    state = torch.load(path)["state_dict"]
    assert {k for k in state if k.startswith("params.")} == {f"params.{kind}.{n}" for kind in ("raw", "center", "bound", "ceiling")
                                                             for n in NAMES}
    loaded = FilterParameters.from_checkpoint(path)
    assert loaded.bounds() == params.bounds()
    for name, value in params.values().items():
        assert loaded.values()[name] == pytest.approx(value, rel=1e-12, abs=0.0), name
    assert loaded.learned == []


def test_angle_sigmas_stay_below_their_ceilings_with_a_slope_of_one_at_the_start():
    """Roll/pitch 1-σ below π/2 and yaw below π whatever the bound (null too); below the
    start the plain bound; d ln θ / d a = 1 at the start; a start above its ceiling can only fall."""
    from flowins.training.parameters import CEILINGS

    start = some_start() | {"initial_roll_pitch_rad": 0.35, "initial_yaw_rad": 4.0}
    for decades in (2.0, None):
        params = FilterParameters(start, NAMES, bounds={n: decades for n in NAMES})
        for a in (0.5, 3.0, 50.0, 1e4):
            values = _at(params, {n: a for n in NAMES}).values()
            assert start["initial_roll_pitch_rad"] < values["initial_roll_pitch_rad"] <= math.pi / 2
            assert values["initial_yaw_rad"] == start["initial_yaw_rad"]  # above π already: it can't grow
        up = math.log((math.pi / 2) / 0.35) if decades is None else min(decades * math.log(10), math.log(math.pi / 2 / 0.35))
        for a in (0.5, 3.0):  # an independent evaluation in plain floats
            value = _at(params, {"initial_roll_pitch_rad": a}).values()["initial_roll_pitch_rad"]
            assert value == pytest.approx(0.35 * math.exp(up * math.tanh(a / up)), rel=1e-12)
        assert _at(params, {"initial_roll_pitch_rad": 1e4}).values()["initial_roll_pitch_rad"] == pytest.approx(
            math.pi / 2, rel=1e-12)
        down = _at(params, {"initial_roll_pitch_rad": -1e4, "initial_yaw_rad": -1e4}).values()
        if decades is not None:
            assert down["initial_roll_pitch_rad"] == pytest.approx(0.35 * 10 ** -decades, rel=1e-12)
            assert down["initial_yaw_rad"] == pytest.approx(4.0 * 10 ** -decades, rel=1e-12)
        for name in CEILINGS:
            _at(params, {name: 0.0})
            value = params.value(name)
            (grad,) = torch.autograd.grad(torch.log(value), params.raw[name])
            assert float(grad) == pytest.approx(1.0, rel=1e-12) or name == "initial_yaw_rad"
            _at(params, {name: 1e4})
            (grad,) = torch.autograd.grad(params.value(name), params.raw[name])
            assert math.isfinite(float(grad))


def test_a_checkpoint_without_ceilings_keeps_the_values_it_was_learned_with(tmp_path):
    from flowins.training.module import FilterLearner

    params = FilterParameters(some_start() | {"initial_roll_pitch_rad": 0.35}, ceilings={})
    _at(params, {"initial_roll_pitch_rad": 3.0})
    assert params.values()["initial_roll_pitch_rad"] > math.pi / 2  # learned without a ceiling
    state = {k: v for k, v in FilterLearner(params, NavigationConfig(), methods=["ins"]).state_dict().items()
             if ".ceiling." not in k}
    torch.save({"state_dict": state}, tmp_path / "old.ckpt")
    loaded = FilterParameters.from_checkpoint(tmp_path / "old.ckpt")
    assert loaded.values() == pytest.approx(params.values(), rel=1e-12)
    capped = FilterParameters(some_start() | {"initial_roll_pitch_rad": 0.35})
    _at(capped, {"initial_roll_pitch_rad": 3.0})
    torch.save({"state_dict": FilterLearner(capped, NavigationConfig(), methods=["ins"]).state_dict()},
               tmp_path / "new.ckpt")
    assert FilterParameters.from_checkpoint(tmp_path / "new.ckpt").values() == pytest.approx(capped.values(), rel=1e-12)
    assert capped.values()["initial_roll_pitch_rad"] < math.pi / 2


def test_a_checkpoint_of_log_space_values_loads_as_those_values(tmp_path):
    """The layout without starts and bounds: ``raw.<name>`` is the value's log (logit)."""
    values = some_start()
    values["gyro_bias_walk"] = 14.7  # anywhere: no bound applies to a stored value
    raw = {n: torch.tensor(_logit(v) if n == "dropout_p" else v if n in SIGNED else math.log(v), dtype=torch.float64)
           for n, v in values.items()}  # a signed value is stored as itself
    path = tmp_path / "old.ckpt"
    torch.save({"epoch": 2, "state_dict": {"params.raw." + n: x for n, x in raw.items()}}, path)
    loaded = FilterParameters.from_checkpoint(path)
    for name in NAMES:
        assert loaded.values()[name] == pytest.approx(values[name], rel=1e-12), name
        # the very value the log-space formula gives
        legacy = torch.sigmoid(raw[name]) if name == "dropout_p" else raw[name] if name in SIGNED else torch.exp(raw[name])
        assert loaded.values()[name] == float(legacy), name
    assert loaded.bounds() == {n: SIGNED[n][1] if n in SIGNED else None for n in NAMES}
    assert FilterParameters.from_raw(raw).values() == loaded.values()
    # a checkpoint with some starts but not all is refused, naming what is missing
    state = {**{"params.raw." + n: x for n, x in raw.items()}, "params.center.acc_noise": torch.tensor(1e-3)}
    torch.save({"state_dict": state}, path)
    with pytest.raises(ValueError, match=r"missing the center of \['gyro_noise',"):
        FilterParameters.from_checkpoint(path)


def test_a_selection_history_gives_the_values_it_scored(tmp_path):
    """:class:`~flowins.training.module.FilterLearner` records ``raw`` (the coordinates a) in
    its history; the same module loads them back to the same values (``select_best``)."""
    from flowins.training.module import FilterLearner

    params = FilterParameters(some_start())
    learner = FilterLearner(params, NavigationConfig(), methods=["ins_gnss"])
    _at(params, {"acc_noise": 2.0, "dropout_p": -1.0})
    scored = params.values()
    entry = {"label": "epoch 1", "step": 3, "rmse_m": {"ins_gnss": 1.0}, "score": 1.0,
             "raw": {n: float(q.detach()) for n, q in params.raw.items()}}
    _at(params, {"acc_noise": -3.0, "dropout_p": 0.5})
    learner.history = [entry]
    learner.select_best()
    assert params.values() == scored


def test_a_checkpoint_from_before_the_vehicle_constraint_loads_it_at_its_defaults(tmp_path):
    from flowins.measurements.tracks import TrackUpdate
    from flowins.measurements.vehicle import VehicleSettings
    from flowins.training.module import FilterLearner
    from flowins.training.parameters import ADDED_NAMES

    params = FilterParameters(some_start())
    _at(params, {"acc_noise": 0.8, "gyro_noise": -0.3})
    state = {k: v for k, v in FilterLearner(params, NavigationConfig(), methods=["ins"]).state_dict().items()
             if not any(k.endswith("." + n) for n in ADDED_NAMES)}
    torch.save({"state_dict": state}, tmp_path / "old.ckpt")
    loaded = FilterParameters.from_checkpoint(tmp_path / "old.ckpt").values()
    for name in NAMES:
        if name in ADDED_NAMES:  # the settings' own defaults
            default = (TrackUpdate().sigma_px if name == "tracks_sigma_px"
                       else getattr(TrackUpdate().gate, name.removeprefix("tracks_gate_")) if name.startswith("tracks_gate")
                       else getattr(VehicleSettings(), name.removeprefix("vehicle_")))
            assert loaded[name] == pytest.approx(default, rel=1e-12)
        else:
            assert loaded[name] == pytest.approx(params.values()[name], rel=1e-12), name
    # the learned sigmas reach the constraint's settings
    config = FilterParameters(some_start()).apply(NavigationConfig(), training=False)
    assert config.measurements["vehicle"].lateral_sigma_mps == pytest.approx(some_start()["vehicle_lateral_sigma_mps"])


def test_noise_level_likelihood_needs_two_noise_parameters_in_model_learn():
    """Checked with the settings, before any sequence is loaded, where ``model.learn`` names the parameters."""
    from flowins.training.parameters import ModelSettings

    with pytest.raises(ValueError, match=r"model\.noise_level=likelihood: needs at least two .* gives \['acc_noise'\]"):
        ModelSettings(noise_level="likelihood", learn=("acc_noise", "gyro_noise", "flow_gate_threshold"),
                      freeze=("gyro_noise",))
    assert ModelSettings(noise_level="likelihood", learn=("acc_noise", "gyro_noise")).learn == ("acc_noise", "gyro_noise")


def test_signed_parameters_move_by_their_step_within_their_largest_magnitude():
    """A vehicle's mounting and lever arm: ``θ = W tanh(atanh(θ₀ / W) + u a / W)`` (plain floats
    here), any sign, ``θ₀`` at ``a = 0``, ``|θ| < W`` for every ``a``, the slope ``u`` at
    ``θ₀ = 0``, and the gradient a central difference."""
    start = some_start() | {"vehicle_mount_yaw_rad": 0.0, "vehicle_lever_forward_m": -1.2}
    params = FilterParameters(start, learn=list(SIGNED), bounds={"vehicle_lever_forward_m": 2.0})
    assert float(params.bound["vehicle_lever_forward_m"]) == 2.0 and float(params.bound["vehicle_mount_yaw_rad"]) == 0.3
    for name in SIGNED:
        u = SIGNED[name][0]
        W = float(params.bound[name])
        for a in (-1e4, -3.0, 0.0, 0.4, 25.0, 1e4):
            value = float(_at(params, {name: a}).value(name).detach())
            expected = W * math.tanh(math.atanh(start[name] / W) + u * a / W)
            assert value == pytest.approx(expected, rel=1e-12, abs=1e-15), (name, a)
            assert abs(value) <= W, (name, a)
        _at(params, {name: 0.0})
        assert float(params.value(name).detach()) == start[name]
        a = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
        with torch.no_grad():
            params.raw[name].copy_(a)
        params.raw[name].grad = None
        params.value(name).backward()
        h = 1e-6
        with torch.no_grad():
            difference = float(_at(params, {name: 0.3 + h}).value(name)) - float(_at(params, {name: 0.3 - h}).value(name))
        assert float(params.raw[name].grad) == pytest.approx(difference / (2 * h), rel=1e-7)
        _at(params, {name: 0.0})
    params.raw["vehicle_mount_yaw_rad"].grad = None
    params.value("vehicle_mount_yaw_rad").backward()
    assert float(params.raw["vehicle_mount_yaw_rad"].grad) == pytest.approx(SIGNED["vehicle_mount_yaw_rad"][0], rel=1e-12)
    with pytest.raises(ValueError, match="vehicle_lever_up_m starts at 6.0, which its largest magnitude 5.0"):
        FilterParameters(start | {"vehicle_lever_up_m": 6.0})


def test_learned_mounting_reaches_the_vehicle_constraint():
    """``apply`` writes the signed values into the vehicle settings: tensors while learning them,
    plain numbers (0 leaves the term out) when they are kept."""
    from flowins.measurements.vehicle import VehicleSettings

    start = starting_values(NavigationConfig()) | {"vehicle_mount_pitch_rad": -0.02, "vehicle_lever_up_m": 0.7}
    params = FilterParameters(start, learn=["vehicle_mount_pitch_rad"])
    config = params.apply(NavigationConfig(measurements={"vehicle": VehicleSettings(mode="on")}), training=True)
    vehicle = config.measurements["vehicle"]
    assert isinstance(vehicle.mount_pitch_rad, torch.Tensor) and vehicle.mount_pitch_rad.requires_grad
    assert float(vehicle.mount_pitch_rad) == -0.02 and vehicle.lever_up_m == 0.7 and vehicle.mount_yaw_rad == 0.0
    assert vehicle.mode == "on"


@pytest.mark.parametrize("name", ["flow_gate_threshold", "acc_noise", "initial_roll_pitch_rad"])
def test_coordinate_is_the_inverse_of_value(name):
    """The coordinate at which a parameter takes a value gives that value back, within its
    bound (2 decades) and below its ceiling (the roll/pitch 1-σ: π/2, under 2 decades above its
    start); beyond them it is refused, naming the parameter."""
    from flowins.training.parameters import starting_values

    start = starting_values(NavigationConfig())
    params = FilterParameters(start, learn=[name])
    for factor in (0.011, 0.5, 1.0, 1.7, 40.0):
        v = start[name] * factor
        a = params.coordinate(name, v)
        with torch.no_grad():
            params.raw[name].fill_(a)
        assert float(params.value(name).detach()) == pytest.approx(v, rel=1e-10), (name, factor)
    for v in (start[name] * 150.0, start[name] / 150.0, 0.0):
        with pytest.raises(ValueError, match=rf"{name}=.* lies outside its bound"):
            params.coordinate(name, v)
    if name == "initial_roll_pitch_rad":
        assert start[name] * 100.0 > math.pi / 2
        with pytest.raises(ValueError, match="ceiling 1.5708"):
            params.coordinate(name, 1.6)
    with pytest.raises(ValueError, match="dropout_p is not a positive parameter"):
        params.coordinate("dropout_p", 0.5)
