#!/usr/bin/env bash
# Every GPU figure of docs/performance.md ("One GPU"), on one CUDA machine, in one go:
#   bash benchmarks/gpu.sh [CPU_METRICS_JSON]
# run from anywhere (it works in the checkout, with or without flowins installed). Each
# section prints its wall time. CPU_METRICS_JSON: a CPU run's metrics.json of `python
# evaluate.py` (default: benchmarks/table1_cpu.json) that the GPU Table I is compared with, per cell.
# The simulations, the sparse flow (Lucas-Kanade runs on the CPU on any machine) and the
# training walks' flow are cached in $FLOWINS_GPU_CACHE (default ~/.cache/flowins-gpu); the
# dense flow is removed before the timed job, so that it computes it on the GPU.
# A check of the script itself on a CPU: GPU_SH_DEVICE=cpu GPU_SH_QUICK=1 bash benchmarks/gpu.sh
# (every section on the CPU, the 60 s walk, a batch of 4, one training epoch; the device
# tests are skipped there). Its figures mean nothing.
# GPU_SH_SECTIONS="2 5 3 4 6 1" runs only those sections, in that order (default: all nine, in
# order; 3 and 4 need 2's cache, 6 needs 5's). The sections run one at a time: sections 2 and 5
# side by side on an H200 machine's 16 cores finished neither simulation in 590 s, where
# section 2's alone takes 97 s.
# GPU_SH_TRAIN_S=N and GPU_SH_BENCH_S=N stop section 6 and section 4 after N s (they print
# what they measured up to then: section 6 a line per epoch). GPU_SH_PROFILE_S=N: section 4
# also prints torch.profiler's table (CPU and CUDA time per operation) of one run and of the
# batch over the walk's first N s. GPU_SH_BENCH_QUICK=1: section 4 on the 60 s walk. One
# 10-minute call of a 15-minute lease fits GPU_SH_SECTIONS="4 7 3" GPU_SH_BENCH_QUICK=1
# GPU_SH_PROFILE_S=4 GPU_SH_BENCH_S=200 (on an H200: section 4 so, with the profiles, about 200 s;
# section 7 142 s; section 3 with nothing cached 196 s; section 5 alone 144 s). Section 7
# times one training step of a 20 s window on the GPU with GPU_SH_TRAIN_ROWS rows (default 2,8,32; the
# default training's step has 2: one sequence, two methods), what a larger data.batch_size would cost
# per step. Section 8 times the triangulation's eigh against Jacobi (what the GPU runs) and the
# adjugate solve of bench_triangulation.py on the GPU (256 and 2048 points a call). Section 9 times one
# recording of the 60 s walk (cached by section 2 or 4) eager and with filter.compile=true (every
# step as CUDA graphs: inductor, mode="reduce-overhead"), each line with its compile time; capped
# by GPU_SH_COMPILE_S (default 400 s) per run. A section that fails is
# reported and the others still run; the script then exits with 1, naming the failed sections.
set -uo pipefail
cd "$(dirname "$0")/.."
# the checkout's package for every script and child process (a CUDA machine may run it uninstalled)
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 MPLBACKEND=Agg
cache=${FLOWINS_GPU_CACHE:-$HOME/.cache/flowins-gpu}
export FLOWINS_CACHE=$cache
device=${GPU_SH_DEVICE:-cuda}
quick=()
bench_quick=()
batch=256
epochs=()
# the benchmark on the 60 s walk: its simulation, flow and warm-up took about 35 s on an H200,
# where the 300 s walk's simulation alone takes 97 s
[ "${GPU_SH_BENCH_QUICK:-0}" = 1 ] && bench_quick=(--quick)
if [ "${GPU_SH_QUICK:-0}" = 1 ]; then
  quick=(quick=true)
  bench_quick=(--quick)
  batch=4
  epochs=(trainer.max_epochs=1)
fi
reference=${1:-benchmarks/table1_cpu.json}
out=$(mktemp -d)
started=$SECONDS
sections=${GPU_SH_SECTIONS:-1 2 3 4 5 6 7 8 9}
for n in $sections; do
  [[ " 1 2 3 4 5 6 7 8 9 " == *" $n "* ]] || { echo "error: GPU_SH_SECTIONS: no section $n (1 to 9)"; exit 1; }
done
failed=()
section() { echo; echo "== [$((SECONDS - started)) s] $*"; }
# run "$@" for at most $1 s (0: no limit); a stop at the limit is said, and is no failure
capped() {
  local limit=$1; shift
  [ "$limit" = 0 ] && { "$@"; return; }
  timeout "$limit" "$@"
  local rc=$?
  [ "$rc" = 124 ] && { echo "stopped at the limit of $limit s"; return 0; }
  return "$rc"
}

section "the machine"
GPU_SH_DEVICE=$device python - <<'PY' || exit 1
import os

