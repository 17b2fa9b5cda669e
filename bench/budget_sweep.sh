#!/usr/bin/env bash
# What the Gaussian budget costs and buys (docs/training.md, "Budget"): the `full` row of `splat ablate`
# on a room, 3000 iterations at --downscale 2, once per budget ("auto" = the default, 0 = no limit), then
# bench/budget_summary.py writes bench/results/budget_NAME.json and prints the table. SEEDS=K (default 1)
# trains each budget with seeds 0..K-1 (the table gives mean ± spread).
#
#   SEEDS=3 bash bench/budget_sweep.sh ROOM CUES OUT NAME "LABEL" auto 50000 200000
#
# For ICL (no gt/ folder for the floor) the rows were `splat train` + `evaluate -o RUN/metrics.json`:
#   splat train SFM -c CUES -o RUN --iters 3000 --downscale 2 [--strategy.max-gaussians N]
#   evaluate RUN/mesh.ply SFM --gt ICL/reference_mesh.ply --renders RUN/test_renders -o RUN/metrics.json
set -euo pipefail
[ $# -ge 6 ] || { echo "usage: $0 ROOM CUES OUT NAME LABEL BUDGET..." >&2; exit 2; }
room=$1 cues=$2 out=$3 name=$4 label=$5
shift 5
cd "$(dirname "$0")/.."
bin=.venv/bin
mkdir -p "$out"
runs=()
for b in "$@"; do
    flag=()
    [ "$b" != auto ] && flag=(--strategy.max-gaussians "$b")
    $bin/splat ablate "$room" -c "$cues" -o "$out/b_$b" --rows full --seeds "${SEEDS:-1}" --iters 3000 --downscale 2 "${flag[@]}" \
        2> "$out/b_$b.log"
    runs+=("$out/b_$b")
done
$bin/python bench/budget_summary.py --name "$name" --scene "$label" "${runs[@]}"
