#!/usr/bin/env bash
# The built-in ALIKED-N16 on the shared scenes: convert --images --model aliked-n16 (one level),
# its short slice, localize --images (the map names its model), eval. One table row per map,
# beside the SIFT level-2 short rows of benches/scenes_compare.sh (issue 31's target: the ALIKED
# short slice localizes at least as often as the SIFT level-2 short map on every scene).
#
# Usage: bash benches/aliked_scenes.sh [scene dir ...]
#   default: ../shared/data/scenes/sacre-coeur ../shared/data/scenes/south-building and
#   target/scenes/kitti06 when it was built (../shared/data/tools/make_posed_scene.py).
# Needs: target/release/sfpmap. ALIKED runs about 1.6 s an image on 2 cores: ~5 minutes.
set -euo pipefail
cd "$(dirname "$0")/.."
B=target/release/sfpmap
OUT=target/aliked-scenes
mkdir -p "$OUT"
if [ $# -gt 0 ]; then
  scenes=("$@")
else
  scenes=(../shared/data/scenes/sacre-coeur ../shared/data/scenes/south-building)
  [ -d target/scenes/kitti06 ] && scenes+=(target/scenes/kitti06)
fi

jget() { python3 -c "import json,sys;d=json.load(open(sys.argv[1]));print(eval(sys.argv[2],{'d':d}))" "$@"; }

echo "| scene | map | bytes | localized | recall (0.1 x spacing, 2°) | median transl. | median rot. (°) | ms/query (with extraction) |"
echo "|---|---|---|---|---|---|---|---|"
for S in "${scenes[@]}"; do
  scene=$(basename "$S"); C="$OUT/$scene"; mkdir -p "$C"
  "$B" convert --colmap "$S/sparse-map" --images "$S/images" --model aliked-n16 -o "$C/aliked.sfpm" --force -q
  "$B" slice "$C/aliked.sfpm" --level 0 --short -o "$C/aliked-short.sfpm" --force -q
  for v in aliked aliked-short; do
    extra=(); [ "$v" = aliked-short ] && extra=(--short)
    /usr/bin/time -f "%e" -o "$C/$v.time" "$B" localize --map "$C/$v.sfpm" --query-list "$S/queries.txt" \
      --images "$S/images" -o "$C/$v.poses" --force --json "${extra[@]}" >"$C/$v.loc.json"
    # Recall at a tenth of the map's median camera spacing (`scale`) and 2°, as scenes_compare.sh.
    "$B" eval --poses "$C/$v.poses" --gt "$S/gt_poses.txt" --map "$C/$v.sfpm" --json >"$C/$v.eval.json"
    thr=$(jget "$C/$v.eval.json" "0.1 * d['scale']")
    "$B" eval --poses "$C/$v.poses" --gt "$S/gt_poses.txt" --map "$C/$v.sfpm" --json \
      --threshold "$thr,2" >"$C/$v.eval.json"
    n=$(jget "$C/$v.eval.json" "d['queries']")
    jget "$C/$v.eval.json" "f\"| $scene | $v | {d['map_bytes']:,} | {d['localized']}/{d['queries']} | {round(100*d['recall'][0]['recall'])} % | {d['median_translation'] if d['median_translation'] is None else round(d['median_translation'],4)} | {d['median_rotation_deg'] if d['median_rotation_deg'] is None else round(d['median_rotation_deg'],3)} | {round(1000*float(open('$C/$v.time').read().split()[-1])/max($n,1))} |\""
  done
done
