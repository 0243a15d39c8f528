#!/usr/bin/env bash
# Issue 33's throughput table for `python -m sfpmap.batch`: the same places (generated streets,
# cached under target/batch-bench/) converted to a SIFT map and sliced to `l2s` and `pq8` (PQ
# training: CPU-bound), three ways, each into a fresh folder, medians of RUNS runs:
#   1. the plain CLI loop (`sfpmap convert` + two `sfpmap slice`, one place after another, then
#      `sfpmap catalog build` of the l2s maps, as the job's last step);
#   2. the batch job on a Ray cluster of one node with one CPU (a head started here);
#   3. the same with a second node of one CPU (`ray start --address`) beside it;
# and prints places per minute, the ratios (2 nodes vs 1: target >= 1.7x; Ray's overhead per
# place vs the CLI loop: target <= 10 %) and the workers' peak RSS beside the CLI's largest
# step (Ray reuses a worker for up to 16 places; its growth from its first to its last).
# Every run is timed from outside, process start and exit included, as the CLI loop is.
#
# Usage: benches/batch.sh [PLACES] [POINTS] [RUNS]   (default 8 places of 60000 points, 3 runs)
# The CLI and the wheel are built here the same way (release, no debug assertions: the test
# venv may hold CI's wheel, built with them) and the wheel installed into the test venv.
set -euo pipefail
cd "$(dirname "$0")/.."
places=${1:-8} points=${2:-60000} runs=${3:-3}
export ORT_DISABLE_TELEMETRY=1 RAY_USAGE_STATS_ENABLED=0
unset CARGO_PROFILE_RELEASE_DEBUG_ASSERTIONS CARGO_PROFILE_RELEASE_OVERFLOW_CHECKS
venv=$(bash .ci/tools | tail -1)
py=$venv/bin/python
cargo build --release --quiet --all-features --bin sfpmap --example street
wheels=$(mktemp -d)
"$venv/bin/maturin" build --release --quiet -m python/binding/Cargo.toml -o "$wheels"
"$py" -m pip install --quiet --force-reinstall --no-deps "$wheels"/sfpmap-*.whl
rm -rf "$wheels"
target=${CARGO_TARGET_DIR:-$PWD/target}
"$py" - "$target" "$places" "$points" "$runs" <<'PY'
import json, os, secrets, shutil, signal, socket, statistics, subprocess, sys, tempfile, time
from pathlib import Path

target, n_places, points, runs = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
sfpmap, street = target / "release/sfpmap", target / "release/examples/street"
root = target / "batch-bench"
data = root / f"places-{points}"
data.mkdir(parents=True, exist_ok=True)
for i in range(n_places):
    if not (data / f"p{i}/database.db").exists():
        subprocess.run([street, "--points", str(points), "--queries", "1", "--seed", str(i), data / f"p{i}"],
                       check=True, capture_output=True)
manifest = root / "manifest.jsonl"
manifest.write_text("".join(json.dumps({"place": f"p{i}", "colmap": str(data / f"p{i}/sparse"),
                                        "database": str(data / f"p{i}/database.db"),
                                        "variants": ["l2s", "pq8"]}) + "\n" for i in range(n_places)))
mb_in = sum(f.stat().st_size for i in range(n_places)
            for f in [*(data / f"p{i}/sparse").iterdir(), data / f"p{i}/database.db"]) / 1e6


def fresh(name):
    out = root / name
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir()
    return out


def cli_loop():
    out = fresh("out-cli")
    peak = 0
    began = time.perf_counter()
    for i in range(n_places):
        p = data / f"p{i}"
        m = out / f"p{i}.sfpm"
        steps = [[sfpmap, "convert", "--colmap", p / "sparse", "--database", p / "database.db", "-o", m, "--quiet"],
                 [sfpmap, "slice", m, "--level", "2", "--short", "-o", out / f"p{i}-l2s.sfpm", "--quiet"],
                 [sfpmap, "slice", m, "--level", "0", "--level", "1", "--level", "2", "--pq", "8",
                  "-o", out / f"p{i}-pq8.sfpm", "--quiet"]]
        for step in steps:
            r = subprocess.run(["/usr/bin/time", "-f", "%M", *map(str, step)], capture_output=True, text=True, check=True)
            peak = max(peak, int(r.stderr.strip().splitlines()[-1]) / 1024)
    # The same job's last step: a catalog of the places (by their l2s maps).
    subprocess.run([sfpmap, "catalog", "build", *[out / f"p{i}-l2s.sfpm" for i in range(n_places)],
                    *[a for i in range(n_places) for a in ("--name", f"p{i}")], "-o", out / "catalog.sfpc",
                    "--quiet"], check=True)
    return time.perf_counter() - began, peak


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(32), RAY_USAGE_STATS_ENABLED="0")
ray = str(Path(sys.executable).parent / "ray")
temp = tempfile.mkdtemp(prefix="ray-", dir="/tmp")
port = free_port()
common = ["--block", "--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--object-store-memory", "80000000",
          "--disable-usage-stats"]
