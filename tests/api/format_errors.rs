//! One test per `format::Error` variant, each from hand-made bytes.

use crate::common;

use common::{level_info, minimal, patch, with_extra_section, Scene};
use sfpmap::format::{Codec, Dtype, Error, Map, MapWriter, SectionKind, Skipped};
use sfpmap::fuzzing::{checksum, RawEntry, HEADER_LEN, METADATA_MAX_BYTES, NO_LEVEL};
use std::borrow::Cow;

fn open_err(bytes: &[u8]) -> Error {
    Map::from_bytes(bytes).expect_err("must not open")
}

fn verify_err(bytes: &[u8]) -> Error {
    let map = Map::from_bytes(bytes).expect("opens");
    map.verify().expect_err("must not verify")
}

fn levels_map(codec: Codec) -> Vec<u8> {
    Scene::new(3, 12, 2, &[(0, 8.0, 8, 4), (2, 4.0, 4, 2)])
        .writer(codec)
        .to_bytes()
        .unwrap()
}

#[test]
fn io() {
    let err = Map::open("/nonexistent/dir/x.sfpm").unwrap_err();
    assert!(matches!(err, Error::Io { .. }));
    assert!(err.to_string().contains("/nonexistent/dir/x.sfpm"), "{err}");
}

#[test]
fn bad_magic() {
    let mut b = minimal();
    b[0] = 0;
    assert!(matches!(open_err(&b), Error::BadMagic));
    assert!(matches!(open_err(b"hello"), Error::BadMagic));
}

#[test]
fn version_mismatch() {
    let mut b = minimal();
    b[8] = 9;
    assert!(matches!(
        open_err(&b),
        Error::VersionMismatch {
            expected: 1,
            found: 9,
            ..
        }
    ));
}

#[test]
fn bad_endian_check() {
    let mut b = minimal();
    b[12..16].copy_from_slice(&0x1A2B_3C4Du32.to_be_bytes());
    assert!(matches!(open_err(&b), Error::BadEndianCheck { .. }));
}

#[test]
fn truncated() {
    let b = minimal();
    assert!(matches!(
        open_err(&b[..b.len() - 1]),
        Error::Truncated { what: "file", .. }
    ));
    assert!(matches!(
        open_err(&b[..20]),
        Error::Truncated { what: "header", .. }
    ));
    let huge_table = patch(&b, |h, _| h.file_len = 1 << 40);
    assert!(matches!(open_err(&huge_table), Error::Truncated { .. }));
}

#[test]
fn trailing_bytes() {
    let mut b = minimal();
    b.extend_from_slice(&[0; 64]);
    assert!(matches!(open_err(&b), Error::TrailingBytes { .. }));
    // The header's file_len agrees, but the last section ends before it.
    let mut b = minimal();
    let n = b.len() as u64;
    b.extend_from_slice(&[0; 64]);
    let b = patch(&b, |h, _| h.file_len = n + 64);
    assert!(matches!(open_err(&b), Error::TrailingBytes { .. }));
}

#[test]
fn bad_index() {
    let b = minimal();
    assert!(matches!(
        open_err(&patch(&b, |h, _| h.entry_len = 32)),
        Error::BadIndex { .. }
    ));
    assert!(matches!(
        open_err(&patch(&b, |h, _| h.metadata_offset += 8)),
        Error::BadIndex { .. }
    ));
    // The last section moved 64 bytes on into a file 64 bytes longer: in bounds, but a
    // gap larger than the alignment padding.
    let b = levels_map(Codec::Raw);
    let mut longer = b.clone();
    longer.extend_from_slice(&[0; 64]);
    let gap = patch(&longer, |h, e| {
        let last = e.len() - 1;
        e[last].offset += 64;
        h.file_len += 64;
    });
    assert!(
        matches!(open_err(&gap), Error::BadIndex { what } if what.contains("gap")),
        "{:?}",
        open_err(&gap)
    );
    let two = patch(&b, |h, _| h.section_count = 1 << 20);
    assert!(matches!(open_err(&two), Error::BadIndex { .. }));
}

