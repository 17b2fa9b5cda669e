#!/usr/bin/env bash
# README command 1: install what is missing (idempotent), then run the main job end to end on the
# bundled default scene — a procedural benchmark room (textured layout, seed 0) with exact ground truth.
#   bash scripts/demo.sh [OUT]        (default OUT: outputs/demo; steps whose outputs exist are skipped)
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}"
OUT="${1:-outputs/demo}"
BIN=.venv/bin
mkdir -p "$OUT"
say() { printf '\n=== %s\n' "$*"; }

say "1/7 default scene: benchmark room (images, known poses, pycolmap SfM points, GT mesh, simulated priors)"
[ -d "$OUT/room" ] || $BIN/evaluate make-room "$OUT/room" --layout textured --seed 0
$BIN/geocues info "$OUT/room"

say "2/7 geometric cues: SfM (SOR), 3D lines, plane-like points"
$BIN/geocues extract "$OUT/room" -o "$OUT/cues"

say "3/7 cue accuracy and coverage against the GT mesh"
$BIN/evaluate cues "$OUT/cues" --scene "$OUT/room" --json "$OUT/cue_metrics.json"

say "4/7 mesh metrics protocol check: GT mesh against itself, exact point-to-surface distances"
$BIN/evaluate "$OUT/room/gt/mesh.ply" --scene "$OUT/room" --mode surface --json "$OUT/mesh_metrics_gt.json"

say "5/7 rasterizer: forward+backward seconds per backend (small sizes; full table: splat bench)"
$BIN/splat bench --quick --json "$OUT/splat_bench.json"

say "6/7 training: typed Gaussians from the cues, IndoorGS losses and density control, TSDF mesh (short run)"
$BIN/splat train "$OUT/room" -c "$OUT/cues" -o "$OUT/train" --iters 500 --downscale 4 --sh-degree 1 \
    --strategy.max-gaussians 60000 --tsdf.voxel-size 0.03

say "7/7 the trained mesh against the GT mesh, and the held-out views"
$BIN/evaluate "$OUT/train/mesh.ply" --scene "$OUT/room" --renders "$OUT/train/test_renders" \
    --json "$OUT/mesh_metrics_trained.json"

say "done: results in $OUT (cue_metrics.json, mesh_metrics_gt.json, splat_bench.json, train/, mesh_metrics_trained.json)"