nodes = []


def start(args, wait_port):
    p = subprocess.Popen([ray, "start", *args, *common], env=env, stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL, start_new_session=True)
    nodes.append(p)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", wait_port)) == 0:
                return
        time.sleep(0.2)
    raise SystemExit(f"ray start {args} is not listening")


def batch():
    out = fresh("out-ray")
    began = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "sfpmap.batch", str(manifest), "--out", str(out),
                        "--address", f"127.0.0.1:{port}", "--json"], env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - began
    if r.returncode != 0:
        raise SystemExit(r.stderr[-2000:])
    report = json.loads(r.stdout)
    assert report["places"]["done"] == n_places, report["places"]
    # Per worker process: its peak after each of its places (ru_maxrss only grows, so the
    # spread is the growth from its first place to its last).
    workers = {}
    for row in report["rows"]:
        workers.setdefault(row["worker_pid"], []).append(row["worker_peak_rss_mb"])
    growth = max(max(w) - min(w) for w in workers.values())
    return seconds, max(row["worker_peak_rss_mb"] for row in report["rows"]), \
        len({row["node"] for row in report["rows"]}), growth, max(len(w) for w in workers.values())


try:
    cli = [cli_loop() for _ in range(runs)]
    start(["--head", "--port", str(port), "--include-dashboard=false", "--temp-dir", temp], port)
    one = [batch() for _ in range(runs)]
    manager = free_port()
    start(["--address", f"127.0.0.1:{port}", "--node-manager-port", str(manager)], manager)
    time.sleep(2)  # the node registers
    two = [batch() for _ in range(runs)]
finally:
    for p in reversed(nodes):
        try:
            os.killpg(p.pid, signal.SIGTERM)
            p.wait(timeout=15)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(p.pid, signal.SIGKILL)
    shutil.rmtree(temp, ignore_errors=True)

med = lambda xs, i=0: statistics.median(x[i] for x in xs)
t_cli, t_one, t_two = med(cli), med(one), med(two)
rate = lambda t: n_places * 60 / t
print(f"{n_places} places of {points} points ({mb_in:.0f} MB of COLMAP model and database), each converted and "
      f"sliced to l2s and pq8; median of {runs} runs; {os.cpu_count()} cores")
spread = lambda xs: f"{min(x[0] for x in xs):.1f}-{max(x[0] for x in xs):.1f}"
print(f"{'run':<34} {'seconds':>8} {'(min-max)':>11} {'places/min':>11} {'peak RSS MB':>12}")
for label, xs, t in (("CLI loop (one place at a time)", cli, t_cli), ("Ray, 1 node x 1 CPU", one, t_one),
                     ("Ray, 2 nodes x 1 CPU", two, t_two)):
    print(f"{label:<34} {t:8.1f} {spread(xs):>11} {rate(t):11.1f} {max(x[1] for x in xs):12.0f}")
print(f"2 nodes vs 1: {t_one / t_two:.2f}x places per minute (target >= 1.7x); nodes used: {max(o[2] for o in two)}")
print(f"a worker's peak RSS grew by at most {max(o[3] for o in one + two):.0f} MB from its first place to its last "
      f"(up to {max(o[4] for o in one + two)} places per worker)")
print(f"Ray's overhead vs the CLI loop, per place: {(t_one - t_cli) / n_places * 1000:.0f} ms, "
      f"{(t_one / t_cli - 1) * 100:+.1f} % (target <= 10 %)")
PY