#[test]
fn index_checksum_mismatch() {
    let mut b = minimal();
    let meta_at = HEADER_LEN + 64 + 2; // inside the metadata JSON
    b[meta_at] ^= 0x20;
    assert!(matches!(open_err(&b), Error::IndexChecksumMismatch { .. }));
}

#[test]
fn metadata_too_large() {
    let b = patch(&minimal(), |h, _| h.metadata_len = METADATA_MAX_BYTES + 1);
    assert!(matches!(open_err(&b), Error::MetadataTooLarge { .. }));
}

#[test]
fn bad_metadata() {
    let mut w = MapWriter::default();
    w.metadata_mut().format = "not-sfpmap".into();
    w.set_points_world(&[[0.0; 3]]);
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::BadMetadata { .. }
    ));
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    w.metadata_mut().levels.push(level_info(1, 4.0, 4, 8));
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::BadMetadata { .. }
    ));
}

#[test]
fn bad_entry() {
    let b = minimal();
    assert!(matches!(
        open_err(&patch(&b, |_, e| e[0].dtype = 99)),
        Error::BadEntry { .. }
    ));
    assert!(matches!(
        open_err(&patch(&b, |_, e| e[0].codec = 7)),
        Error::BadEntry { .. }
    ));
    assert!(matches!(
        open_err(&patch(&b, |_, e| e[0].reserved = 1)),
        Error::BadEntry { .. }
    ));
    assert!(matches!(
        open_err(&patch(&b, |_, e| e[0].flags |= 0x80)),
        Error::BadEntry { .. }
    ));
    assert!(matches!(
        open_err(&patch(&b, |_, e| e[0].level = 3)),
        Error::BadEntry { .. }
    ));
}

#[test]
fn size_mismatch() {
    let b = minimal();
    let overflow = patch(&b, |_, e| {
        e[0].rows = u64::MAX / 3;
        e[0].cols = 3;
    });
    assert!(matches!(open_err(&overflow), Error::SizeMismatch { .. }));
    assert!(matches!(
        open_err(&patch(&b, |_, e| e[0].rows = 3)),
        Error::SizeMismatch { .. }
    ));
}

#[test]
fn wrong_layout() {
    let mut w = MapWriter::default();
    let xyz: Vec<f64> = vec![0.0; 6];
    w.add_raw_section(
        SectionKind::PointPositions,
        NO_LEVEL,
        Dtype::F64,
        2,
        3,
        true,
        Cow::Owned(bytemuck::cast_slice(&xyz).to_vec()),
        None,
    )
    .unwrap();
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::WrongLayout { .. }
    ));
}

#[test]
fn section_out_of_bounds() {
    let b = minimal();
    let far = patch(&b, |_, e| e[0].offset = 1 << 20);
    assert!(matches!(open_err(&far), Error::SectionOutOfBounds { .. }));
    let wrap = patch(&b, |_, e| e[0].offset = !63);
    assert!(matches!(open_err(&wrap), Error::SectionOutOfBounds { .. }));
}

#[test]
fn misaligned() {
    let b = patch(&minimal(), |_, e| e[0].offset += 8);
    assert!(matches!(open_err(&b), Error::Misaligned { .. }));
}

#[test]
fn overlap() {
    let b = levels_map(Codec::Raw);
    let b = patch(&b, |_, e| e[1].offset = e[0].offset);
    assert!(matches!(open_err(&b), Error::Overlap { .. }));
}

#[test]
fn bad_padding() {
    let b = minimal();
    let map = Map::from_bytes(&b).unwrap();
    let at = map.sections()[0].offset() as usize - 1;
    let mut b = b.clone();
    b[at] = 1;
    assert!(matches!(open_err(&b), Error::BadPadding { .. }));
}

