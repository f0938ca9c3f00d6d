"""flowins on one CUDA GPU against the same work on the CPU (skipped without CUDA; run by
``benchmarks/gpu.sh``). The CPU's own device tests run everywhere on the fake device of
``conftest.FakeDevice``; these check the real one.

Tolerances: the flow network in float32 on a GPU (cuDNN, TF32 allowed) differs from the CPU's
by rounding, at most 0.05 px on these frames; the filter in float64 given the same flow agrees
within 4x what rounding alone moves it on the CPU (the flow times 1 + 1e-15 N(0, 1); the
spread grows from the still start, where the flow has no parallax) and at
least to 1e-6 m; the filter without flow to 1e-6 m; a training step to 1e-6 in each raw
parameter.
"""
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from flowins.data.synthetic import synthetic_walk_recording
from flowins.navigation import NavigationConfig, NavigationRun, navigate, navigate_batch
from flowins.state import STATE

pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (torch.cuda.is_available())")]

CONFIGS = str(Path(__file__).resolve().parents[1] / "configs")
CUDA = torch.device("cuda")


def _config(job: str, overrides: list[str]) -> dict:
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        return OmegaConf.to_container(compose(job, overrides=overrides), resolve=True)


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """A 20 s simulated walk with its camera frames (written once)."""
    from flowins.data.simulate import SimulationConfig, simulate

    folder = tmp_path_factory.mktemp("walk")
    simulate(folder, SimulationConfig(duration_s=20.0, seed=0, flow_every=0), progress=False)
    return folder


def test_the_job_on_the_gpu_agrees_with_the_job_on_the_cpu_cached_and_not(walk, tmp_path):
    from flowins.data.load import load_recording
    from flowins.flow.pairs import FlowPairs
    from flowins.jobs.evaluate import run
    from flowins.measurements.flow import FlowCamera

    def job(device: str, name: str) -> dict:
        run(_config("evaluate", [f"sequence.path={walk}", f"output_dir={tmp_path / name}", f"cache_dir={tmp_path / device}",
                                 f"flow.device={device}", f"filter.device={device}", "flow.mc_mode=moments",
                                 "combinations=[ins_gnss,ins_dense]", "plots=false", "progress=false"]))
        return json.loads((tmp_path / name / "metrics.json").read_text())

    cpu, gpu, cached = job("cpu", "cpu"), job("cuda", "gpu"), job("cuda", "gpu-cached")
    (cpu_file,), (gpu_file,) = ((tmp_path / d / "flow").glob("dense-*.npz") for d in ("cpu", "cuda"))
    a, b = FlowPairs.load(cpu_file), FlowPairs.load(gpu_file)
    flow_a = torch.cat([p.flow_px for p in a.points])
    flow_b = torch.cat([p.flow_px for p in b.points])
    assert flow_a.shape == flow_b.shape and float((flow_a - flow_b).abs().max()) < 0.05
    # the filter on the GPU: no flow, the same numbers; with its own flow, close; cached, the same again
    assert gpu["ins_gnss"]["filter_rmse_m"] == pytest.approx(cpu["ins_gnss"]["filter_rmse_m"], abs=1e-6)
    assert gpu["ins_dense"]["filter_rmse_m"] == pytest.approx(cpu["ins_dense"]["filter_rmse_m"], abs=0.05)
    assert cached["ins_dense"]["filter_rmse_m"] == pytest.approx(gpu["ins_dense"]["filter_rmse_m"], abs=1e-6)
    # given the same (the CPU's) flow, the GPU filter's positions are the CPU filter's
    sequence = _config("evaluate", [f"sequence.path={walk}", f"output_dir={tmp_path / 'read'}"])["sequence"]
    rec = load_recording(sequence, quick=False, progress=False)
    camera = FlowCamera.from_sequence(rec.sequence)
    one = NavigationRun(rec.imu, rec.gnss, flow=a, camera=camera)
    on_cpu = navigate(one, config=NavigationConfig())
    on_gpu = navigate(one, config=NavigationConfig(device=CUDA))
    assert on_gpu.filter.node_mean.device.type == "cuda"
    # what rounding alone does on the CPU: the same flow times (1 + 1e-15 N(0, 1)), two draws
    spread = {"filter": 1e-6, "smoother": 1e-6}
    for seed in (1, 2):
        g = torch.Generator().manual_seed(seed)
        jittered = dataclasses.replace(a, points=[type(p)(p[0], p[1] * (1 + 1e-15 * torch.randn(p[1].shape, generator=g,
                                                  dtype=p[1].dtype)), *p[2:]) for p in a.points])
        again = navigate(dataclasses.replace(one, flow=jittered), config=NavigationConfig())
        for kind, most in list(spread.items()):
            d = (getattr(again, kind).node_mean[:, STATE.p] - getattr(on_cpu, kind).node_mean[:, STATE.p]).norm(dim=-1)
            spread[kind] = max(most, float(d.max()))
    for kind in ("filter", "smoother"):
        p_cpu = getattr(on_cpu, kind).node_mean[:, STATE.p]
        p_gpu = getattr(on_gpu, kind).node_mean[:, STATE.p].cpu()
        assert float((p_cpu - p_gpu).norm(dim=-1).max()) < 4 * spread[kind], (kind, spread)


