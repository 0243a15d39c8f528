//! MCAP logs (feature `mcap`): camera images in from one topic, `foxglove.PoseInFrame` out.
//!
//! Images: `sensor_msgs/msg/CompressedImage` and `sensor_msgs/msg/Image` (ROS 2, message
//! encoding `cdr`), `foxglove.CompressedImage` (message encoding `json` or `protobuf`).
//! Intrinsics: `sensor_msgs/msg/CameraInfo` (`cdr`). The few fields we need are decoded by
//! hand: a schema-less reader of exactly these layouts is smaller than a ROS or protobuf stack,
//! and every length is checked against the message before it is used.
//!
//! Poses go out as `foxglove.PoseInFrame` with schema encoding `jsonschema` and message encoding
//! `json`, the pairing the MCAP registry allows for Foxglove schemas and that Foxglove and the
//! `mcap` CLI read without a plugin.

mod pose_writer;
mod reader;
mod records;
mod wire;

pub use pose_writer::{pose_in_frame_json, PoseWriter, POSE_IN_FRAME_JSON_SCHEMA};
pub use reader::{
    Damage, Limits, LogReader, LogSummary, Skipped, CHUNK_FLOOR, CHUNK_RATIO, MAX_RECORD,
};
pub use records::ChunkIndex;
#[cfg(test)]
use wire::fuzz_wire;
pub use wire::{base64_decode, base64_encode, CdrError, Stamp};

use crate::geometry::{Camera, CameraModel};
use image::DynamicImage;
use std::fmt;
use wire::{
    foxglove_compressed_image, ros_camera_info, ros_compressed_image, ros_image, RosCameraInfo,
};

/// ROS 2 `sensor_msgs/msg/CompressedImage`.
pub const ROS_COMPRESSED_IMAGE: &str = "sensor_msgs/msg/CompressedImage";
/// ROS 2 `sensor_msgs/msg/Image`.
pub const ROS_IMAGE: &str = "sensor_msgs/msg/Image";
/// ROS 2 `sensor_msgs/msg/CameraInfo`.
pub const ROS_CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";
/// Foxglove's compressed image.
pub const FOXGLOVE_COMPRESSED_IMAGE: &str = "foxglove.CompressedImage";
/// The schema name of the poses we write.
pub const POSE_IN_FRAME: &str = "foxglove.PoseInFrame";

/// What [`decode_image`] reads, for error messages.
const IMAGE_SCHEMAS: &str = "sensor_msgs/msg/CompressedImage and sensor_msgs/msg/Image as cdr, foxglove.CompressedImage as json or protobuf";
/// What [`decode_camera_info`] reads, for error messages.
const CAMERA_INFO_SCHEMAS: &str = "sensor_msgs/msg/CameraInfo as cdr";

/// Raw `sensor_msgs/msg/Image` encodings we turn into pixels.
pub const RAW_ENCODINGS: &[&str] = &["mono8", "rgb8", "bgr8", "rgba8", "bgra8", "mono16"];