#[test]
fn unknown_required_section() {
    let b = with_extra_section(SectionKind::Unknown(0x7000), NO_LEVEL, true, None);
    assert!(matches!(open_err(&b), Error::UnknownRequiredSection { .. }));
    // The same section marked optional is skipped and listed.
    let b = with_extra_section(SectionKind::Unknown(0x7000), NO_LEVEL, false, None);
    let map = Map::from_bytes(&b).unwrap();
    assert_eq!(map.skipped_sections().count(), 1);
    map.verify().unwrap();
}

/// 1.1: an optional section this reader cannot decode (dtype, codec or flag bit of a later
/// minor) is skipped and listed, also when its kind is known; a required one is refused.
#[test]
fn optional_sections_with_unknown_encodings_are_skipped() {
    let colors = [[1u8, 2, 3], [4, 5, 6]];
    let mut w = MapWriter::default();
    w.set_points_world(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    w.add_raw_section(
        SectionKind::PointColors,
        NO_LEVEL,
        Dtype::U8,
        2,
        3,
        false,
        Cow::Owned(colors.concat()),
        None,
    )
    .unwrap();
    let b = w.to_bytes().unwrap();
    assert!(Map::from_bytes(&b)
        .unwrap()
        .point_colors()
        .unwrap()
        .is_some());
    let at = |b: &[u8]| {
        let map = Map::from_bytes(b).unwrap();
        map.sections()
            .iter()
            .position(|s| s.kind() == SectionKind::PointColors)
            .unwrap()
    };
    let i = at(&b);
    type Edit = fn(&mut RawEntry);
    let edits: [(Edit, Skipped); 3] = [
        (|e| e.dtype = 9, Skipped::Dtype(9)),
        (|e| e.codec = 3, Skipped::Codec(3)),
        (|e| e.flags |= 0x40, Skipped::Flags(0x40)),
    ];
    for (edit, why) in edits {
        let skipped = patch(&b, |_, e| edit(&mut e[i]));
        let map = Map::from_bytes(&skipped).unwrap();
        let listed: Vec<_> = map.skipped_sections().map(|s| s.skipped()).collect();
        assert_eq!(listed, [Some(why)]);
        // Skipped is absent: the colours are gone, the rest of the map reads.
        assert!(map.point_colors().unwrap().is_none());
        assert_eq!(map.point_positions().unwrap().len(), 2);
        let section = &map.sections()[i];
        assert!(map.section_bytes(section).is_err());
        map.verify().unwrap();
        // Its checksum is still checked.
        let mut flipped = skipped.clone();
        flipped[section.offset() as usize] ^= 1;
        assert!(matches!(
            Map::from_bytes(&flipped).unwrap().verify(),
            Err(Error::ChecksumMismatch { .. })
        ));
        // The same entry marked required keeps 1.0's rule: refused at open.
        let required = patch(&b, |_, e| {
            edit(&mut e[i]);
            e[i].flags |= 1;
        });
        assert!(matches!(open_err(&required), Error::BadEntry { .. }));
    }
}

/// 1.1: header flags are required features; this version knows none.
#[test]
fn unknown_required_feature() {
    let b = patch(&minimal(), |h, _| h.flags = 1 << 5);
    assert!(matches!(
        open_err(&b),
        Error::UnknownRequiredFeature { bits: 32 }
    ));
}

#[test]
fn missing_section() {
    let w = MapWriter::default();
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::MissingSection {
            kind: SectionKind::PointPositions,
            ..
        }
    ));
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    w.metadata_mut().levels.push(level_info(1, 4.0, 4, 2));
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::MissingSection {
            kind: SectionKind::LevelPoints,
            level: Some(1)
        }
    ));
}

