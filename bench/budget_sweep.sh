#!/usr/bin/env bash
# What the Gaussian budget costs and buys (docs/training.md, "Budget"): the `full` row of `splat ablate`
# on a room, 3000 iterations at --downscale 2, once per budget ("auto" = the default, 0 = no limit), then
# bench/budget_summary.py writes bench/results/budget_NAME.json and prints the table. SEEDS=K (default 1)
# trains each budget with seeds 0..K-1 (the table gives mean ± spread).
#
#   SEEDS=3 bash bench/budget_sweep.sh ROOM CUES OUT NAME "LABEL" auto 50000 200000 [-- ABLATE_OPTION...]
#
# Options after `--` go to every `splat ablate` (a scene without gt/: --gt MESH --gt-depth DEPTH_DIR, e.g. ICL:
#   SEEDS=2 bash bench/budget_sweep.sh outputs/icl_sfm outputs/icl_cues OUT icl_livingroom1 "ICL living room 1,
#   prior-free" 50000 auto 300000 -- --gt ../shared/data/icl_livingroom1/reference_mesh.ply
#   --gt-depth ../shared/data/icl_livingroom1/depth).
# ICL's one-seed rows of 2026-11-29 were `splat train` + `evaluate -o RUN/metrics.json` folders (also read).
set -euo pipefail
[ $# -ge 6 ] || { echo "usage: $0 ROOM CUES OUT NAME LABEL BUDGET... [-- ABLATE_OPTION...]" >&2; exit 2; }
room=$1 cues=$2 out=$3 name=$4 label=$5
shift 5
budgets=()
while [ $# -gt 0 ] && [ "$1" != -- ]; do budgets+=("$1"); shift; done
[ $# -gt 0 ] && shift
extra=("$@")
[ ${#budgets[@]} -gt 0 ] || { echo "usage: $0 ROOM CUES OUT NAME LABEL BUDGET... [-- ABLATE_OPTION...]: no budget" >&2; exit 2; }
cd "$(dirname "$0")/.."
bin=.venv/bin
mkdir -p "$out"
runs=()
for b in "${budgets[@]}"; do
    flag=()
    [ "$b" != auto ] && flag=(--strategy.max-gaussians "$b")
    $bin/splat ablate "$room" -c "$cues" -o "$out/b_$b" --rows full --seeds "${SEEDS:-1}" --iters 3000 --downscale 2 ${flag[@]+"${flag[@]}"} ${extra[@]+"${extra[@]}"} \
        2> "$out/b_$b.log"
    runs+=("$out/b_$b")
done
$bin/python bench/budget_summary.py --name "$name" --scene "$label" "${runs[@]}"
