#!/usr/bin/env bash
# Issue 34's latency and soak figures for `sfpmap ros2`: KITTI 06 query frames (JPEGs of the
# scenes `make_posed_scene.py` builds, cached under target/ros2-bench/: `full` at KITTI's
# 1226x370, `vga` resized to 1005x303, the pixels of a 640x480 frame) published by Cyclone DDS
# (cli/tests/e2e/ros2_peer.py, loopback only) at the camera's 10 Hz, looped, to the node on the
# scene's SFP map, best effort as a camera driver publishes. For --threads 1 and 2 it prints the
# node's own latency (frame taken off the topic -> pose published: median, p99) over all frames
# and over the frames localized by tracking (each loop's first frame jumps back to the start and
# retrieves), its stages, the peer's latency (published -> pose received), the counts, the
# node's RSS after warm-up and at the end (the soak: growth target <= 5 MB over 10 minutes), and
# the default model's extraction time on this machine today as a reference (sfp-v3 since stop
# 54: sfp-v2's network, 1.14-1.25x its time a frame).
#
# Usage: benches/ros2_node.sh [SECONDS] [THREADS...]   (default 60 s, threads 1 and 2;
#        `ROS2_BENCH_SCENES=vga benches/ros2_node.sh 600 2` is the 10-minute soak;
#        ROS2_BENCH_NODE_ARGS=--spin runs the node with more flags)
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
seq=$shared/sequences/kitti06
rss() { awk '/VmRSS/ {print $2}' "/proc/$1/status"; }

# The scenes, built once: KITTI's own 1226x370 frames, and the same frames resized to 1005x303
# (0.30 MP, the pixels of a 640x480 frame: the issue's "640x480 class"), the calibration scaled
# with them. Every second frame is a query (25 of 51), so consecutive queries are 0.2 s apart.
scene_of() {
  local name=$1 scene=$root/$1
  if [ ! -f "$scene/queries.txt" ]; then
    mkdir -p "$root"
    local images=$seq/images calib=$seq/calib.txt
    if [ "$name" = vga ]; then
      images=$root/vga-source/images calib=$root/vga-source/calib.txt
      "$py" - "$seq" "$root/vga-source" <<'PY'
import pathlib, sys
from PIL import Image
src, out = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])
(out / "images").mkdir(parents=True, exist_ok=True)
w, h = 1005, 303
for p in sorted((src / "images").glob("*.jpg")):
    im = Image.open(p)
    sx, sy = w / im.width, h / im.height
    im.resize((w, h), Image.Resampling.LANCZOS).save(out / "images" / p.name, quality=95)
rows = []
for line in open(src / "calib.txt"):
    v = [float(x) for x in line.split()]
    # P = K [R|t]: the image rows scale with the pixels (centres of pixels kept on centres).
    v[0:4] = [x * sx for x in v[0:4]]
    v[4:8] = [x * sy for x in v[4:8]]
    v[2] += 0.5 * sx - 0.5; v[6] += 0.5 * sy - 0.5
    rows.append(" ".join(repr(x) for x in v))
(out / "calib.txt").write_text("\n".join(rows) + "\n")
PY
    fi
    "$py" $shared/tools/make_posed_scene.py "$images" $seq/poses.txt "$calib" "$scene" --every 2 \
      > "$root/$name-scene.log" 2>&1 || { tail -5 "$root/$name-scene.log"; exit 1; }
  fi
  [ -f "$scene/sfp.sfpm" ] || "$sfpmap" convert --colmap "$scene/sparse-map" --images "$scene/images" \
    -o "$scene/sfp.sfpm" --quiet
}

f_ms() { "$py" -c 'import json,sys; d=json.load(sys.stdin)["ms_median_parts"]; print("%.1f" % d["network"])'; }
printf '%-10s %-8s %7s %7s %9s %9s %11s %11s %10s %10s %8s %9s %9s\n' frames threads sent poses \
  "node p50" "node p99" "tracked p50" "tracked p99" "peer p50" "peer p99" dropped "RSS 10s" "RSS end"
for name in ${ROS2_BENCH_SCENES:-full vga}; do
  scene_of "$name"
  scene=$root/$name
  camera=$(head -1 "$scene/queries.txt" | cut -d' ' -f2-)
  size=$(echo "$camera" | cut -d' ' -f2,3 | tr ' ' x)
  names=$(cut -d' ' -f1 "$scene/queries.txt" | paste -sd,)
  for t in ${threads[*]}; do
    domain=$((60 + t))
    out=$(mktemp)
    "$sfpmap" ros2 --map "$scene/sfp.sfpm" --image-topic /camera/image_raw/compressed --camera "$camera" \
      --threads "$t" --domain-id $domain --interface 127.0.0.1 --json --quiet ${ROS2_BENCH_NODE_ARGS:-} > "$out" &
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
    "$py" - "$out" "$out.peer" "$t" "$early" "$late" "$size" <<'PY'
import json, sys
node, peer = json.load(open(sys.argv[1])), json.load(open(sys.argv[2]))
t, early, late, size = sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), sys.argv[6]
f = lambda v: "-" if v is None else f"{v:.1f}"
lat, tr = node["latency_ms"], node["tracked_latency_ms"]
print(f"{size:<10} {t:<8} {peer['sent']:>7} {peer['poses']:>7} {f(lat['median']):>9} {f(lat['p99']):>9} "
      f"{f(tr['median']):>11} {f(tr['p99']):>11} {f(peer['latency_ms']['median']):>10} "
      f"{f(peer['latency_ms']['p99']):>10} {node['dropped']:>8} {early / 1024:>8.1f}M {late / 1024:>8.1f}M")
print(f"  {tr['frames']} of {lat['frames']} frames tracked; stages (median / p99 ms): "
      + ", ".join(f"{k} {f(v['median'])} / {f(v['p99'])}" for k, v in node["stages_ms"].items()))
print("  counts: " + ", ".join(f"{k} {v}" for k, v in node.items() if isinstance(v, int) and v and k != "threads"))
PY
    rm -f "$out" "$out.peer"
  done
done
# This machine's speed today, for reading the figures against other days: the network alone on
# the 640x480-class frames, as `sfpmap extract` times it (benchmarks.md's extractor table).
frames=$(ls "$root"/vga/images/*.jpg 2>/dev/null | head -8)
if [ -n "$frames" ]; then
  for t in 1 2; do
    ms=$("$sfpmap" extract $frames -o "$root/speed.h5" --force --threads $t --json --quiet | f_ms)
    echo "reference: the default model (sfp-v3) on a 1005x303 frame, $t thread(s): median $ms ms"
  done
  rm -f "$root/speed.h5"
fi
