"""`python -m sfpmap.batch` on a real Ray cluster on loopback (a head and a second node started
here with `ray start`, token authentication on) and the S3 test server (s3s-fs, as the Rust
remote tests use): 40 generated streets, Sacre Coeur and broken places converted from a bucket
into a bucket; the second node's raylet killed mid-run; a rerun that changes nothing; a folder
as PREFIX.

Environment: SFPMAP_STREET (the street generator, `cargo build --release --example street`;
default target/release/examples/street), s3s-fs on PATH or in ~/.cargo/bin (`.ci/tools`).
"""

from __future__ import annotations

import http.server
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

import sfpmap
from sfpmap import _sfpmap
from sfpmap import batch

from conftest import REPO, _need, need_module

STREETS = 40


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_listening(port: int, proc: subprocess.Popen, what: str, seconds: float = 60) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            pytest.fail(f"{what} exited ({proc.returncode})")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    pytest.fail(f"{what} is not listening on {port} after {seconds} s")


def stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM to the process group (`ray start --block` stops its node), SIGKILL after 10 s."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=10)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def kill_matching(needle: str) -> None:
    """SIGKILL every process whose command line holds `needle` (a node's workers left behind)."""
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if needle in cmdline and int(pid) != os.getpid():
            try:
                os.kill(int(pid), signal.SIGKILL)
            except ProcessLookupError:
                pass


@pytest.fixture(scope="module")
def street_bin() -> Path:
    return _need(Path(os.environ.get("SFPMAP_STREET", REPO / "target/release/examples/street")),
                 "the street generator (cargo build --release --example street)")


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    binary = shutil.which("s3s-fs") or str(Path.home() / ".cargo/bin/s3s-fs")
    _need(Path(binary), "s3s-fs (.ci/tools installs it)")
    root = tmp_path_factory.mktemp("buckets")
    for bucket in ("inputs", "outputs"):
        (root / bucket).mkdir()
    port = free_port()
    key, secret = "sfpmap-test", "sfpmap-test-secret"
    proc = subprocess.Popen(
        [binary, "--host", "127.0.0.1", "--port", str(port), "--access-key", key, "--secret-key", secret, str(root)],
        stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    wait_listening(port, proc, "s3s-fs")
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": key,
           "AWS_SECRET_ACCESS_KEY": secret, "AWS_REGION": "us-east-1", "AWS_ALLOW_HTTP": "true"}
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)  # this process's object_* calls
    yield {"root": root, "env": env}
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    stop_group(proc)


@pytest.fixture(scope="module")
def cluster(s3):
    need_module("ray")
    ray_bin = str(Path(sys.executable).parent / "ray")
    token = secrets.token_hex(32)
    # The nodes start without the S3 settings: the tasks get the driver's (--pass-credentials).
    node_env = {k: v for k, v in os.environ.items() if not k.startswith(("RAY_", "AWS_"))}
    node_env.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=token, RAY_USAGE_STATS_ENABLED="0")
    env = {**node_env, **s3["env"]}
    # Short: Ray's socket paths live under it.
    temp = tempfile.mkdtemp(prefix="ray-", dir="/tmp")
    port, manager_port = free_port(), free_port()
    common = ["--block", "--node-ip-address", "127.0.0.1", "--num-cpus", "1",
              "--object-store-memory", "80000000", "--disable-usage-stats"]
    logs = open(os.path.join(temp, "start.log"), "wb")
    head = subprocess.Popen([ray_bin, "start", "--head", "--port", str(port), "--include-dashboard=false",
                             "--temp-dir", temp, *common],
                            env=node_env, stdin=subprocess.DEVNULL, stdout=logs, stderr=logs, start_new_session=True)
    worker = None
    try:
        wait_listening(port, head, "the Ray head")
        worker = subprocess.Popen([ray_bin, "start", "--address", f"127.0.0.1:{port}",
                                   "--node-manager-port", str(manager_port), *common],
                                  env=node_env, stdin=subprocess.DEVNULL, stdout=logs, stderr=logs,
                                  start_new_session=True)
        wait_listening(manager_port, worker, "the second Ray node")
        yield {"address": f"127.0.0.1:{port}", "env": env, "manager_port": manager_port, "temp": temp}
    finally:
        for proc in (worker, head):
            if proc is not None:
                stop_group(proc)
        kill_matching(temp)
        logs.close()
        shutil.rmtree(temp, ignore_errors=True)


