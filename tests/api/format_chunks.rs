//! (1.2) Chunk checksums: written for maps with a section of more than one chunk, checked a
//! chunk at a time where a reader reads (`Map::by_chunk`), and by `verify` chunk by chunk too.
#![cfg(feature = "fuzzing")]

use sfpmap::format::{
    slice, Codec, Descriptors, Error, LevelInfo, Map, MapWriter, SectionKind, SliceOptions,
};
use sfpmap::fuzzing::{checksum, CHUNK_LEN, ENTRY_LEN, HEADER_LEN};

/// Points on a line, one level holding all of them (8 full, 2 short dims), one image seeing
/// every point: positions 240 KB, the blocks 80 and 240 KB, visibility 80 KB for 20,000.
fn map(n: u32) -> Vec<u8> {
    let positions: Vec<[f64; 3]> = (0..n).map(|i| [f64::from(i), 0.0, 1.0]).collect();
    let points: Vec<u32> = (0..n).collect();
    // Pseudo-random values: the blocks stay over a chunk compressed too.
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let descriptors: Vec<f32> = (0..n * 8)
        .map(|_| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
            (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        })
        .collect();
    let names = ["db0.jpg"];
    let cams = [0u32];
    let poses = [[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]];
    let offsets = [0u64, u64::from(n)];
    let mut w = MapWriter::default();
    w.add_camera(sfpmap::format::CameraInfo {
        id: Some(1),
        model: "PINHOLE".into(),
        width: 640,
        height: 480,
        params: vec![500.0, 500.0, 320.0, 240.0],
    });
    w.set_points_world(&positions);
    w.set_images(&names, &cams, &poses, None).unwrap();
    w.set_visibility(&offsets, &points, None).unwrap();
    let info = LevelInfo {
        level: 0,
        stride: 4.0,
        descriptor: "test".into(),
        dim_full: 8,
        dim_short: 2,
        normalization: "l2".into(),
        extra: Default::default(),
    };
    w.add_level(info, &points, Some(Descriptors::F32(&descriptors)), true)
        .unwrap();
    w.to_bytes().unwrap()
}

fn section(map: &Map<'_>, kind: SectionKind, level: Option<u16>) -> sfpmap::format::Section {
    *map.find(kind, level).unwrap()
}

/// `bytes` with the byte at `at` changed, and the section it is in given a matching whole
/// checksum and index checksum: only the chunk checksum can tell.
fn damaged_chunk(bytes: &[u8], at: usize, value: u8) -> Vec<u8> {
    let mut out = bytes.to_vec();
    out[at] = value;
    let map = Map::from_bytes(bytes).unwrap();
    let s = map
        .sections()
        .iter()
        .find(|s| (s.offset() as usize..(s.offset() + s.stored_len()) as usize).contains(&at))
        .copied()
        .unwrap();
    let whole = checksum(&out[s.offset() as usize..(s.offset() + s.stored_len()) as usize]);
    // The entry's `checksum` field (bytes 48..56).
    let entry = HEADER_LEN + s.index() * ENTRY_LEN;
    out[entry + 48..entry + 56].copy_from_slice(&whole.to_le_bytes());
    // The index checksum: header bytes 0..56, the table, the metadata.
    let field = |at: usize| u64::from_le_bytes(out[at..at + 8].try_into().unwrap()) as usize;
    let metadata_end = field(32) + field(40);
    let mut index = out[..56].to_vec();
    index.extend_from_slice(&out[HEADER_LEN..metadata_end]);
    let sum = checksum(&index);
    out[56..64].copy_from_slice(&sum.to_le_bytes());
    out
}

#[test]
fn a_map_with_a_section_over_one_chunk_carries_chunk_checksums_and_a_small_one_does_not() {
    let big = map(20_000);
    let m = Map::from_bytes(&big).unwrap();
    assert_eq!(m.version(), "1.2");
    let chunks = section(&m, SectionKind::ChunkChecksums, None);
    assert_eq!(chunks.index(), m.sections().len() - 1, "written last");
    assert!(!chunks.required());
    let expected: u64 = m
        .sections()
        .iter()
        .filter(|s| s.kind() != SectionKind::ChunkChecksums)
        .map(|s| s.stored_len().div_ceil(CHUNK_LEN))
        .sum();
    assert_eq!(chunks.rows(), expected);
    assert!(
        expected > m.sections().len() as u64,
        "some section spans chunks"
    );
    // Read by chunk before anything is checked whole: only the chunks asked for are checked,
    // and the values are the stored ones.
    let level = m.level(0).unwrap();
    let rest = level.desc_rest_by_chunk().unwrap().unwrap();
    let per_chunk = (CHUNK_LEN / 2) as usize;
    assert!(!rest.is_checked(0..1));
    assert_eq!(rest.get(3..9).unwrap().len(), 6);
    assert!(rest.is_checked(0..per_chunk) && !rest.is_checked(per_chunk..per_chunk + 1));
    // A row straddling the first chunk boundary checks both chunks, and no other.
    rest.check_rows([per_chunk / 6], 6).unwrap();
    assert!(rest.is_checked(0..2 * per_chunk));
    assert!(!rest.is_checked(2 * per_chunk..2 * per_chunk + 1));
    let all = rest.get(0..rest.len()).unwrap().to_vec();
    assert_eq!(all, &level.desc_rest().unwrap().unwrap()[..]);
    m.verify().unwrap();
    // Checked whole first, a view checks no chunk: every range is checked already.
    let fresh = Map::from_bytes(&big).unwrap();
    fresh.verify().unwrap();
    let short = fresh.level(0).unwrap().desc_short_by_chunk().unwrap();
    assert!(short.is_checked(0..short.len()));
    // Values of another size than the section's dtype are refused.
    let section = *fresh.find(SectionKind::LevelDescShort, Some(0)).unwrap();
    assert_eq!(
        fresh.by_chunk::<u32>(&section).unwrap_err().kind_name(),
        "invalid_input"
    );

    let small = map(100);
    let m = Map::from_bytes(&small).unwrap();
    assert!(m.find(SectionKind::ChunkChecksums, None).is_none());
    assert_eq!(m.version(), "1.0");
}

