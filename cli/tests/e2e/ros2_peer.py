"""A ROS 2 peer that is not ours: Eclipse Cyclone DDS (PyPI `cyclonedds`) publishing camera
frames under ROS 2's topic and type names and reading back what `sfpmap ros2` publishes.
`cli/tests/e2e/ros2_node.rs` runs it; `benches/ros2_node.sh` too.

Cyclone is configured for this machine only (loopback, no multicast, unicast discovery of
peers on 127.0.0.1), and `sfpmap ros2 --interface 127.0.0.1` likewise: nothing leaves it.

Modes (one JSON line of results on stdout):
  lockstep  publish each frame, wait for its pose (or its status when it failed), then the
            next: every frame reaches the node and is localized in order
  rate      publish frames at --hz for --seconds (looping over them), best effort; latency
            from publishing to the pose's arrival, by stamp
  hostile   publish malformed messages (a truncated CompressedImage, another type on the
            topic, an empty image), then one good frame that must still be localized
  info      publish a CameraInfo (reliable, transient local) every 0.2 s until stopped
  raw       sensor_msgs/Image (mono8, decoded here with Pillow): a 0x0 image, the frames in
            lockstep, then a burst of frames with no wait; reads /tf and /diagnostics back
"""

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import array, float64, int32, sequence, uint8, uint32
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

LOOPBACK = """<CycloneDDS><Domain id="any"><General><Interfaces>
<NetworkInterface address="127.0.0.1"/></Interfaces><AllowMulticast>false</AllowMulticast>
</General><Discovery><ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>30
</MaxAutoParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain>
</CycloneDDS>"""


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class CompressedImage(IdlStruct, typename="sensor_msgs::msg::dds_::CompressedImage_"):
    header: Header
    format: str
    data: sequence[uint8]


@dataclass
class CutCompressedImage(IdlStruct, typename="sensor_msgs::msg::dds_::CompressedImage_"):
    """A CompressedImage cut after its format: the data's length and bytes are missing."""

    header: Header
    format: str


@dataclass
class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header
    height: uint32
    width: uint32
    encoding: str
    is_bigendian: uint8
    step: uint32
    data: sequence[uint8]


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: float64
    y: float64
    z: float64


@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str


@dataclass
class RegionOfInterest(IdlStruct, typename="sensor_msgs::msg::dds_::RegionOfInterest_"):
    x_offset: uint32
    y_offset: uint32
    height: uint32
    width: uint32
    do_rectify: bool


@dataclass
class CameraInfo(IdlStruct, typename="sensor_msgs::msg::dds_::CameraInfo_"):
    header: Header
    height: uint32
    width: uint32
    distortion_model: str
    d: sequence[float64]
    k: array[float64, 9]
    r: array[float64, 9]
    p: array[float64, 12]
    binning_x: uint32
    binning_y: uint32
    roi: RegionOfInterest


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose
    covariance: array[float64, 36]


@dataclass
class PoseWithCovarianceStamped(
    IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
):
    header: Header
    pose: PoseWithCovariance


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: sequence[TransformStamped]


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: uint8
    name: str
    message: str
    hardware_id: str
    values: sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header
    status: sequence[DiagnosticStatus]


def qos(reliable, depth=1, transient=False):
    policies = [
        Policy.Reliability.Reliable(duration(seconds=1))
        if reliable
        else Policy.Reliability.BestEffort,
        Policy.History.KeepLast(depth),
    ]
    if transient:
        policies.append(Policy.Durability.TransientLocal)
    return Qos(*policies)


def stamp_of(ns):
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def key(t):
    return (t.sec, t.nanosec)


