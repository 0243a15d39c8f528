//! The wire formats under the messages, read by hand: CDR (ROS 2), protobuf fields
//! (Foxglove), and base64 (bytes inside JSON messages).

use super::{McapIoError, Stamp};

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
    pub(super) fn new(data: &'a [u8]) -> Result<Self, McapIoError> {
        let truncated = McapIoError::CdrTruncated {
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
            id => return Err(McapIoError::CdrEncapsulation { id }),
        };
        Ok(Cdr {
            body: &data[4..],
            pos: 0,
            little,
            max_align,
        })
    }

    fn take(
        &mut self,
        field: &'static str,
        n: usize,
        align: usize,
    ) -> Result<&'a [u8], McapIoError> {
        let a = align.min(self.max_align);
        let start = self.pos.div_ceil(a) * a;
        let end = start.checked_add(n).filter(|&e| e <= self.body.len());
        let Some(end) = end else {
            return Err(McapIoError::CdrTruncated {
                field,
                offset: start + 4,
                needed: n,
                len: self.body.len() + 4,
            });
        };
        self.pos = end;
        Ok(&self.body[start..end])
    }

    pub(super) fn u8(&mut self, field: &'static str) -> Result<u8, McapIoError> {
        Ok(self.take(field, 1, 1)?[0])
    }

    pub(super) fn u32(&mut self, field: &'static str) -> Result<u32, McapIoError> {
        let b: [u8; 4] = self.take(field, 4, 4)?.try_into().expect("4 bytes");
        Ok(if self.little {
            u32::from_le_bytes(b)
        } else {
            u32::from_be_bytes(b)
        })
    }

    pub(super) fn f64(&mut self, field: &'static str) -> Result<f64, McapIoError> {
        let b: [u8; 8] = self.take(field, 8, 8)?.try_into().expect("8 bytes");
        Ok(if self.little {
            f64::from_le_bytes(b)
        } else {
            f64::from_be_bytes(b)
        })
    }

    /// A string: u32 length including the NUL, the bytes, the NUL. Length 0 is read as empty
    /// (some writers emit it for "").
    pub(super) fn string(&mut self, field: &'static str) -> Result<&'a str, McapIoError> {
        let n = self.u32(field)? as usize;
        if n == 0 {
            return Ok("");
        }
        let bytes = self.take(field, n, 1)?;
        match bytes.split_last() {
            Some((0, text)) => {
                std::str::from_utf8(text).map_err(|_| McapIoError::BadString { field })
            }
            _ => Err(McapIoError::BadString { field }),
        }
    }

    pub(super) fn byte_sequence(&mut self, field: &'static str) -> Result<&'a [u8], McapIoError> {
        let n = self.u32(field)? as usize;
        self.take(field, n, 1)
    }

    /// `std_msgs/Header`: stamp (sec i32, nanosec u32) and frame_id.
    pub(super) fn header(&mut self) -> Result<(Stamp, String), McapIoError> {
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
            Err(McapIoError::CdrTruncated { field: "c", .. })
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
