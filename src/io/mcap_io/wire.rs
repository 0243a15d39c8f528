//! The wire formats under the messages, read by hand: CDR (ROS 2), protobuf fields
//! (Foxglove), and base64 (bytes inside JSON messages).
//!
//! This file uses nothing but `std`: `fuzz/fuzz_targets/mcap_wire.rs` compiles it as it is
//! (`#[path]`), so the fuzz crate needs neither the `mcap` feature nor its ONNX stack.

use std::fmt;

/// A time as ROS and Foxglove carry it: seconds and nanoseconds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Default)]
pub struct Stamp {
    /// Whole seconds since the epoch.
    pub sec: i64,
    /// Nanoseconds past `sec` (below 10⁹).
    pub nsec: u32,
}

impl Stamp {
    /// From MCAP's nanoseconds since the epoch (log and publish times).
    pub fn from_nanos(ns: u64) -> Stamp {
        Stamp {
            sec: (ns / 1_000_000_000) as i64,
            nsec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// What can go wrong reading a CDR message.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum CdrError {
    /// The message ends before the field.
    Truncated {
        /// The field.
        field: &'static str,
        /// Where it starts in the message.
        offset: usize,
        /// The bytes it needs.
        needed: usize,
        /// The message's length.
        len: usize,
    },
    /// The 4-byte encapsulation header names a representation we do not read.
    Encapsulation {
        /// The representation id the header gives.
        id: [u8; 2],
    },
    /// A string field without its terminating NUL or not UTF-8.
    BadString {
        /// The field.
        field: &'static str,
    },
}

impl fmt::Display for CdrError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CdrError::Truncated {
                field,
                offset,
                needed,
                len,
            } => write!(
                f,
                "cdr message truncated: {field} needs {needed} bytes at offset {offset}, the message has {len}"
            ),
            CdrError::Encapsulation { id } => write!(
                f,
                "unsupported cdr encapsulation {:#04x}{:02x} (expected plain CDR or XCDR2, little or big endian)",
                id[0], id[1]
            ),
            CdrError::BadString { field } => {
                write!(f, "cdr string {field} is not NUL-terminated UTF-8")
            }
        }
    }
}

impl std::error::Error for CdrError {}

/// A reader of CDR as ROS 2 writes it: after the 4-byte encapsulation header, each primitive
/// is aligned to its size relative to the first byte after that header (XCDR2 caps the
/// alignment at 4).
pub(super) struct Cdr<'a> {
    body: &'a [u8],
    pos: usize,
    little: bool,
    max_align: usize,
}

impl<'a> Cdr<'a> {
    pub(super) fn new(data: &'a [u8]) -> Result<Self, CdrError> {
        let truncated = CdrError::Truncated {
            field: "encapsulation header",
            offset: 0,
            needed: 4,
            len: data.len(),
        };
        let header = data.get(..4).ok_or(truncated)?;
        let (little, max_align) = match [header[0], header[1]] {
            [0, 0] => (false, 8),
            [0, 1] => (true, 8),
            [0, 6] => (false, 4),
            [0, 7] => (true, 4),
            id => return Err(CdrError::Encapsulation { id }),
        };
        Ok(Cdr {
            body: &data[4..],
            pos: 0,
            little,
            max_align,
        })
    }