#[test]
fn duplicate_section() {
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    let two: Vec<u16> = vec![1, 2];
    w.add_raw_section(
        SectionKind::Unknown(0x7001),
        NO_LEVEL,
        Dtype::U16,
        2,
        1,
        false,
        Cow::Owned(bytemuck::cast_slice(&two).to_vec()),
        None,
    )
    .unwrap();
    w.add_raw_section(
        SectionKind::Unknown(0x7002),
        NO_LEVEL,
        Dtype::U16,
        2,
        1,
        false,
        Cow::Owned(bytemuck::cast_slice(&two).to_vec()),
        None,
    )
    .unwrap();
    let b = patch(&w.to_bytes().unwrap(), |_, e| e[2].kind = 0x7001);
    assert!(matches!(open_err(&b), Error::DuplicateSection { .. }));
}

#[test]
fn checksum_mismatch() {
    let mut b = minimal();
    let last = b.len() - 1;
    b[last] ^= 1;
    let err = verify_err(&b);
    assert!(matches!(err, Error::ChecksumMismatch { .. }));
    assert!(err.to_string().contains("point_positions"), "{err}");
}

#[test]
fn decode() {
    // Corrupt a zstd frame but fix the checksum, so only decoding can notice.
    let b = levels_map(Codec::Zstd);
    let map = Map::from_bytes(&b).unwrap();
    let s = *map
        .sections()
        .iter()
        .find(|s| s.codec() == Codec::Zstd && s.stored_len() > 16)
        .unwrap();
    let mut bad = b.clone();
    let start = s.offset() as usize;
    bad[start..start + 4].copy_from_slice(&[0xde, 0xad, 0xbe, 0xef]);
    let sum = checksum(&bad[start..start + s.stored_len() as usize]);
    let bad = patch(&bad, |_, e| e[s.index()].checksum = sum);
    assert!(matches!(verify_err(&bad), Error::Decode { .. }));
    // A frame that decodes to fewer bytes than declared.
    let mut short = with_extra_section(
        SectionKind::Unknown(0x7000),
        NO_LEVEL,
        false,
        Some(Codec::Zstd),
    );
    short = patch(&short, |_, e| {
        e[1].rows = 5;
        e[1].raw_len = 5 * 3 * 2;
    });
    assert!(matches!(verify_err(&short), Error::Decode { .. }));
}

#[test]
fn decoded_too_large() {
    let b = with_extra_section(
        SectionKind::Unknown(0x7000),
        NO_LEVEL,
        false,
        Some(Codec::Zstd),
    );
    let b = patch(&b, |_, e| {
        e[1].rows = 1 << 50;
        e[1].raw_len = (1 << 50) * 6;
    });
    assert!(matches!(verify_err(&b), Error::DecodedTooLarge { .. }));
}

#[test]
fn inconsistent() {
    // Level points out of order, written around the writer's own check.
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3], [1.0; 3]]);
    w.metadata_mut().geometry_only = true;
    w.metadata_mut().levels.push(level_info(0, 4.0, 4, 2));
    let pts: Vec<u32> = vec![1, 0];
    w.add_raw_section(
        SectionKind::LevelPoints,
        0,
        Dtype::U32,
        2,
        1,
        true,
        Cow::Owned(bytemuck::cast_slice(&pts).to_vec()),
        None,
    )
    .unwrap();
    let b = w.to_bytes().unwrap();
    assert!(matches!(verify_err(&b), Error::Inconsistent { .. }));
    let map = Map::from_bytes(&b).unwrap();
    assert!(matches!(
        map.level(0).unwrap().points(),
        Err(Error::Inconsistent { .. })
    ));
    // Row counts that disagree are caught at open.
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3], [1.0; 3]]);
    w.set_point_colors(&[[1, 2, 3]]);
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::Inconsistent { .. }
    ));
}

#[test]
fn no_such_level() {
    let b = levels_map(Codec::Raw);
    let map = Map::from_bytes(&b).unwrap();
    let err = map.level(1).unwrap_err();
    assert_eq!(
        err,
        Error::NoSuchLevel {
            level: 1,
            available: vec![0, 2]
        }
    );
}