/// What can go wrong reading images and intrinsics from MCAP messages or writing poses.
#[derive(Debug)]
#[non_exhaustive]
pub enum McapIoError {
    /// A CDR message that does not hold the fields of its type.
    Cdr(CdrError),
    /// A channel whose schema and message encoding are not what the decoder reads (an image,
    /// or camera info).
    UnsupportedSchema {
        /// The channel's schema name.
        schema: String,
        /// The channel's message encoding.
        encoding: String,
        /// What the decoder reads.
        expected: &'static str,
    },
    /// A raw image encoding (or compressed format) we do not turn into pixels.
    UnsupportedImageEncoding {
        /// The encoding (or format) the message gives.
        encoding: String,
    },
    /// Raw image fields that do not fit together (step, size, data length).
    BadImage {
        /// Which, and how.
        reason: String,
    },
    /// JPEG/PNG decoding failed.
    ImageDecode {
        /// The format the message gives.
        format: String,
        /// The decoder's error.
        source: image::ImageError,
    },
    /// A JSON or protobuf message that does not hold the fields of its schema.
    BadMessage {
        /// The schema name.
        schema: String,
        /// Which field, and how.
        reason: String,
    },
    /// Camera info we cannot express as a COLMAP camera.
    Camera {
        /// Why.
        reason: String,
    },
    /// The file does not start with the MCAP magic.
    NotMcap,
    /// The log is a directory, FIFO or device, not a file; the value says which (`"a FIFO"`).
    NotRegularFile(&'static str),
    /// Reading the log failed.
    Io(std::io::Error),
    /// A record's fields do not fit together or in the record.
    BadRecord {
        /// The record's kind (`"chunk"`, `"message"`, ...).
        record: &'static str,
        /// Which field, and how.
        reason: String,
    },
    /// A record's length runs past the end of what holds it (the data section, the summary
    /// or a chunk).
    RecordTooLong {
        /// The record's kind.
        record: &'static str,
        /// The length it gives.
        len: u64,
        /// The bytes left in what holds it.
        available: u64,
        /// What holds it (`"data section"`, `"summary"`, `"chunk"`).
        within: &'static str,
    },
    /// A record longer than [`MAX_RECORD`].
    RecordOverLimit {
        /// The record's kind.
        record: &'static str,
        /// The length it gives.
        len: u64,
    },
    /// The log ends without a footer: it was cut off.
    CutOff,
    /// Fewer bytes than a record header left at the end of the data section, summary or chunk.
    Truncated {
        /// The bytes of a record header.
        needed: u64,
        /// The bytes left.
        available: u64,
        /// What ends there.
        within: &'static str,
    },
    /// A chunk that says it decompresses to more than this file may ([`Limits`]).
    ChunkTooLarge {
        /// The size the chunk gives.
        uncompressed: u64,
        /// [`Limits::chunk_uncompressed`].
        limit: u64,
    },
    /// A chunk that would take the log's chunks together past what they may decompress to
    /// ([`Limits::log_uncompressed`]).
    LogBudgetSpent {
        /// The size the chunk gives.
        uncompressed: u64,
        /// What the chunks before it took.
        spent: u64,
        /// [`Limits::log_uncompressed`].
        limit: u64,
    },
    /// A chunk whose records do not match its CRC.
    ChunkCrc {
        /// The CRC the chunk gives.
        stored: u32,
        /// The CRC of its records.
        computed: u32,
    },
    /// A summary section that does not match the footer's CRC.
    SummaryCrc {
        /// The CRC the footer gives.
        stored: u32,
        /// The CRC of the summary.
        computed: u32,
    },
    /// A chunk's compressed records do not decompress.
    Decompress {
        /// `"zstd"` or `"lz4"`.
        compression: &'static str,
        /// The decompressor's error.
        reason: String,
    },
    /// A chunk compression other than zstd and lz4.
    UnsupportedCompression {
        /// The compression the chunk gives.
        compression: String,
    },
    /// A message on a channel no channel record defines.
    UnknownChannel {
        /// The message's channel id.
        id: u16,
    },
    /// Writing the output MCAP.
    Mcap(mcap::McapError),
}

impl fmt::Display for McapIoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            McapIoError::Cdr(e) => write!(f, "{e}"),
            McapIoError::UnsupportedSchema {
                schema,
                encoding,
                expected,
            } => write!(
                f,
                "unsupported message type {schema:?} with message encoding {encoding:?} (supported: {expected})"
            ),
            McapIoError::UnsupportedImageEncoding { encoding } => write!(
                f,
                "unsupported image encoding {encoding:?} (supported: {}, or JPEG/PNG compressed)",
                RAW_ENCODINGS.join(", ")
            ),
            McapIoError::BadImage { reason } => write!(f, "bad image: {reason}"),
            McapIoError::ImageDecode { format, source } => {
                write!(f, "cannot decode {format:?} image: {source}")
            }
            McapIoError::BadMessage { schema, reason } => write!(f, "bad {schema} message: {reason}"),
            McapIoError::Camera { reason } => write!(f, "camera info: {reason}"),
            McapIoError::NotMcap => write!(f, "not an MCAP file (no MCAP magic at its start)"),
            McapIoError::NotRegularFile(kind) => write!(f, "is {kind}, not a regular file"),
            McapIoError::CutOff => write!(f, "the log ends here without its footer (cut off)"),
            McapIoError::Io(e) => write!(f, "{e}"),
            McapIoError::BadRecord { record, reason } => write!(f, "bad {record} record: {reason}"),
            McapIoError::RecordTooLong {
                record,
                len,
                available,
                within,
            } => write!(
                f,
                "{record} record length {len} runs past the end of the {within} ({available} bytes left)"
            ),
            McapIoError::RecordOverLimit { record, len } => write!(
                f,
                "{record} record length {len} is over the limit of {MAX_RECORD} bytes"
            ),
            McapIoError::Truncated {
                needed,
                available,
                within,
            } => write!(
                f,
                "the {within} ends {available} bytes into a record header of {needed}"
            ),
            McapIoError::ChunkTooLarge {
                uncompressed,
                limit,
            } => write!(
                f,
                "chunk says it decompresses to {uncompressed} bytes, over this file's limit of {limit} ({CHUNK_RATIO} × the file size, at least {CHUNK_FLOOR}, at most {MAX_RECORD})"
            ),
            McapIoError::LogBudgetSpent {
                uncompressed,
                spent,
                limit,
            } => write!(
                f,
                "chunk says it decompresses to {uncompressed} bytes, but the chunks before it took {spent} of this file's limit of {limit} for all chunks together ({CHUNK_RATIO} × the file size, at least {CHUNK_FLOOR})"
            ),
            McapIoError::ChunkCrc { stored, computed } => write!(
                f,
                "chunk CRC mismatch (stored {stored:#010x}, computed {computed:#010x})"
            ),
            McapIoError::SummaryCrc { stored, computed } => write!(
                f,
                "summary CRC mismatch (stored {stored:#010x}, computed {computed:#010x})"
            ),
            McapIoError::Decompress {
                compression,
                reason,
            } => write!(f, "{compression} chunk does not decompress: {reason}"),
            McapIoError::UnsupportedCompression { compression } => write!(
                f,
                "unsupported chunk compression {compression:?} (supported: zstd, lz4, none)"
            ),
            McapIoError::UnknownChannel { id } => {
                write!(f, "message on channel {id}, which no channel record defines")
            }
            McapIoError::Mcap(e) => write!(f, "mcap: {e}"),
        }
    }
}

