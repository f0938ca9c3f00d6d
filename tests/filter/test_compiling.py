"""``filter.compile`` (:mod:`flowins.filter.compiling`): which compiler a setting gives, and a
filter pass whose flow frames run through ``torch.compile`` against the eager pass."""
import dataclasses
import logging

import pytest
import torch

from flowins.filter import compiling
from flowins.filter.compiling import Compiler, bucket, compiler_for
from flowins.filter.runner import run_filters
from flowins.flow.points import FlowPoints
from flowins.ins.mechanization import ProcessNoise


def test_bucket_is_the_next_power_of_two_from_the_smallest():
    assert [bucket(n) for n in (0, 1, 64, 65, 128, 129, 300)] == [64, 64, 64, 128, 128, 256, 512]
    assert bucket(5, smallest=8) == 8 and bucket(9, smallest=8) == 16


def test_the_setting_gives_eager_inductor_or_an_error_that_names_it(monkeypatch):
    cpu = torch.device("cpu")
    assert not compiler_for("false", cpu).enabled
    monkeypatch.setenv("CXX", "no-such-compiler-flowins")
    assert compiling.cpp_compiler() is None
    auto = compiler_for("auto", cpu)
    assert not auto.enabled and "no C++ compiler" in auto.reason and "eager" in auto.describe()
    with pytest.raises(ValueError, match=r"filter.compile=true: no C\+\+ compiler found"):
        compiler_for("true", cpu)
    with pytest.raises(ValueError, match="filter.compile='sometimes': expected one of false, true, auto"):
        compiler_for("sometimes", cpu)
    monkeypatch.setenv("CXX", "sh")  # any program on the path stands for one here
    found = compiler_for("auto", cpu)
    assert found.backend == "inductor" and found.mode is None and "sh" in found.reason
    cuda = compiler_for("true", torch.device("cuda"))  # a setting, not a device: nothing runs on it here
    assert cuda.backend == "inductor" and cuda.mode == "reduce-overhead" and cuda.all_steps
    assert not found.all_steps  # on a CPU only the flow frames compile


def test_the_filter_config_reads_yaml_booleans_and_names_a_bad_value():
    from flowins.settings import navigation_config

    base = {"acc_noise": 0.01, "gyro_noise": 0.001, "acc_bias_walk": 0.0, "gyro_bias_walk": 0.0}
    assert navigation_config({**base, "compile": False}).compile == "false"
    assert navigation_config({**base, "compile": True}).compile == "true"
    assert navigation_config({**base, "compile": "auto"}).compile == "auto"
    with pytest.raises(ValueError, match="compile"):
        navigation_config({**base, "compile": "sometimes"})


def _thinned(run, counts):
    """``run`` with its flow frames' points cut to ``counts`` in turn (frames without points kept)."""
    events, k = [], 0
    for event in run.events:
        if len(getattr(event, "points", ())) > 0:
            n = counts[k % len(counts)]
            k += 1
            event = dataclasses.replace(event, points=FlowPoints(*(p[:n] for p in event.points[:3])))
        events.append(event)
    return dataclasses.replace(run, events=events)


