#!/usr/bin/env bash
# Issue 13's "behaviour unchanged": runs two builds over the shared scenes (convert the
# sacre-coeur SIFT map from a copy of its database, slice level 2 short, localize both with the
# query database; convert sacre-coeur and south-building with --images, slice, localize) in the
# same folder one after the other (maps record their input paths), and prints per output
# whether the two builds wrote the same bytes.
# Usage: benches/same_behaviour.sh BINARY_A BINARY_B [DATA=../shared/data]
set -euo pipefail
a=$1 b=$2 data=${3:-../shared/data}
d=$(realpath "$data")/scenes
out=$(mktemp -d)
run() { # binary → md5 lines of every output
  local bin=$1
  rm -rf "${out:?}"/*
  cp "$d/sacre-coeur/database.db" "$out/sc-db.db"; cp "$d/sacre-coeur/queries.db" "$out/sc-q.db"
  "$bin" convert --colmap "$d/sacre-coeur/sparse-map" --database "$out/sc-db.db" -o "$out/sc-sift.sfpm" -q
  "$bin" slice "$out/sc-sift.sfpm" --level 2 --short -o "$out/sc-sift-l2.sfpm" -q
  "$bin" localize --map "$out/sc-sift.sfpm" --query-list "$d/sacre-coeur/queries.txt" --database "$out/sc-q.db" -o "$out/sc-sift-poses.txt" -q
  "$bin" localize --map "$out/sc-sift-l2.sfpm" --short --query-list "$d/sacre-coeur/queries.txt" --database "$out/sc-q.db" -o "$out/sc-sift-l2-poses.txt" -q
  "$bin" convert --colmap "$d/sacre-coeur/sparse-map" --images "$d/sacre-coeur/images" -o "$out/sc-sfp.sfpm" -q
  "$bin" localize --map "$out/sc-sfp.sfpm" --query-list "$d/sacre-coeur/queries.txt" --images "$d/sacre-coeur/images" -o "$out/sc-sfp-poses.txt" -q
  "$bin" convert --colmap "$d/south-building/sparse-map" --images "$d/south-building/images" -o "$out/sb-sfp.sfpm" -q
  "$bin" slice "$out/sb-sfp.sfpm" --level 2 --short -o "$out/sb-sfp-l2.sfpm" -q
  "$bin" localize --map "$out/sb-sfp-l2.sfpm" --short --query-list "$d/south-building/queries.txt" --images "$d/south-building/images" -o "$out/sb-sfp-l2-poses.txt" -q
  (cd "$out" && md5sum ./*.sfpm ./*poses.txt)
}
first=$(run "$a")
second=$(run "$b")
rm -rf "$out"
if diff <(echo "$first") <(echo "$second"); then
  echo "same bytes: every map and pose file ($(echo "$first" | wc -l) files)"
else
  echo "the builds differ (above)"; exit 1
fi
