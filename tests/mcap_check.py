#!/usr/bin/env python3
"""`sfpmap localize --mcap` checked by an independent MCAP client (PyPI `mcap`).

Writes an input log with the Python writer (ROS 2 sensor_msgs/msg/CompressedImage as CDR, each
query image of the scene at two stamps on its own topic, plus an unrelated topic), runs the
sfpmap binary on it, and reads the output back with the Python reader: message counts, schema
names and encodings, log times and stamps, and rotations against the scene's gt_poses.txt.

    python3 tests/mcap_check.py target/release/sfpmap ../shared/data/scenes/sacre-coeur
"""

import json
import math
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import Writer

SEC = 1_000_000_000
MAX_ROTATION_ERROR_DEG = 2.0
# The scene's units: the model spans a few units; the pseudo-GT centres agree to ~0.02.
MAX_CENTER_ERROR = 0.1


def cdr_compressed_image(sec, nsec, frame_id, fmt, data):
    """sensor_msgs/msg/CompressedImage, CDR little endian: alignment counts from after the
    4-byte encapsulation header."""
    body = bytearray()

    def align(n):
        while len(body) % n:
            body.append(0)

    def u32(v):
        align(4)
        body.extend(struct.pack("<I", v))

    def string(s):
        b = s.encode() + b"\0"
        u32(len(b))
        body.extend(b)

    body.extend(struct.pack("<iI", sec, nsec))
    string(frame_id)
    string(fmt)
    u32(len(data))
    body.extend(data)
    return b"\x00\x01\x00\x00" + bytes(body)


def rotation_error_deg(orientation, cam_from_world):
    """Angle between a PoseInFrame orientation (world_from_cam) and a COLMAP cam_from_world."""
    q = [orientation[k] for k in ("w", "x", "y", "z")]
    g = [cam_from_world[0], -cam_from_world[1], -cam_from_world[2], -cam_from_world[3]]
    dot = abs(sum(a * b for a, b in zip(q, g))) / (
        math.sqrt(sum(a * a for a in q)) * math.sqrt(sum(b * b for b in g))
    )
    return math.degrees(2 * math.acos(min(1.0, dot)))


def center(cam_from_world):
    """-R^T t of a COLMAP cam_from_world (qw qx qy qz tx ty tz): the camera's position."""
    w, x, y, z = cam_from_world[:4]
    r = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    t = cam_from_world[4:]
    return [-sum(r[i][j] * t[i] for i in range(3)) for j in range(3)]


def run(cmd):
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"{' '.join(map(str, cmd))} failed:\n{out.stderr}")
    return out.stdout


