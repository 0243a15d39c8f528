#!/usr/bin/env bash
# Two builds side by side on the shared real scenes (issue 11's "not lower than today's"):
# sacre-coeur, south-building and the KITTI 06 scene (metric ground truth; built once into
# target/scenes/kitti06 by ../shared/data/tools/make_posed_scene.py, about 2 minutes). Per
# scene and variant (SIFT map, its level-2 short slice, SFP map, its level-2 short slice),
# each binary converts its own maps and localizes the queries (1 thread): queries localized,
# recall at (0.1 x the median spacing of neighbouring map cameras, 2 deg), median errors and
# ms per query after features.
#
# Usage: bash benches/scenes_compare.sh BEFORE_BIN AFTER_BIN [scene ...]
set -euo pipefail
cd "$(dirname "$0")/.."
before=$1; after=$2; shift 2
scenes=${*:-sacre-coeur south-building kitti06}
source benches/scenes.sh

echo "| scene | variant | build | map MB | localized | recall (0.1 x spacing, 2°) | median transl. | median rot. (°) | ms/query |"
echo "|---|---|---|---|---|---|---|---|---|"
for scene in $scenes; do
  S=$(scene_dir "$scene"); C="$CACHE/$scene-compare"; mkdir -p "$C"
  scene_databases "$S" "$C"
  for build in before after; do
    B=$before; [ "$build" = after ] && B=$after
    W="$C/$build"; mkdir -p "$W"
    "$B" convert --colmap "$S/sparse-map" --database "$C/database.db" -o "$W/sift.sfpm" --force -q
    "$B" slice "$W/sift.sfpm" --level 2 --short -o "$W/sift-l2s.sfpm" --force -q
    "$B" convert --colmap "$S/sparse-map" --images "$S/images" -o "$W/sfp.sfpm" --force -q
    "$B" slice "$W/sfp.sfpm" --level 2 --short -o "$W/sfp-l2s.sfpm" --force -q
  done
  for v in sift sift-l2s sfp sfp-l2s; do
    for build in before after; do
      B=$before; [ "$build" = after ] && B=$after
      W="$C/$build"
      extra=(); [[ "$v" == *l2s ]] && extra=(--short)
      if [[ "$v" == sift* ]]; then src=(--database "$C/queries.db"); else src=(--images "$S/images"); fi
      "$B" localize --map "$W/$v.sfpm" --query-list "$S/queries.txt" "${src[@]}" --threads 1 \
        -o "$W/$v.poses" --force --json "${extra[@]}" >"$W/$v.loc.json"
      "$after" eval --poses "$W/$v.poses" --gt "$S/gt_poses.txt" --map "$W/$v.sfpm" --json >"$W/$v.scale.json"
      spacing=$(jget "$W/$v.scale.json" "d['scale']")
      "$after" eval --poses "$W/$v.poses" --gt "$S/gt_poses.txt" --map "$W/$v.sfpm" \
        --threshold "$(python3 -c "print(0.1*$spacing)"),2" --json >"$W/$v.ev.json"
      jget "$W/$v.ev.json" "f\"| $scene | $v | $build | {d['map_bytes']/1e6:.2f} | {d['localized']}/{d['queries']} | {round(100*d['recall'][0]['recall'])} % | {'-' if d['median_translation'] is None else round(d['median_translation'],4)} | {'-' if d['median_rotation_deg'] is None else round(d['median_rotation_deg'],3)} | $(jget "$W/$v.loc.json" "round(d['median_ms']['total'],1)") |\""
    done
  done
done