#[test]
fn invalid_input() {
    let mut w = MapWriter::default();
    assert!(matches!(
        w.set_visibility(&[0, 5], &[1, 2], None),
        Err(Error::InvalidInput { .. })
    ));
    assert!(matches!(
        w.add_level(level_info(0, 4.0, 4, 2), &[2, 1], None, true),
        Err(Error::InvalidInput { .. })
    ));
    assert!(matches!(
        w.set_image_global(3, &[0.0; 4]),
        Err(Error::InvalidInput { .. })
    ));
}

/// Every error the committed invalid vectors produce (at open or verify), plus one built
/// by hand, is one lowercase line.
#[test]
fn messages_are_one_lowercase_line() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("spec/vectors/invalid");
    let mut errors = vec![Error::NoSuchLevel {
        level: 1,
        available: vec![],
    }];
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "sfpm") {
            let bytes = std::fs::read(&path).unwrap();
            let err = match Map::from_bytes(&bytes) {
                Err(e) => e,
                Ok(map) => map.verify().expect_err("an invalid vector verifies"),
            };
            errors.push(err);
        }
    }
    assert!(errors.len() >= 10, "{} errors", errors.len());
    for err in errors {
        let msg = err.to_string();
        assert!(!msg.contains('\n'), "{msg}");
        assert!(!msg.chars().next().unwrap().is_uppercase(), "{msg}");
        assert!(!msg.ends_with('.'), "{msg}");
    }
}

/// The scene of [`levels_map`] (level 2 has `dim_short` 2) with VLAD retrieval on level 2,
/// then `edit` (1.1 sections added or replaced around `set_vlad`'s shapes).
fn vlad_map(edit: impl FnOnce(&mut MapWriter<'_>)) -> Vec<u8> {
    let s = Scene::new(3, 12, 2, &[(0, 8.0, 8, 4), (2, 4.0, 4, 2)]);
    let vlad = s.vlad(2, 2, vec![1.0, 0.0, 0.0, 1.0]);
    let mut w = s.writer_with_vlad(Codec::Raw, &vlad);
    edit(&mut w);
    w.to_bytes().unwrap()
}

/// `[rows × cols]` of `dtype` (f32 or f16), every value 0.5, as an optional section.
fn add_array(
    w: &mut MapWriter<'_>,
    kind: SectionKind,
    level: u16,
    dtype: Dtype,
    rows: u64,
    cols: u64,
) {
    let n = (rows * cols) as usize;
    let bytes = match dtype {
        Dtype::F32 => bytemuck::cast_slice(&vec![0.5f32; n]).to_vec(),
        Dtype::F16 => bytemuck::cast_slice(&vec![sfpmap::format::f16::from_f32(0.5); n]).to_vec(),
        _ => unreachable!(),
    };
    w.add_raw_section(
        kind,
        level,
        dtype,
        rows,
        cols,
        false,
        Cow::Owned(bytes),
        None,
    )
    .unwrap();
}

fn inconsistent_saying(bytes: &[u8], words: &str) {
    match open_err(bytes) {
        Error::Inconsistent { what } => assert!(what.contains(words), "{what}"),
        e => panic!("{e:?}, expected inconsistent ({words})"),
    }
}

#[test]
fn vlad_the_fixture_opens() {
    let b = vlad_map(|_| {});
    let map = Map::from_bytes(&b).unwrap();
    map.verify().unwrap();
    let v = map.vlad().unwrap().unwrap();
    assert_eq!((v.level, v.clusters, v.dims), (2, 2, 2));
    assert_eq!(v.images.len(), 2 * 4);
}

#[test]
fn vlad_missing_section_either_way() {
    // A codebook without image VLADs, and image VLADs without a codebook.
    let s = Scene::new(3, 12, 2, &[(0, 8.0, 8, 4), (2, 4.0, 4, 2)]);
    let mut w = s.writer(Codec::Raw);
    add_array(&mut w, SectionKind::LevelVladCentroids, 2, Dtype::F32, 2, 2);
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::MissingSection {
            kind: SectionKind::ImageVlad,
            level: None
        }
    ));
    let mut w = s.writer(Codec::Raw);
    add_array(&mut w, SectionKind::ImageVlad, NO_LEVEL, Dtype::F16, 2, 4);
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::MissingSection {
            kind: SectionKind::LevelVladCentroids,
            level: None
        }
    ));
}