// No `source()`: every message already ends with its cause, and `{:#}` (the CLI's
// `error: {err:#}`) would print it twice.
impl std::error::Error for McapIoError {}

impl From<CdrError> for McapIoError {
    fn from(e: CdrError) -> Self {
        McapIoError::Cdr(e)
    }
}

impl From<std::io::Error> for McapIoError {
    fn from(e: std::io::Error) -> Self {
        McapIoError::Io(e)
    }
}

impl From<mcap::McapError> for McapIoError {
    fn from(e: mcap::McapError) -> Self {
        McapIoError::Mcap(e)
    }
}

/// A decoded image message.
#[derive(Debug, Clone)]
pub struct ImageMessage {
    /// The message's own stamp (`header.stamp`, `timestamp`); `None` when the message has none.
    pub stamp: Option<Stamp>,
    /// The message's `frame_id` (empty when it has none).
    pub frame_id: String,
    /// The pixels.
    pub image: DynamicImage,
}

/// Whether a channel with this schema and message encoding carries images we read.
pub fn is_image_schema(schema: &str, message_encoding: &str) -> bool {
    matches!(
        (schema, message_encoding),
        (ROS_COMPRESSED_IMAGE | ROS_IMAGE, "cdr")
            | (FOXGLOVE_COMPRESSED_IMAGE, "json" | "protobuf")
    )
}

