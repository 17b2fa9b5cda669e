#!/usr/bin/env bash
# docs/training.md's room table (<!-- room-table -->): today's `full` against the room presets, the
# floor, issue 12's targets and `no-cues`, per benchmark room, from the committed ablation results.
# The seed-7 rooms were made after the presets were fixed and never used before (bench/heldout_room_check.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/python bench/recipe_table.py --doc docs/training.md --marker room-table \
    --before "today's full" --after "room presets" \
    --room "textured s0" textured_s0_expected textured_s0_room_wallsnap textured_s0_expected \
    --room "textured s2 (held out)" textured_s2_heldout_expected textured_s2_room_wallsnap textured_s2_heldout_expected \
    --room "textured s3 (held out)" textured_s3_heldout_expected textured_s3_room_wallsnap textured_s3_heldout_expected \
    --room "textured s5 (never tuned on)" textured_s5_plain textured_s5_room_wallsnap textured_s5_nocues \
    --room "textured s7 (new, after the presets)" heldout_textured_s7 heldout_textured_s7_room:room heldout_textured_s7 \
    --room "bare s0" bare_s0_expected bare_s0_room_wallsnap bare_s0_expected \
    --room "bare s2 (held out)" bare_s2_heldout_expected bare_s2_room_wallsnap bare_s2_heldout_expected \
    --room "bare s3 (held out)" bare_s3_heldout_expected bare_s3_room_wallsnap bare_s3_heldout_expected \
    --room "bare s5 (never tuned on)" bare_s5_plain bare_s5_room_wallsnap bare_s5_nocues \
    --room "bare s7 (new, after the presets)" heldout_bare_s7 heldout_bare_s7_room:room heldout_bare_s7
