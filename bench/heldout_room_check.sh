#!/usr/bin/env bash
# A benchmark room never used while developing (a new seed): does the README's claim hold there?
# Rows: the exact-depth floor, `no-cues` and `full` on the default cues, and `room` on
# `geocues extract --preset room` cues (README: "every figure beats today's full" on eight rooms).
# 3000 iterations at 320x240, training seeds 0..SEEDS-1, --jobs 2 (one core per row); run again with
# a larger SEEDS, it trains only the new seeds (splat ablate resumes) and the collected results merge.
# Usage: bash bench/heldout_room_check.sh LAYOUT SEED [SEEDS=1] [WORK=outputs/heldout_LAYOUT_sSEED]
# Writes WORK/* and bench/results/ablation_heldout_LAYOUT_sSEED{,_room}/ (splat ablate's reports).
set -euo pipefail
cd "$(dirname "$0")/.."
layout="$1" seed="$2"
seeds="${3:-1}"
work="${4:-outputs/heldout_${layout}_s${seed}}"
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}"
bin=.venv/bin
train=(--iters 3000 --downscale 2 --strategy.max-gaussians 100000 --jobs 2 --seeds "$seeds")
name="heldout_${layout}_s${seed}"
[ -d "$work/room" ] || $bin/evaluate make-room "$work/room" --layout "$layout" --seed "$seed"
[ -f "$work/cues/report.json" ] || $bin/geocues extract "$work/room" -o "$work/cues"
[ -f "$work/cues_room/report.json" ] || $bin/geocues extract "$work/room" -o "$work/cues_room" --preset room
$bin/splat ablate "$work/room" -c "$work/cues" -o "$work/ablation" --rows full no-cues "${train[@]}" \
    --scene-label "$layout room, seed $seed (held out)"
$bin/splat ablate "$work/room" -c "$work/cues_room" -o "$work/ablation_room" --rows room "${train[@]}" \
    --scene-label "$layout room, seed $seed (held out), geocues extract --preset room cues"
$bin/python bench/ablation_summary.py --collect "$work/ablation" "$name" \
    --label "$layout room, seed $seed (held out), default cues"
$bin/python bench/ablation_summary.py --collect "$work/ablation_room" "${name}_room" \
    --label "$layout room, seed $seed (held out), geocues extract --preset room cues"