class Forbidden(http.server.BaseHTTPRequestHandler):
    """A web server that refuses everything with 403."""

    def do_HEAD(self):
        self.send_response(403)
        self.send_header("Content-Length", "0")
        self.end_headers()

    do_GET = do_HEAD

    def log_message(self, *args):
        pass


@pytest.fixture
def forbidden():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Forbidden)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def upload_place(src: Path, bucket_prefix: str, model: str = "sparse") -> None:
    for f in sorted((src / model).iterdir()):
        _sfpmap.object_upload(str(f), f"{bucket_prefix}/sparse/{f.name}")
    _sfpmap.object_upload(str(src / "database.db"), f"{bucket_prefix}/database.db")


def run_batch(cluster, *args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sfpmap.batch", *args, "--address", cluster["address"],
                           "--pass-credentials"],
                          env=cluster["env"], capture_output=True, text=True, timeout=timeout)


def snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


def processes():
    """(pid, parent pid, command line parts) of every process."""
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            parent = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        yield int(pid), parent, cmdline


def raylet_of(manager_port: int):
    for pid, _, cmdline in processes():
        if cmdline and cmdline[0].endswith(b"/raylet") and f"--node_manager_port={manager_port}".encode() in cmdline:
            return pid
    return None


def running_a_place(raylet: int) -> bool:
    """Whether a worker of that raylet is running a place now (Ray titles it `ray::run_place`)."""
    return any(parent == raylet and cmdline[0].startswith(b"ray::run_place") for _, parent, cmdline in processes())


