//! The MCAP records a log reader needs, parsed from a slice with every length checked against
//! the bytes that are there (spec: <https://mcap.dev/spec>).
//!
//! Why not `mcap::parse_record`: its binrw parser reserves a string's declared u32 length
//! before reading it, so one forged length in a few-byte record costs 4 GiB (or aborts under
//! a memory limit). Here a length is a claim to check, never a size to allocate.

use super::McapIoError;
use std::collections::BTreeMap;

pub(super) use mcap::records::op;

/// The name of a record's opcode, for messages.
pub(super) fn record_name(opcode: u8) -> &'static str {
    match opcode {
        op::HEADER => "header",
        op::FOOTER => "footer",
        op::SCHEMA => "schema",
        op::CHANNEL => "channel",
        op::MESSAGE => "message",
        op::CHUNK => "chunk",
        op::MESSAGE_INDEX => "message index",
        op::CHUNK_INDEX => "chunk index",
        op::ATTACHMENT => "attachment",
        op::ATTACHMENT_INDEX => "attachment index",
        op::STATISTICS => "statistics",
        op::METADATA => "metadata",
        op::METADATA_INDEX => "metadata index",
        op::SUMMARY_OFFSET => "summary offset",
        op::DATA_END => "data end",
        _ => "unknown",
    }
}

/// Opcode (u8) and length (u64) before every record body.
pub(super) const RECORD_HEADER_LEN: u64 = 9;

/// A little-endian field reader over one record body.
pub(super) struct Fields<'a> {
    record: &'static str,
    data: &'a [u8],
    pos: usize,
}

impl<'a> Fields<'a> {
    pub(super) fn new(record: &'static str, data: &'a [u8]) -> Self {
        Fields {
            record,
            data,
            pos: 0,
        }
    }

    fn bad(&self, reason: String) -> McapIoError {
        McapIoError::BadRecord {
            record: self.record,
            reason,
        }
    }

    pub(super) fn bytes(&mut self, field: &str, n: u64) -> Result<&'a [u8], McapIoError> {
        let left = self.data.len() - self.pos;
        let n = usize::try_from(n)
            .ok()
            .filter(|&n| n <= left)
            .ok_or_else(|| {
                self.bad(format!(
                    "{field} needs {n} bytes at offset {}, the record has {left} left",
                    self.pos
                ))
            })?;
        let out = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(out)
    }

    fn array<const N: usize>(&mut self, field: &str) -> Result<[u8; N], McapIoError> {
        let b = self.bytes(field, N as u64)?;
        Ok(b.try_into().expect("N bytes"))
    }

    pub(super) fn u16(&mut self, field: &str) -> Result<u16, McapIoError> {
        Ok(u16::from_le_bytes(self.array(field)?))
    }

    pub(super) fn u32(&mut self, field: &str) -> Result<u32, McapIoError> {
        Ok(u32::from_le_bytes(self.array(field)?))
    }

    pub(super) fn u64(&mut self, field: &str) -> Result<u64, McapIoError> {
        Ok(u64::from_le_bytes(self.array(field)?))
    }

    /// u32 length, then that many bytes.
    pub(super) fn prefixed(&mut self, field: &str) -> Result<&'a [u8], McapIoError> {
        let n = self.u32(field)?;
        self.bytes(field, u64::from(n))
    }

    pub(super) fn string(&mut self, field: &str) -> Result<String, McapIoError> {
        let bytes = self.prefixed(field)?;
        String::from_utf8(bytes.to_vec()).map_err(|_| self.bad(format!("{field} is not UTF-8")))
    }

    /// What is left of the record.
    pub(super) fn rest(&mut self) -> &'a [u8] {
        let out = &self.data[self.pos..];
        self.pos = self.data.len();
        out
    }

    /// A map stored as its byte length (u32) and then its entries.
    fn map<K: Ord, V>(
        &mut self,
        field: &str,
        mut entry: impl FnMut(&mut Fields<'a>) -> Result<(K, V), McapIoError>,
    ) -> Result<BTreeMap<K, V>, McapIoError> {
        let bytes = self.prefixed(field)?;
        let mut inner = Fields {
            record: self.record,
            data: bytes,
            pos: 0,
        };
        let mut map = BTreeMap::new();
        while inner.pos < bytes.len() {
            let (k, v) = entry(&mut inner)?;
            if map.insert(k, v).is_some() {
                return Err(self.bad(format!("{field} has a key twice")));
            }
        }
        Ok(map)
    }
}

/// Schema (op 0x03).
pub(super) struct Schema<'a> {
    pub id: u16,
    pub name: String,
    pub encoding: String,
    pub data: &'a [u8],
}

pub(super) fn schema(body: &[u8]) -> Result<Schema<'_>, McapIoError> {
    let mut f = Fields::new("schema", body);
    Ok(Schema {
        id: f.u16("id")?,
        name: f.string("name")?,
        encoding: f.string("encoding")?,
        data: f.prefixed("data")?,
    })
}

/// Channel (op 0x04).
pub(super) struct Channel {
    pub id: u16,
    pub schema_id: u16,
    pub topic: String,
    pub message_encoding: String,
    pub metadata: BTreeMap<String, String>,
}

pub(super) fn channel(body: &[u8]) -> Result<Channel, McapIoError> {
    let mut f = Fields::new("channel", body);
    Ok(Channel {
        id: f.u16("id")?,
        schema_id: f.u16("schema_id")?,
        topic: f.string("topic")?,
        message_encoding: f.string("message_encoding")?,
        metadata: f.map("metadata", |e| Ok((e.string("key")?, e.string("value")?)))?,
    })
}

/// Message (op 0x05).
pub(super) struct Message<'a> {
    pub channel_id: u16,
    pub sequence: u32,
    pub log_time: u64,
    pub publish_time: u64,
    pub data: &'a [u8],
}