/// Decodes one image message of a channel with this schema name and message encoding.
pub fn decode_image(
    schema: &str,
    message_encoding: &str,
    data: &[u8],
) -> Result<ImageMessage, McapIoError> {
    match (schema, message_encoding) {
        (ROS_COMPRESSED_IMAGE, "cdr") => {
            let m = ros_compressed_image(data)?;
            Ok(ImageMessage {
                stamp: Some(m.stamp),
                image: decode_compressed(m.format, m.data)?,
                frame_id: m.frame_id,
            })
        }
        (ROS_IMAGE, "cdr") => {
            let m = ros_image(data)?;
            Ok(ImageMessage {
                stamp: Some(m.stamp),
                image: raw_image(m.width, m.height, m.encoding, m.big_endian, m.step, m.data)?,
                frame_id: m.frame_id,
            })
        }
        (FOXGLOVE_COMPRESSED_IMAGE, "json") => {
            let bad = |reason: String| McapIoError::BadMessage {
                schema: schema.to_owned(),
                reason,
            };
            let v: serde_json::Value =
                serde_json::from_slice(data).map_err(|e| bad(e.to_string()))?;
            let stamp = match v.get("timestamp") {
                None | Some(serde_json::Value::Null) => None,
                Some(t) => {
                    let sec = t.get("sec").and_then(|s| s.as_i64());
                    let nsec = t
                        .get("nsec")
                        .and_then(|s| s.as_u64())
                        .and_then(|n| u32::try_from(n).ok());
                    match (sec, nsec) {
                        (Some(sec), Some(nsec)) => Some(Stamp { sec, nsec }),
                        _ => return Err(bad("timestamp needs integer sec and nsec".into())),
                    }
                }
            };
            let frame_id = v
                .get("frame_id")
                .and_then(|f| f.as_str())
                .unwrap_or_default()
                .to_owned();
            let format = v
                .get("format")
                .and_then(|f| f.as_str())
                .unwrap_or_default()
                .to_owned();
            let encoded = v
                .get("data")
                .and_then(|d| d.as_str())
                .ok_or_else(|| bad("no base64 string field \"data\"".into()))?;
            let bytes = base64_decode(encoded).map_err(|e| bad(format!("data: {e}")))?;
            Ok(ImageMessage {
                stamp,
                frame_id,
                image: decode_compressed(&format, &bytes)?,
            })
        }
        (FOXGLOVE_COMPRESSED_IMAGE, "protobuf") => {
            let m = foxglove_compressed_image(data).map_err(|reason| McapIoError::BadMessage {
                schema: schema.to_owned(),
                reason,
            })?;
            Ok(ImageMessage {
                stamp: m.stamp,
                image: decode_compressed(&m.format, m.data)?,
                frame_id: m.frame_id,
            })
        }
        _ => Err(McapIoError::UnsupportedSchema {
            schema: schema.to_owned(),
            encoding: message_encoding.to_owned(),
            expected: IMAGE_SCHEMAS,
        }),
    }
}

/// The width and height of an image message of a ROS 2 image schema (cdr), read from its
/// header (`sensor_msgs/msg/Image`) or its JPEG or PNG header, without decoding any pixel:
/// a caller that knows the size it wants (a camera's) refuses another before paying for it.
/// An image of no pixels (0 wide or high) is an error, as decoding it is.
pub fn image_size(
    schema: &str,
    message_encoding: &str,
    data: &[u8],
) -> Result<(u32, u32), McapIoError> {
    let (w, h) = stated_image_size(schema, message_encoding, data)?;
    if w == 0 || h == 0 {
        return Err(McapIoError::BadImage {
            reason: format!("{w}x{h} pixels"),
        });
    }
    Ok((w, h))
}

/// The size an image message states, whatever it is.
fn stated_image_size(
    schema: &str,
    message_encoding: &str,
    data: &[u8],
) -> Result<(u32, u32), McapIoError> {
    match (schema, message_encoding) {
        (ROS_COMPRESSED_IMAGE, "cdr") => {
            let m = ros_compressed_image(data)?;
            let unknown = || McapIoError::UnsupportedImageEncoding {
                encoding: if m.format.is_empty() {
                    "unknown (no JPEG or PNG signature)".to_owned()
                } else {
                    m.format.to_owned()
                },
            };
            image::ImageReader::new(std::io::Cursor::new(m.data))
                .with_guessed_format()
                .map_err(|_| unknown())?
                .into_dimensions()
                .map_err(|e| McapIoError::BadImage {
                    reason: format!("its {} header does not read: {e}", m.format),
                })
        }
        (ROS_IMAGE, "cdr") => {
            let m = ros_image(data)?;
            Ok((m.width, m.height))
        }
        _ => Err(McapIoError::UnsupportedSchema {
            schema: schema.to_owned(),
            encoding: message_encoding.to_owned(),
            expected: IMAGE_SCHEMAS,
        }),
    }
}

/// JPEG or PNG bytes (format from the content; the `format` string only names errors),
/// decoded as query files are ([`decode_complete`](crate::extract::image::decode_complete)):
/// a cut-off or damaged JPEG is an error, not an image with its lost part grey.
fn decode_compressed(format: &str, bytes: &[u8]) -> Result<DynamicImage, McapIoError> {
    // Depth images are 16-bit distances behind a private header, not a photo to match.
    if format.contains("compressedDepth") {
        return Err(McapIoError::UnsupportedImageEncoding {
            encoding: format.to_owned(),
        });
    }
    image::guess_format(bytes).map_err(|_| McapIoError::UnsupportedImageEncoding {
        encoding: if format.is_empty() {
            "unknown (no JPEG or PNG signature)".to_owned()
        } else {
            format.to_owned()
        },
    })?;
    crate::extract::image::decode_complete(bytes).map_err(|source| McapIoError::ImageDecode {
        format: format.to_owned(),
        source,
    })
}