    fn take(&mut self, field: &'static str, n: usize, align: usize) -> Result<&'a [u8], CdrError> {
        let a = align.min(self.max_align);
        let start = self.pos.div_ceil(a) * a;
        let end = start.checked_add(n).filter(|&e| e <= self.body.len());
        let Some(end) = end else {
            return Err(CdrError::Truncated {
                field,
                offset: start + 4,
                needed: n,
                len: self.body.len() + 4,
            });
        };
        self.pos = end;
        Ok(&self.body[start..end])
    }

    pub(super) fn u8(&mut self, field: &'static str) -> Result<u8, CdrError> {
        Ok(self.take(field, 1, 1)?[0])
    }

    pub(super) fn u32(&mut self, field: &'static str) -> Result<u32, CdrError> {
        let b: [u8; 4] = self.take(field, 4, 4)?.try_into().expect("4 bytes");
        Ok(if self.little {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    pub(super) fn f64(&mut self, field: &'static str) -> Result<f64, CdrError> {
        let b: [u8; 8] = self.take(field, 8, 8)?.try_into().expect("8 bytes");
        Ok(if self.little {
            f64::from_le_bytes(b)
        } else {
            f64::from_be_bytes(b)
        })
    }

    /// A string: u32 length including the NUL, the bytes, the NUL. Length 0 is read as empty
    /// (some writers emit it for "").
    pub(super) fn string(&mut self, field: &'static str) -> Result<&'a str, CdrError> {
        let n = self.u32(field)? as usize;
        if n == 0 {
            return Ok("");
        }
        let bytes = self.take(field, n, 1)?;
        match bytes.split_last() {
            Some((0, text)) => std::str::from_utf8(text).map_err(|_| CdrError::BadString { field }),
            _ => Err(CdrError::BadString { field }),
        }
    }

    pub(super) fn byte_sequence(&mut self, field: &'static str) -> Result<&'a [u8], CdrError> {
        let n = self.u32(field)? as usize;
        self.take(field, n, 1)
    }

    /// `std_msgs/Header`: stamp (sec i32, nanosec u32) and frame_id.
    pub(super) fn header(&mut self) -> Result<(Stamp, String), CdrError> {
        let sec = self.u32("header.stamp.sec")? as i32;
        let nsec = self.u32("header.stamp.nanosec")?;
        let frame_id = self.string("header.frame_id")?.to_owned();
        Ok((
            Stamp {
                sec: i64::from(sec),
                nsec,
            },
            frame_id,
        ))
    }
}

/// A protobuf field's payload (groups and fixed-width fields are skipped, not decoded).
pub(super) enum Wire<'a> {
    Varint(u64),
    Bytes(&'a [u8]),
    Fixed,
}

/// Iterates `(field number, payload)` over a protobuf message; stops after the first error.
pub(super) struct Protobuf<'a>(pub(super) &'a [u8]);

impl<'a> Protobuf<'a> {
    fn varint(&mut self) -> Result<u64, String> {
        let mut value = 0u64;
        for shift in (0..64).step_by(7) {
            let (&b, rest) = self.0.split_first().ok_or("varint runs past the end")?;
            self.0 = rest;
            value |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Ok(value);
            }
        }
        Err("varint longer than 10 bytes".into())
    }

    fn skip(&mut self, n: u64) -> Result<&'a [u8], String> {
        let n = usize::try_from(n)
            .ok()
            .filter(|&n| n <= self.0.len())
            .ok_or_else(|| format!("field of {n} bytes runs past the end"))?;
        let (head, rest) = self.0.split_at(n);
        self.0 = rest;
        Ok(head)
    }

    fn field(&mut self) -> Result<(u64, Wire<'a>), String> {
        let key = self.varint()?;
        let wire = match key & 7 {
            0 => Wire::Varint(self.varint()?),
            1 => {
                self.skip(8)?;
                Wire::Fixed
            }
            2 => {
                let n = self.varint()?;
                Wire::Bytes(self.skip(n)?)
            }
            5 => {
                self.skip(4)?;
                Wire::Fixed
            }
            other => return Err(format!("unsupported protobuf wire type {other}")),
        };
        Ok((key >> 3, wire))
    }
}

impl<'a> Iterator for Protobuf<'a> {
    type Item = Result<(u64, Wire<'a>), String>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.0.is_empty() {
            return None;
        }
        let item = self.field();
        if item.is_err() {
            self.0 = &[];
        }
        Some(item)
    }
}

/// `sensor_msgs/msg/CompressedImage` (CDR): header, format, data.
pub(super) struct RosCompressedImage<'a> {
    pub stamp: Stamp,
    pub frame_id: String,
    pub format: &'a str,
    pub data: &'a [u8],
}

pub(super) fn ros_compressed_image(data: &[u8]) -> Result<RosCompressedImage<'_>, CdrError> {
    let mut r = Cdr::new(data)?;
    let (stamp, frame_id) = r.header()?;
    Ok(RosCompressedImage {
        stamp,
        frame_id,
        format: r.string("format")?,
        data: r.byte_sequence("data")?,
    })
}