class Peer:
    def __init__(self, args):
        self.dp = DomainParticipant(args.domain)
        self.args = args
        self.image_topic = Topic(self.dp, "rt" + args.image_topic, CompressedImage)
        self.poses = DataReader(
            self.dp,
            Topic(self.dp, "rt" + args.pose_topic, PoseWithCovarianceStamped),
            qos=qos(True, 100),
        )
        self.status = DataReader(
            self.dp,
            Topic(self.dp, "rt" + args.status_topic, DiagnosticArray),
            qos=qos(True, 100),
        )

    def writer(self, topic, reliable):
        return DataWriter(self.dp, topic, qos=qos(reliable, 1000 if reliable else 1))

    def wait_matched(self, writer, timeout=30.0):
        """Until the node's reader matched `writer` (discovery done)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if writer.get_matched_subscriptions():
                return
            time.sleep(0.05)
        raise SystemExit(f"no subscriber matched {self.args.image_topic} in {timeout} s")

    def drain(self, poses, statuses):
        """Takes every pose and status that arrived, by stamp."""
        now = time.monotonic()
        for p in self.poses.take(N=100):
            poses[key(p.header.stamp)] = (p, now)
        for s in self.status.take(N=100):
            statuses[key(s.header.stamp)] = (s, now)


def frame(path, ns, fmt="jpeg", frame_id="camera_left"):
    with open(path, "rb") as f:
        data = f.read()
    return CompressedImage(Header(stamp_of(ns), frame_id), fmt, data)


def pose_json(p):
    q, c = p.pose.pose, p.pose.covariance
    return {
        "position": [q.position.x, q.position.y, q.position.z],
        "orientation": [q.orientation.x, q.orientation.y, q.orientation.z, q.orientation.w],
        "covariance": list(c),
        "frame_id": p.header.frame_id,
    }


def status_json(s):
    st = s.status[0]
    return {"level": st.level, "message": st.message, "values": {kv.key: kv.value for kv in st.values}}


def lockstep(peer, args, writer=None, make=None):
    """Each frame published, then its pose (or its failed status) awaited."""
    if writer is None:
        writer = peer.writer(peer.image_topic, reliable=True)
        peer.wait_matched(writer)
    make = make or (lambda path, ns: frame(path, ns))
    poses, statuses, out = {}, {}, []
    for name, ns in zip(args.names, args.stamps):
        writer.write(make(os.path.join(args.images, name), ns))
        end = time.monotonic() + args.timeout
        k = key(stamp_of(ns))
        while k not in statuses and time.monotonic() < end:
            time.sleep(0.002)
            peer.drain(poses, statuses)
        # The pose is published before the status: both are here once the status is.
        peer.drain(poses, statuses)
        out.append(
            {
                "name": name,
                "stamp": ns,
                "pose": pose_json(poses[k][0]) if k in poses else None,
                "status": status_json(statuses[k][0]) if k in statuses else None,
            }
        )
    return {"frames": out}


def rate(peer, args):
    """Frames at --hz, looping over them for --seconds, best effort; latency by stamp."""
    writer = peer.writer(peer.image_topic, reliable=False)
    peer.wait_matched(writer)
    data = [frame(os.path.join(args.images, n), 0) for n in args.names]
    sent, poses, statuses = {}, {}, {}
    period = 1.0 / args.hz
    start = time.monotonic()
    ns0 = 2_000_000_000_000_000_000 // 1_000_000_000 * 1_000_000_000
    i = 0
    while time.monotonic() - start < args.seconds:
        due = start + i * period
        while time.monotonic() < due:
            peer.drain(poses, statuses)
            time.sleep(0.001)
        msg = data[i % len(data)]
        ns = ns0 + i * 1_000_000
        msg.header.stamp = stamp_of(ns)
        sent[key(msg.header.stamp)] = time.monotonic()
        writer.write(msg)
        i += 1
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        peer.drain(poses, statuses)
        time.sleep(0.01)
    latencies = sorted((poses[k][1] - sent[k]) * 1e3 for k in poses if k in sent)
    pick = lambda q: latencies[min(len(latencies) - 1, int(q * len(latencies)))] if latencies else None
    return {
        "sent": len(sent),
        "poses": len(poses),
        "statuses": len(statuses),
        "latency_ms": {"median": pick(0.5), "p99": pick(0.99)},
    }


def hostile(peer, args):
    """Malformed messages on the topic, one over the node's size limit and a frame of another
    size, each given time to be taken alone (a newer frame would replace it), then the good
    frames in lockstep."""
    sent = {}
    pause = lambda: time.sleep(0.4)
    cut = DataWriter(peer.dp, Topic(peer.dp, "rt" + args.image_topic, CutCompressedImage), qos=qos(True, 10))
    peer.wait_matched(cut)
    cut.write(CutCompressedImage(Header(stamp_of(1), "camera_left"), "jpeg"))
    sent["truncated"] = 1
    pause()
    images = peer.writer(peer.image_topic, reliable=True)
    peer.wait_matched(images)
    images.write(CompressedImage(Header(stamp_of(2), "camera_left"), "jpeg", b""))
    sent["empty_image"] = 1
    pause()
    images.write(CompressedImage(Header(stamp_of(3), "camera_left"), "jpeg", b"\xff\xd8\xff\xe0 not a jpeg"))
    sent["undecodable"] = 1
    pause()
    if args.oversize:
        images.write(CompressedImage(Header(stamp_of(4), "camera_left"), "jpeg", bytes(args.oversize)))
        sent["oversize"] = 1
        pause()
    if args.small:
        images.write(frame(args.small, 5))
        sent["other_size"] = 1
        pause()
    # Another type under the topic's name: DDS matches writers and readers by type name,
    # so this one may never reach the node; whether it did is in the node's counts.
    other = DataWriter(peer.dp, Topic(peer.dp, "rt" + args.image_topic, String), qos=qos(True, 10))
    time.sleep(1.0)
    other_matched = bool(other.get_matched_subscriptions())
    other.write(String("not an image"))
    pause()
    good = lockstep(peer, args)
    return {"sent": sent, "other_type_matched": other_matched, **good}


def mono8(path, ns, frame_id="camera_left"):
    """A frame as sensor_msgs/Image mono8, decoded with Pillow."""
    from PIL import Image as Pil

    g = Pil.open(path).convert("L")
    return Image(Header(stamp_of(ns), frame_id), g.height, g.width, "mono8", 0, g.width, g.tobytes())


def raw(peer, args):
    """An empty (0x0) Image, the frames in lockstep, a burst of them with no wait; /tf and
    /diagnostics read back."""
    topic = Topic(peer.dp, "rt" + args.image_topic, Image)
    tf = DataReader(peer.dp, Topic(peer.dp, "rt/tf", TFMessage), qos=qos(True, 100))
    diagnostics = DataReader(peer.dp, Topic(peer.dp, "rt/diagnostics", DiagnosticArray), qos=qos(True, 100))
    writer = DataWriter(peer.dp, topic, qos=qos(True, 1000))
    peer.wait_matched(writer)
    writer.write(Image(Header(stamp_of(1), "camera_left"), 0, 0, "mono8", 0, 0, []))
    time.sleep(0.4)
    result = lockstep(peer, args, writer, lambda path, ns: mono8(path, ns, "kitti/camera_left"))
    # A burst: every frame at once, several times over; the node keeps the newest.
    burst = [mono8(os.path.join(args.images, n), 10_000 + i) for i, n in enumerate(args.names * 3)]
    for m in burst:
        writer.write(m)
    time.sleep(3.0)
    transforms, summaries = [], []
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        for m in tf.take(N=100):
            transforms.extend(m.transforms)
        for m in diagnostics.take(N=100):
            summaries.extend(m.status)
        time.sleep(0.05)
    result["tf"] = [
        {"parent": t.header.frame_id, "child": t.child_frame_id, "stamp": [t.header.stamp.sec, t.header.stamp.nanosec],
         "translation": [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z]}
        for t in transforms
    ]
    result["diagnostics"] = [
        {"level": d.level, "name": d.name, "message": d.message, "values": {kv.key: kv.value for kv in d.values}}
        for d in summaries
    ]
    result["burst"] = len(burst)
    return result


def info(peer, args):
    """A CameraInfo of --camera (PINHOLE W H fx fy cx cy, COLMAP's), every 0.2 s."""
    _, w, h, fx, fy, cx, cy = args.camera.split()
    w, h = int(w), int(h)
    fx, fy, cx, cy = map(float, (fx, fy, cx, cy))
    topic = Topic(peer.dp, "rt" + args.camera_info_topic, CameraInfo)
    writer = DataWriter(peer.dp, topic, qos=qos(True, 1, transient=True))
    # ROS (OpenCV) puts the first pixel's centre at 0, COLMAP at 0.5.
    k = [fx, 0.0, cx - 0.5, 0.0, fy, cy - 0.5, 0.0, 0.0, 1.0]
    msg = CameraInfo(
        Header(stamp_of(0), "camera_left"), h, w, "plumb_bob", [0.0] * 5, k,
        [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], k[:3] + [0.0] + k[3:6] + [0.0] + k[6:] + [0.0],
        0, 0, RegionOfInterest(0, 0, 0, 0, False),
    )
    end = time.monotonic() + args.seconds
    n = 0
    while time.monotonic() < end:
        writer.write(msg)
        n += 1
        time.sleep(0.2)
    return {"camera_info": n}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=["lockstep", "rate", "hostile", "info", "raw"])
    parser.add_argument("--domain", type=int, required=True)
    parser.add_argument("--image-topic", default="/camera/image_raw/compressed")
    parser.add_argument("--pose-topic", default="/sfpmap/pose")
    parser.add_argument("--status-topic", default="/sfpmap/status")
    parser.add_argument("--camera-info-topic", default="/camera/camera_info")
    parser.add_argument("--camera", help="PINHOLE W H fx fy cx cy (info mode)")
    parser.add_argument("--images", help="folder of the frames")
    parser.add_argument("--names", type=lambda s: s.split(","), default=[])
    parser.add_argument("--stamps", type=lambda s: [int(v) for v in s.split(",")], default=[])
    parser.add_argument("--hz", type=float, default=10.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--timeout", type=float, default=60.0)
    parser.add_argument("--small", help="a frame of another size (hostile mode)")
    parser.add_argument("--read-tf", action="store_true", help="also read /tf back (lockstep mode)")
    parser.add_argument("--oversize", type=int, default=0, help="bytes of an oversized image (hostile mode)")
    args = parser.parse_args()
    os.environ.setdefault("CYCLONEDDS_URI", LOOPBACK)
    peer = Peer(args)
    modes = {"lockstep": lockstep, "rate": rate, "hostile": hostile, "info": info, "raw": raw}
    tf = DataReader(peer.dp, Topic(peer.dp, "rt/tf", TFMessage), qos=qos(True, 100)) if args.read_tf else None
    result = modes[args.mode](peer, args)
    if tf is not None:
        time.sleep(1.0)
        result["tf"] = [
            {"parent": t.header.frame_id, "child": t.child_frame_id, "stamp": [t.header.stamp.sec, t.header.stamp.nanosec],
             "translation": [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z]}
            for m in tf.take(N=1000) for t in m.transforms
        ]
    json.dump(result, sys.stdout)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
