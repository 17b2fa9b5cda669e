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

say "1/5 default scene: benchmark room (images, known poses, pycolmap SfM points, GT mesh, simulated priors)"
[ -d "$OUT/room" ] || $BIN/evaluate make-room "$OUT/room" --layout textured --seed 0
$BIN/geocues info "$OUT/room"

say "2/5 geometric cues: SfM (SOR), 3D lines, plane-like points"
$BIN/geocues extract "$OUT/room" -o "$OUT/cues"

say "3/5 cue accuracy and coverage against the GT mesh"
$BIN/evaluate cues "$OUT/cues" --scene "$OUT/room" --json "$OUT/cue_metrics.json"

say "4/5 mesh metrics protocol check: GT mesh against itself, exact point-to-surface distances"
$BIN/evaluate "$OUT/room/gt/mesh.ply" --scene "$OUT/room" --mode surface --json "$OUT/mesh_metrics_gt.json"

say "5/5 rasterizer: forward+backward seconds per backend (small sizes; full table: splat bench)"
$BIN/splat bench --quick --json "$OUT/splat_bench.json"

say "done: results in $OUT (cue_metrics.json, mesh_metrics_gt.json, splat_bench.json)"
