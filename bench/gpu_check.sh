#!/usr/bin/env bash
# On a machine with a CUDA GPU and a python3 that holds torch, numpy, scipy and pytest (no project
# install needed: splat/ imports none of open3d, pycolmap, tyro): run the rasterizer tests, which
# include the CUDA ones (tests/test_composite_cuda.py builds the CUDA kernels on first use, about a
# minute), then `splat bench` with the CUDA kernels and the torch backend on the GPU next to the CPU
# backends. Usage: bash bench/gpu_check.sh OUT_DIR   (writes OUT_DIR/pytest_cuda.log,
# OUT_DIR/splat_bench_cuda.json and OUT_DIR/splat_bench_cuda.txt)
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:?usage: bench/gpu_check.sh OUT_DIR}"
mkdir -p "$out"
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}" PYTHONUNBUFFERED=1
python3 - <<'PY'
import torch
print("torch", torch.__version__, "cuda", torch.version.cuda, "device",
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else None)
PY
tests_rc=0
python3 -m pytest -q -p no:cacheprovider tests/test_composite_cuda.py tests/test_project_cuda.py tests/test_cuda.py tests/test_losses_cuda.py tests/test_render_hard_cases.py \
    tests/test_render.py tests/test_composite_torch.py tests/test_projection.py 2>&1 | tee "$out/pytest_cuda.log" \
    || tests_rc=$?
python3 - "$out" <<'PY'
import logging, sys
from pathlib import Path
from splat.bench import BenchConfig, format_table, run_bench
logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
out = Path(sys.argv[1])
result = run_bench(BenchConfig(backends=("cuda", "torch-cuda", "torch", "cpu")), json_out=out / "splat_bench_cuda.json")
table = format_table(result)
(out / "splat_bench_cuda.txt").write_text(table + "\n")
print(table)
PY
exit "$tests_rc"  # the bench runs even when a test failed; the exit status tells
