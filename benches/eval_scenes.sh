#!/usr/bin/env bash
# Real-scene evaluation: convert -> slice -> localize -> eval on ../shared/data/scenes/*, for
# the SIFT map (from database.db), its level-2 short slice, the SFP maps (full and level-2
# short, when this build has the extractor) and the pycolmap reference. Prints one table.
#
# Usage: bash benches/eval_scenes.sh [scene ...]     (default: sacre-coeur south-building)
# Needs: target/release/sfpmap (cargo build --release), python3 with pycolmap==4.2.1.
# South Building's databases are rebuilt once into target/scenes/ (about 2 minutes).
set -euo pipefail
cd "$(dirname "$0")/.."
B=target/release/sfpmap
DATA=../shared/data/scenes
CACHE=target/scenes
mkdir -p "$CACHE"
scenes=${*:-sacre-coeur south-building}
rows=()

jget() { python3 -c "import json,sys;d=json.load(open(sys.argv[1]));print(eval(sys.argv[2],{'d':d}))" "$@"; }

row() { # scene variant map poses ms [bytes: the size to report instead of the map's]
  local ev="$CACHE/ev.json"
  "$B" eval --poses "$4" --gt "$DATA/$1/gt_poses.txt" --map "$3" --json >"$ev"
  rows+=("$(jget "$ev" "f\"| $1 | $2 | {${6:-d['map_bytes']}/1e6:.2f} | {d['localized']}/{d['queries']} | {d['median_translation'] if d['median_translation'] is None else round(d['median_translation'],4)} | {d['median_rotation_deg'] if d['median_rotation_deg'] is None else round(d['median_rotation_deg'],3)} | {'-' if d['median_translation_rel'] is None else round(100*d['median_translation_rel'],2)} | {' / '.join(str(round(100*r['recall'])) for r in d['recall'])} | $5 |\"")")
}

for scene in $scenes; do
  S="$DATA/$scene"; C="$CACHE/$scene"; mkdir -p "$C"
  if [ -f "$S/database.db" ]; then cp "$S/database.db" "$C/database.db"; cp "$S/queries.db" "$C/queries.db"
  elif [ ! -f "$C/database.db" ]; then
    python3 ../shared/data/tools/make_scene.py IGNORED "$S" "$(mktemp -d)" --camera-mode SINGLE --every 5 \
      --steps regen-db --regen-out "$C/database.db" --regen-queries-out "$C/queries.db" >"$C/regen.log" 2>&1
  fi
  "$B" convert --colmap "$S/sparse-map" --database "$C/database.db" -o "$C/sift.sfpm" --force -q
  "$B" slice "$C/sift.sfpm" --level 2 --short -o "$C/sift-l2s.sfpm" --force -q
  for v in sift sift-l2s; do
    extra=(); [ "$v" = sift-l2s ] && extra=(--short)
    "$B" localize --map "$C/$v.sfpm" --query-list "$S/queries.txt" --database "$C/queries.db" \
      -o "$C/$v.poses" --force --json "${extra[@]}" >"$C/$v.loc.json"
    row "$scene" "$v" "$C/$v.sfpm" "$C/$v.poses" "$(jget "$C/$v.loc.json" "round(d['median_ms']['total'])")"
  done
  if "$B" --help | grep -qE '^\s+extract\b'; then
    "$B" convert --colmap "$S/sparse-map" --images "$S/images" -o "$C/sfp.sfpm" --force -q
    "$B" slice "$C/sfp.sfpm" --level 2 --short -o "$C/sfp-l2s.sfpm" --force -q
    for v in sfp sfp-l2s; do
      extra=(); [ "$v" = sfp-l2s ] && extra=(--short)
      "$B" localize --map "$C/$v.sfpm" --query-list "$S/queries.txt" --images "$S/images" \
        -o "$C/$v.poses" --force --json "${extra[@]}" >"$C/$v.loc.json"
      row "$scene" "$v" "$C/$v.sfpm" "$C/$v.poses" "$(jget "$C/$v.loc.json" "round(d['median_ms']['total'])")"
    done
  fi
  ref_ms=$(python3 benches/reference_localize.py "$S" "$C/database.db" "$C/queries.db" "$C/ref.poses" | sed -n 's/.*median \([0-9.]*\) ms.*/\1/p')
  # The reference's "map" is the COLMAP model plus its database.
  ref_bytes=$(( $(du -cb "$S"/sparse-map/* | tail -1 | cut -f1) + $(stat -c %s "$C/database.db") ))
  row "$scene" "pycolmap reference (model + database.db)" "$C/sift.sfpm" "$C/ref.poses" "$ref_ms" "$ref_bytes"
done
echo "| scene | variant | map MB | localized | median transl. (units) | median rot. (deg) | median transl. (% of cam spacing) | recall 0.25m,2° / 0.5m,5° / 5m,10° (%) | ms/query |"
echo "|---|---|---|---|---|---|---|---|---|"
printf '%s\n' "${rows[@]}"