/// `sensor_msgs/msg/Image` pixels as an image; rows may be padded (`step` ≥ row bytes).
fn raw_image(
    width: u32,
    height: u32,
    encoding: &str,
    big_endian: bool,
    step: u32,
    data: &[u8],
) -> Result<DynamicImage, McapIoError> {
    let (channels, depth) = match encoding {
        "mono8" | "8UC1" => (1usize, 1usize),
        "rgb8" | "bgr8" | "8UC3" => (3, 1),
        "rgba8" | "bgra8" | "8UC4" => (4, 1),
        "mono16" | "16UC1" => (1, 2),
        other => {
            return Err(McapIoError::UnsupportedImageEncoding {
                encoding: other.to_owned(),
            })
        }
    };
    let bad = |reason: String| McapIoError::BadImage { reason };
    if width == 0 || height == 0 {
        return Err(bad(format!("{width}x{height} pixels")));
    }
    let row = (width as usize)
        .checked_mul(channels * depth)
        .ok_or_else(|| bad(format!("width {width} overflows")))?;
    let step = step as usize;
    if step < row {
        return Err(bad(format!(
            "step {step} is less than a {encoding} row of {width} pixels ({row} bytes)"
        )));
    }
    // The last row need not carry its padding.
    let needed = step
        .checked_mul(height as usize - 1)
        .and_then(|n| n.checked_add(row))
        .ok_or_else(|| bad(format!("{width}x{height} with step {step} overflows")))?;
    if data.len() < needed {
        return Err(bad(format!(
            "{width}x{height} {encoding} with step {step} needs {needed} bytes, data has {}",
            data.len()
        )));
    }
    let rows = (0..height as usize).map(|y| &data[y * step..y * step + row]);
    let too_big = || bad(format!("{width}x{height} does not fit in memory"));
    Ok(match (channels, depth) {
        (1, 2) => {
            let pixels: Vec<u16> = rows
                .flat_map(|r| r.chunks_exact(2))
                .map(|b| {
                    if big_endian {
                        u16::from_be_bytes([b[0], b[1]])
                    } else {
                        u16::from_le_bytes([b[0], b[1]])
                    }
                })
                .collect();
            DynamicImage::ImageLuma16(
                image::ImageBuffer::from_raw(width, height, pixels).ok_or_else(too_big)?,
            )
        }
        _ => {
            let mut pixels: Vec<u8> = rows.flatten().copied().collect();
            if encoding.starts_with("bgr") {
                pixels.chunks_exact_mut(channels).for_each(|p| p.swap(0, 2));
            }
            match channels {
                1 => DynamicImage::ImageLuma8(
                    image::GrayImage::from_raw(width, height, pixels).ok_or_else(too_big)?,
                ),
                3 => DynamicImage::ImageRgb8(
                    image::RgbImage::from_raw(width, height, pixels).ok_or_else(too_big)?,
                ),
                _ => DynamicImage::ImageRgba8(
                    image::RgbaImage::from_raw(width, height, pixels).ok_or_else(too_big)?,
                ),
            }
        }
    })
}