import torch
if os.environ["GPU_SH_DEVICE"] == "cpu":
    print(f"the CPU (a check of the script), torch {torch.__version__}")
elif not torch.cuda.is_available():
    raise SystemExit("error: torch.cuda.is_available() is False: no CUDA GPU for benchmarks/gpu.sh")
else:
    print(f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}, CUDA {torch.version.cuda}, "
          f"{torch.cuda.get_device_properties(0).total_memory / 2**30:.0f} GiB")
PY

s1() {
  section "1. the device tests (tests/test_cuda.py: both devices agree; a pass's waits for the GPU)"
  python -m pytest -q -p no:cacheprovider -o addopts="-ra --import-mode=importlib" -m cuda tests/test_cuda.py \
    tests/measurements/test_flow_frames.py  # no xdist there
}

s2() {
  section "2. the 300 s walk simulated and its sparse flow computed, once (CPU; cached in $cache)"
  python evaluate.py "${quick[@]}" progress=false plots=false 'combinations=[ins,ins_sparse]' \
    hydra.run.dir="$out/simulate" | grep --line-buffered -E "sequence:|flow:|error" || return
  rm -f "$cache"/flow/dense-*.npz
}

s3() {
  section "3. python evaluate.py flow.device=cuda filter.device=cuda (simulation and sparse flow cached; target <= 60 s)"
  local t0=$SECONDS
  python evaluate.py "${quick[@]}" flow.device="$device" filter.device="$device" progress=false plots=false \
    hydra.run.dir="$out/gpu" || return
  echo "evaluate.py on the GPU: $((SECONDS - t0)) s"
  python benchmarks/gpu_table.py "$out/gpu/metrics.json" "$reference"
}

s4() {
  section "4. bench_flow_filter.py --device cuda --batch 256 (cached flow; target >= 2000x in all)"
  capped "${GPU_SH_BENCH_S:-0}" python benchmarks/bench_flow_filter.py "${bench_quick[@]}" --device "$device" \
    --batch "$batch" --repeats 1 --reference-s 0 --breakdown-s 0 --count-ops-s 0 --profile-s "${GPU_SH_PROFILE_S:-0}" \
    2>&1 | grep --line-buffered -v "^filter:"
}

trainer=gpu
[ "$device" = cpu ] && trainer=cpu
s5() {
  section "5. the training walks simulated and their flow computed (train.py trainer.max_epochs=0)"
  python train.py experiment=mistuned 'data.select=[]' trainer="$trainer" trainer.max_epochs=0 flow.device="$device" \
    progress=false hydra.run.dir="$out/train-data" 2>&1 | tail -n 3
}

s6() {
  section "6. python train.py experiment=mistuned trainer=gpu (walks and flow cached; target: 4x the 2-core CPU's time, held out within 5 %)"
  local t0=$SECONDS
  # without the three 300 s selection walks, as the CPU's reference time was taken
  capped "${GPU_SH_TRAIN_S:-0}" python train.py experiment=mistuned 'data.select=[]' trainer="$trainer" "${epochs[@]}" \
    flow.device="$device" progress=false hydra.run.dir="$out/train" 2>&1 \
    | grep --line-buffered -v "read from the cache" || return  # a line per validation as it ends (grep flushes each line: a capped run still shows them)
  echo "train.py on the GPU: $((SECONDS - t0)) s"
}

s7() {
  section "7. a training step as its rows grow (bench_train_ops.py: one 20 s window, repeated as a larger data.batch_size would)"
  # grep -v finding nothing to print is no failure; the benchmark's own exit status is the section's
  python benchmarks/bench_train_ops.py --device "$device" --rows "${GPU_SH_TRAIN_ROWS:-2,8,32}" 2>&1 \
    | { grep --line-buffered -v "read from the cache" || true; }
}

s8() {
  section "8. the triangulation: eigh + Newton step against the eigh-free solve (bench_triangulation.py)"
  local points
  for points in 256 2048; do
    python benchmarks/bench_triangulation.py --device "$device" --points "$points" --frames 100 || return
  done
}

s9() {
  section "9. filter.compile=true: one recording's steps as CUDA graphs (bench_flow_filter.py --quick --batch 0)"
  local setting
  for setting in false true; do
    echo "filter.compile=$setting"
    capped "${GPU_SH_COMPILE_S:-400}" python benchmarks/bench_flow_filter.py --quick --device "$device" --batch 0 \
      --repeats 3 --reference-s 0 --breakdown-s 0 --count-ops-s 0 filter.compile="$setting" 2>&1 \
      | { grep --line-buffered -E "compiled|flowins:|RESULT|error" || true; } || return
  done
}

for n in $sections; do
  "s$n" || { echo "error: section $n failed (exit $?)"; failed+=("$n"); }
done

section "done in $((SECONDS - started)) s; outputs in $out"
if [ ${#failed[@]} -gt 0 ]; then
  echo "error: sections failed: ${failed[*]}"
  exit 1
fi
