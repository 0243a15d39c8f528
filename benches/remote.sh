#!/usr/bin/env bash
# Issue 16's figures: localize against a map served over loopback by nginx (range requests),
# side by side with the same map read locally. The map is the generated street's SIFT map
# (sfpmap::demo::street, cached under target/street/r2/N), about 100 MB at 250,000 points;
# localize uses level 2 (--level 2 --short), 1 thread, the queries' SIFT features from
# their database. For each run: bytes and requests that crossed the wire, what the sections
# it reads add up to (index + level 2's sections + retrieval + the shared geometry the
# localizer reads), opening and localizer-building ms, median ms per query and when the
# first pose was ready (open + localizer + the first query). Runs: local file; remote with
# no cache (cold); remote again with a filled cache (warm). Medians over REPEAT runs.
# Usage: benches/remote.sh [POINTS] [REPEAT]   (default 250000 3; needs nginx: apt-get install nginx-light)
set -euo pipefail
cd "$(dirname "$0")/.."
n=${1:-250000}
repeat=${2:-3}
work=$(mktemp -d)
nginx_pid=
cleanup() {
  [ -n "$nginx_pid" ] && kill "$nginx_pid" 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT
cargo build --release --quiet --all-features --example street
cargo build --release --quiet --all-features
bin=$PWD/target/release/sfpmap
dir=target/street/r2/$n  # r2: the generator since detection follows the viewpoint (stop 47)
if [ ! -f "$dir/queries.txt" ]; then
  rm -rf "$dir"
  target/release/examples/street --points "$n" --queries 20 "$dir" >&2
fi
if [ ! -f "$dir/sift.sfpm" ]; then
  cp "$dir/database.db" "$work/db.db"
  "$bin" convert --colmap "$dir/sparse" --database "$work/db.db" -o "$dir/sift.sfpm" -q
fi
cp "$dir/queries.db" "$work/q.db"
mkdir -p "$work/www" "$work/logs"
ln "$dir/sift.sfpm" "$work/www/sift.sfpm" 2>/dev/null || cp "$dir/sift.sfpm" "$work/www/sift.sfpm"
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
cat >"$work/nginx.conf" <<EOF
daemon off;
master_process off;
pid $work/nginx.pid;
error_log $work/logs/error.log;
events { worker_connections 64; }
http {
  access_log off;
  client_body_temp_path $work/body;
  proxy_temp_path $work/proxy;
  fastcgi_temp_path $work/fastcgi;
  uwsgi_temp_path $work/uwsgi;
  scgi_temp_path $work/scgi;
  server { listen 127.0.0.1:$port; root $work/www; }
}
EOF
nginx=$(command -v nginx || echo /usr/sbin/nginx)
"$nginx" -c "$work/nginx.conf" -p "$work" -e "$work/logs/error.log" &
nginx_pid=$!
for _ in $(seq 100); do (echo >"/dev/tcp/127.0.0.1/$port") 2>/dev/null && break; sleep 0.05; done
url=http://127.0.0.1:$port/sift.sfpm
"$bin" info "$dir/sift.sfpm" --json >"$work/info.json"
run() { # NAME MAP CACHE_DIR
  for i in $(seq "$repeat"); do
    SFPMAP_CACHE_DIR=$3 "$bin" localize --map "$2" --level 2 --short --query-list "$dir/queries.txt" \
      --database "$work/q.db" --threads 1 -o "$work/poses.txt" --force --json >"$work/$1.$i.json"
  done
}
run local "$dir/sift.sfpm" off
run cold "$url" off
SFPMAP_CACHE_DIR=$work/cache "$bin" info "$url" -q >/dev/null
SFPMAP_CACHE_DIR=$work/cache "$bin" localize --map "$url" --level 2 --short --query-list "$dir/queries.txt" \
  --database "$work/q.db" --threads 1 -o "$work/poses.txt" --force -q
run warm "$url" "$work/cache"
python3 - "$work" "$repeat" <<'PY'
import json, statistics, sys
work, repeat = sys.argv[1], int(sys.argv[2])
info = json.load(open(f"{work}/info.json"))
secs = info["sections"]
first = min(s["offset"] for s in secs)
shared_skip = {"point_colors", "point_ids", "visibility_keypoints"}
def used(s):
    if s.get("level") is None:
        return s["kind"] not in shared_skip
    return s["level"] == 2 and s["kind"] != "level_desc_rest" or s["kind"] == "level_vlad_centroids"
need = first + sum(s["stored_bytes"] for s in secs if used(s))
print(f"map: {info['file_bytes'] / 1e6:.1f} MB, {info['points']} points; index {first} B; "
      f"index + what localize --level 2 --short reads: {need / 1e6:.2f} MB")
print(f"{'run':<6} {'MB read':>8} {'requests':>8} {'cache hits':>10} {'open ms':>8} {'localizer ms':>12} "
      f"{'ms/query':>9} {'first pose ms':>13} {'localized':>9}")
base = None
for name in ["local", "cold", "warm"]:
    runs = [json.load(open(f"{work}/{name}.{i}.json")) for i in range(1, repeat + 1)]
    t = [r["transfer"] or {"bytes": 0, "requests": 0, "cache_hits": 0} for r in runs]
    med = lambda xs: statistics.median(xs)
    open_ms = med([r["map_ms"]["open"] for r in runs])
    loc_ms = med([r["map_ms"]["localizer"] for r in runs])
    q_ms = med([r["median_ms"]["total"] for r in runs])
    first_pose = open_ms + loc_ms + q_ms
    base = base or q_ms
    print(f"{name:<6} {med([x['bytes'] for x in t]) / 1e6:8.2f} {med([x['requests'] for x in t]):8.0f} "
          f"{med([x['cache_hits'] for x in t]):10.0f} {open_ms:8.1f} {loc_ms:12.1f} {q_ms:9.1f} "
          f"{first_pose:13.1f} {runs[0]['localized']:>4}/{runs[0]['queries']} "
          f"(ms/query {q_ms / base:.2f}x local)")
PY
