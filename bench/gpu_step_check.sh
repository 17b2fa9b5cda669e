#!/usr/bin/env bash
# One short GPU check of the training step, for a machine with a CUDA GPU and a python3 that holds
# torch (no project install: the packages it lacks installed beforehand, e.g. from carried wheels).
# In order, inside BUDGET_S seconds (default 330), each step under its own timeout:
#   1. the CUDA extension build (rasterizer and loss kernels; about 100 s on a fresh machine)
#   2. tests/test_losses_cuda.py and the CUDA training-step test (tests/test_train_step.py -k cuda)
#   3. bench/train_step_bench.py at 640x480 with 100k and 300k Gaussians: the step with torch's loss
#      code ("fused-adam") beside the CUDA loss kernels ("fused-loss", the default), syncs per step
#   4. the CUDA rasterizer tests in the time that is left
# Usage: bash bench/gpu_step_check.sh OUT [NAME]   (writes OUT/pytest_*.log, OUT/train_step_NAME.json;
# NAME defaults to cuda_<card>_fused_loss)
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:?usage: bench/gpu_step_check.sh OUT [NAME]}" budget="${BUDGET_S:-330}"
gpu=$(python3 -c "import torch; print(torch.cuda.get_device_name(0).split()[1].lower() if torch.cuda.is_available() else 'cpu')" 2>/dev/null)
name="${2:-cuda_${gpu:-gpu}_fused_loss}"  # e.g. cuda_h200_fused_loss: the card in the result's name
mkdir -p "$out"
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}" PYTHONUNBUFFERED=1
left() { echo $(( budget - SECONDS )); }
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no GPU')"
timeout 240 python3 -c "from splat.cuda_ext import ext; print('built', ext.__name__)" 2>&1 | tail -3
echo "build done at ${SECONDS}s"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/test_losses_cuda.py tests/test_train_step.py -k cuda \
    >"$out/pytest_losses.log" 2>&1
echo "loss tests rc $? at ${SECONDS}s"; tail -4 "$out/pytest_losses.log"
timeout -k 5 $(( $(left) > 150 ? 120 : $(left) - 30 )) python3 bench/train_step_bench.py --name "$name" --device cuda \
    --sizes 640x480 --counts 100000 300000 --variants fused-adam fused-loss --iters 20 2>&1 | grep -v Warning | tail -8
cp "bench/results/train_step_$name.json" "$out/" 2>/dev/null
if [ "$(left)" -gt 30 ]; then
    timeout $(( $(left) - 10 )) python3 -m pytest -q -x -p no:cacheprovider tests/test_composite_cuda.py \
        tests/test_project_cuda.py >"$out/pytest_cuda.log" 2>&1
    echo "cuda tests rc $? at ${SECONDS}s"; tail -3 "$out/pytest_cuda.log"
fi
