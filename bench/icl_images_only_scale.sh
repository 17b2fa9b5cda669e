#!/usr/bin/env bash
# What the unit of an images-only model does to the photos-only recipe, on ICL living room 1: every
# third photo (71, no poses, no intrinsics) -> `geocues sfm` (incremental mapping) -> `geocues
# undistort`, then three scenes that differ only in their unit:
#   mapped  COLMAP's normalised unit, as a user who skips `geocues rescale` trains it;
#   guess   `geocues rescale --median-depth 2` (photos taken about 2 m from what they show);
#   exact   `geocues rescale --scale S`, S from the camera-centre similarity to the dataset's poses.
# Each: `geocues mvs`, `geocues extract --preset mvs`, `splat train --preset mvs --iters 3000
# --downscale 2 --strategy.max-gaussians 150000`, `evaluate --align-to` the dataset, with and without ICP.
# Usage: bash bench/icl_images_only_scale.sh [WORK=outputs/icl_scale] [SEED=0]
# Writes WORK/* and bench/results/icl_images_only_scale[_seedN].json. Resumable: finished steps are skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
work="${1:-outputs/icl_scale}" seed="${2:-0}"
data=../shared/data/icl_livingroom1
export INDOORGS_CACHE="${INDOORGS_CACHE:-$PWD/.cache}"
bin=.venv/bin
mkdir -p "$work/photos/images"
for f in $(ls "$data/images" | awk 'NR % 3 == 1'); do  # 00000, 00003, ...
    ln -sfn "$(cd "$data/images" && pwd)/$f" "$work/photos/images/$f"
done
[ -f "$work/map/sfm_report.json" ] || $bin/geocues sfm "$work/photos" -o "$work/map" --mode map
[ -d "$work/mapped" ] || $bin/geocues undistort "$work/map" -o "$work/mapped"
exact=$($bin/python -c "
from evaluation.align import align_scenes
print(align_scenes('$work/mapped', '$data').transform.s)" | tail -1)
[ -d "$work/guess" ] || $bin/geocues rescale "$work/mapped" -o "$work/guess" --median-depth 2
[ -d "$work/exact" ] || $bin/geocues rescale "$work/mapped" -o "$work/exact" --scale "$exact"
sfx=$([ "$seed" = 0 ] && echo "" || echo "_seed$seed")
for v in mapped guess exact; do
    [ -f "$work/${v}_mvs/mvs_report.json" ] || $bin/geocues mvs "$work/$v" -o "$work/${v}_mvs"
    [ -f "$work/${v}_cues/report.json" ] || $bin/geocues extract "$work/${v}_mvs" -o "$work/${v}_cues" --preset mvs
    run="$work/${v}_train$sfx"
    [ -f "$run/report.json" ] || $bin/splat train "$work/${v}_mvs" -c "$work/${v}_cues" -o "$run" --preset mvs \
        --iters 3000 --downscale 2 --strategy.max-gaussians 150000 --seed "$seed" 2> "$run.log"
    for icp in no-icp icp; do
        flag=$([ $icp = icp ] && echo --icp || echo "")
        [ -f "$run/eval_$icp.json" ] || $bin/evaluate "$run/mesh.ply" "$work/$v" --align-to "$data" $flag \
            --gt "$data/reference_mesh.ply" -o "$run/eval_$icp.json"
    done
done
$bin/python - "$work" "$exact" "$sfx" <<'PY'
import json, sys
from pathlib import Path
from geocues.rescale import median_view_depth
from geocues.scene import Scene
work, exact, sfx = Path(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
out = {"what": "ICL living room 1, every third photo, mapped from images alone and trained with the photos-only "
               "recipe in three units: as mapped, rescaled by a guess (--median-depth 2), rescaled exactly "
               "(bench/icl_images_only_scale.sh)",
       "exact_m_per_unit": exact, "sfm_report": json.loads((work / "map" / "sfm_report.json").read_text()),
       "variants": {}}
for v in ("mapped", "guess", "exact"):
    meta = json.loads((work / v / "scene.json").read_text()) if (work / v / "scene.json").is_file() else {}
    scale = meta.get("rescaled", {}).get("scale", 1.0)
    train = json.loads((work / f"{v}_train{sfx}" / "report.json").read_text())
    scene = Scene.load(work / v, check_priors=False)
    out["variants"][v] = {
        "m_per_unit": scale, "metres_per_unit_error": scale / exact - 1,
        "median_view_depth_units": median_view_depth(scene),
        "train_s": train["timings"]["train_s"], "test_psnr": train["test_metrics"]["psnr"],
        "gaussians_init": train["gaussians_init"], "gaussians_final": train["gaussians_final"],
        **{icp: json.loads((work / f"{v}_train{sfx}" / f"eval_{icp}.json").read_text()) for icp in ("no-icp", "icp")}}
path = Path(f"bench/results/icl_images_only_scale{sfx}.json")
path.write_text(json.dumps(out, indent=1))
print(f"wrote {path}")
PY
