//! Tests of the log reader: logs written by the `mcap` crate, then damaged.

use super::*;
use std::io::Cursor;

/// A log of `n` messages alternating between two topics, one message per chunk.
fn log(chunks: Option<Option<mcap::Compression>>, n: u32) -> Vec<u8> {
    let mut out = Cursor::new(Vec::new());
    let options = match chunks {
        Some(c) => mcap::WriteOptions::new()
            .compression(c)
            .chunk_size(Some(16)),
        None => mcap::WriteOptions::new().use_chunks(false),
    };
    let mut w = options.create(&mut out).unwrap();
    let schema = w.add_schema("s", "jsonschema", b"{}").unwrap();
    let a = w
        .add_channel(schema, "/a", "json", &BTreeMap::new())
        .unwrap();
    let b = w.add_channel(0, "/b", "raw", &BTreeMap::new()).unwrap();
    for i in 0..n {
        let header = mcap::records::MessageHeader {
            channel_id: if i % 2 == 0 { a } else { b },
            sequence: i,
            log_time: u64::from(i),
            publish_time: u64::from(i),
        };
        w.write_to_known_channel(&header, format!("message {i}").repeat(3).as_bytes())
            .unwrap();
    }
    w.finish().unwrap();
    drop(w);
    out.into_inner()
}

type Items = Vec<Result<(String, u64, Vec<u8>), Damage>>;

// A damage is rare and carries its error: its size does not matter.
#[allow(clippy::result_large_err)]
fn read(bytes: &[u8]) -> Items {
    LogReader::new(Cursor::new(bytes), bytes.len() as u64)
        .unwrap()
        .map(|r| r.map(|m| (m.channel.topic.clone(), m.log_time, m.data.into_owned())))
        .collect()
}

/// The top-level records `(offset, opcode, body length)` before the data end record.
fn top_level(bytes: &[u8]) -> Vec<(usize, u8, usize)> {
    let mut out = Vec::new();
    let mut at = 8;
    while bytes[at] != op::DATA_END {
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        out.push((at, bytes[at], len));
        at += 9 + len;
    }
    out
}

/// The log times of the messages in the chunk record at `at`.
fn chunk_message_times(bytes: &[u8], at: usize, len: usize) -> Vec<u64> {
    let limits = Limits::for_file(bytes.len() as u64);
    let records = decompress_chunk(&bytes[at + 9..at + 9 + len], &limits).unwrap();
    let mut times = Vec::new();
    let mut pos = 0;
    while pos < records.len() {
        let len = u64::from_le_bytes(records[pos + 1..pos + 9].try_into().unwrap()) as usize;
        if records[pos] == op::MESSAGE {
            let t = &records[pos + 9 + 6..pos + 9 + 14];
            times.push(u64::from_le_bytes(t.try_into().unwrap()));
        }
        pos += 9 + len;
    }
    times
}

const LAYOUTS: [Option<Option<mcap::Compression>>; 4] = [
    None,
    Some(None),
    Some(Some(mcap::Compression::Zstd)),
    Some(Some(mcap::Compression::Lz4)),
];

#[test]
fn reads_what_the_mcap_crate_reads() {
    for layout in LAYOUTS {
        let bytes = log(layout, 5);
        let expected: Vec<_> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                (m.channel.topic.clone(), m.log_time, m.data.into_owned())
            })
            .collect();
        let got: Vec<_> = read(&bytes).into_iter().map(Result::unwrap).collect();
        assert_eq!(got, expected, "{layout:?}");
        let reader = LogReader::new(Cursor::new(&bytes), bytes.len() as u64).unwrap();
        let summary = reader.summary().expect("intact summary");
        let topics: Vec<_> = summary.channels.values().map(|c| &c.topic).collect();
        assert_eq!(topics, ["/a", "/b"]);
        assert_eq!(
            summary
                .message_counts
                .as_ref()
                .unwrap()
                .values()
                .sum::<u64>(),
            5
        );
        let chunks = top_level(&bytes)
            .iter()
            .filter(|r| r.1 == op::CHUNK)
            .count();
        assert_eq!(summary.chunks.len(), chunks);
        assert!(layout.is_none() || chunks >= 5, "one chunk per message");
    }
}

#[test]
fn a_chunk_that_fails_its_crc_is_skipped_alone() {
    for layout in &LAYOUTS[1..] {
        let bytes = log(*layout, 5);
        let chunks: Vec<_> = top_level(&bytes)
            .into_iter()
            .filter(|r| r.1 == op::CHUNK)
            .collect();
        for (i, &(at, _, len)) in chunks.iter().enumerate() {
            let mut b = bytes.clone();
            // The last byte of the chunk's records.
            b[at + 9 + len - 1] ^= 1;
            let items = read(&b);
            let damage: Vec<_> = items.iter().filter_map(|r| r.as_ref().err()).collect();
            assert_eq!(damage.len(), 1, "{layout:?} chunk {i}: {items:?}");
            let d = damage[0];
            let n = chunks.len();
            assert_eq!(
                (d.offset, d.chunk, d.skipped),
                (at as u64, Some((i + 1, n)), Skipped::Chunk)
            );
            if layout.is_none() {
                assert!(matches!(d.error, McapIoError::ChunkCrc { .. }), "{d}");
                assert!(d.to_string().starts_with(&format!(
                    "chunk {} of {n} at byte {at}: chunk CRC mismatch (stored 0x",
                    i + 1
                )));
            }
            // The others are read, the channels of a lost chunk coming from the summary.
            let lost = chunk_message_times(&bytes, at, len);
            let times: Vec<u64> = items.iter().flatten().map(|m| m.1).collect();
            let expected: Vec<u64> = (0..5).filter(|t| !lost.contains(t)).collect();
            assert_eq!(times, expected, "{layout:?} chunk {i}");
        }
    }
}

