#!/usr/bin/env bash
# Issue 34's latency and soak figures for `sfpmap ros2`: the KITTI 06 query frames (1241x376
# JPEGs, the scene `make_posed_scene.py` builds, cached under target/ros2-bench/) published by
# Cyclone DDS (cli/tests/e2e/ros2_peer.py, loopback only) at the camera's 10 Hz, looped, to the
# node on the scene's SFP map, best effort as a camera driver publishes. For --threads 1 and 2
# it prints the node's own latency (frame taken off the topic -> pose published: median, p99),
# the peer's (published -> pose received), the counts, and the node's RSS after warm-up and at
# the end (the soak: growth target <= 5 MB over 10 minutes).
#
# Usage: benches/ros2_node.sh [SECONDS] [THREADS...]   (default 60 s, threads 1 and 2;
#        `benches/ros2_node.sh 600 2` is the 10-minute soak)
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-60}
shift || true
threads=("${@:-1 2}")
export ORT_DISABLE_TELEMETRY=1
unset CARGO_PROFILE_RELEASE_DEBUG_ASSERTIONS CARGO_PROFILE_RELEASE_OVERFLOW_CHECKS
venv=$(bash .ci/tools | tail -1)
py=$venv/bin/python
cargo build --release --quiet -p sfpmap-cli --features ros2
target=${CARGO_TARGET_DIR:-$PWD/target}
sfpmap=$target/release/sfpmap
root=$target/ros2-bench
shared=../shared/data
scene=$root/kitti06
if [ ! -f "$scene/queries.txt" ]; then
  mkdir -p "$root"
  "$py" $shared/tools/make_posed_scene.py $shared/sequences/kitti06/images \
    $shared/sequences/kitti06/poses.txt $shared/sequences/kitti06/calib.txt "$scene"
fi
map=$root/sfp.sfpm
[ -f "$map" ] || "$sfpmap" convert --colmap "$scene/sparse-map" --images "$scene/images" -o "$map" --quiet
camera=$(head -1 "$scene/queries.txt" | cut -d' ' -f2-)
names=$(cut -d' ' -f1 "$scene/queries.txt" | paste -sd,)
rss() { awk '/VmRSS/ {print $2}' "/proc/$1/status"; }

printf '%-8s %8s %8s %10s %10s %12s %12s %8s %10s %10s\n' threads sent poses "node p50" "node p99" "peer p50" "peer p99" dropped "RSS 10s" "RSS end"
for t in ${threads[*]}; do
  domain=$((60 + t))
  out=$(mktemp)
  "$sfpmap" ros2 --map "$map" --image-topic /camera/image_raw/compressed --camera "$camera" \
    --threads "$t" --domain-id $domain --interface 127.0.0.1 --json --quiet > "$out" &
  node=$!
  "$py" cli/tests/e2e/ros2_peer.py rate --domain $domain --images "$scene/images" \
    --names "$names" --hz 10 --seconds "$seconds" > "$out.peer" &
  peer=$!
  sleep 10
  early=$(rss $node)
  wait $peer
  late=$(rss $node)
  kill -TERM $node
  wait $node
  "$py" - "$out" "$out.peer" "$t" "$early" "$late" <<'PY'
import json, sys
node, peer = json.load(open(sys.argv[1])), json.load(open(sys.argv[2]))
t, early, late = sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
f = lambda v: "-" if v is None else f"{v:.1f}"
print(f"{t:<8} {peer['sent']:>8} {peer['poses']:>8} {f(node['latency_ms']['median']):>10} {f(node['latency_ms']['p99']):>10} "
      f"{f(peer['latency_ms']['median']):>12} {f(peer['latency_ms']['p99']):>12} {node['dropped']:>8} "
      f"{early / 1024:>9.1f}M {late / 1024:>9.1f}M")
print("  counts: " + ", ".join(f"{k} {v}" for k, v in node.items() if isinstance(v, int) and v and k != "threads"))
PY
  rm -f "$out" "$out.peer"
done
