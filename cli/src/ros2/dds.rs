//! The node's side of DDS, on `ros2-client` (pure Rust, RustDDS: no ROS installation): the
//! participant and node, raw readers of the camera topics, and the messages it publishes.
//!
//! Incoming messages are taken as their CDR bytes, not deserialised by serde: the library's
//! CDR readers (`sfpmap::io::mcap_io`, the ones `localize --mcap` uses and the fuzz crate
//! runs) decode them, so a truncated or foreign message is the same counted error here as
//! in a log, and its size is known before anything is decoded.

use anyhow::Context as _;
use ros2_client::dds::rustdds;
use ros2_client::{Context, MessageTypeName, Name, Node, NodeName, NodeOptions};
use rustdds::no_key::{self, Decode, DefaultDecoder, DeserializerAdapter};
use rustdds::{RepresentationIdentifier, Topic};
use serde::ser::SerializeTuple;
use serde::Serialize;
use std::net::IpAddr;

/// The node's name in the ROS graph.
pub const NODE_NAME: &str = "sfpmap_localizer";

/// One message as it came: the CDR encapsulation header (rebuilt from the representation
/// the writer declared) and the body, as `mcap_io` reads a CDR message.
pub struct RawMessage {
    pub bytes: Vec<u8>,
}

/// What decoding an incoming sample can fail with: nothing, the bytes are kept.
#[derive(Debug)]
pub struct NoError;

impl std::fmt::Display for NoError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("no error")
    }
}

impl std::error::Error for NoError {}

/// The representations `mcap_io`'s CDR reader takes: plain CDR and XCDR2, either byte order.
const RAW_ENCODINGS: [RepresentationIdentifier; 4] = [
    RepresentationIdentifier::CDR_LE,
    RepresentationIdentifier::CDR_BE,
    RepresentationIdentifier::CDR2_LE,
    RepresentationIdentifier::CDR2_BE,
];

/// RustDDS's adapter that keeps a sample's bytes.
pub struct RawAdapter;

impl DeserializerAdapter<RawMessage> for RawAdapter {
    type Error = NoError;
    type Decoded = RawMessage;

    fn supported_encodings() -> &'static [RepresentationIdentifier] {
        &RAW_ENCODINGS
    }

    fn transform_decoded(decoded: RawMessage) -> RawMessage {
        decoded
    }
}

#[derive(Clone)]
pub struct RawDecoder;

impl<'de> Decode<'de, RawMessage> for RawDecoder {
    type Error = NoError;

    fn decode_bytes(
        self,
        input: &'de [u8],
        encoding: RepresentationIdentifier,
    ) -> Result<RawMessage, NoError> {
        let id = encoding.to_bytes();
        let mut bytes = Vec::with_capacity(input.len() + 4);
        bytes.extend_from_slice(&[id[0], id[1], 0, 0]);
        bytes.extend_from_slice(input);
        Ok(RawMessage { bytes })
    }
}

impl DefaultDecoder<RawMessage> for RawAdapter {
    type Decoder = RawDecoder;
    const DECODER: RawDecoder = RawDecoder;
}

/// A reader of one topic's raw messages.
pub type RawReader = no_key::SimpleDataReader<RawMessage, RawAdapter>;

/// The DDS participant and the ROS node on it.
pub struct Participant {
    pub context: Context,
    pub node: Node,
}

impl Participant {
    /// Joins `domain` as node [`NODE_NAME`]; `interfaces`: only these local addresses carry
    /// discovery and multicast (e.g. `127.0.0.1` to stay on this machine), else all.
    pub fn join(domain: u16, interfaces: &[IpAddr]) -> anyhow::Result<Participant> {
        let mut builder = rustdds::DomainParticipantBuilder::new(domain);
        if !interfaces.is_empty() {
            builder = builder.with_only_networks(interfaces.iter().copied());
        }
        let participant = builder
            .build()
            .with_context(|| format!("joining DDS domain {domain}"))?;
        let context = Context::from_domain_participant(participant)
            .with_context(|| format!("joining DDS domain {domain}"))?;
        let node = context
            .new_node(NodeName::new("/", NODE_NAME)?, NodeOptions::new())
            .map_err(|e| anyhow::anyhow!("creating the ROS node: {e:?}"))?;
        Ok(Participant { context, node })
    }

    /// The DDS topic of ROS topic `name` (absolute, e.g. `/camera/image/compressed`) with
    /// messages of `package/msg/Type`.
    pub fn topic(
        &self,
        name: &str,
        package: &str,
        ty: &str,
        qos: &ros2_client::QosProfile,
    ) -> anyhow::Result<Topic> {
        let parsed = Name::parse(name).map_err(|e| anyhow::anyhow!("topic {name:?}: {e:?}"))?;
        self.node
            .create_topic(&parsed, MessageTypeName::new(package, ty), qos)
            .map_err(|e| anyhow::anyhow!("topic {name:?}: {e:?}"))
    }

    /// A reader of `topic`'s raw messages with `qos`.
    pub fn raw_reader(
        &self,
        topic: &Topic,
        qos: &ros2_client::QosProfile,
    ) -> anyhow::Result<RawReader> {
        let policies: rustdds::QosPolicies = qos.into();
        let subscriber = self
            .context
            .domain_participant()
            .create_subscriber(&policies)
            .map_err(|e| anyhow::anyhow!("creating a DDS subscriber: {e:?}"))?;
        subscriber
            .create_simple_datareader_no_key::<RawMessage, RawAdapter>(topic, Some(policies))
            .map_err(|e| anyhow::anyhow!("creating a DDS reader: {e:?}"))
    }

