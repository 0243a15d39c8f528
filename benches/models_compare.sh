#!/usr/bin/env bash
# SFP models side by side on the shared real scenes (issue 17's table): per scene and model,
# the SFP map (`convert --images --model`) and its level-2 short slice, each localizing the
# scene's queries with the same model (1 thread): bytes, queries localized, recall at
# (0.1 x the median spacing of neighbouring map cameras, 2 deg), median errors, ms per query,
# and retrieval recall@1/5/10 of the ground-truth most co-visible database image over the
# ranking `localize --format json` reports (python/eval_retrieval.py --localized: the SFP
# map's global descriptor, the SIFT map's VLAD). The SIFT level-2 short map is the reference
# row; the SIFT map of all levels and its level-2 short `--pq 8 --minimal` slice (issue 36's
# smallest SIFT map) the next; each SFP model's level-2 short map is also sliced `--pq 8 --minimal`.
# A model of one level
# (aliked-n16, the v3 teacher) gets its map only, no level-2 slice. Maps are rebuilt at every run.
#
# A model given as MODEL.onnx+snap is converted with `--snap` (its rows: NAME-snap), as
# MODEL.onnx+triangulate with `--triangulate` (NAME-triangulate).
#
# python3 must have numpy, pillow and pycolmap (the KITTI 06 scene, South Building's databases,
# the retrieval scores): the tests' venv has them, PATH="$(bash .ci/tools | tail -1)/bin:$PATH".
#
# Usage: bash benches/models_compare.sh MODEL.onnx[+snap|+triangulate] [...] [-- scene ...]
set -euo pipefail
cd "$(dirname "$0")/.."
models=()
while [ $# -gt 0 ] && [ "$1" != -- ]; do models+=("$1"); shift; done
[ $# -gt 0 ] && shift
scenes=${*:-sacre-coeur south-building kitti06}
source benches/scenes.sh
cargo build --release --quiet --all-features
bin=target/release/sfpmap

retrieval() { # SCENE MAP QUERY_FEATURE_ARGS...: r@1 / r@5 / r@10 of the map's retrieval
  local scene=$1 map=$2; shift 2
  local S; S=$(scene_dir "$scene")
  "$bin" localize --map "$map" --query-list "$S/queries.txt" "$@" --top-k 10 --threads 1 \
    --format json -o "$map.ranked.json" --force -q
  python3 python/eval_retrieval.py --localized "map:$scene=$map.ranked.json" --json "$map.ret" >/dev/null
  jget "$map.ret" "' / '.join(f\"{d['results']['map']['$scene'][k]:.2f}\" for k in ('r@1', 'r@5', 'r@10'))"
}

row() { # SCENE LABEL MAP POSES LOC_JSON RETRIEVAL
  local S=$(scene_dir "$1") ev=$5.ev
  "$bin" eval --poses "$4" --gt "$S/gt_poses.txt" --map "$3" --json >"$ev"
  local spacing; spacing=$(jget "$ev" "d['scale']")
  "$bin" eval --poses "$4" --gt "$S/gt_poses.txt" --map "$3" \
    --threshold "$(python3 -c "print(0.1*$spacing)"),2" --json >"$ev"
  jget "$ev" "f\"| $1 | $2 | {d['map_bytes']/1e6:.2f} | {d['localized']}/{d['queries']} | {round(100*d['recall'][0]['recall'])} % | {'-' if d['median_translation'] is None else round(d['median_translation'],4)} | {'-' if d['median_rotation_deg'] is None else round(d['median_rotation_deg'],3)} | $(jget "$5" "round(d['median_ms']['total'],1)") | $6 |\""
}

echo "| scene | map | MB | localized | recall (0.1 x spacing, 2°) | median transl. | median rot. (°) | ms/query | retrieval r@1 / 5 / 10 |"
echo "|---|---|---|---|---|---|---|---|---|"
for scene in $scenes; do
  S=$(scene_dir "$scene"); C="$CACHE/$scene-models"; mkdir -p "$C"
  scene_databases "$S" "$C"
  "$bin" convert --colmap "$S/sparse-map" --database "$C/database.db" -o "$C/sift.sfpm" --force -q
  "$bin" slice "$C/sift.sfpm" --level 2 --short -o "$C/sift-l2s.sfpm" --force -q
  "$bin" localize --map "$C/sift-l2s.sfpm" --short --query-list "$S/queries.txt" --database "$C/queries.db" \
    --threads 1 -o "$C/sift-l2s.poses" --force --json >"$C/sift-l2s.json"
  ret=$(retrieval "$scene" "$C/sift.sfpm" --database "$C/queries.db")
  row "$scene" "SIFT level 2 short" "$C/sift-l2s.sfpm" "$C/sift-l2s.poses" "$C/sift-l2s.json" "$ret (VLAD)"
  # The SIFT map itself: issue 36's bar for an SFP map of all levels.
  "$bin" localize --map "$C/sift.sfpm" --query-list "$S/queries.txt" --database "$C/queries.db" \
    --threads 1 -o "$C/sift.poses" --force --json >"$C/sift.json"
  row "$scene" "SIFT (all levels)" "$C/sift.sfpm" "$C/sift.poses" "$C/sift.json" "$ret (VLAD)"
  "$bin" slice "$C/sift.sfpm" --level 2 --short --minimal --pq 8 -o "$C/sift-l2s-pq8.sfpm" --force -q
  "$bin" localize --map "$C/sift-l2s-pq8.sfpm" --short --query-list "$S/queries.txt" --database "$C/queries.db" \
    --threads 1 -o "$C/sift-l2s-pq8.poses" --force --json >"$C/sift-l2s-pq8.json"
  row "$scene" "SIFT level 2 short --pq 8 --minimal" "$C/sift-l2s-pq8.sfpm" "$C/sift-l2s-pq8.poses" \
    "$C/sift-l2s-pq8.json" "$ret (VLAD)"
  for given in "${models[@]}"; do
    model=$given how=()
    case "$given" in
      *+snap | *+triangulate) model=${given%+*} how=(--"${given##*+}") ;;
    esac
    name=$(basename "$model" .onnx)
    [ ${#how[@]} -eq 0 ] || name=$name-${given##*+}
    "$bin" convert --colmap "$S/sparse-map" --images "$S/images" --model "$model" "${how[@]}" \
      -o "$C/$name.sfpm" --force -q
    variants=("$name")
    info=$("$bin" info "$C/$name.sfpm" --json)
    # Level 2's short dims (0: no level 2).
    short_2=$(python3 -c "import json,sys; print(next((l['dim_short'] for l in json.load(sys.stdin)['levels'] if l['level'] == 2), 0))" <<<"$info")
    if [ "$short_2" -gt 0 ]; then
      "$bin" slice "$C/$name.sfpm" --level 2 --short -o "$C/$name-l2s.sfpm" --force -q
      "$bin" slice "$C/$name.sfpm" --level 2 --short --minimal --pq 8 -o "$C/$name-l2s-pq8.sfpm" --force -q
      variants+=("$name-l2s" "$name-l2s-pq8")
      # As many short dims as SIFT's level-2 short map keeps (32), where level 2 has more.
      if [ "$short_2" -gt 32 ]; then
        "$bin" slice "$C/$name.sfpm" --level 2 --short --short-dims 32 -o "$C/$name-l2s32.sfpm" --force -q
        variants+=("$name-l2s32")
      fi
    fi
    ret=$(retrieval "$scene" "$C/$name.sfpm" --images "$S/images" --model "$model")
    for v in "${variants[@]}"; do
      extra=(); [[ "$v" == *-l2s* ]] && extra=(--short)
      "$bin" localize --map "$C/$v.sfpm" "${extra[@]}" --query-list "$S/queries.txt" --images "$S/images" \
        --model "$model" --threads 1 -o "$C/$v.poses" --force --json >"$C/$v.json"
      case "$v" in
        *-l2s) label="$name level 2 short" ;;
        *-l2s-pq8) label="$name level 2 short --pq 8 --minimal" ;;
        *-l2s32) label="$name level 2 short --short-dims 32" ;;
        *) label="$name" ;;
      esac
      row "$scene" "$label" "$C/$v.sfpm" "$C/$v.poses" "$C/$v.json" "$ret"
    done
  done
done
