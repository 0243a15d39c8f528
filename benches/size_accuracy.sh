#!/usr/bin/env bash
# Accuracy per megabyte (issue 14): per shared scene (sacre-coeur, south-building, the KITTI 06
# scene built once into target/scenes/kitti06) and map kind (SIFT from the scene's database,
# SFP from its images), the level-2 short f16 map (`slice --level 2 --short`, "l2s") against
# its compact slices: `--minimal` ("min": positions on a 16-bit grid, no ids, colours or
# visibility keypoints, compressed indices) and `--pq M` ("pqM": M one-byte codes per point):
# bytes, bytes per point, queries localized, recall at (0.1 x the median spacing of
# neighbouring map cameras, 2 deg), median errors.
#
# Usage: bash benches/size_accuracy.sh [BIN] [scene ...]   (BIN: target/release/sfpmap)
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${1:-target/release/sfpmap}; shift || true
scenes=${*:-sacre-coeur south-building kitti06}
source benches/scenes.sh

echo "| scene | map | variant | bytes | bytes/point | localized | recall (0.1 x spacing, 2°) | median transl. | median rot. (°) |"
echo "|---|---|---|---|---|---|---|---|---|"
for scene in $scenes; do
  S=$(scene_dir "$scene"); C="$CACHE/$scene-size"; mkdir -p "$C"
  scene_databases "$S" "$C"
  scene_maps "$bin" "$S" "$C"
  for kind in sift sfp; do
    dims=$("$bin" info "$C/$kind.sfpm" --json | python3 -c "import json,sys;d=json.load(sys.stdin);print([l['dim_short'] for l in d['levels'] if l['level']==2][0])")
    variants="l2s l2s-pq8 l2s-min"
    for m in 4 8 16; do [ $((dims % m)) -eq 0 ] && [ "$m" -le "$dims" ] && variants="$variants l2s-min-pq$m"; done
    for v in $variants; do
      out="$C/$kind-$v.sfpm"
      opts=(); [[ "$v" == *pq* ]] && opts=(--pq "${v##*pq}")
      [[ "$v" == *min* ]] && opts+=(--minimal)
      "$bin" slice "$C/$kind.sfpm" --level 2 --short "${opts[@]}" -o "$out" --force -q
      if [ "$kind" = sift ]; then src=(--database "$C/queries.db"); else src=(--images "$S/images"); fi
      "$bin" localize --map "$out" --query-list "$S/queries.txt" "${src[@]}" --threads 1 --short \
        -o "$C/$kind-$v.poses" --force --json >"$C/$kind-$v.loc.json"
      "$bin" eval --poses "$C/$kind-$v.poses" --gt "$S/gt_poses.txt" --map "$out" --json >"$C/$kind-$v.scale.json"
      spacing=$(jget "$C/$kind-$v.scale.json" "d['scale']")
      "$bin" eval --poses "$C/$kind-$v.poses" --gt "$S/gt_poses.txt" --map "$out" \
        --threshold "$(python3 -c "print(0.1*$spacing)"),2" --json >"$C/$kind-$v.ev.json"
      points=$("$bin" info "$out" --json | python3 -c "import json,sys;print(json.load(sys.stdin)['points'])")
      jget "$C/$kind-$v.ev.json" "f\"| $scene | $kind | $v (L2 {$dims} dims) | {d['map_bytes']} | {d['map_bytes']/max($points,1):.1f} | {d['localized']}/{d['queries']} | {round(100*d['recall'][0]['recall'])} % | {'-' if d['median_translation'] is None else round(d['median_translation'],4)} | {'-' if d['median_rotation_deg'] is None else round(d['median_rotation_deg'],3)} |\""
    done
  done
done