def test_the_batched_filter_on_the_gpu_equals_each_run_alone_on_the_cpu():
    runs = []
    for seed, duration in ((1, 20.0), (2, 25.0), (3, 30.0)):
        rec = synthetic_walk_recording(duration_s=duration, seed=seed)
        runs.append(NavigationRun(rec.imu, rec.gnss))
    batched = navigate_batch(runs, config=NavigationConfig(device=CUDA))
    for run, result in zip(runs, batched):
        alone = navigate(run, config=NavigationConfig())
        assert result.filter.node_mean.device.type == "cuda"
        for kind in ("filter", "smoother"):  # the smoother magnifies rounding (docs/performance.md): 1e-6 m still
            gap = getattr(result, kind).node_mean[:, STATE.p].cpu() - getattr(alone, kind).node_mean[:, STATE.p]
            assert float(gap.norm(dim=-1).max()) < 1e-6, kind


def test_one_training_epoch_on_the_gpu_takes_the_cpu_steps(tmp_path):
    from flowins.jobs.train import run
    from flowins.training.parameters import NAMES, FilterParameters

    raw = {}
    for trainer in ("cpu", "gpu"):
        out = tmp_path / trainer
        run(_config("train", [f"output_dir={out}", f"cache_dir={tmp_path / 'cache'}", "progress=false", "logger=csv",
                              f"trainer={trainer}", "methods=[ins_gnss]", "filter.gnss_heading.enabled=false",
                              "data.train=[{seed: 1, duration_s: 12.0}]", "data.val=[{seed: 1, duration_s: 12.0}]",
                              "window_s=6.0", "curriculum_window_s=[]", "trainer.max_epochs=1", "model.warmup_steps=0"]))
        last = FilterParameters.from_checkpoint(out / "checkpoints" / "last.ckpt")
        raw[trainer] = np.array([float(last.raw[n]) for n in NAMES])
    assert np.abs(raw["gpu"] - raw["cpu"]).max() < 1e-6


def test_the_free_memory_a_pass_checks_against_is_the_gpu_s():
    from flowins.memory import available_memory_bytes

    torch.cuda.empty_cache()  # the allocator's cached blocks back to the driver: the next allocation takes new memory
    free, total = torch.cuda.mem_get_info(CUDA)
    held = torch.empty(256 << 20, dtype=torch.uint8, device=CUDA)  # 256 MiB more in use
    after = available_memory_bytes(CUDA)
    assert 0 < after <= total
    assert after <= free - (200 << 20)  # the allocation shows (the caching allocator may round up)
    del held
