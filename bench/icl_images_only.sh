#!/usr/bin/env bash
# The images-only path on ICL living room 1, scored against the reference after alignment (issue 12):
# the 211 photos alone (no poses, no intrinsics) -> incremental SfM -> undistortion -> metric scale
# -> cues -> training (the settings of the prior-free ICL ablation's `full` row) -> mesh, scored
# with `evaluate --align-to` the known-pose scene, with and without ICP.
# The scale: a photo collection has none; here it is the similarity that maps the SfM camera centres
# onto the dataset's (what `--align-to` fits anyway), i.e. the case of a user who knows one length.
# Usage: bash bench/icl_images_only.sh [WORK=outputs/icl_imgonly_run] [GT_SCENE=outputs/icl_sfm]
# (GT_SCENE: the known-pose scene of `geocues sfm ../shared/data/icl_livingroom1 -o outputs/icl_sfm`).
# Writes WORK/* and bench/results/icl_images_only.json.
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-outputs/icl_imgonly_run}" gt="${2:-outputs/icl_sfm}"
data=../shared/data/icl_livingroom1
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}"
bin=.venv/bin
mkdir -p "$work/photos"
ln -sfn "$(cd "$data" && pwd)/images" "$work/photos/images"  # the photos and nothing else
t0=$SECONDS
[ -f "$work/map/sfm_report.json" ] || $bin/geocues sfm "$work/photos" -o "$work/map" --mode map
t_sfm=$((SECONDS - t0))
[ -d "$work/undist" ] || $bin/geocues undistort "$work/map" -o "$work/undist"
scale=$($bin/python -c "
from evaluation.align import align_scenes
a = align_scenes('$work/undist', '$gt')
print(a.transform.s)" | tail -1)
[ -d "$work/metric" ] || $bin/geocues rescale "$work/undist" -o "$work/metric" --scale "$scale"
t0=$SECONDS
[ -f "$work/cues/report.json" ] || $bin/geocues extract "$work/metric" -o "$work/cues"
t_cues=$((SECONDS - t0))
[ -f "$work/train/report.json" ] || $bin/splat train "$work/metric" -c "$work/cues" -o "$work/train" \
    --iters 3000 --downscale 2 --strategy.max-gaussians 150000
for icp in no-icp icp; do
    flag=$([ $icp = icp ] && echo --icp || echo "")
    [ -f "$work/eval_$icp.json" ] || $bin/evaluate "$work/train/mesh.ply" "$work/metric" --align-to "$gt" $flag \
        --gt "$data/reference_mesh.ply" --renders "$work/train/test_renders" -o "$work/eval_$icp.json"
done
$bin/python - "$work" "$scale" "$t_sfm" "$t_cues" <<'PY'
import json, sys
from pathlib import Path
work, scale = Path(sys.argv[1]), float(sys.argv[2])
sfm = json.loads((work / "map" / "sfm_report.json").read_text())
train = json.loads((work / "train" / "report.json").read_text())
out = {"what": "ICL living room 1 from its photos alone: geocues sfm --mode map, undistort, rescale (scale from "
               "the camera-centre similarity to the known poses), extract, splat train --iters 3000 --downscale 2 "
               "--strategy.max-gaussians 150000, evaluate --align-to the known-pose scene (bench/icl_images_only.sh)",
       "scale_m_per_unit": scale, "sfm_report": sfm, "train_s": train["timings"]["train_s"],
       "test_psnr": train["test_metrics"]["psnr"], "gaussians_final": train["gaussians_final"]}
for icp in ("no-icp", "icp"):
    out[icp] = json.loads((work / f"eval_{icp}.json").read_text())
path = Path("bench/results/icl_images_only.json")
path.write_text(json.dumps(out, indent=1))
print(f"wrote {path}")
PY
