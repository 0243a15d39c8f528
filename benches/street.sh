#!/usr/bin/env bash
# Issue 11's scale table on the generated street (sfpmap::demo::street): per size, generate
# (cached under target/street/), convert the SIFT map, slice level 2 short, localize the
# queries with both maps (1 thread), and print median ms per query, localized share, map
# bytes and localize's peak RSS side by side.
# Usage: benches/street.sh [POINTS ...]   (default 100000; 1000000 takes ~5 min and ~8 GB to generate)
set -euo pipefail
cd "$(dirname "$0")/.."
sizes=("${@:-100000}")
cargo build --release --quiet --all-features --example street
bin=target/release/sfpmap
[ -x "$bin" ] || cargo build --release --quiet --all-features
printf '%-9s %-16s %9s %10s %12s %10s\n' points map MB localized "ms/query" "peak RSS MB"
for n in "${sizes[@]}"; do
  dir=target/street/$n
  if [ ! -f "$dir/gt_poses.txt" ]; then
    rm -rf "$dir"
    target/release/examples/street --points "$n" --queries 20 "$dir" >&2
  fi
  work=$(mktemp -d)
  cp "$dir/database.db" "$work/db.db"; cp "$dir/queries.db" "$work/q.db"
  "$bin" convert --colmap "$dir/sparse" --database "$work/db.db" -o "$work/sift.sfpm" -q
  "$bin" slice "$work/sift.sfpm" --level 2 --short -o "$work/l2.sfpm" -q
  for variant in sift l2; do
    short=(); [ "$variant" = l2 ] && short=(--short)
    /usr/bin/time -f '%M' -o "$work/rss" "$bin" localize --map "$work/$variant.sfpm" "${short[@]}" \
      --query-list "$dir/queries.txt" --database "$work/q.db" --threads 1 -o "$work/$variant.txt" --json >"$work/$variant.json"
    python3 - "$n" "$variant" "$work" <<'PY'
import json, os, sys
n, variant, work = sys.argv[1], sys.argv[2], sys.argv[3]
r = json.load(open(f"{work}/{variant}.json"))
rss = int(open(f"{work}/rss").read().split()[-1]) / 1024
mb = os.path.getsize(f"{work}/{variant}.sfpm") / 1e6
name = {"sift": "SIFT full", "l2": "level 2 short"}[variant]
print(f"{n:<9} {name:<16} {mb:9.1f} {r['localized']:>4}/{r['queries']:<5} {r['median_ms']['total']:12.1f} {rss:10.0f}")
PY
  done
  rm -rf "$work"
done
