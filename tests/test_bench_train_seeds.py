"""``benchmarks/bench_train_seeds.py``: issue 62's criteria over training runs, by hand."""
import pytest


def test_the_criteria_of_runs_against_hand_tuning(repo_module):
    """Hand-tuning 4, 5, 6 m (mean 5). Run 0: 4, 4, 4 (mean 4, 0.8x); run 1: 3, 6, 6 (mean 5,
    1.0x; walk 9 is 6/5 = +20 %, at the limit): both at or below, spread 5/4 = 1.25, worst
    +20 %: met. A third run 6, 6, 6 (mean 6) is above: 2 of 3, spread 1.5, worst 6/4 = +50 %."""
    bench = repo_module("benchmarks/bench_train_seeds.py")
    hand = {8: 4.0, 9: 5.0, 10: 6.0}
    runs = {0: {8: 4.0, 9: 4.0, 10: 4.0}, 1: {8: 3.0, 9: 6.0, 10: 6.0}}
    result = bench.criteria(runs, hand)
    assert result["hand_mean"] == pytest.approx(5.0)
    assert result["means"] == pytest.approx({0: 4.0, 1: 5.0})
    assert result["ratios"] == pytest.approx({0: 0.8, 1: 1.0})
    assert result["at_or_below"] == 2
    assert result["spread"] == pytest.approx(1.25)
    assert result["worst_walk"] == {"ratio": pytest.approx(1.2), "run": 1, "walk": 9}
    assert result["met"]
    runs[2] = {8: 6.0, 9: 6.0, 10: 6.0}
    result = bench.criteria(runs, hand)
    assert result["at_or_below"] == 2 and not result["met"]
    assert result["spread"] == pytest.approx(1.5)
    assert result["worst_walk"] == {"ratio": pytest.approx(1.5), "run": 2, "walk": 8}
    printed = bench.table(runs, hand, result)
    assert printed.splitlines()[-1] == "RESULT runs=3 at_or_below=2 spread=1.50 worst_walk=+50.0%"
    assert "seed 2" in printed and "1.20x" in printed  # run 2's mean 6 against 5
    # the runs' means 4, 5, 6: mean 5, sample standard deviation 1, median 5
    assert (result["runs_mean"], result["runs_std"], result["runs_median"]) == pytest.approx((5.0, 1.0, 5.0))
    assert "the runs' means: 5.00 ± 1.00 m (mean ± std over 3 runs; median 5.00 m)" in printed


def test_arguments_after_the_separator_go_to_training(repo_module, tmp_path, monkeypatch):
    """``-- KEY=VALUE`` reaches every ``train.py`` call; ``--jobs 0`` is refused."""
    bench = repo_module("benchmarks/bench_train_seeds.py")
    calls = []

    def fake_call(args, **kwargs):
        calls.append(args)
        if "train.py" in args:
            run = next(a.split("=", 1)[1] for a in args if a.startswith("hydra.run.dir="))
            (tmp_path / run / "checkpoints").mkdir(parents=True, exist_ok=True)
            (tmp_path / run / "checkpoints" / "best.ckpt").write_text("")
        return 0

    monkeypatch.setattr(bench.subprocess, "call", fake_call)
    monkeypatch.setattr(bench, "score", lambda label, ckpt, heldout, out, reuse: {w: 1.0 for w in heldout})
    assert bench.main(["--out", str(tmp_path), "--seeds", "3", "--", "trainer.max_epochs=2"]) == 0
    (train,) = calls
    assert "seed=3" in train and "trainer.max_epochs=2" in train and "experiment=mistuned" in train
    with pytest.raises(SystemExit):
        bench.main(["--out", str(tmp_path), "--jobs", "0"])


def test_reuse_keeps_only_what_the_same_arguments_made(repo_module, tmp_path, monkeypatch):
    """``--reuse``: a score of other held-out walks, or a run with other overrides, is made
    again; one of the same arguments is read back without a call."""
    import json

    bench = repo_module("benchmarks/bench_train_seeds.py")
    calls = []

    def fake_call(args, **kwargs):
        calls.append(args)
        run = next(a.split("=", 1)[1] for a in args if a.startswith("hydra.run.dir="))
        if "train.py" in args:
            (tmp_path / run / "checkpoints").mkdir(parents=True, exist_ok=True)
            (tmp_path / run / "checkpoints" / "best.ckpt").write_text("")
        else:
            seeds = next(a for a in args if a.startswith("sequence.seeds="))[len("sequence.seeds=["):-1].split(",")
            per_seed = {s: {"filter_rmse_m": float(s)} for s in seeds}
            (tmp_path / run / "metrics.json").write_text(json.dumps({"ins_dense": {"per_seed": per_seed}}))
        return 0

    monkeypatch.setattr(bench.subprocess, "call", fake_call)
    assert bench.score("hand-tuned", None, [8, 9], tmp_path, True) == {8: 8.0, 9: 9.0}
    assert bench.score("hand-tuned", None, [8, 9], tmp_path, True) == {8: 8.0, 9: 9.0}
    assert len(calls) == 1
    assert bench.score("hand-tuned", None, [8, 10], tmp_path, True) == {8: 8.0, 10: 10.0}
    assert len(calls) == 2
    bench.train(0, tmp_path, 1, ["a=1"], True)
    bench.train(0, tmp_path, 1, ["a=1"], True)
    assert len(calls) == 3
    bench.train(0, tmp_path, 1, ["a=2"], True)
    assert len(calls) == 4
