#!/usr/bin/env bash
# Issue 11's scale table on the generated street (sfpmap::demo::street): per size, generate
# (cached under target/street/r2/), convert the SIFT map (with its VLAD; a line with convert's
# time, peak RSS and the image index it stored or why not), slice level 2 short,
# and localize with both maps (1 thread, after features; medians): the brute-force path
# (--retrieval off, every point a candidate) side by side with retrieval ranking every
# image (--retrieval-probe 0) and retrieval as the map says (its image index, where it has
# one; a line gives the share of every image's top k it retrieved, recall@k, from one more
# untimed run of each with --format json), and the walk
# (sequence.txt) with --sequence. Prints ms per query, queries within 0.5 m and 2°, map
# bytes and localize's peak RSS; then open to first pose: a fresh process that opens the map,
# builds the localizer and localizes the first query, 5 runs, the median of the three times
# (the map's pages in the page cache, as right after it was written or read).
# Usage: benches/street.sh [POINTS ...]   (default 100000; generating 1000000 takes about
# 1.5 min and 150 MB of memory, 5000000 about 10 GB of disk; a line gives the generator's
# time and peak RSS when it runs). Convert runs with
# `--memory ${STREET_MEMORY:-4GB}` (issue 35's budget) and says how it planned to keep to it.
set -euo pipefail
cd "$(dirname "$0")/.."
work=
trap 'rm -rf "$work"' EXIT
sizes=("${@:-100000}")
cargo build --release --quiet --all-features --example street
cargo build --release --quiet --all-features
bin=target/release/sfpmap
printf '%-9s %-14s %8s %-38s %10s %16s %12s %12s\n' points map MB path "ms/query" "retr/coarse/fine" "within bar" "peak RSS MB"
for n in "${sizes[@]}"; do
  dir=target/street/r2/$n  # r2: the generator since detection follows the viewpoint (stop 47)
  mkdir -p target/street/r2
  if [ ! -f "$dir/sequence_gt.txt" ]; then
    rm -rf "$dir"
    /usr/bin/time -f '%e %M' -o "$dir.generate_time" target/release/examples/street --points "$n" --queries 20 "$dir" >&2
    read -r seconds rss <"$dir.generate_time"
    echo "$n generate: $seconds s, peak RSS $((rss / 1024)) MB" >&2
  fi
  work=$(mktemp -d)
  # The map database is read in place (convert never writes its inputs; a copy of the 10 M
  # street's would be another 20 GB); the small query databases are copied.
  cp "$dir/queries.db" "$work/q.db"; cp "$dir/sequence.db" "$work/s.db"
  /usr/bin/time -f '%e %M' -o "$work/convert_time" \
    "$bin" convert --colmap "$dir/sparse" --database "$dir/database.db" -o "$work/sift.sfpm" \
    --memory "${STREET_MEMORY:-4GB}" --json >"$work/convert.json"
  python3 - "$n" "$work" <<'PY'
import json, sys
n, work = sys.argv[1:3]
c = json.load(open(f"{work}/convert.json"))
seconds, rss = open(f"{work}/convert_time").read().split()
i = c.get("image_index")
index = "none tried" if i is None else (
    f"{i['lists']} lists, {i['probe']} probed, ~{i['scored']} images scored, recall {i['recall']:.3f}"
    + ("" if i["stored"] else " (not stored: no gain)"))
m = c.get("memory") or {}
memory = (f"budget {m['budget'] / 1e6:.0f} MB, {m['passes']} read(s) of the features, planned peak "
          f"{m['planned_peak'] / 1e6:.0f} MB" if m else "no budget")
print(f"{n:<9} convert: {float(seconds):.1f} s, peak RSS {int(rss) / 1024:.0f} MB ({memory}), "
      f"{c['images']} images, {c['observations']} observations, map {c['output_bytes'] / 1e6:.1f} MB; image index: {index}")