/// `sensor_msgs/msg/Image` (CDR): header, size, encoding, endianness, row step, pixels.
pub(super) struct RosImage<'a> {
    pub stamp: Stamp,
    pub frame_id: String,
    pub height: u32,
    pub width: u32,
    pub encoding: &'a str,
    pub big_endian: bool,
    pub step: u32,
    pub data: &'a [u8],
}

pub(super) fn ros_image(data: &[u8]) -> Result<RosImage<'_>, CdrError> {
    let mut r = Cdr::new(data)?;
    let (stamp, frame_id) = r.header()?;
    Ok(RosImage {
        stamp,
        frame_id,
        height: r.u32("height")?,
        width: r.u32("width")?,
        encoding: r.string("encoding")?,
        big_endian: r.u8("is_bigendian")? != 0,
        step: r.u32("step")?,
        data: r.byte_sequence("data")?,
    })
}

/// `sensor_msgs/msg/CameraInfo` (CDR), up to K: size, distortion model and coefficients.
pub(super) struct RosCameraInfo<'a> {
    pub height: u32,
    pub width: u32,
    pub distortion_model: &'a str,
    pub d: Vec<f64>,
    pub k: [f64; 9],
}

pub(super) fn ros_camera_info(data: &[u8]) -> Result<RosCameraInfo<'_>, CdrError> {
    let mut r = Cdr::new(data)?;
    r.header()?;
    let height = r.u32("height")?;
    let width = r.u32("width")?;
    let distortion_model = r.string("distortion_model")?;
    // The count is a claim: each coefficient read is checked against the message.
    let n = r.u32("d")?;
    let d = (0..n).map(|_| r.f64("d")).collect::<Result<Vec<_>, _>>()?;
    let mut k = [0.0; 9];
    for v in &mut k {
        *v = r.f64("k")?;
    }
    Ok(RosCameraInfo {
        height,
        width,
        distortion_model,
        d,
        k,
    })
}

/// `foxglove.CompressedImage` (protobuf): timestamp (1), data (2), format (3), frame_id (4).
pub(super) struct FoxgloveCompressedImage<'a> {
    pub stamp: Option<Stamp>,
    pub frame_id: String,
    pub format: String,
    pub data: &'a [u8],
}

pub(super) fn foxglove_compressed_image(
    data: &[u8],
) -> Result<FoxgloveCompressedImage<'_>, String> {
    let mut image = FoxgloveCompressedImage {
        stamp: None,
        frame_id: String::new(),
        format: String::new(),
        data: &[],
    };
    let text = |s: &[u8], field: &str| {
        String::from_utf8(s.to_vec()).map_err(|_| format!("{field} is not UTF-8"))
    };
    for field in Protobuf(data) {
        match field? {
            (1, Wire::Bytes(t)) => {
                let mut s = Stamp::default();
                for f in Protobuf(t) {
                    match f? {
                        (1, Wire::Varint(v)) => s.sec = v as i64,
                        (2, Wire::Varint(v)) => {
                            s.nsec = u32::try_from(v).map_err(|_| format!("timestamp nanos {v}"))?
                        }
                        _ => {}
                    }
                }
                image.stamp = Some(s);
            }
            (2, Wire::Bytes(d)) => image.data = d,
            (3, Wire::Bytes(s)) => image.format = text(s, "format")?,
            (4, Wire::Bytes(s)) => image.frame_id = text(s, "frame_id")?,
            _ => {}
        }
    }
    Ok(image)
}