def test_a_pass_with_its_steps_compiled_equals_the_eager_pass_and_compiles_one_shape_per_kind(repo_module):
    """Three runs of flow frames with 20 to 60 points (each frame's count its own), at times of
    their own (one, two or three rows meet at a frame), through ``torch.compile(fullgraph=True)``
    with a backend that needs no compiler: the same nodes, transitions and logs as eager to 1e-9,
    and one compiled shape of each step for the whole pass (every row at every frame, the points
    padded to one bucket of 64 with a mask; every segment's IMU steps, nodes and intervals padded
    to one size), not one per count of points, steps and rows; alone, the same."""
    frames = repo_module("tests/measurements/test_flow_frames.py")
    runs = [_thinned(frames._flow_run(5.0, 6.5, 60, 1, own_camera=False)[0], [60, 20, 47, 33]),
            _thinned(frames._flow_run(5.03, 6.2, 60, 2, own_camera=False)[0], [25, 58]),
            _thinned(frames._flow_run(5.0, 6.0, 60, 3, own_camera=True)[0], [40, 21, 59])]
    torch._dynamo.reset()
    compiling._COMPILED.clear()
    compiler = Compiler("eager", reason="test", all_steps=True)
    with torch.inference_mode():
        eager = run_filters(runs, noise=ProcessNoise())
        compiled = run_filters(runs, noise=ProcessNoise(), compiler=compiler)
    for a, b in zip(compiled, eager, strict=True):
        assert torch.equal(a.t_s, b.t_s)
        assert [e.get("valid") for e in a.log] == [e.get("valid") for e in b.log]
        for name in ("node_mean", "node_cov"):
            x, y = getattr(a, name), getattr(b, name)
            torch.testing.assert_close(x, y, rtol=0, atol=1e-9 * max(1.0, float(y.abs().max())))
        torch.testing.assert_close(a.transition, b.transition, rtol=0, atol=1e-9)
    assert sum(e.get("kind") == "flow" for e in eager[0].log) >= 10
    # one shape per kind of step: the flow frame and the propagation between events
    assert compiler.compiles == 2 and compiler.calls >= 20, compiler
    assert "compiled with eager" in compiler.describe()
    with torch.inference_mode():  # one run (its steps padded, not sliced); and the flow frames alone, as on a CPU
        alone, frames_only = Compiler("eager", reason="test", all_steps=True), Compiler("eager", reason="test")
        a, b = run_filters(runs[:1], noise=ProcessNoise(), compiler=alone)[0], eager[0]
        c = run_filters(runs[:1], noise=ProcessNoise(), compiler=frames_only)[0]
    for name in ("node_mean", "node_cov", "transition"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=0, atol=1e-9)
        torch.testing.assert_close(getattr(c, name), getattr(b, name), rtol=0, atol=1e-9)
    assert alone.compiles == 2 and alone.calls >= 20, alone
    assert frames_only.calls == sum(e.get("kind") == "flow" for e in eager[0].log), frames_only


def test_a_run_reports_its_steps_where_compiling_was_asked(monkeypatch):
    """``NavigationResult.filter_steps``: None with ``filter.compile=false``; compiled, the steps
    that compiled (a run without flow frames: its propagation and its fixes' update); with
    ``auto`` and no compiler, why the steps ran eagerly."""
    from flowins.data.synthetic import synthetic_walk_recording
    from flowins.navigation import NavigationConfig, NavigationRun, navigate

    rec = synthetic_walk_recording(duration_s=8.0, seed=5)
    run = NavigationRun(rec.imu, rec.gnss)
    assert navigate(run, config=NavigationConfig()).filter_steps is None
    import flowins.navigation as navigation
    torch._dynamo.reset()  # the shape compiles here, not in an earlier test
    compiling._COMPILED.clear()
    with monkeypatch.context() as patch:  # compiled (a backend that needs no compiler), every step
        patch.setattr(navigation, "compiler_for",
                      lambda setting, device: Compiler("eager", reason="test", all_steps=True))
        steps = navigate(run, config=NavigationConfig(compile="true")).filter_steps
    assert steps.startswith("filter steps: compiled with eager (test); 2 shape(s)"), steps  # propagation, fixes
    monkeypatch.setenv("CXX", "no-such-compiler-flowins")
    steps = navigate(run, config=NavigationConfig(compile="auto")).filter_steps
    assert steps.startswith("filter steps: eager") and "no C++ compiler" in steps


def test_a_step_says_when_it_compiles_a_shape_and_what_that_took(caplog):
    """Compiling takes minutes on a CPU, with nothing else on the job's output: the log says so
    before the call that compiles a shape (naming the step and its largest input) and after it,
    and says nothing for a shape met before."""
    def doubled(x, y):
        return x * 2 + y.sum()

    compiler = Compiler("eager", reason="test")
    with caplog.at_level(logging.INFO, logger="flowins"):
        for rows in (3, 3, 5):
            compiler(doubled, torch.ones(rows, 2), torch.ones(4))
    lines = [r.getMessage() for r in caplog.records if r.name == "flowins.filter.compiling"]
    name = "test_a_step_says_when_it_compiles_a_shape_and_what_that_took.<locals>.doubled"
    assert [line.split(" for ")[0] for line in lines if "compiling" in line] == [
        f"filter steps: compiling {name} (shape {k} of it in this process) with eager" for k in (1, 2)], lines
    assert "inputs up to (3, 2)" in lines[0] and "inputs up to (5, 2)" in lines[2], lines
    assert len(lines) == 4 and all(" compiled in " in line and "backward" not in line for line in lines[1::2]), lines
    assert compiler.compiles == 2
    caplog.clear()  # with a gradient: its backward compiles later, in the backward pass, and the log says so
    with caplog.at_level(logging.INFO, logger="flowins"):
        compiler(doubled, torch.ones(3, 2, requires_grad=True), torch.ones(4))
    lines = [r.getMessage() for r in caplog.records if r.name == "flowins.filter.compiling"]
    assert "shape 3 of it" in lines[0] and "with gradients" in lines[0], lines
    assert lines[1].endswith("; its backward compiles at the first backward pass"), lines


