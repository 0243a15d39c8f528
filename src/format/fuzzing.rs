//! Fuzz-target bodies, kept in the library so `cargo test` can replay the corpus and the
//! committed crashing inputs without cargo-fuzz.
//!
//! Random bytes almost never carry correct checksums, so a body that only opened its input
//! would test little past the index checksum. Each body therefore runs on the input as it is
//! and again with every checksum (and the header's `file_len`) fixed up ([`fix_checksums`]),
//! which reaches the table, metadata, content and decoding checks behind them. Fixing up in
//! the body, not in the target, keeps a crash reproducible by replaying its input file.

use super::layout::index_checksum;
use super::{slice, Catalog, Error, Map, RangeSource, SliceOptions, Wanted};
use std::ops::Range;

// The raw layout the fuzz crate and the tests craft maps with.
pub use super::layout::{
    align_up, checksum, Header, RawEntry, CHUNK_LEN, ENTRY_LEN, HEADER_LEN, METADATA_MAX_BYTES,
    NO_LEVEL, SECTION_REQUIRED,
};
pub use super::reader::{decode_budget, decode_cap};
pub use super::source::{COALESCE_GAP, HEAD_READ};

/// A [`RangeSource`] over bytes in memory: what a server holding them would answer.
pub struct BytesSource(pub Vec<u8>);

impl RangeSource for BytesSource {
    fn name(&self) -> &str {
        "memory"
    }
    fn len(&self) -> u64 {
        self.0.len() as u64
    }
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, Error> {
        Ok(self.0[range.start as usize..range.end as usize].to_vec())
    }
    fn read_sections(&self, _: u64, wanted: &[Wanted], _: bool) -> Result<Vec<Vec<u8>>, Error> {
        Ok(wanted
            .iter()
            .map(|w| self.0[w.range.start as usize..w.range.end as usize].to_vec())
            .collect())
    }
}

/// `data` with the header's `file_len` set to its length, every section checksum that covers
/// bytes inside `data` recomputed, and the index checksum recomputed; `data` unchanged when
/// it has no header or table to fix.
pub fn fix_checksums(data: &[u8]) -> Vec<u8> {
    let mut out = data.to_vec();
    let Ok(mut header) = Header::decode(data) else {
        return out;
    };
    let entry_len = header.entry_len as usize;
    let Some(table_end) = (header.section_count as usize)
        .checked_mul(entry_len)
        .and_then(|t| t.checked_add(HEADER_LEN))
        .filter(|&end| end <= out.len() && entry_len >= ENTRY_LEN)
    else {
        return out;
    };
    fix_chunk_checksums(&mut out, table_end, entry_len);
    for at in (HEADER_LEN..table_end).step_by(entry_len) {
        let mut entry = RawEntry::decode(&out[at..at + ENTRY_LEN]);
        if let Some(range) = stored_range(&entry, out.len()) {
            entry.checksum = checksum(&out[range]);
            out[at..at + ENTRY_LEN].copy_from_slice(&entry.encode());
        }
    }
    header.file_len = out.len() as u64;
    let metadata_end = (header.metadata_offset as usize)
        .checked_add(header.metadata_len as usize)
        .filter(|&end| end <= out.len() && header.metadata_offset as usize == table_end);
    if let Some(end) = metadata_end {
        header.index_checksum = index_checksum(
            &header.encode()[..56],
            &out[HEADER_LEN..table_end],
            &out[table_end..end],
        );
    }
    out[..HEADER_LEN].copy_from_slice(&header.encode());
    out
}

/// The bytes `entry` says it stores, if they lie within a file of `len` bytes.
fn stored_range(entry: &RawEntry, len: usize) -> Option<std::ops::Range<usize>> {
    (entry.offset as usize)
        .checked_add(entry.stored_len as usize)
        .filter(|&end| end <= len)
        .map(|end| entry.offset as usize..end)
}