def main():
    sfpmap, scene = Path(sys.argv[1]), Path(sys.argv[2])
    queries = [
        line.split(maxsplit=1)
        for line in (scene / "queries.txt").read_text().splitlines()
        if line.strip()
    ]
    gt = {}
    for line in (scene / "gt_poses.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            t = line.split()
            gt[t[0]] = [float(v) for v in t[1:8]]

    failures = []
    checks = 0

    def check(cond, what):
        nonlocal checks
        checks += 1
        if not cond:
            failures.append(what)
            print(f"FAIL: {what}")

    localized_total = images_total = 0
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        map_path = tmp / "map.sfpm"
        # A shared scene has `sparse-map/`, the demo's output folder `sparse/`.
        model = scene / "sparse-map" if (scene / "sparse-map").is_dir() else scene / "sparse"
        run([sfpmap, "convert", "--colmap", model, "--images",
             scene / "images", "-o", map_path, "--quiet"])

        stamps = {}
        input_path = tmp / "in.mcap"
        with open(input_path, "wb") as f:
            w = Writer(f)
            w.start(profile="ros2", library="sfpmap mcap_check.py")
            schema = w.register_schema("sensor_msgs/msg/CompressedImage", "ros2msg",
                                       b"std_msgs/Header header\nstring format\nuint8[] data\n")
            other = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data\n")
            status = w.register_channel("/status", "cdr", other)
            for i, (name, _) in enumerate(queries):
                topic = f"/cam{i}/image/compressed"
                channel = w.register_channel(topic, "cdr", schema)
                jpeg = (scene / "images" / name).read_bytes()
                fmt = "png" if name.lower().endswith(".png") else "jpeg"
                stamps[topic] = [(1_700_000_000 + 10 * i + k, 1000 * k + 7) for k in range(2)]
                for seq, (sec, nsec) in enumerate(stamps[topic]):
                    t = sec * SEC + nsec
                    w.add_message(channel, log_time=t, publish_time=t, sequence=seq,
                                  data=cdr_compressed_image(sec, nsec, f"cam{i}", fmt, jpeg))
                    w.add_message(status, log_time=t, publish_time=t,
                                  data=b"\x00\x01\x00\x00\x03\x00\x00\x00ok\x00")
            w.finish()

        for i, (name, camera) in enumerate(queries):
            topic = f"/cam{i}/image/compressed"
            out_path = tmp / f"out{i}.mcap"
            cmd = [sfpmap, "localize", "--map", map_path, "--mcap", input_path, "--topic",
                   topic, "--camera", camera, "-o", out_path, "--json"]
            passthrough = i == 0
            if passthrough:
                cmd.append("--passthrough-images")
            summary = json.loads(run(cmd))
            print(f"{name}: {summary['localized']}/{summary['images']} localized "
                  f"in {summary['seconds']:.1f} s")

            with open(out_path, "rb") as f:
                reader = make_reader(f)
                s = reader.get_summary()
                pose_channels = [c for c in s.channels.values() if c.topic == "/sfpmap/pose"]
                check(len(pose_channels) == 1, f"{name}: one pose channel")
                pc = pose_channels[0]
                schema = s.schemas[pc.schema_id]
                check(schema.name == "foxglove.PoseInFrame", f"{name}: schema {schema.name}")
                check(schema.encoding == "jsonschema", f"{name}: schema encoding {schema.encoding}")
                check(pc.message_encoding == "json", f"{name}: message encoding")
                check(json.loads(schema.data)["properties"]["pose"]["type"] == "object",
                      f"{name}: schema is JSON schema")
                # One pose per localized image; a query the localizer cannot place gets none
                # (the share of those is checked over all queries below).
                want = summary["localized"]
                localized_total += want
                images_total += summary["images"]
                check(s.statistics.channel_message_counts.get(pc.id, 0) == want,
                      f"{name}: statistics count {want} poses")
                poses, images = [], []
                for sch, ch, msg in reader.iter_messages():
                    if ch.topic == "/sfpmap/pose":
                        poses.append((msg.log_time, msg.publish_time, json.loads(msg.data)))
                    else:
                        images.append((sch.name, ch.topic, ch.message_encoding, msg.log_time))
                check(len(poses) == want, f"{name}: {len(poses)} pose messages, expected {want}")
                by_stamp = {(p["timestamp"]["sec"], p["timestamp"]["nsec"]): (lt, pt, p) for lt, pt, p in poses}
                check(set(by_stamp) <= set(stamps[topic]), f"{name}: pose stamps {sorted(by_stamp)}")
                for (sec, nsec) in stamps[topic]:
                    if (sec, nsec) not in by_stamp:
                        continue
                    log_time, publish_time, p = by_stamp[(sec, nsec)]
                    check(log_time == sec * SEC + nsec and publish_time == log_time,
                          f"{name}: log time {log_time} for stamp {sec}.{nsec:09}")
                    check(p["timestamp"] == {"sec": sec, "nsec": nsec},
                          f"{name}: timestamp {p['timestamp']}")
                    check(p["frame_id"] == "map", f"{name}: frame_id {p['frame_id']}")
                    err = rotation_error_deg(p["pose"]["orientation"], gt[name])
                    check(err < MAX_ROTATION_ERROR_DEG, f"{name}: rotation error {err:.2f} deg")
                    position = [p["pose"]["position"][k] for k in "xyz"]
                    dist = math.dist(position, center(gt[name]))
                    check(dist < MAX_CENTER_ERROR, f"{name}: centre error {dist:.3f}")
                    print(f"  {sec}.{nsec:09}: rotation error {err:.3f} deg, centre error {dist:.3f}")
                expected_images = [("sensor_msgs/msg/CompressedImage", topic, "cdr",
                                    sec * SEC + nsec) for sec, nsec in stamps[topic]]
                check(images == (expected_images if passthrough else []),
                      f"{name}: passed-through images {images}")

    check(images_total > 0 and localized_total >= 0.75 * images_total,
          f"only {localized_total} of {images_total} images localized")
    print(f"mcap_check: {localized_total}/{images_total} images localized; "
          f"{checks - len(failures)} passed, {len(failures)} failed")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