    /// A publisher of `M` on `topic`.
    pub fn publisher<M: Serialize>(
        &mut self,
        topic: &Topic,
        qos: ros2_client::QosProfile,
    ) -> anyhow::Result<ros2_client::Publisher<M>> {
        self.node
            .create_publisher(topic, Some(qos))
            .map_err(|e| anyhow::anyhow!("creating a publisher: {e:?}"))
    }
}

/// `builtin_interfaces/msg/Time`.
#[derive(Serialize, Clone, Copy, Debug, Default)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

/// `std_msgs/msg/Header`.
#[derive(Serialize, Clone, Debug)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `geometry_msgs/msg/Point` and `Vector3` (the same layout).
#[derive(Serialize, Clone, Copy, Debug)]
pub struct Xyz {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Serialize, Clone, Copy, Debug)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

/// `geometry_msgs/msg/Pose`.
#[derive(Serialize, Clone, Copy, Debug)]
pub struct PoseMsg {
    pub position: Xyz,
    pub orientation: Quaternion,
}

/// `float64[36]`: a fixed array is its elements, no length (serde derives stop at 32).
#[derive(Clone, Copy, Debug)]
pub struct Covariance(pub [f64; 36]);

impl Serialize for Covariance {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut t = s.serialize_tuple(36)?;
        for v in &self.0 {
            t.serialize_element(v)?;
        }
        t.end()
    }
}

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Serialize, Clone, Copy, Debug)]
pub struct PoseWithCovariance {
    pub pose: PoseMsg,
    pub covariance: Covariance,
}

/// `geometry_msgs/msg/PoseWithCovarianceStamped`.
#[derive(Serialize, Clone, Debug)]
pub struct PoseWithCovarianceStamped {
    pub header: Header,
    pub pose: PoseWithCovariance,
}

/// `geometry_msgs/msg/Transform`.
#[derive(Serialize, Clone, Copy, Debug)]
pub struct Transform {
    pub translation: Xyz,
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`.
#[derive(Serialize, Clone, Debug)]
pub struct TransformStamped {
    pub header: Header,
    pub child_frame_id: String,
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Serialize, Clone, Debug)]
pub struct TfMessage {
    pub transforms: Vec<TransformStamped>,
}

/// `diagnostic_msgs/msg/KeyValue`.
#[derive(Serialize, Clone, Debug)]
pub struct KeyValue {
    pub key: String,
    pub value: String,
}

/// `diagnostic_msgs/msg/DiagnosticStatus` (`level`: 0 OK, 1 WARN, 2 ERROR, 3 STALE).
#[derive(Serialize, Clone, Debug)]
pub struct DiagnosticStatus {
    pub level: u8,
    pub name: String,
    pub message: String,
    pub hardware_id: String,
    pub values: Vec<KeyValue>,
}

/// `diagnostic_msgs/msg/DiagnosticArray`.
#[derive(Serialize, Clone, Debug)]
pub struct DiagnosticArray {
    pub header: Header,
    pub status: Vec<DiagnosticStatus>,
}

/// A ROS time from seconds and nanoseconds, normalised (nanoseconds below 10⁹;
/// `builtin_interfaces/msg/Time` holds an `int32` of seconds: a stamp outside it is clamped).
pub fn ros_time(sec: i64, nanosec: u32) -> Time {
    let sec = sec.saturating_add(i64::from(nanosec / 1_000_000_000));
    Time {
        sec: sec.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32,
        nanosec: nanosec % 1_000_000_000,
    }
}

/// Now, as a ROS time.
pub fn now() -> Time {
    let d = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    ros_time(d.as_secs() as i64, d.subsec_nanos())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The layout ROS 2 readers expect (checked against the bytes `rosidl` CDR gives for the
    /// same message: header, then 7 doubles aligned to 8 from the body's start, then 36).
    #[test]
    fn a_pose_with_covariance_is_laid_out_as_ros_reads_it() {
        let message = PoseWithCovarianceStamped {
            header: Header {
                stamp: Time { sec: 5, nanosec: 7 },
                frame_id: "map".into(),
            },
            pose: PoseWithCovariance {
                pose: PoseMsg {
                    position: Xyz {
                        x: 1.0,
                        y: 2.0,
                        z: 3.0,
                    },
                    orientation: Quaternion {
                        x: 0.0,
                        y: 0.0,
                        z: 0.0,
                        w: 1.0,
                    },
                },
                covariance: Covariance(std::array::from_fn(|i| i as f64)),
            },
        };
        let body = <rustdds::CDRSerializerAdapter<PoseWithCovarianceStamped> as no_key::SerializerAdapter<_>>::to_bytes(&message)
            .expect("serialises");
        // stamp (8) + frame_id (4 + "map\0") = 16, then doubles from offset 16.
        assert_eq!(&body[0..8], &[5, 0, 0, 0, 7, 0, 0, 0]);
        assert_eq!(&body[8..16], &[4, 0, 0, 0, b'm', b'a', b'p', 0]);
        assert_eq!(f64::from_le_bytes(body[16..24].try_into().unwrap()), 1.0);
        assert_eq!(body.len(), 16 + 7 * 8 + 36 * 8);
        let last = &body[body.len() - 8..];
        assert_eq!(f64::from_le_bytes(last.try_into().unwrap()), 35.0);
    }
}