/// A `sensor_msgs/msg/CameraInfo` (cdr) as a COLMAP camera.
///
/// `plumb_bob` and `rational_polynomial` become OPENCV (FULL_OPENCV when k3..k6 are not zero),
/// `equidistant` OPENCV_FISHEYE, and all-zero distortion PINHOLE. The principal point moves by
/// half a pixel: ROS (OpenCV) puts the first pixel's centre at 0, COLMAP at 0.5.
pub fn decode_camera_info(
    schema: &str,
    message_encoding: &str,
    data: &[u8],
) -> Result<Camera, McapIoError> {
    if (schema, message_encoding) != (ROS_CAMERA_INFO, "cdr") {
        return Err(McapIoError::UnsupportedSchema {
            schema: schema.to_owned(),
            encoding: message_encoding.to_owned(),
            expected: CAMERA_INFO_SCHEMAS,
        });
    }
    let RosCameraInfo {
        height,
        width,
        distortion_model: model,
        d,
        k,
    } = ros_camera_info(data)?;
    let (fx, fy, cx, cy) = (k[0], k[4], k[2] + 0.5, k[5] + 0.5);
    let coef = |i: usize| d.get(i).copied().unwrap_or(0.0);
    let (colmap_model, params) = if d.iter().all(|&v| v == 0.0) {
        (CameraModel::Pinhole, vec![fx, fy, cx, cy])
    } else {
        match model {
            "plumb_bob" | "rational_polynomial" if (4..=8).contains(&d.len()) => {
                if (4..8).all(|i| coef(i) == 0.0) {
                    (
                        CameraModel::OpenCv,
                        vec![fx, fy, cx, cy, coef(0), coef(1), coef(2), coef(3)],
                    )
                } else {
                    let mut p = vec![fx, fy, cx, cy];
                    p.extend((0..8).map(coef));
                    (CameraModel::FullOpenCv, p)
                }
            }
            "equidistant" if d.len() == 4 => (
                CameraModel::OpenCvFisheye,
                vec![fx, fy, cx, cy, coef(0), coef(1), coef(2), coef(3)],
            ),
            _ => {
                return Err(McapIoError::Camera {
                    reason: format!(
                        "distortion model {model:?} with {} coefficients (supported: plumb_bob, rational_polynomial, equidistant, or all zero)",
                        d.len()
                    ),
                })
            }
        }
    };
    Camera::new(colmap_model, width, height, params).map_err(|e| McapIoError::Camera {
        reason: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cdr_string(out: &mut Vec<u8>, s: &str) {
        while (out.len() - 4) % 4 != 0 {
            out.push(0);
        }
        out.extend(((s.len() + 1) as u32).to_le_bytes());
        out.extend(s.as_bytes());
        out.push(0);
    }

    /// A 2x1 `bgr8` `sensor_msgs/msg/Image` stamped 7 s 9 ns.
    fn raw_bgr8() -> Vec<u8> {
        let mut msg = vec![0, 1, 0, 0];
        msg.extend(7i32.to_le_bytes());
        msg.extend(9u32.to_le_bytes());
        cdr_string(&mut msg, "cam");
        while (msg.len() - 4) % 4 != 0 {
            msg.push(0);
        }
        msg.extend(1u32.to_le_bytes()); // height
        msg.extend(2u32.to_le_bytes()); // width
        cdr_string(&mut msg, "bgr8");
        msg.push(0); // is_bigendian
        while (msg.len() - 4) % 4 != 0 {
            msg.push(0);
        }
        msg.extend(8u32.to_le_bytes()); // step: 6 bytes of pixels + 2 of padding
        msg.extend(8u32.to_le_bytes());
        msg.extend([1, 2, 3, 4, 5, 6, 0, 0]);
        msg
    }

    #[test]
    fn raw_bgr8_with_padding_and_unsupported_encoding() {
        let msg = raw_bgr8();
        let m = decode_image(ROS_IMAGE, "cdr", &msg).unwrap();
        assert_eq!(m.stamp, Some(Stamp { sec: 7, nsec: 9 }));
        assert_eq!(m.frame_id, "cam");
        assert_eq!(m.image.to_rgb8().into_raw(), vec![3, 2, 1, 6, 5, 4]);

        let yuv = String::from_utf8_lossy(&msg).replace("bgr8", "yuv4");
        let err = decode_image(ROS_IMAGE, "cdr", yuv.as_bytes()).unwrap_err();
        assert!(
            err.to_string()
                .contains("unsupported image encoding \"yuv4\""),
            "{err}"
        );

        let err = decode_image(ROS_IMAGE, "cdr", &msg[..msg.len() - 3]).unwrap_err();
        assert!(
            matches!(
                err,
                McapIoError::Cdr(CdrError::Truncated { field: "data", .. })
            ),
            "{err}"
        );
    }

    fn camera_info(model: &str, d: &[f64]) -> Vec<u8> {
        let mut msg = vec![0, 1, 0, 0];
        msg.extend(1i32.to_le_bytes());
        msg.extend(2u32.to_le_bytes());
        cdr_string(&mut msg, "cam");
        while (msg.len() - 4) % 4 != 0 {
            msg.push(0);
        }
        msg.extend(480u32.to_le_bytes());
        msg.extend(640u32.to_le_bytes());
        cdr_string(&mut msg, model);
        while (msg.len() - 4) % 4 != 0 {
            msg.push(0);
        }
        msg.extend((d.len() as u32).to_le_bytes());
        let k = [500.0, 0.0, 319.5, 0.0, 510.0, 239.5, 0.0, 0.0, 1.0];
        for v in d.iter().chain(&k) {
            while (msg.len() - 4) % 8 != 0 {
                msg.push(0);
            }
            msg.extend(v.to_le_bytes());
        }
        msg
    }

    #[test]
    fn camera_info_models() {
        let c = decode_camera_info(ROS_CAMERA_INFO, "cdr", &camera_info("plumb_bob", &[0.0; 5]))
            .unwrap();
        assert_eq!(c.model(), CameraModel::Pinhole);
        assert_eq!(c.params(), &[500.0, 510.0, 320.0, 240.0]);
        assert_eq!((c.width(), c.height()), (640, 480));
        let d = [0.1, -0.01, 0.001, 0.002, 0.0];
        let c = decode_camera_info(ROS_CAMERA_INFO, "cdr", &camera_info("plumb_bob", &d)).unwrap();
        assert_eq!(c.model(), CameraModel::OpenCv);
        assert_eq!(&c.params()[4..], &d[..4]);
        let d = [0.1, -0.01, 0.001, 0.002, 0.003];
        let c = decode_camera_info(ROS_CAMERA_INFO, "cdr", &camera_info("plumb_bob", &d)).unwrap();
        assert_eq!(c.model(), CameraModel::FullOpenCv);
        assert_eq!(&c.params()[4..9], &d);
        let c = decode_camera_info(ROS_CAMERA_INFO, "cdr", &camera_info("equidistant", &d[..4]))
            .unwrap();
        assert_eq!(c.model(), CameraModel::OpenCvFisheye);
        let err = decode_camera_info(ROS_CAMERA_INFO, "cdr", &camera_info("unified", &[0.5]))
            .unwrap_err();
        assert!(
            err.to_string().contains("distortion model \"unified\""),
            "{err}"
        );
        let err = decode_camera_info(ROS_IMAGE, "cdr", &[]).unwrap_err();
        assert!(
            matches!(err, McapIoError::UnsupportedSchema { .. }),
            "{err}"
        );
        assert_eq!(
            err.to_string(),
            "unsupported message type \"sensor_msgs/msg/Image\" with message encoding \"cdr\" (supported: sensor_msgs/msg/CameraInfo as cdr)"
        );
    }

    #[test]
    fn cdr_big_endian_and_bad_headers() {
        let mut msg = vec![0, 0, 0, 0];
        msg.extend(3i32.to_be_bytes());
        msg.extend(4u32.to_be_bytes());
        msg.extend(1u32.to_be_bytes());
        msg.push(0); // frame_id ""
        msg.extend([0, 0, 0]);
        msg.extend(4u32.to_be_bytes());
        msg.extend(b"png\0");
        msg.extend(3u32.to_be_bytes());
        msg.extend(b"abc");
        let err = decode_image(ROS_COMPRESSED_IMAGE, "cdr", &msg).unwrap_err();
        assert!(
            matches!(err, McapIoError::UnsupportedImageEncoding { .. }),
            "{err}"
        );
        msg[1] = 3;
        let err = decode_image(ROS_COMPRESSED_IMAGE, "cdr", &msg).unwrap_err();
        assert!(
            matches!(
                err,
                McapIoError::Cdr(CdrError::Encapsulation { id: [0, 3] })
            ),
            "{err}"
        );
        let err = decode_image(ROS_COMPRESSED_IMAGE, "cdr", &msg[..2]).unwrap_err();
        assert!(
            matches!(err, McapIoError::Cdr(CdrError::Truncated { .. })),
            "{err}"
        );
        let err = decode_image("sensor_msgs/msg/PointCloud2", "cdr", &msg).unwrap_err();
        assert!(
            err.to_string().contains("unsupported message type"),
            "{err}"
        );
        let err = decode_image(ROS_CAMERA_INFO, "cdr", &msg)
            .unwrap_err()
            .to_string();
        for supported in [ROS_COMPRESSED_IMAGE, ROS_IMAGE, FOXGLOVE_COMPRESSED_IMAGE] {
            assert!(err.contains(supported), "{err}");
        }
        assert!(!err.contains('\n'), "{err}");
    }

    /// A 3x2 grey PNG.
    fn png() -> Vec<u8> {
        let mut out = std::io::Cursor::new(Vec::new());
        DynamicImage::ImageLuma8(image::GrayImage::new(3, 2))
            .write_to(&mut out, image::ImageFormat::Png)
            .unwrap();
        out.into_inner()
    }

    /// `foxglove.CompressedImage` as protobuf: the PNG, stamped 5 s 6 ns, frame "c".
    fn protobuf_image() -> Vec<u8> {
        let png = png();
        let mut msg = vec![0x0a, 4, 0x08, 5, 0x10, 6]; // timestamp {seconds 5, nanos 6}
        msg.extend([0x12, png.len() as u8]);
        msg.extend(&png);
        msg.extend([0x1a, 3]);
        msg.extend(b"png");
        msg.extend([0x22, 1, b'c']);
        msg
    }

    /// `sensor_msgs/msg/CompressedImage` as CDR: the PNG, stamped 1 s 2 ns, frame "cam".
    fn compressed_image() -> Vec<u8> {
        let mut msg = vec![0, 1, 0, 0];
        msg.extend(1i32.to_le_bytes());
        msg.extend(2u32.to_le_bytes());
        cdr_string(&mut msg, "cam");
        cdr_string(&mut msg, "png");
        while (msg.len() - 4) % 4 != 0 {
            msg.push(0);
        }
        let png = png();
        msg.extend((png.len() as u32).to_le_bytes());
        msg.extend(png);
        msg
    }

    /// The seeds of the `mcap_wire` fuzz target (fuzz/corpus/mcap_wire/): one message of each
    /// layout we read, built as above. `SFPMAP_WRITE_FUZZ_SEEDS=1 cargo test --all-features
    /// --lib io::mcap_io` rewrites them. Every file there and in fuzz/regressions/mcap_wire/
    /// goes through the target's body, so a crash found once stays fixed.
    #[test]
    fn fuzz_seeds_decode_are_current_and_replay() {
        let seeds = [
            ("ros_compressed_image.cdr", compressed_image()),
            ("ros_image_bgr8.cdr", raw_bgr8()),
            (
                "ros_camera_info.cdr",
                camera_info("plumb_bob", &[0.1, -0.01, 0.001, 0.002, 0.0]),
            ),
            ("foxglove_compressed_image.pb", protobuf_image()),
            ("png.base64", base64_encode(&png()).into_bytes()),
        ];
        decode_image(ROS_COMPRESSED_IMAGE, "cdr", &seeds[0].1).unwrap();
        decode_image(ROS_IMAGE, "cdr", &seeds[1].1).unwrap();
        decode_camera_info(ROS_CAMERA_INFO, "cdr", &seeds[2].1).unwrap();
        decode_image(FOXGLOVE_COMPRESSED_IMAGE, "protobuf", &seeds[3].1).unwrap();
        let text = std::str::from_utf8(&seeds[4].1).unwrap();
        assert_eq!(base64_decode(text).unwrap(), png());

        let fuzz = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
        let corpus = fuzz.join("corpus/mcap_wire");
        if std::env::var_os("SFPMAP_WRITE_FUZZ_SEEDS").is_some() {
            std::fs::create_dir_all(&corpus).unwrap();
            for (name, bytes) in &seeds {
                std::fs::write(corpus.join(name), bytes).unwrap();
            }
        }
        for (name, bytes) in &seeds {
            let committed = std::fs::read(corpus.join(name)).unwrap_or_default();
            assert!(
                committed == *bytes,
                "fuzz/corpus/mcap_wire/{name} is stale: SFPMAP_WRITE_FUZZ_SEEDS=1 rewrites it"
            );
        }
        let mut replayed = 0;
        for dir in [corpus, fuzz.join("regressions/mcap_wire")] {
            for entry in std::fs::read_dir(dir).into_iter().flatten() {
                fuzz_wire(&std::fs::read(entry.unwrap().path()).unwrap());
                replayed += 1;
            }
        }
        assert!(replayed >= seeds.len());
    }

    #[test]
    fn protobuf_compressed_image_fields() {
        let msg = protobuf_image();
        let m = decode_image(FOXGLOVE_COMPRESSED_IMAGE, "protobuf", &msg).unwrap();
        assert_eq!(m.stamp, Some(Stamp { sec: 5, nsec: 6 }));
        assert_eq!(m.frame_id, "c");
        assert_eq!((m.image.width(), m.image.height()), (3, 2));
    }
}