/// (1.2) Rewrites the values of a `chunk_checksums` entry (the last of its kind) from the other
/// entries' stored bytes, when every entry's bytes lie inside `out` and it has room for
/// exactly their chunks; otherwise leaves `out` as it is.
fn fix_chunk_checksums(out: &mut [u8], table_end: usize, entry_len: usize) {
    let entries: Vec<RawEntry> = (HEADER_LEN..table_end)
        .step_by(entry_len)
        .map(|at| RawEntry::decode(&out[at..at + ENTRY_LEN]))
        .collect();
    let is_chunks = |e: &RawEntry| e.kind == super::layout::SectionKind::ChunkChecksums.code();
    let Some(chunks) = entries.iter().rev().find(|e| is_chunks(e)) else {
        return;
    };
    let stored: Option<Vec<&[u8]>> = entries
        .iter()
        .filter(|e| !is_chunks(e))
        .map(|e| stored_range(e, out.len()).map(|range| &out[range]))
        .collect();
    let Some(stored) = stored else {
        return;
    };
    let sums = super::chunks::chunk_checksums(stored);
    let start = chunks.offset as usize;
    if chunks.stored_len != sums.len() as u64 * 8 {
        return;
    }
    if let Some(target) = start
        .checked_add(sums.len() * 8)
        .and_then(|end| out.get_mut(start..end))
    {
        for (bytes, sum) in target.chunks_exact_mut(8).zip(&sums) {
            bytes.copy_from_slice(&sum.to_le_bytes());
        }
    }
}

/// `data` (a map whose header and table entries point inside it) with `metadata` as its
/// metadata block: every section moved to the offset the tiling rule gives it, checksums fixed.
/// `None` when `data` has no such header and table. Lets a fuzz target edit the metadata
/// (which changes its length) of a map the writer made.
pub fn with_metadata(data: &[u8], metadata: &[u8]) -> Option<Vec<u8>> {
    let mut header = Header::decode(data).ok()?;
    let entry_len = header.entry_len as usize;
    let table_end = (header.section_count as usize)
        .checked_mul(entry_len)?
        .checked_add(HEADER_LEN)
        .filter(|&end| end <= data.len() && entry_len >= ENTRY_LEN)?;
    let mut out = data[..table_end].to_vec();
    out.extend_from_slice(metadata);
    for at in (HEADER_LEN..table_end).step_by(entry_len) {
        let mut entry = RawEntry::decode(&data[at..at + ENTRY_LEN]);
        let start = entry.offset as usize;
        let stored = data.get(start..start.checked_add(entry.stored_len as usize)?)?;
        entry.offset = super::layout::align_up(out.len() as u64)?;
        out.resize(entry.offset as usize, 0);
        out.extend_from_slice(stored);
        out[at..at + ENTRY_LEN].copy_from_slice(&entry.encode());
    }
    header.metadata_offset = table_end as u64;
    header.metadata_len = metadata.len() as u64;
    out[..HEADER_LEN].copy_from_slice(&header.encode());
    Some(fix_checksums(&out))
}

/// Runs `body` on `data`, then on `data` with its checksums fixed up if that changes it.
fn as_is_and_fixed(data: &[u8], body: fn(&[u8])) {
    body(data);
    let fixed = fix_checksums(data);
    if fixed != data {
        body(&fixed);
    }
}

/// Open + validate, then touch every view. Must never panic.
pub fn open_and_read(data: &[u8]) {
    as_is_and_fixed(data, open_and_read_once);
}

fn open_and_read_once(data: &[u8]) {
    // Read by range, a map is valid exactly when it is in memory (by range, the padding
    // between sections is checked when they are fetched, so a bad one may open and then
    // fail to verify).
    let by_range = Map::open_source(Box::new(BytesSource(data.to_vec())));
    let Ok(map) = Map::from_bytes(data) else {
        if let Ok(m) = by_range {
            assert!(m.verify().is_err(), "valid by range, not in memory");
        }
        return;
    };
    read_by_chunk(data);
    let by_range = by_range.expect("opened in memory, not by range");
    let _ = by_range.prefetch(|s| s.index() % 2 == 0);
    assert_eq!(
        by_range.verify().is_ok(),
        map.verify().is_ok(),
        "verify by range and in memory disagree"
    );
    if let Ok(Some(catalog)) = Catalog::of(&map) {
        let _ = catalog.places().len();
    }
    let _ = map.point_positions();
    let _ = map.point_colors();
    let _ = map.point_ids();
    if let Ok(Some(images)) = map.images() {
        for i in 0..images.len() {
            let _ = images.name(i);
        }
    }
    let _ = map.image_global();
    let _ = map.vlad();
    if let Ok(Some(index)) = map.image_index() {
        // Checked on access: every list is a range of the images.
        for l in 0..index.lists() {
            let _ = index.list(l);
        }
        // (1.4) A search along the neighbours from image 0, each image scored by its index
        // (any order a hostile graph makes): ends, scoring each image at most once.
        if let Some(neighbours) = &index.neighbours {
            let n = index.images.len();
            let mut scored = vec![(0u32, 0.0f32)];
            neighbours.widen(&mut scored, n, 4, |picks| {
                picks.iter().map(|&i| (i % 7) as f32).collect()
            });
            let mut seen: bitvec::vec::BitVec = bitvec::vec::BitVec::repeat(false, n.max(1));
            for &(i, _) in &scored {
                assert!(!seen.replace(i as usize, true), "image {i} scored twice");
            }
        }
    }
    if let Ok(Some(vis)) = map.visibility() {
        for i in 0..vis.offsets.len().saturating_sub(1) {
            let _ = vis.points_of(i);
            let _ = vis.keypoints_of(i);
        }
    }
    for level in map.levels() {
        let _ = level.points();
        let _ = level.desc_short();
        let _ = level.desc_rest();
        let _ = level.projection();
    }
    let _ = map.verify();
    assert!(
        map.decoded_bytes() <= map.decode_budget(),
        "decoded past the budget"
    );
}