#[test]
fn vlad_two_codebooks_are_inconsistent() {
    let b = vlad_map(|w| {
        add_array(w, SectionKind::LevelVladCentroids, 0, Dtype::F32, 2, 2);
    });
    inconsistent_saying(&b, "second VLAD codebook");
}

#[test]
fn vlad_codebook_dims_must_be_within_dim_short() {
    // Level 2 has dim_short 2: 3 codebook dims are past it (and image VLADs of 2 x 3 match).
    let b = vlad_map(|w| {
        w.set_vlad(2, 3, vec![0.5; 6], &[0.5; 12]).unwrap();
    });
    inconsistent_saying(&b, "dim_short (2)");
    // On level 0 (dim_short 4), 4 dims are fine and 5 are not.
    let b = vlad_map(|w| {
        w.set_vlad(0, 4, vec![0.5; 8], &[0.5; 16]).unwrap();
    });
    let map = Map::from_bytes(&b).unwrap();
    assert_eq!(map.vlad().unwrap().unwrap().level, 0, "set_vlad replaces");
    let b = vlad_map(|w| {
        w.set_vlad(0, 5, vec![0.5; 10], &[0.5; 20]).unwrap();
    });
    inconsistent_saying(&b, "dim_short (4)");
    // No centroid at all.
    let b = vlad_map(|w| {
        add_array(w, SectionKind::LevelVladCentroids, 2, Dtype::F32, 0, 2);
        add_array(w, SectionKind::ImageVlad, NO_LEVEL, Dtype::F16, 2, 0);
    });
    inconsistent_saying(&b, "at least one centroid");
}

#[test]
fn vlad_image_vlad_shape_follows_the_codebook_and_the_images() {
    // 3 columns where the 2 x 2 codebook makes 4.
    let b = vlad_map(|w| add_array(w, SectionKind::ImageVlad, NO_LEVEL, Dtype::F16, 2, 3));
    inconsistent_saying(&b, "expected clusters x dims = 2 x 2");
    // One row for two images.
    let b = vlad_map(|w| add_array(w, SectionKind::ImageVlad, NO_LEVEL, Dtype::F16, 1, 4));
    inconsistent_saying(&b, "one per image");
    // No images at all.
    let descriptors = [0.5f32; 8];
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3], [1.0; 3]]);
    w.add_level(
        level_info(0, 4.0, 4, 2),
        &[0, 1],
        Some(sfpmap::format::Descriptors::F32(&descriptors)),
        false,
    )
    .unwrap();
    w.set_vlad(0, 2, vec![0.5; 4], &[]).unwrap();
    inconsistent_saying(
        &w.to_bytes().unwrap(),
        "(image_vlad) present without image_poses",
    );
}

#[test]
fn vlad_in_a_geometry_only_map_is_inconsistent() {
    let s = Scene::new(5, 6, 2, &[]);
    let points = [0u32, 2, 4];
    let mut w = s.writer(Codec::Raw);
    w.metadata_mut().geometry_only = true;
    w.add_level(level_info(0, 8.0, 4, 2), &points, None, false)
        .unwrap();
    w.set_vlad(0, 2, vec![0.5; 4], &[0.5; 8]).unwrap();
    inconsistent_saying(&w.to_bytes().unwrap(), "geometry-only");
}