def test_copied_clones_every_tensor_through_named_tuples_dicts_and_lists():
    """What is kept of a CUDA graph's outputs (``mode="reduce-overhead"``) is a copy: every tensor
    in the step's named tuple, its dict of values and any list, in new memory, equal; the rest as is."""
    from flowins.measurements.flow_update import FlowFrameStep

    t = torch.arange(6.0).reshape(2, 3)
    out = FlowFrameStep(t, t[0], {"valid": t[1]}, None, [t, "x"], None, 3)
    got = compiling.copied(out)
    assert type(got) is FlowFrameStep and got.gated is None and got.nll is None and got.nll_count == 3
    tensors = [(got.mean, out.mean), (got.cov, out.cov), (got.values["valid"], out.values["valid"]),
               (got.failed[0], out.failed[0])]
    for new, old in tensors:
        assert torch.equal(new, old) and new.data_ptr() != old.data_ptr()
    assert got.failed[1] == "x"


def test_compiling_does_not_print_what_tracing_says_about_cached_constants():
    """Tracing a step through a cached constant (:func:`~flowins.constants.cached_constant`) makes
    dynamo warn once per function, dozens of lines on a job's output: the compiler keeps them out,
    and the step is still exact."""
    import warnings

    from flowins.constants import cached_constant

    @cached_constant
    def _twos(dtype, device):  # a function of its own: dynamo warns once per function
        return torch.full((3,), 2.0, dtype=dtype, device=device)

    def step(x):
        return x * _twos(x.dtype, x.device)

    x = torch.arange(3.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        got = Compiler("eager", reason="test")(step, x)
    assert torch.equal(got, 2 * x)
    assert not [w for w in seen if "lru_cache" in str(w.message)], [str(w.message) for w in seen]


def _two_runs_of_every_event_kind(repo_module) -> list:
    """The runs of every event kind ending at 7 s and at 6 s (their events differ), with nothing
    compiled yet in this process."""
    frames = repo_module("tests/measurements/test_flow_frames.py")
    runs = []
    for end_s in (7.0, 6.0):
        run, events = frames._every_event_kind(end_s)
        runs.append(dataclasses.replace(run, events=events))
    torch._dynamo.reset()
    compiling._COMPILED.clear()
    return runs


def test_a_pass_of_every_event_kind_with_every_step_compiled_equals_the_eager_pass(repo_module):
    """``Compiler.all_steps`` (what CUDA runs): the flow frames, the propagation and every other
    event's gated update (GNSS fixes with a reset, a zero-velocity and two vehicle updates) through
    ``torch.compile(fullgraph=True)`` with a backend that needs no compiler, alone and as a batch of
    two runs whose events differ (one row at a fix the other lacks: the update's rows and blocks
    padded to a fixed shape): the same nodes, transitions and logs as eager to 1e-9, a shape per
    kind of step, not one per call."""
    runs = _two_runs_of_every_event_kind(repo_module)
    for batch in (runs[:1], runs):
        compiler = Compiler("eager", reason="test", all_steps=True)
        with torch.inference_mode():
            eager = run_filters(batch, noise=ProcessNoise(), likelihood=True)
            compiled = run_filters(batch, noise=ProcessNoise(), likelihood=True, compiler=compiler)
        for a, b in zip(compiled, eager, strict=True):
            assert torch.equal(a.t_s, b.t_s)
            assert [(e.get("kind"), e.get("accepted")) for e in a.log] == [(e.get("kind"), e.get("accepted"))
                                                                           for e in b.log]
            for name in ("node_mean", "node_cov", "transition"):  # padded sums round apart: 1e-9 of the largest
                want = getattr(b, name)
                torch.testing.assert_close(getattr(a, name), want, rtol=0, atol=1e-9 * max(1.0, float(want.abs().max())))
            torch.testing.assert_close(a.nll, b.nll, rtol=1e-9, atol=0)  # log-dets summed in another order
        kinds = {e.get("kind") for e in eager[0].log}
        assert {"flow", "gnss", "zero_velocity", "vehicle"} <= kinds, kinds
        updates = sum(e.get("kind") in ("gnss", "zero_velocity", "vehicle") for e in eager[0].log)
        assert compiler.calls >= updates + 20 and compiler.compiles <= 8, compiler


def _training_pass(runs, compiler, scale_value, acc_value):
    """Loss and gradients of a pass over ``runs`` whose flow noise scale and accelerometer noise
    density are tensors that carry a gradient (as a training step's are)."""
    from flowins.measurements.flow_update import FlowFrame

    scale = torch.tensor(scale_value, dtype=torch.float64, requires_grad=True)
    acc = torch.tensor(acc_value, dtype=torch.float64, requires_grad=True)
    learned = []
    for run in runs:
        events = [dataclasses.replace(e, update=dataclasses.replace(e.update, sigma_scale=scale))
                  if isinstance(e, FlowFrame) else e for e in run.events]
        learned.append(dataclasses.replace(run, events=events))
    tracks = run_filters(learned, noise=ProcessNoise(acc_noise=acc), likelihood=True, compiler=compiler)
    loss = sum(t.node_mean[:, :6].square().sum() + t.node_cov.diagonal(dim1=-2, dim2=-1).sum() + t.nll
               for t in tracks)
    return loss.detach(), torch.autograd.grad(loss, (scale, acc))


def test_a_window_whose_first_frames_mean_has_no_gradient_compiles_one_shape(repo_module):
    """A training window starts from the detached state of the one before: at its first flow
    frames the mean carries no gradient while the covariance does (the process noise is learned).
    The compiled step still meets one shape in the pass, not one for each, and its loss and
    gradients are the eager pass's."""
    frames = repo_module("tests/measurements/test_flow_frames.py")
    run, _, _ = frames._flow_run(5.0, 6.0, 40, 3, own_camera=False)
    torch._dynamo.reset()
    compiling._COMPILED.clear()
    assert not run.mean0.requires_grad
    compiler = Compiler("eager", reason="test")
    want_loss, want = _training_pass([run], None, 1.0, 3e-3)
    got_loss, got = _training_pass([run], compiler, 1.0, 3e-3)
    assert compiler.calls >= 5 and compiler.compiles == 1, compiler
    torch.testing.assert_close(got_loss, want_loss, rtol=1e-9, atol=0)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-9, atol=0)