PY
  "$bin" slice "$work/sift.sfpm" --level 2 --short -o "$work/l2.sfpm" -q
  for variant in sift l2; do
    short=(); [ "$variant" = l2 ] && short=(--short)
    for path in brute-force every-image retrieval sequence; do
      case $path in
        brute-force) args=(--retrieval off --query-list "$dir/queries.txt" --database "$work/q.db"); gt=$dir/gt_poses.txt ;;
        every-image) args=(--retrieval-probe 0 --query-list "$dir/queries.txt" --database "$work/q.db"); gt=$dir/gt_poses.txt ;;
        retrieval) args=(--query-list "$dir/queries.txt" --database "$work/q.db"); gt=$dir/gt_poses.txt ;;
        sequence) args=(--sequence --query-list "$dir/sequence.txt" --database "$work/s.db"); gt=$dir/sequence_gt.txt ;;
      esac
      /usr/bin/time -f '%M' -o "$work/rss" "$bin" localize --map "$work/$variant.sfpm" "${short[@]}" \
        "${args[@]}" --threads 1 -o "$work/poses.txt" --force --json >"$work/run.json"
      "$bin" eval --poses "$work/poses.txt" --gt "$gt" --threshold 0.5,2 --json >"$work/eval.json"
      # Which images each query retrieved: every-image's are the exhaustive top k that
      # retrieval's (the image index, where the map has one) is measured against.
      if [ "$path" = every-image ] || [ "$path" = retrieval ]; then
        "$bin" localize --map "$work/$variant.sfpm" "${short[@]}" "${args[@]}" --threads 1 \
          -o "$work/$path.json" --format json --force -q
      fi
      python3 - "$n" "$variant" "$path" "$work" <<'PY'
import json, os, sys
n, variant, path, work = sys.argv[1:5]
r = json.load(open(f"{work}/run.json"))
e = json.load(open(f"{work}/eval.json"))
rss = int(open(f"{work}/rss").read().split()[-1]) / 1024
mb = os.path.getsize(f"{work}/{variant}.sfpm") / 1e6
name = {"sift": "SIFT full", "l2": "level 2 short"}[variant]
paths = ", ".join(f"{k} {v}" for k, v in sorted(r.get("path", {}).items()))
within = round(e["recall"][0]["recall"] * r["queries"])
m = r["median_ms"]
stages = f"{m['retrieval']:.1f}/{m['coarse_match'] + m['coarse_ransac']:.1f}/{m['fine']:.1f}"
print(f"{n:<9} {name:<14} {mb:8.1f} {path + ' (' + paths + ')':<38} {m['total']:10.1f} {stages:>16} {within:>5}/{r['queries']:<6} {rss:12.0f}")
if path == "retrieval":
    every = {q["name"]: q["retrieved"] for q in json.load(open(f"{work}/every-image.json"))}
    got = {q["name"]: q["retrieved"] for q in json.load(open(f"{work}/retrieval.json"))}
    shares = [len(set(got.get(q, [])) & set(top)) / len(top) for q, top in every.items() if top]
    recall = sum(shares) / len(shares) if shares else float("nan")
    print(f"{n:<9} {name:<14} {'':>8} recall@k of every image's top k: {recall:.3f} (lowest {min(shares, default=float('nan')):.2f}, {len(shares)} queries)")
PY
    done
    head -1 "$dir/queries.txt" >"$work/one.txt"
    head -1 "$dir/gt_poses.txt" >"$work/one_gt.txt"
    for run in 1 2 3 4 5; do
      /usr/bin/time -f '%M' -o "$work/rss$run" "$bin" localize --map "$work/$variant.sfpm" "${short[@]}" \
        --query-list "$work/one.txt" --database "$work/q.db" --threads 1 -o "$work/poses$run.txt" --force --json >"$work/first$run.json"
      "$bin" eval --poses "$work/poses$run.txt" --gt "$work/one_gt.txt" --threshold 0.5,2 --json >"$work/first_eval$run.json"
    done
    python3 - "$n" "$variant" "$work" <<'PY'
import json, os, sys
n, variant, work = sys.argv[1:4]
runs = [json.load(open(f"{work}/first{i}.json")) for i in range(1, 6)]
evals = [json.load(open(f"{work}/first_eval{i}.json")) for i in range(1, 6)]
ms = [r["map_ms"]["open"] + r["map_ms"]["localizer"] + r["median_ms"]["total"] for r in runs]
# The median run, and its parts (open, Localizer::new, the first query).
median = sorted(range(len(runs)), key=lambda i: ms[i])[len(runs) // 2]
parts = [runs[median]["map_ms"]["open"], runs[median]["map_ms"]["localizer"]]
first = runs[median]["median_ms"]["total"]
rss = max(int(open(f"{work}/rss{i}").read().split()[-1]) for i in range(1, 6)) / 1024
mb = os.path.getsize(f"{work}/{variant}.sfpm") / 1e6
name = {"sift": "SIFT full", "l2": "level 2 short"}[variant]
within = sum(round(e["recall"][0]["recall"]) for e in evals)
path = f"open to first pose ({parts[0]:.1f}+{parts[1]:.1f}+{first:.1f})"
print(f"{n:<9} {name:<14} {mb:8.1f} {path:<38} {ms[median]:10.1f} {'':>16} {within:>5}/{len(runs):<6} {rss:12.0f}")
PY
  done
  rm -rf "$work"
done