/// The fuzz target `mcap_wire`: every message layout above on any bytes (none may panic),
/// and base64 round trips.
// The library's own use is its test over the corpus; the fuzz crate includes this file.
#[cfg_attr(not(test), allow(dead_code))]
pub fn fuzz_wire(data: &[u8]) {
    let _ = ros_compressed_image(data);
    let _ = ros_image(data);
    let _ = ros_camera_info(data);
    let _ = foxglove_compressed_image(data);
    for field in Protobuf(data).flatten() {
        if let (_, Wire::Bytes(inner)) = field {
            Protobuf(inner).for_each(drop);
        }
    }
    if let Ok(Ok(bytes)) = std::str::from_utf8(data).map(base64_decode) {
        assert_eq!(base64_decode(&base64_encode(&bytes)), Ok(bytes));
    }
    assert_eq!(base64_decode(&base64_encode(data)).as_deref(), Ok(data));
}

/// Standard base64 (RFC 4648, padding optional, whitespace ignored), as JSON carries bytes.
pub fn base64_decode(text: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(text.len() / 4 * 3);
    let (mut acc, mut bits) = (0u32, 0u32);
    let mut padding = false;
    for (i, c) in text.bytes().enumerate() {
        let v = match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            b'=' => {
                padding = true;
                continue;
            }
            b' ' | b'\n' | b'\r' | b'\t' => continue,
            _ => return Err(format!("invalid base64 byte {c:#04x} at {i}")),
        };
        if padding {
            return Err(format!("base64 data after padding at {i}"));
        }
        acc = (acc << 6) | u32::from(v);
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
        }
    }
    if bits >= 6 {
        return Err("base64 length is not a whole number of bytes".into());
    }
    Ok(out)
}

/// Standard base64 with padding.
pub fn base64_encode(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_round_trip() {
        for n in 0..10 {
            let bytes: Vec<u8> = (0..n).map(|i| (i * 37 + 5) as u8).collect();
            assert_eq!(base64_decode(&base64_encode(&bytes)).unwrap(), bytes);
        }
        assert_eq!(base64_encode(b"foobar"), "Zm9vYmFy");
        assert!(base64_decode("Zm9v!").is_err());
    }

    #[test]
    fn cdr_alignment_is_capped_at_4_in_xcdr2() {
        // A u8, then an f64: plain CDR pads to offset 8, XCDR2 (id 0x0007) to offset 4.
        let value = 2.5f64.to_le_bytes();
        let mut plain = vec![0, 1, 0, 0, 9, 0, 0, 0, 0, 0, 0, 0];
        plain.extend(value);
        let mut r = Cdr::new(&plain).unwrap();
        assert_eq!((r.u8("a").unwrap(), r.f64("b").unwrap()), (9, 2.5));
        let mut xcdr2 = vec![0, 7, 0, 0, 9, 0, 0, 0];
        xcdr2.extend(value);
        let mut r = Cdr::new(&xcdr2).unwrap();
        assert_eq!((r.u8("a").unwrap(), r.f64("b").unwrap()), (9, 2.5));
        assert!(matches!(
            r.u32("c"),
            Err(CdrError::Truncated { field: "c", .. })
        ));
    }

    #[test]
    fn protobuf_fields_and_errors() {
        // Field 1 varint 300, field 2 bytes "hi", field 3 fixed64 (skipped).
        let mut msg = vec![0x08, 0xac, 0x02, 0x12, 2, b'h', b'i', 0x19];
        msg.extend([0; 8]);
        let fields: Vec<_> = Protobuf(&msg).collect::<Result<_, _>>().unwrap();
        assert!(matches!(
            fields[..],
            [
                (1, Wire::Varint(300)),
                (2, Wire::Bytes(b"hi")),
                (3, Wire::Fixed)
            ]
        ));
        // A length past the end is an error, after which the iterator stops.
        let mut it = Protobuf(&[0x12, 5, b'x']);
        assert!(it.next().unwrap().is_err());
        assert!(it.next().is_none());
        assert!(Protobuf(&[0xff; 11]).next().unwrap().is_err());
    }
}