def _gradients_agree(repo_module, *, backend: str, all_steps: bool, rtol: float) -> None:
    """The two runs of every event kind as one batch, at two sets of parameter values: the compiled
    pass's loss and gradients against the eager pass's, and nothing compiled at the second values."""
    runs = _two_runs_of_every_event_kind(repo_module)
    for scale, acc in ((1.0, 3e-3), (1.7, 8e-3)):
        compiler = Compiler(backend, reason="test", all_steps=all_steps)
        want_loss, want = _training_pass(runs, None, scale, acc)
        got_loss, got = _training_pass(runs, compiler, scale, acc)
        assert compiler.calls >= 10, compiler
        torch.testing.assert_close(got_loss, want_loss, rtol=rtol, atol=0)
        for g, w in zip(got, want, strict=True):
            assert float(w.abs()) > 0
            torch.testing.assert_close(g, w, rtol=rtol, atol=0)
        if scale != 1.0:  # other values, the same shapes: nothing compiled again
            assert compiler.compiles == 0, compiler


def test_a_pass_with_a_gradient_through_its_compiled_flow_frames_gives_the_eager_gradients(repo_module):
    """A training pass (its noise parameters carry a gradient) runs its flow frames compiled, as
    ``filter.compile`` does on a CPU: two runs of every event kind in one batch (the flow frames
    iterated, gated, with the recovery; one row at a frame the other lacks, padded), through
    ``torch.compile(fullgraph=True)`` with a backend that needs no compiler. The loss and the
    gradients of the flow noise scale and the accelerometer noise density equal the eager pass's to
    1e-9, relative; the next step's parameter values compile nothing new."""
    _gradients_agree(repo_module, backend="eager", all_steps=False, rtol=1e-9)


@pytest.mark.slow
def test_a_pass_with_a_gradient_through_every_compiled_step_gives_the_eager_gradients(repo_module):
    """As above, with the backward traced by AOT autograd as inductor traces it (``aot_eager``), and
    every step compiled (``Compiler.all_steps``): the propagation between events and the GNSS
    fixes' (with a reset), the zero-velocity and the vehicle updates too, their steps, nodes, rows
    and blocks padded to fixed shapes. The padded sums round apart from eager's, which the
    gradients magnify: they agree to 1e-7, relative (3e-8 seen); the flow frames alone to 1e-9."""
    _gradients_agree(repo_module, backend="aot_eager", all_steps=True, rtol=1e-7)
    _gradients_agree(repo_module, backend="aot_eager", all_steps=False, rtol=1e-9)