#[test]
fn a_forged_length_skips_to_the_next_indexed_chunk_or_ends_the_log() {
    for layout in [None, Some(Some(mcap::Compression::Zstd))] {
        let bytes = log(layout, 5);
        let records = top_level(&bytes);
        for (n, &(at, opcode, len)) in records.iter().enumerate() {
            for forged in [1u64 << 32, 1 << 40, u64::MAX, 0] {
                let mut b = bytes.clone();
                b[at + 1..at + 9].copy_from_slice(&forged.to_le_bytes());
                let items = read(&b);
                let damage: Vec<_> = items.iter().filter_map(|r| r.as_ref().err()).collect();
                let messages = items.iter().filter(|r| r.is_ok()).count();
                if forged == 0 && opcode != op::MESSAGE && opcode != op::CHUNK {
                    continue;
                }
                assert!(!damage.is_empty(), "{layout:?} record {n} = {forged}");
                let skipped = damage[0].skipped;
                let before = records[..n].iter().filter(|r| r.1 == op::MESSAGE).count();
                match layout {
                    // A zero length leaves the record's body to be read as records.
                    _ if forged == 0 => {}
                    // Without a chunk index nothing after the damage can be found.
                    None => {
                        assert_eq!(skipped, Skipped::Rest);
                        assert_eq!(messages, before, "{layout:?} record {n}");
                    }
                    // With one, only the damaged record is lost.
                    Some(_) => {
                        let later_chunk = records[n + 1..].iter().any(|r| r.1 == op::CHUNK);
                        assert_eq!(
                            matches!(skipped, Skipped::UntilChunk(_)),
                            later_chunk,
                            "{layout:?} record {n}: {}",
                            damage[0]
                        );
                        let lost = match opcode {
                            op::CHUNK => chunk_message_times(&bytes, at, len).len(),
                            _ => 0,
                        };
                        assert_eq!(messages, 5 - lost, "{layout:?} record {n}");
                    }
                }
            }
        }
    }
}

#[test]
fn a_cut_off_log_is_read_up_to_the_cut() {
    let bytes = log(None, 4);
    let records = top_level(&bytes);
    let messages: Vec<_> = records.iter().filter(|r| r.1 == op::MESSAGE).collect();
    // The data end record follows the last record.
    let (last, _, last_len) = records.last().unwrap();
    let data_end = last + 9 + last_len + 9 + 4;
    for cut in 8..bytes.len() {
        let items = read(&bytes[..cut]);
        let read_messages = items.iter().filter(|r| r.is_ok()).count();
        let whole = messages.iter().filter(|r| r.0 + 9 + r.2 <= cut).count();
        assert_eq!(read_messages, whole, "cut at {cut}");
        if cut < data_end {
            let last = items.last().unwrap().as_ref().err();
            let d = last.unwrap_or_else(|| panic!("cut at {cut}: no damage"));
            assert_eq!(d.skipped, Skipped::Rest, "cut at {cut}");
        }
    }
    assert!(matches!(
        LogReader::new(Cursor::new(&bytes[..7]), 7),
        Err(McapIoError::NotMcap)
    ));
}

#[test]
fn a_damaged_summary_is_not_used() {
    let bytes = log(Some(Some(mcap::Compression::Zstd)), 3);
    let footer_at = bytes.len() - FOOTER_AND_MAGIC_LEN as usize;
    let summary_start =
        u64::from_le_bytes(bytes[footer_at + 9..footer_at + 17].try_into().unwrap()) as usize;
    assert!(summary_start > 8);
    let mut b = bytes.clone();
    // The last summary record's last byte (a summary offset's group length).
    b[footer_at - 1] ^= 1;
    let reader = LogReader::new(Cursor::new(&b), b.len() as u64).unwrap();
    assert!(reader.summary().is_none());
    let err = reader.summary_error().unwrap().to_string();
    assert!(err.starts_with("summary CRC mismatch"), "{err}");
    assert_eq!(reader.filter(Result::is_ok).count(), 3);
}

#[test]
fn flipped_bytes_anywhere_end_in_messages_or_damage() {
    // What a fuzzer does, in `cargo test`: every byte of two small logs flipped in turn.
    for layout in [None, Some(Some(mcap::Compression::Zstd))] {
        let bytes = log(layout, 3);
        for at in 0..bytes.len() {
            for mask in [0x01, 0x80, 0xff] {
                let mut b = bytes.clone();
                b[at] ^= mask;
                let Ok(reader) = LogReader::new(Cursor::new(&b), b.len() as u64) else {
                    assert!(at < 8, "only the magic makes a file not MCAP");
                    continue;
                };
                let items: Vec<_> = reader.take(100).collect();
                assert!(items.len() < 100, "byte {at}: runaway reader");
                for d in items.iter().filter_map(|r| r.as_ref().err()) {
                    assert!(!d.to_string().contains('\n'));
                }
            }
        }
    }
}

#[test]
fn limits_follow_the_file_size() {
    assert_eq!(Limits::for_file(1000).chunk_uncompressed, CHUNK_FLOOR);
    assert_eq!(
        Limits::for_file(10 << 20).chunk_uncompressed,
        CHUNK_RATIO * (10 << 20)
    );
    assert_eq!(Limits::for_file(u64::MAX).chunk_uncompressed, MAX_RECORD);
}