pub(super) fn message(body: &[u8]) -> Result<Message<'_>, McapIoError> {
    let mut f = Fields::new("message", body);
    Ok(Message {
        channel_id: f.u16("channel_id")?,
        sequence: f.u32("sequence")?,
        log_time: f.u64("log_time")?,
        publish_time: f.u64("publish_time")?,
        data: f.rest(),
    })
}

/// Chunk (op 0x06): its header and its (compressed) records.
pub(super) struct Chunk<'a> {
    pub uncompressed_size: u64,
    pub uncompressed_crc: u32,
    pub compression: String,
    pub records: &'a [u8],
}

pub(super) fn chunk(body: &[u8]) -> Result<Chunk<'_>, McapIoError> {
    let mut f = Fields::new("chunk", body);
    f.u64("message_start_time")?;
    f.u64("message_end_time")?;
    let uncompressed_size = f.u64("uncompressed_size")?;
    let uncompressed_crc = f.u32("uncompressed_crc")?;
    let compression = f.string("compression")?;
    let compressed_size = f.u64("compressed_size")?;
    let records = f.bytes("records", compressed_size)?;
    Ok(Chunk {
        uncompressed_size,
        uncompressed_crc,
        compression,
        records,
    })
}

/// Chunk Index (op 0x08): where a chunk is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChunkIndex {
    /// The chunk record's offset in the file (its opcode byte).
    pub offset: u64,
    /// The chunk record's length, opcode and length field included.
    pub length: u64,
}

pub(super) fn chunk_index(body: &[u8]) -> Result<ChunkIndex, McapIoError> {
    let mut f = Fields::new("chunk index", body);
    f.u64("message_start_time")?;
    f.u64("message_end_time")?;
    let offset = f.u64("chunk_start_offset")?;
    let length = f.u64("chunk_length")?;
    // The per-channel message index offsets, the compression and the sizes are not needed:
    // the chunk record states them again and is checked against its own CRC.
    f.map("message_index_offsets", |e| {
        Ok((e.u16("channel_id")?, e.u64("offset")?))
    })?;
    Ok(ChunkIndex { offset, length })
}

/// Statistics (op 0x0B): messages per channel.
pub(super) fn channel_message_counts(body: &[u8]) -> Result<BTreeMap<u16, u64>, McapIoError> {
    let mut f = Fields::new("statistics", body);
    f.u64("message_count")?;
    f.u16("schema_count")?;
    f.u32("channel_count")?;
    f.u32("attachment_count")?;
    f.u32("metadata_count")?;
    f.u32("chunk_count")?;
    f.u64("message_start_time")?;
    f.u64("message_end_time")?;
    f.map("channel_message_counts", |e| {
        Ok((e.u16("channel_id")?, e.u64("count")?))
    })
}

/// Footer (op 0x02).
pub(super) struct Footer {
    pub summary_start: u64,
    pub summary_crc: u32,
}

/// Footer record and end magic: opcode, length (20), summary_start, summary_offset_start,
/// summary_crc, magic.
pub(super) const FOOTER_AND_MAGIC_LEN: u64 = 9 + 20 + 8;

/// The footer from the last [`FOOTER_AND_MAGIC_LEN`] bytes of a file, if they are one.
pub(super) fn footer(tail: &[u8; FOOTER_AND_MAGIC_LEN as usize]) -> Option<Footer> {
    let (record, magic) = tail.split_at(29);
    if magic != mcap::MAGIC || record[0] != op::FOOTER || record[1..9] != 20u64.to_le_bytes() {
        return None;
    }
    let mut f = Fields::new("footer", &record[9..]);
    let summary_start = f.u64("summary_start").ok()?;
    f.u64("summary_offset_start").ok()?;
    let summary_crc = f.u32("summary_crc").ok()?;
    Some(Footer {
        summary_start,
        summary_crc,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn forged_string_lengths_are_errors_not_allocations() {
        // A channel whose topic claims u32::MAX bytes: an error naming the field, at once.
        let mut body = vec![1, 0, 0, 0];
        body.extend(u32::MAX.to_le_bytes());
        body.extend(b"/cam");
        let Err(err) = channel(&body) else {
            panic!("accepted")
        };
        assert_eq!(
            err.to_string(),
            "bad channel record: topic needs 4294967295 bytes at offset 8, the record has 4 left"
        );
        // A chunk whose compressed size is more than the record holds.
        let mut body = vec![0; 28];
        body.extend(0u32.to_le_bytes());
        body.extend((1u64 << 40).to_le_bytes());
        body.extend([0; 16]);
        let err = chunk(&body).err().unwrap().to_string();
        assert!(err.contains("records needs 1099511627776 bytes"), "{err}");
        // A map entry cut in half, and a duplicate key.
        let mut body = vec![7, 0, 1, 0];
        for s in ["/t", "cdr"] {
            body.extend((s.len() as u32).to_le_bytes());
            body.extend(s.as_bytes());
        }
        let mut cut = body.clone();
        cut.extend(6u32.to_le_bytes());
        cut.extend([1, 0, 0, 0, b'k', 0]);
        assert!(channel(&cut).is_err());
        let mut twice = body.clone();
        twice.extend(18u32.to_le_bytes());
        for _ in 0..2 {
            twice.extend([1, 0, 0, 0, b'k', 0, 0, 0, 0]);
        }
        let err = channel(&twice).err().unwrap().to_string();
        assert!(err.contains("metadata has a key twice"), "{err}");
        body.extend(0u32.to_le_bytes());
        let c = channel(&body).unwrap();
        assert_eq!((c.id, c.schema_id, c.topic.as_str()), (7, 1, "/t"));
    }
}
