#!/usr/bin/env bash
# One timed GPU session, for a machine with a CUDA GPU and a python3 that holds torch (no project
# install; the packages it lacks installed beforehand from carried wheels: pycolmap, which reads the
# scene (a text model without its 2D points keeps the scene small), plyfile and tyro). In order,
# inside a budget of BUDGET_S seconds (default 580), each step under its own timeout so that a slow
# step leaves the others their time:
#   1. tests/test_compiled.py (the compiled loss terms and render maps on CUDA), beside 2.
#   2. the CUDA extension build (about 100 s on a fresh machine)
#   3. bench/gpu_train.py: a whole training run (preset full, ITERS iterations, 640x480; TRAIN_ARGS=--compile
#      for splat/compiled.py) on SCENE with CUES, the Gaussians written compactly for `splat mesh` on a machine with Open3D
#   4. bench/train_step_bench.py: one training step at 640x480 with 300k Gaussians, the step without
#      splat/compiled.py ("fused-adam") and with it ("today") side by side
#   5. the CUDA rasterizer tests, in the time that is left
# Usage: bash bench/gpu_session.sh OUT SCENE CUES [ITERS]
# Writes at most 8 files: OUT/pytest.log, OUT/train_step_*.json, OUT/train_console.log, OUT/run/.
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:?usage: bench/gpu_session.sh OUT SCENE CUES [ITERS]}" scene="${2:?SCENE}" cues="${3:?CUES}"
iters="${4:-30000}" budget="${BUDGET_S:-580}" device="${DEVICE:-cuda}"  # DEVICE=cpu: a dry run of the script
mkdir -p "$out/run"
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}" PYTHONUNBUFFERED=1
left() { echo $(( budget - SECONDS )); }
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no GPU')"
(timeout 200 python3 -m pytest -q -p no:cacheprovider tests/test_compiled.py >"$out/pytest.log" 2>&1;
 echo "test_compiled rc $?" >>"$out/pytest.log") &
tests=$!
timeout 240 python3 -c "from splat.cuda_ext import ext; print('built', ext)" 2>&1 | tail -3
echo "build done at ${SECONDS}s"
wait "$tests"; tail -3 "$out/pytest.log"
echo "$(left) s left for the run"
timeout -k 20 $(( $(left) - 100 )) python3 bench/gpu_train.py "$scene" "$cues" /tmp/gpu_run --iters "$iters" \
    --device "$device" --backend auto --split-mb 15 ${TRAIN_ARGS:-} >"$out/train_console.log" 2>&1
echo "train rc $? at ${SECONDS}s"; tail -5 "$out/train_console.log"
cp /tmp/gpu_run/gpu_train.json /tmp/gpu_run/gaussians.npz.part-* "$out/run/" 2>/dev/null
log=/tmp/gpu_run/train_log.jsonl; [ -f "$log" ] || log=/tmp/gpu_run.partial/train_log.jsonl  # a stopped run
gzip -c "$log" >"$out/run/train_log.jsonl.gz" 2>/dev/null
timeout -k 5 $(( $(left) > 110 ? 90 : $(left) - 20 )) python3 bench/train_step_bench.py --name cuda_h100_compiled --device "$device" --sizes 640x480 \
    --counts "${COUNT:-300000}" --variants fused-adam today --iters 20 2>&1 | grep -v Warning | tail -8
cp bench/results/train_step_cuda_h100_compiled.json "$out/" 2>/dev/null
if [ "$(left)" -gt 20 ]; then
    timeout $(( $(left) - 10 )) python3 -m pytest -q -x -p no:cacheprovider tests/test_cuda.py \
        tests/test_composite_cuda.py tests/test_project_cuda.py >>"$out/pytest.log" 2>&1
    echo "cuda tests rc $? at ${SECONDS}s"; tail -3 "$out/pytest.log"
fi
