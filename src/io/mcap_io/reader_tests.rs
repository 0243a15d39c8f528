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
    let records = decompress_chunk(&bytes[at + 9..at + 9 + len], &limits, &mut 0).unwrap();
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

/// A chunk record (opcode, length, body) holding `records` uncompressed, without a CRC.
fn raw_chunk(records: &[u8]) -> Vec<u8> {
    chunk_record(records, records.len() as u64, "")
}

/// A chunk record of `stored` records bytes, compressed with `compression`, that decompress to
/// `uncompressed` bytes; no CRC.
fn chunk_record(stored: &[u8], uncompressed: u64, compression: &str) -> Vec<u8> {
    let mut body = Vec::new();
    body.extend_from_slice(&0u64.to_le_bytes()); // message_start_time
    body.extend_from_slice(&0u64.to_le_bytes()); // message_end_time
    body.extend_from_slice(&uncompressed.to_le_bytes());
    body.extend_from_slice(&0u32.to_le_bytes()); // no CRC
    body.extend_from_slice(&(compression.len() as u32).to_le_bytes());
    body.extend_from_slice(compression.as_bytes());
    body.extend_from_slice(&(stored.len() as u64).to_le_bytes());
    body.extend_from_slice(stored);
    let mut out = vec![op::CHUNK];
    out.extend_from_slice(&(body.len() as u64).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

/// The items of a log that holds no readable message, as their messages.
fn only_damage(bytes: &[u8]) -> Vec<String> {
    read(bytes)
        .iter()
        .map(|r| r.as_ref().expect_err("no message is readable").to_string())
        .collect()
}

/// A message record on `channel` with no data.
fn message_record(channel: u16) -> Vec<u8> {
    let mut body = channel.to_le_bytes().to_vec();
    body.extend_from_slice(&[0; 4 + 8 + 8]);
    let mut out = vec![op::MESSAGE];
    out.extend_from_slice(&(body.len() as u64).to_le_bytes());
    out.extend_from_slice(&body);
    out
}

#[test]
fn a_chunk_of_bad_records_is_two_damage_items_not_one_per_record() {
    // 10,000 messages on a channel no record defines: a 28 KB log had cost one item (and a
    // string in --json) per record.
    let records: Vec<u8> = (0..10_000).flat_map(|_| message_record(7)).collect();
    let mut bytes = mcap::MAGIC.to_vec();
    bytes.extend_from_slice(&raw_chunk(&records));
    bytes.extend_from_slice(&raw_chunk(&message_record(8)));
    let damage = only_damage(&bytes);
    // Per chunk: the first bad record, then how many more; then the missing footer.
    assert_eq!(damage.len(), 4, "{damage:#?}");
    assert!(damage[0].ends_with("record skipped"), "{}", damage[0]);
    assert!(damage[0].contains("channel 7"), "{}", damage[0]);
    assert!(
        damage[1].ends_with("9999 more records of this chunk skipped"),
        "{}",
        damage[1]
    );
    assert!(damage[2].contains("channel 8"), "{}", damage[2]);
    assert!(damage[3].contains("cut off"), "{}", damage[3]);
}

#[test]
fn all_chunks_of_a_log_share_one_decompression_budget() {
    let limits = Limits {
        file_len: 1000,
        chunk_uncompressed: 1000,
        log_uncompressed: 2500,
    };
    let records = vec![0u8; 1000];
    let body = {
        let chunk = raw_chunk(&records);
        chunk[1 + 8..].to_vec()
    };
    let mut spent = 0;
    for _ in 0..2 {
        assert_eq!(
            decompress_chunk(&body, &limits, &mut spent).unwrap().len(),
            1000
        );
    }
    let e = decompress_chunk(&body, &limits, &mut spent).unwrap_err();
    assert!(
        matches!(e, McapIoError::LogBudgetSpent { spent: 2000, .. }),
        "{e}"
    );
    assert_eq!(spent, 2000, "a refused chunk is not charged");
    // From the file size: 64 x the file, at least 64 MiB, and not capped at 1 GiB like a chunk.
    assert_eq!(Limits::for_file(1000).log_uncompressed, CHUNK_FLOOR);
    assert_eq!(
        Limits::for_file(1 << 30).log_uncompressed,
        CHUNK_RATIO << 30
    );
}

#[test]
fn bad_records_before_a_cut_in_the_chunk_are_still_counted() {
    let mut records: Vec<u8> = (0..5).flat_map(|_| message_record(7)).collect();
    records.extend_from_slice(&[op::MESSAGE, 1, 2]); // a record header cut short
    let mut bytes = mcap::MAGIC.to_vec();
    bytes.extend_from_slice(&raw_chunk(&records));
    let damage = only_damage(&bytes);
    assert_eq!(damage.len(), 4, "{damage:#?}");
    assert!(damage[0].ends_with("record skipped"), "{}", damage[0]);
    assert!(
        damage[1].ends_with("4 more records of this chunk skipped"),
        "{}",
        damage[1]
    );
    assert!(damage[2].contains("record header"), "{}", damage[2]);
    assert!(damage[2].ends_with("chunk skipped"), "{}", damage[2]);
    assert!(damage[3].contains("cut off"), "{}", damage[3]);
}

#[test]
fn a_log_whose_chunks_decompress_past_its_budget_is_read_up_to_it() {
    // Each chunk: one record of an opcode nobody reads, 40 MiB of zeros, a few KB stored. Two
    // of them pass 64 MiB, the budget of a file this small.
    let size = 40u64 << 20;
    let mut records = vec![0u8; size as usize];
    records[0] = 0x80;
    records[1..9].copy_from_slice(&(size - 9).to_le_bytes());
    let stored = zstd::bulk::compress(&records, 1).unwrap();
    let mut bytes = mcap::MAGIC.to_vec();
    for _ in 0..3 {
        bytes.extend_from_slice(&chunk_record(&stored, size, "zstd"));
    }
    assert!(bytes.len() < 1 << 20);
    let damage = only_damage(&bytes);
    // Chunk 1 is read; chunks 2 and 3 are over the budget; then the missing footer.
    assert_eq!(damage.len(), 3, "{damage:#?}");
    for d in &damage[..2] {
        assert!(d.contains("the chunks before it took 41943040"), "{d}");
        assert!(d.ends_with("chunk skipped"), "{d}");
    }
}

#[test]
fn an_attachment_past_the_record_limit_is_skipped_not_the_end_of_the_log() {
    // A 1.5 GiB attachment (a sparse file: no disk), then a channel and a message on it.
    fn record(opcode: u8, body: &[u8]) -> Vec<u8> {
        let mut out = vec![opcode];
        out.extend_from_slice(&(body.len() as u64).to_le_bytes());
        out.extend_from_slice(body);
        out
    }
    let mut channel = 1u16.to_le_bytes().to_vec();
    channel.extend_from_slice(&0u16.to_le_bytes()); // no schema
    for s in ["/a", "raw"] {
        channel.extend_from_slice(&(s.len() as u32).to_le_bytes());
        channel.extend_from_slice(s.as_bytes());
    }
    channel.extend_from_slice(&0u32.to_le_bytes()); // no metadata
    let attachment_len = MAX_RECORD + (MAX_RECORD >> 1);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("attached.mcap");
    {
        use std::io::Write as _;
        let mut f = std::fs::File::create(&path).unwrap();
        f.write_all(mcap::MAGIC).unwrap();
        f.write_all(&[op::ATTACHMENT]).unwrap();
        f.write_all(&attachment_len.to_le_bytes()).unwrap();
        f.seek(SeekFrom::Current(attachment_len as i64)).unwrap();
        f.write_all(&record(op::CHANNEL, &channel)).unwrap();
        f.write_all(&message_record(1)).unwrap();
    }
    let items: Vec<_> = LogReader::open(&path).unwrap().collect();
    assert_eq!(items.len(), 2, "{items:#?}");
    assert_eq!(items[0].as_ref().unwrap().channel.topic, "/a");
    assert!(items[1]
        .as_ref()
        .unwrap_err()
        .to_string()
        .contains("cut off"));
}

#[test]
fn only_the_wanted_topic_s_payloads_are_handed_out() {
    let bytes = log(Some(Some(mcap::Compression::Zstd)), 6);
    let all = read(&bytes);
    let only_a: Vec<_> = LogReader::new(Cursor::new(&bytes), bytes.len() as u64)
        .unwrap()
        .data_of("/a")
        .map(|r| r.unwrap())
        .collect();
    assert_eq!(only_a.len(), all.len());
    for (m, (topic, time, data)) in only_a.iter().zip(all.iter().map(|r| r.as_ref().unwrap())) {
        assert_eq!((&m.channel.topic, m.log_time), (topic, *time));
        if topic == "/a" {
            assert_eq!(&m.data[..], &data[..]);
        } else {
            assert!(m.data.is_empty(), "{topic} at {time}");
        }
    }
}
