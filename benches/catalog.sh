#!/usr/bin/env bash
# Issue 16's catalog figure: one catalog of the shared scenes' SIFT maps (South Building,
# Sacre Coeur, KITTI 06) and the generated street (target/street/r2/N, its SIFT map as
# benches/remote.sh makes it), then each scene's queries localized with --catalog. Prints, per
# scene, how many queries (with features) rank their own place first, how many are localized
# in it with --places 1 and with the default --places 2, and the catalog's size.
# Usage: benches/catalog.sh [STREET_POINTS]   (default 250000; run benches/remote.sh first, or
# it generates and converts the street itself)
set -euo pipefail
cd "$(dirname "$0")/.."
source benches/scenes.sh
n=${1:-250000}
cargo build --release --quiet --all-features --example street
cargo build --release --quiet --all-features
bin=target/release/sfpmap
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
street=target/street/r2/$n  # r2: the generator since detection follows the viewpoint (stop 47)
if [ ! -f "$street/sift.sfpm" ]; then
  [ -f "$street/queries.txt" ] || target/release/examples/street --points "$n" --queries 20 "$street" >&2
  cp "$street/database.db" "$work/db.db"
  "$bin" convert --colmap "$street/sparse" --database "$work/db.db" -o "$street/sift.sfpm" -q
fi
maps=()
for s in south-building sacre-coeur kitti06; do
  S=$(scene_dir "$s"); C=$CACHE/$s-size; mkdir -p "$C"
  scene_databases "$S" "$C"
  [ -f "$C/sift.sfpm" ] || { cp "$C/database.db" "$work/db.db"; "$bin" convert --colmap "$S/sparse-map" --database "$work/db.db" -o "$C/sift.sfpm" -q; }
  maps+=("$C/sift.sfpm")
done
maps+=("$street/sift.sfpm")
"$bin" catalog build "${maps[@]}" --name south-building --name sacre-coeur --name kitti06 --name street \
  -o "$work/city.sfpc" -q
echo "catalog: $(stat -c %s "$work/city.sfpc") bytes for 4 places"
printf '%-15s %8s %14s %18s %18s\n' scene queries "ranked first" "localized, 1 place" "localized, 2 places"
for s in south-building sacre-coeur kitti06 street; do
  if [ "$s" = street ]; then list=$street/queries.txt; cp "$street/queries.db" "$work/q.db"
  else S=$(scene_dir "$s"); list=$S/queries.txt; cp "$CACHE/$s-size/queries.db" "$work/q.db"; fi
  for k in 1 2; do
    "$bin" localize --catalog "$work/city.sfpc" --query-list "$list" --database "$work/q.db" --places $k \
      -o "$work/p$k.txt" --force --json >"$work/$s.$k.json"
  done
  python3 - "$s" "$work/$s.1.json" "$work/$s.2.json" <<'PY'
import json, sys
name, one, two = sys.argv[1], json.load(open(sys.argv[2])), json.load(open(sys.argv[3]))
ranked = [q for q in one["chosen"] if q["ranked"]]
first = sum(q["ranked"][0]["place"] == name for q in ranked)
right = lambda r: sum(q["place"] == name for q in r["chosen"])
print(f"{name:<15} {len(ranked):>8} {first:>8}/{len(ranked):<5} {right(one):>12}/{one['queries']:<5} {right(two):>12}/{two['queries']:<5}")
PY
done