#[test]
fn a_damaged_chunk_fails_where_it_is_read_and_in_verify_only() {
    let good = map(20_000);
    let m = Map::from_bytes(&good).unwrap();
    let rest = section(&m, SectionKind::LevelDescRest, Some(0));
    assert!(rest.stored_len() > 3 * CHUNK_LEN);
    // A byte of the rest block's second chunk.
    let at = (rest.offset() + CHUNK_LEN + 10) as usize;
    let bad = damaged_chunk(&good, at, good[at] ^ 0x40);
    let m = Map::from_bytes(&bad).unwrap();
    let level = m.level(0).unwrap();
    let block = level.desc_rest_by_chunk().unwrap().unwrap();
    let per_chunk = (CHUNK_LEN / 2) as usize;
    // The first and third chunks read; the second fails, every time it is asked for.
    block.check(0..per_chunk).unwrap();
    block.check(2 * per_chunk..3 * per_chunk).unwrap();
    for _ in 0..2 {
        let err = block.check(per_chunk + 5..per_chunk + 6).unwrap_err();
        assert!(
            matches!(err, Error::ChunkChecksumMismatch { chunk: 1, .. }),
            "{err}"
        );
        assert_eq!(err.kind_name(), "checksum_mismatch");
        let text = err.to_string();
        assert!(
            text.contains("level_desc_rest") && text.contains("bytes 65536 to 131072"),
            "{text}"
        );
    }
    // Rows spanning chunks 0..=2 ask for the damaged one.
    assert!(block
        .check_rows([0, per_chunk / 6 + 1, 2 * per_chunk / 6], 6)
        .is_err());
    // The whole section's own checksum matches (the damage is only in the chunk sums'
    // view): verify walks every chunk and finds it.
    assert!(matches!(
        m.verify(),
        Err(Error::ChunkChecksumMismatch { .. })
    ));
}

#[test]
fn a_visibility_chunk_holding_an_index_past_the_points_is_refused_when_read() {
    let good = map(20_000);
    let m = Map::from_bytes(&good).unwrap();
    let vis = section(&m, SectionKind::VisibilityPoints, None);
    assert!(vis.stored_len() > CHUNK_LEN);
    let mut bad = good.clone();
    let at = (vis.offset() + CHUNK_LEN + 8) as usize;
    bad[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    // Every checksum fixed: only the contents rule can tell.
    let bad = sfpmap::fuzzing::fix_checksums(&bad);
    let m = Map::from_bytes(&bad).unwrap();
    let v = m.visibility_by_chunk().unwrap().unwrap();
    let err = v.points_of(0).unwrap_err();
    assert_eq!(err.kind_name(), "inconsistent", "{err}");
    assert!(err.to_string().contains("out of range"), "{err}");
    assert!(m.verify().is_err());
}

#[test]
fn a_wrong_chunk_count_is_refused_at_open() {
    let good = map(20_000);
    let m = Map::from_bytes(&good).unwrap();
    let chunks = section(&m, SectionKind::ChunkChecksums, None);
    // One chunk sum more than the sections have: the entry and file grow by 8 bytes.
    let mut bad = good.clone();
    bad.extend_from_slice(&[0; 8]);
    let entry = 64 + chunks.index() * 64;
    for (field, add) in [(8usize, 1u64), (32, 8), (40, 8)] {
        let v = u64::from_le_bytes(bad[entry + field..entry + field + 8].try_into().unwrap());
        bad[entry + field..entry + field + 8].copy_from_slice(&(v + add).to_le_bytes());
    }
    let len = bad.len() as u64;
    bad[48..56].copy_from_slice(&len.to_le_bytes());
    let bad = sfpmap::fuzzing::fix_checksums(&bad);
    let err = Map::from_bytes(&bad).unwrap_err();
    assert_eq!(err.kind_name(), "inconsistent", "{err}");
    assert!(err.to_string().contains("chunk_checksums"), "{err}");
}

/// A slice stores visibility delta-coded (`--minimal`) or zstd: such sections are checked by
/// chunk in `verify` (their stored bytes against the chunk sums) and whole for their contents,
/// never by the contents rules on compressed bytes; read by chunk, they are checked whole.
#[test]
fn compressed_sections_of_a_chunked_map_verify_and_read() {
    let good = map(20_000);
    let m = Map::from_bytes(&good).unwrap();
    for (minimal, codec) in [(true, None), (false, Some(Codec::Zstd))] {
        let options = SliceOptions {
            levels: vec![0],
            short: false,
            codec,
            zstd_level: 1,
            minimal,
        };
        let bytes = slice(&m, &options).unwrap().0.to_bytes().unwrap();
        let sliced = Map::from_bytes(&bytes).unwrap();
        assert!(sliced.find(SectionKind::ChunkChecksums, None).is_some());
        let vis = *sliced.find(SectionKind::VisibilityPoints, None).unwrap();
        assert_ne!(
            vis.codec(),
            Codec::Raw,
            "minimal {minimal}, codec {codec:?}"
        );
        let v = sliced.visibility_by_chunk().unwrap().unwrap();
        assert_eq!(v.points_of(0).unwrap().len(), 20_000);
        sliced.verify().unwrap();
        Map::from_bytes(&bytes).unwrap().verify().unwrap();
    }
}