/// (1.2) Reads a fresh open of `data` by chunk, as the localizer does (rows, then all of it),
/// before anything is checked whole; then verify must agree: a map that verifies has no chunk
/// a view refuses.
fn read_by_chunk(data: &[u8]) {
    let Ok(map) = Map::from_bytes(data) else {
        return;
    };
    let mut by_chunk = Vec::new();
    for level in map.levels() {
        if let Ok(short) = level.desc_short_by_chunk() {
            let row = level.dim_short().max(1);
            let rows = short.len() / row;
            let _ = short.check_rows((0..rows).step_by(7), row);
            by_chunk.push(short.check_all());
        }
        if let Ok(Some(rest)) = level.desc_rest_by_chunk() {
            by_chunk.push(rest.check_all());
        }
    }
    if let Ok(Some(vis)) = map.visibility_by_chunk() {
        let listed =
            (0..vis.offsets.len().saturating_sub(1)).try_for_each(|i| vis.points_of(i).map(|_| ()));
        by_chunk.push(listed);
    }
    if map.verify().is_ok() {
        assert!(
            by_chunk.iter().all(Result::is_ok),
            "verified, yet a chunk fails: {by_chunk:?}"
        );
    }
}

/// Decode every section directly (raw and zstd paths), in table order; then verify, which
/// must not decode again what is already decoded.
pub fn decode_sections(data: &[u8]) {
    as_is_and_fixed(data, decode_sections_once);
}

fn decode_sections_once(data: &[u8]) {
    let Ok(map) = Map::from_bytes(data) else {
        return;
    };
    for section in map.sections() {
        let _ = map.section_bytes(section);
    }
    let decoded = map.decoded_bytes();
    let _ = map.verify();
    assert_eq!(
        map.decoded_bytes(),
        decoded,
        "verify decoded a kept section again"
    );
}

/// Slice in memory to each single level (short and full) and re-open the result.
pub fn slice_in_memory(data: &[u8]) {
    as_is_and_fixed(data, slice_in_memory_once);
}

fn slice_in_memory_once(data: &[u8]) {
    let Ok(map) = Map::from_bytes(data) else {
        return;
    };
    let levels = map.level_ids();
    for (i, &level) in levels.iter().enumerate().take(4) {
        let options = SliceOptions {
            levels: vec![level],
            short: i % 2 == 0,
            codec: None,
            zstd_level: 1,
            // Every other pair of levels: --minimal (grid positions, sorted visibility).
            minimal: i / 2 % 2 == 1 || levels.len() == 1,
        };
        if let Ok((writer, _)) = slice(&map, &options) {
            let bytes = writer
                .to_bytes()
                .expect("slicing a verified map gives valid input");
            Map::from_bytes(&bytes)
                .and_then(|m| m.verify())
                .expect("a slice of a readable map must be valid");
        }
    }
}

/// The structure-aware target's checks on a map it built: every body above.
pub fn all_format_bodies(map: &[u8]) {
    open_and_read_once(map);
    decode_sections_once(map);
    slice_in_memory_once(map);
}