def test_a_bucket_of_places_on_two_nodes_survives_a_killed_node_and_a_rerun_does_nothing(
        cluster, s3, street_bin, shared, tmp_path, forbidden):
    gen = tmp_path / "streets"
    gen.mkdir()
    lines = []
    for i in range(STREETS):
        name = f"street-{i:02d}"
        subprocess.run([str(street_bin), "--points", "2500", "--queries", "1", "--seed", str(100 + i),
                        str(gen / name)], check=True, capture_output=True)
        upload_place(gen / name, f"s3://inputs/city/{name}")
        lines.append({"place": name, "colmap": f"s3://inputs/city/{name}/sparse",
                      "database": f"s3://inputs/city/{name}/database.db", "variants": ["l2s"]})
    sacre = shared / "scenes/sacre-coeur"
    upload_place(sacre, "s3://inputs/city/sacre-coeur", model="sparse-map")
    lines.append({"place": "sacre-coeur", "colmap": "s3://inputs/city/sacre-coeur/sparse",
                  "database": "s3://inputs/city/sacre-coeur/database.db", "variants": ["l2s", "pq8"],
                  "budget": "300kB"})
    # Broken places: a damaged model, a missing one, a bucket that does not exist, a server that
    # answers 403, a bad line.
    damaged = gen / "damaged"
    shutil.copytree(gen / "street-00", damaged)
    points = damaged / "sparse/points3D.bin"
    points.write_bytes(points.read_bytes()[: points.stat().st_size // 2])
    upload_place(damaged, "s3://inputs/city/damaged")
    lines.append({"place": "damaged", "colmap": "s3://inputs/city/damaged/sparse",
                  "database": "s3://inputs/city/damaged/database.db"})
    lines.append({"place": "missing", "colmap": "s3://inputs/city/missing/sparse",
                  "database": "s3://inputs/city/street-00/database.db"})
    lines.append({"place": "no-bucket", "colmap": "s3://no-such-bucket/sparse",
                  "database": "s3://inputs/city/street-00/database.db"})
    lines.append({"place": "refused", "colmap": f"{forbidden}/city/sparse",
                  "database": f"{forbidden}/city/database.db"})
    closed = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    lines.append({"place": "unreachable", "colmap": f"{closed}/city/sparse",
                  "database": f"{closed}/city/database.db"})
    lines.append({"place": "typo", "colmap": "s3://inputs/city/street-01/sparse",
                  "database": "s3://inputs/city/street-01/database.db", "varaints": ["l2s"]})
    manifest = tmp_path / "city.jsonl"
    manifest.write_text("".join(json.dumps(line) + "\n" for line in lines))
    report_path = tmp_path / "report.json"

    # The job, and the second node's raylet SIGKILLed once a few places are done.
    errors = open(tmp_path / "driver.err", "w+")
    driver = subprocess.Popen([sys.executable, "-m", "sfpmap.batch", str(manifest), "--out", "s3://outputs/city",
                               "--address", cluster["address"], "--report", str(report_path), "--pass-credentials"],
                              env=cluster["env"], stdout=subprocess.PIPE, stderr=errors, text=True)
    raylet = raylet_of(cluster["manager_port"])
    assert raylet is not None, "the second node's raylet is not running"
    deadline = time.monotonic() + 300
    killed_after = None
    while driver.poll() is None and time.monotonic() < deadline:
        errors.seek(0)
        done = sum(1 for line in errors if line.startswith("[") and " done" in line)
        # Killed while one of its workers runs a place: that task is lost and must be retried.
        if done >= 6 and running_a_place(raylet):
            os.kill(raylet, signal.SIGKILL)
            killed_after = done
            break
        time.sleep(0.05)
    assert killed_after is not None, ("the job ended before the node could be killed", done, raylet,
                                      [(p, c[:1]) for p, parent, c in processes() if parent == raylet])
    out, _ = driver.communicate(timeout=600)
    errors.seek(0)
    stderr = errors.read()
    assert driver.returncode == 1, stderr  # the broken places failed
    assert raylet_of(cluster["manager_port"]) is None
    report = json.loads(report_path.read_text())
    rows = {r["place"]: r for r in report["rows"]}
    assert len(report["rows"]) == len(lines) == len(rows)
    good = [f"street-{i:02d}" for i in range(STREETS)] + ["sacre-coeur"]
    assert all(rows[p]["status"] == "done" for p in good), [(p, rows[p]["error"]) for p in good if rows[p]["status"] != "done"]
    assert report["places"] == {"total": len(lines), "done": len(good), "skipped": 0, "failed": 6}
    assert "points3D.bin" in rows["damaged"]["error"], rows["damaged"]["error"]
    assert "no COLMAP model" in rows["missing"]["error"]
    assert "no-such-bucket" in rows["no-bucket"]["error"] and "NoSuchBucket" in rows["no-bucket"]["error"]
    assert "403" in rows["refused"]["error"] and forbidden in rows["refused"]["error"], rows["refused"]["error"]
    assert closed in rows["unreachable"]["error"], rows["unreachable"]["error"]
    assert rows["unreachable"]["seconds"] == {} or sum(rows["unreachable"]["seconds"].values()) < 60
    assert "unknown key 'varaints'" in rows["typo"]["error"] and "line" in rows["typo"]["error"]
    assert all("\n" not in r["error"] for r in report["rows"] if r["error"])
    # Both nodes converted places before the kill.
    assert len({r["node"] for r in report["rows"] if r["status"] == "done"}) == 2
    # The table names every place; the report's totals add up.
    assert all(p in out for p in rows) and "47 places: 41 done, 0 skipped, 6 failed" in out
    assert report["bytes_out"] == sum(r["bytes_out"] for r in report["rows"]) > 0
    assert report["catalog"]["status"] == "written" and report["catalog"]["places"] == len(good)

    # Exactly once, nothing partial: the bucket holds each output once, and nothing else.
    expected = {f"s3://outputs/city/{p}/{n}" for p in good for n in ("map.sfpm", "l2s.sfpm")}
    expected |= {"s3://outputs/city/sacre-coeur/pq8.sfpm", "s3://outputs/city/sacre-coeur/budget-300000.sfpm",
                 "s3://outputs/city/catalog.sfpc"}
    listed = [u for u, *_ in _sfpmap.object_list("s3://outputs/city")]
    assert sorted(listed) == sorted(expected)
    bucket = s3["root"] / "outputs"
    for url in expected:
        path = bucket / url[len("s3://outputs/"):]
        with sfpmap.Map(path) as m:
            m.verify()
            job = batch.job_of(m.metadata)
        if url.endswith("catalog.sfpc"):
            assert [p[0] for p in job["places"]] == sorted(good)
        else:
            place = url.split("/")[-2]
            assert job["fingerprint"] == rows[place]["fingerprint"] and job["place"] == place
    on_disk = sorted(f"s3://outputs/{p.relative_to(bucket)}" for p in bucket.rglob("*") if p.is_file())
    assert on_disk == sorted(expected)  # no temp, part or stray file either

    # A rerun does nothing: every good place skipped, the catalog unchanged, no object written.
    before = snapshot(bucket)
    again = run_batch(cluster, str(manifest), "--out", "s3://outputs/city", "--json")
    assert again.returncode == 1, again.stderr
    second = json.loads(again.stdout)
    assert second["places"] == {"total": len(lines), "done": 0, "skipped": len(good), "failed": 6}
    assert second["catalog"]["status"] == "unchanged"
    assert snapshot(bucket) == before

    # A changed input is made again, alone.
    gen_changed = gen / "street-03-v2"
    subprocess.run([str(street_bin), "--points", "2500", "--queries", "1", "--seed", "7",
                    str(gen_changed)], check=True, capture_output=True)
    upload_place(gen_changed, "s3://inputs/city/street-03")
    third = json.loads(run_batch(cluster, str(manifest), "--out", "s3://outputs/city", "--json").stdout)
    assert [r["place"] for r in third["rows"] if r["status"] == "done"] == ["street-03"]
    assert third["places"] == {"total": len(lines), "done": 1, "skipped": len(good) - 1, "failed": 6}
    assert third["catalog"]["status"] == "written"

    # A place that fails now (its database gone) keeps its catalog entry while its map is there.
    _sfpmap.object_delete("s3://inputs/city/street-05/database.db")
    fourth = json.loads(run_batch(cluster, str(manifest), "--out", "s3://outputs/city", "--json").stdout)
    assert {r["place"]: r["status"] for r in fourth["rows"]}["street-05"] == "failed"
    assert fourth["catalog"]["status"] == "unchanged"
    with sfpmap.Map(bucket / "city/catalog.sfpc") as c:
        assert "street-05" in {p["name"] for p in c.metadata["catalog"]["places"]}

    # A manifest read from a bucket: relative names beside it; a local file or another bucket
    # refused.
    url_manifest = tmp_path / "url.jsonl"
    url_manifest.write_text("\n".join(json.dumps(line) for line in [
        {"place": "beside", "colmap": "../city/street-00/sparse", "database": "../city/street-00/database.db"},
        {"place": "local", "colmap": str(gen / "street-00/sparse"), "database": str(gen / "street-00/database.db")},
        {"place": "elsewhere", "colmap": "s3://outputs/x/sparse", "database": "s3://outputs/x/database.db"},
    ]) + "\n")
    _sfpmap.object_upload(str(url_manifest), "s3://inputs/lists/city.jsonl")
    from_url = json.loads(run_batch(cluster, "s3://inputs/lists/city.jsonl", "--out", "s3://outputs/url",
                                    "--json").stdout)
    by_place = {r["place"]: r for r in from_url["rows"]}
    assert by_place["beside"]["status"] == "done", by_place["beside"]["error"]
    assert "names no local file" in by_place["local"]["error"]
    assert "names only objects beside it" in by_place["elsewhere"]["error"]

    # A bucket prefix instead of a manifest: its folders are the places, listed by folder.
    for name in ("street-00", "street-01"):
        upload_place(gen / name, f"s3://inputs/few/{name}")
    _sfpmap.object_upload(str(gen / "street-02/database.db"), "s3://inputs/few/no-model/database.db")
    listed_run = json.loads(run_batch(cluster, "s3://inputs/few/", "--out", "s3://outputs/few", "--json").stdout)
    assert [(r["place"], r["status"]) for r in listed_run["rows"]] == [
        ("no-model", "failed"), ("street-00", "done"), ("street-01", "done")]
    assert "no COLMAP model" in listed_run["rows"][0]["error"]

    # An SFP place from a bucket: its images listed and fetched, the map made by the SFP model.
    sacre_images = sorted((sacre / "images").iterdir())
    for f in sorted((sacre / "sparse-map").iterdir()):
        _sfpmap.object_upload(str(f), f"s3://inputs/sfp/sacre-coeur/sparse/{f.name}")
    for f in sacre_images:
        _sfpmap.object_upload(str(f), f"s3://inputs/sfp/sacre-coeur/images/{f.name}")
    sfp_run = json.loads(run_batch(cluster, "s3://inputs/sfp/", "--out", "s3://outputs/sfp", "--json").stdout)
    (sfp_row,) = sfp_run["rows"]
    assert sfp_row["status"] == "done", sfp_row["error"]
    model = [sacre / "sparse-map" / n for n in ("cameras.bin", "images.bin", "points3D.bin")]  # not rigs, frames
    assert sfp_row["bytes_in"] == sum(f.stat().st_size for f in [*sacre_images, *model])
    with sfpmap.Map(s3["root"] / "outputs/sfp/sacre-coeur/map.sfpm") as m:
        assert m.levels[2].descriptor.startswith("sfp-")
        assert batch.job_of(m.metadata)["options"]["kind"] == "sfp"


def test_a_folder_prefix_relative_inputs_variants_and_a_budget(cluster, street_bin, shared, tmp_path):
    for i in range(3):
        subprocess.run([str(street_bin), "--points", "2500", "--queries", "1", "--seed", str(i), str(tmp_path / f"s{i}")],
                       check=True, capture_output=True)
    lines = [
        {"place": "s0", "colmap": "s0/sparse", "database": "s0/database.db", "variants": ["l2s", "pq8", "l2s-pq8-min"]},
        {"place": "s1", "colmap": "s1/sparse", "database": "s1/database.db", "budget": "200kB"},
        {"place": "s2", "colmap": str(tmp_path / "s2/sparse"), "database": str(tmp_path / "s2/database.db")},
    ]
    manifest = tmp_path / "places.jsonl"
    manifest.write_text("\n".join(json.dumps(line) for line in lines) + "\n\n")
    inputs_before = snapshot(tmp_path)
    out = tmp_path / "maps"
    first = run_batch(cluster, str(manifest), "--out", str(out), "--report", str(tmp_path / "r.json"))
    assert first.returncode == 0, first.stderr + first.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["places"] == {"total": 3, "done": 3, "skipped": 0, "failed": 0}
    # Nothing the user named was modified; nothing but outputs in PREFIX.
    assert {k: v for k, v in snapshot(tmp_path).items() if k.startswith(("s0/", "s1/", "s2/"))} == \
        {k: v for k, v in inputs_before.items() if k.startswith(("s0/", "s1/", "s2/"))}
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == sorted([
        "catalog.sfpc", "s0/map.sfpm", "s0/l2s.sfpm", "s0/pq8.sfpm", "s0/l2s-pq8-min.sfpm",
        "s1/map.sfpm", "s1/budget-200000.sfpm", "s2/map.sfpm"])
    with sfpmap.Map(out / "s0/l2s-pq8-min.sfpm") as m:
        assert [lv.id for lv in m.levels] == [2] and m.levels[2].pq_codes is not None
        assert batch.job_of(m.metadata)["fingerprint"] == report["rows"][0]["fingerprint"]
    assert (out / "s1/budget-200000.sfpm").stat().st_size <= 200_000
    # The catalog names its places relative to its folder: the folder can move.
    moved = tmp_path / "moved"
    shutil.move(str(out), str(moved))
    with sfpmap.Map(moved / "catalog.sfpc") as c:
        listed = {p["name"]: p["map"] for p in c.metadata["catalog"]["places"]}
    assert listed == {"s0": "s0/l2s.sfpm", "s1": "s1/map.sfpm", "s2": "s2/map.sfpm"}
    with sfpmap.Map(moved / listed["s0"]) as m:
        m.verify()
    shutil.move(str(moved), str(out))
    # An output the job did not make is refused, named; --force replaces it, and the catalog.
    foreign = out / "s2/l2s.sfpm"
    lines[2]["variants"] = ["l2s"]
    manifest.write_text("\n".join(json.dumps(line) for line in lines) + "\n")
    foreign.write_bytes(b"not a map, a user's file")
    refused = json.loads(run_batch(cluster, str(manifest), "--out", str(out), "--json").stdout)
    assert refused["rows"][2]["status"] == "failed" and "not made by sfpmap.batch" in refused["rows"][2]["error"]
    assert foreign.read_bytes() == b"not a map, a user's file"
    forced = json.loads(run_batch(cluster, str(manifest), "--out", str(out), "--json", "--force").stdout)
    assert forced["places"]["done"] == 3 and forced["catalog"]["status"] == "written"
    with sfpmap.Map(foreign) as m:
        m.verify()
    # Rerun: skipped. A touched input: that place again.
    assert json.loads(run_batch(cluster, str(manifest), "--out", str(out), "--json").stdout)["places"]["skipped"] == 3
    os.utime(tmp_path / "s2/database.db")
    rows = json.loads(run_batch(cluster, str(manifest), "--out", str(out), "--json").stdout)["rows"]
    assert [(r["place"], r["status"]) for r in rows] == [("s0", "skipped"), ("s1", "skipped"), ("s2", "done")]


def test_manifest_lines_variants_and_sizes_are_checked_before_any_work(tmp_path):
    manifest = tmp_path / "m.jsonl"
    manifest.write_text("\n".join([
        '{"place": "a", "colmap": "x", "database": "d.db"}',
        'not json',
        '{"place": "../up", "colmap": "x", "database": "d.db"}',
        '{"place": "b", "colmap": "x"}',
        '{"place": "c", "colmap": "x", "database": "d", "images": "i"}',
        '{"place": "a", "colmap": "y", "database": "d.db"}',
        '{"place": "e", "colmap": "x", "database": "d.db", "variants": ["l2s", "q9"]}',
        '{"place": "f", "colmap": "x", "database": "d.db", "budget": "lots"}',
        '[1, 2]',
    ]))
    places, failed = batch.read_manifest(str(manifest))
    assert [p["place"] for p in places] == ["a"]
    assert places[0]["colmap"] == str(tmp_path / "x") and places[0]["database"] == str(tmp_path / "d.db")
    errors = [f["error"] for f in failed]
    assert [f["line"] for f in failed] == [2, 3, 4, 5, 6, 7, 8, 9]
    for needle, error in zip(["not JSON", "place: 1 to 128", "database (a feature map) or images",
                              "one of them", "listed twice", "variant 'q9'", "'lots' is not a size",
                              "not a JSON object"], errors):
        assert needle in error and error.startswith(f"{manifest}: line"), error
    assert batch.parse_variant("l2s") == {"levels": [2], "short": True, "pq": None, "minimal": False}
    assert batch.parse_variant("pq8-min") == {"levels": None, "short": False, "pq": 8, "minimal": True}
    assert batch.parse_variant("l1-pq16") == {"levels": [1], "short": False, "pq": 16, "minimal": False}
    for bad in ["", "l", "s", "l2x", "pq", 7, None]:
        with pytest.raises(ValueError):
            batch.parse_variant(bad)
    assert batch.parse_size("2MB") == 2_000_000 and batch.parse_size("1.5MiB") == 1_572_864
    assert batch.parse_size(500) == 500 and batch.parse_size("500kB") == 500_000
    for bad in ["0", "-1MB", "2 parsecs", True, 0, 1.5]:
        with pytest.raises(ValueError):
            batch.parse_size(bad)
    # A missing manifest is one line naming it, exit 2: the job cannot start (no Ray started).
    gone = subprocess.run([sys.executable, "-m", "sfpmap.batch", str(tmp_path / "nope.jsonl"), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=120)
    assert gone.returncode == 2 and gone.stderr.strip().count("\n") == 0, gone.stderr
    assert "nope.jsonl" in gone.stderr