#[test]
fn vlad_codebook_of_an_unlisted_level_or_wrong_dtype() {
    let b = vlad_map(|w| {
        w.set_vlad(7, 2, vec![0.5; 4], &[0.5; 8]).unwrap();
    });
    inconsistent_saying(&b, "does not list");
    let b = vlad_map(|w| add_array(w, SectionKind::LevelVladCentroids, 2, Dtype::F16, 2, 2));
    assert!(matches!(open_err(&b), Error::WrongLayout { .. }));
    let b = vlad_map(|w| add_array(w, SectionKind::ImageVlad, NO_LEVEL, Dtype::F32, 2, 4));
    assert!(matches!(open_err(&b), Error::WrongLayout { .. }));
    // The codebook's columns are descriptor dimensions: the writer keeps to the cap.
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    assert!(matches!(
        w.set_vlad(0, 4097, vec![0.5; 4097], &[])
            .unwrap()
            .to_bytes(),
        Err(Error::InvalidInput { .. })
    ));
    assert!(matches!(
        w.set_vlad(0, 3, vec![0.5; 4], &[]),
        Err(Error::InvalidInput { .. })
    ));
}

/// (1.1) A position grid that cannot give finite f32 positions, at either corner, or a grid
/// without quantised positions, is refused at open; the writer refuses non-finite positions.
#[test]
fn hostile_position_grids_are_bad_metadata() {
    use sfpmap::format::PositionGrid;
    let quantised = |grid: Option<PositionGrid>| {
        let mut w = MapWriter::default();
        w.set_points_world(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        w.set_points_q16(&[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
            .unwrap();
        w.metadata_mut().position_grid = grid;
        w.to_bytes().unwrap()
    };
    assert!(Map::from_bytes(&quantised(Some(PositionGrid {
        min: [0.0; 3],
        step: [1e-3; 3]
    })))
    .is_ok());
    for grid in [
        None,
        Some(PositionGrid {
            min: [1e39, 0.0, 0.0],
            step: [1.0; 3],
        }),
        Some(PositionGrid {
            min: [-1e39, 0.0, 0.0],
            step: [1.55e34, 1.0, 1.0],
        }),
        Some(PositionGrid {
            min: [0.0; 3],
            step: [1e35, 1.0, 1.0],
        }),
        Some(PositionGrid {
            min: [0.0; 3],
            step: [0.0, 1.0, 1.0],
        }),
    ] {
        assert!(
            matches!(open_err(&quantised(grid)), Error::BadMetadata { .. }),
            "{grid:?}"
        );
    }
    let mut w = MapWriter::default();
    w.set_points_world(&[[1.0, 2.0, 3.0]]);
    w.metadata_mut().position_grid = Some(PositionGrid {
        min: [0.0; 3],
        step: [1.0; 3],
    });
    assert!(matches!(
        open_err(&w.to_bytes().unwrap()),
        Error::BadMetadata { .. }
    ));
    assert!(MapWriter::default()
        .set_points_q16(&[[f32::NAN, 0.0, 0.0]])
        .is_err());
}

/// (1.1) A NaN in the VLAD codebook (checksum recomputed) is found on first access: it would
/// make every image VLAD it touches NaN and retrieval's ranking arbitrary.
#[test]
fn a_nonfinite_vlad_centroid_is_inconsistent() {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("spec/vectors/valid/vlad.sfpm");
    let good = std::fs::read(path).unwrap();
    let at = Map::from_bytes(&good)
        .unwrap()
        .find(SectionKind::LevelVladCentroids, Some(2))
        .unwrap()
        .offset() as usize;
    let mut b = good.clone();
    b[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let b = sfpmap::fuzzing::fix_checksums(&b);
    let err = Map::from_bytes(&b).unwrap().verify().unwrap_err();
    assert!(
        matches!(err, Error::Inconsistent { .. }) && err.to_string().contains("not finite"),
        "{err}"
    );
}
