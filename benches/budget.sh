#!/usr/bin/env bash
# Byte budgets (issue 14): per shared scene and map kind (SIFT from the scene's database, SFP
# from its images; both built by benches/size_accuracy.sh, or here if missing), what
# `slice --budget B` chooses for a ladder of budgets, the bytes it writes, and how the slice
# localizes: queries localized, recall at (0.1 x the median spacing of neighbouring map
# cameras, 2 deg), median errors. One row per budget; the first row is the whole map.
#
# Usage: bash benches/budget.sh [BIN] [scene ...]   (BIN: target/release/sfpmap)
#        BUDGETS="4MB 1MB 250kB" bash benches/budget.sh
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${1:-target/release/sfpmap}; shift || true
scenes=${*:-south-building kitti06 sacre-coeur}
budgets=${BUDGETS:-"4MB 2MB 1MB 500kB 250kB 100kB 50kB"}
source benches/scenes.sh

echo "| scene | map | budget | chosen | bytes | localized | recall | median transl. | median rot. (°) |"
echo "|---|---|---|---|---|---|---|---|---|"
for scene in $scenes; do
  S=$(scene_dir "$scene"); C="$CACHE/$scene-size"; mkdir -p "$C"
  scene_databases "$S" "$C"
  scene_maps "$bin" "$S" "$C"
  for kind in sift sfp; do
    for budget in whole $budgets; do
      out="$C/$kind-budget-$budget.sfpm"
      if [ "$budget" = whole ]; then
        cp "$C/$kind.sfpm" "$out"; chosen="the whole map"
      elif ! "$bin" slice "$C/$kind.sfpm" --budget "$budget" -o "$out" --force --json >"$C/$kind-budget-$budget.json" 2>"$C/$kind-budget-$budget.err"; then
        echo "| $scene | $kind | $budget | $(tr -d '\n' <"$C/$kind-budget-$budget.err" | sed 's/.*invalid input: //') | - | - | - | - | - |"
        continue
      else
        chosen=$(jget "$C/$kind-budget-$budget.json" "d['budget']['chosen']")
      fi
      if [ "$kind" = sift ]; then src=(--database "$C/queries.db"); else src=(--images "$S/images"); fi
      "$bin" localize --map "$out" --query-list "$S/queries.txt" "${src[@]}" --threads 1 \
        -o "$C/$kind-budget-$budget.poses" --force --json >"$C/$kind-budget-$budget.loc.json"
      "$bin" eval --poses "$C/$kind-budget-$budget.poses" --gt "$S/gt_poses.txt" --map "$out" --json >"$C/$kind-budget-$budget.scale.json"
      spacing=$(jget "$C/$kind-budget-$budget.scale.json" "d['scale']")
      "$bin" eval --poses "$C/$kind-budget-$budget.poses" --gt "$S/gt_poses.txt" --map "$out" \
        --threshold "$(python3 -c "print(0.1*$spacing)"),2" --json >"$C/$kind-budget-$budget.ev.json"
      jget "$C/$kind-budget-$budget.ev.json" "f\"| $scene | $kind | $budget | $chosen | {d['map_bytes']} | {d['localized']}/{d['queries']} | {round(100*d['recall'][0]['recall'])} % | {'-' if d['median_translation'] is None else round(d['median_translation'],4)} | {'-' if d['median_rotation_deg'] is None else round(d['median_rotation_deg'],3)} |\""
    done
  done
done
