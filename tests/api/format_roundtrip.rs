//! Property tests: writer → reader round trips against an f32 reference, and slices.

use crate::common;

use common::{decoded_json, patch, Scene, VladData};
use proptest::prelude::*;
use sfpmap::format::{
    f16, slice, Codec, Descriptors, Map, MapWriter, Retrieval, SectionKind, SliceOptions,
    SliceSummary, VERSION_MINOR,
};

/// |f16(x) − x| for |x| ≤ 1 is at most half an ulp: 2^-11 relative, 2^-25 absolute near 0.
fn within_f16(reference: f32, stored: f32) -> bool {
    (reference - stored).abs() <= reference.abs() * (1.0 / 2048.0) + 1.0 / (1 << 24) as f32
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, .. ProptestConfig::default() })]

    #[test]
    fn descriptors_round_trip_within_f16_precision(
        seed in any::<u64>(),
        n_points in 1usize..60,
        n_images in 0usize..4,
        dims in prop::collection::vec((1u32..40, 0u32..40), 1..4),
        zstd in any::<bool>(),
    ) {
        let levels: Vec<(u16, f64, u32, u32)> = dims
            .iter()
            .enumerate()
            .map(|(i, &(full, short))| (i as u16, 4.0 * (1 << i) as f64, full, short.min(full)))
            .collect();
        let scene = Scene::new(seed, n_points, n_images, &levels);
        let codec = if zstd { Codec::Zstd } else { Codec::Raw };
        let bytes = scene.writer(codec).to_bytes().unwrap();
        let map = Map::from_bytes(&bytes).unwrap();
        map.verify().unwrap();
        prop_assert_eq!(map.levels().count(), scene.levels.len());
        for (level, data) in map.levels().zip(&scene.levels) {
            let (full, short) = (level.dim_full(), level.dim_short());
            let s = level.desc_short().unwrap();
            let r = level.desc_rest().unwrap().unwrap();
            prop_assert_eq!(&*level.points().unwrap(), &data.points[..]);
            for (row, reference) in data.descriptors.chunks(full).enumerate() {
                for (k, &x) in reference.iter().enumerate() {
                    let stored = if k < short { s[row * short + k] } else { r[row * (full - short) + k - short] };
                    prop_assert!(within_f16(x, stored.to_f32()), "{} vs {}", x, stored);
                }
            }
        }
        // Positions: f32 relative to the origin, within f32 precision of the f64 input.
        let positions = map.point_positions().unwrap();
        prop_assert_eq!(positions.len(), scene.positions.len());
        for (p, q) in positions.iter().zip(&scene.positions) {
            let w = map.to_world(*p);
            for k in 0..3 {
                prop_assert!((w[k] - q[k]).abs() <= 1e-5 * q[k].abs().max(1.0));
            }
        }
        // The writer is deterministic.
        prop_assert_eq!(scene.writer(codec).to_bytes().unwrap(), bytes);
    }

    #[test]
    fn slice_equals_the_reference_slice(
        seed in any::<u64>(),
        n_points in 1usize..50,
        n_images in 1usize..4,
        keep in 0usize..3,
        codec in prop::sample::select(vec![None, Some(Codec::Raw), Some(Codec::Zstd)]),
    ) {
        let scene = Scene::new(seed, n_points, n_images, &[(0, 16.0, 12, 3), (1, 8.0, 8, 4), (2, 4.0, 6, 2)]);
        let bytes = scene.writer(Codec::Raw).to_bytes().unwrap();
        let map = Map::from_bytes(&bytes).unwrap();
        let options = SliceOptions { levels: vec![keep as u16], short: true, codec, zstd_level: 1, minimal: false };
        let sliced = slice(&map, &options).unwrap().0.to_bytes().unwrap();
        let out = Map::from_bytes(&sliced).unwrap();
        out.verify().unwrap();
        prop_assert_eq!(decoded_json(&out), scene.sliced(keep as u16).expected_json(map.metadata().origin));
        prop_assert!(sliced.len() < bytes.len());
    }
}

#[test]
fn f32_descriptors_round_to_nearest_even() {
    // 1 + 2^-11 lies exactly between two f16 values: ties go to even (1.0).
    let values = [1.0 + 1.0 / 2048.0, 1.0 + 3.0 / 2048.0, 0.1, -0.3];
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    w.add_level(
        common::level_info(0, 4.0, 4, 2),
        &[0],
        Some(Descriptors::F32(&values)),
        true,
    )
    .unwrap();
    let bytes = w.to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    let level = map.level(0).unwrap();
    let short = level.desc_short().unwrap();
    assert_eq!(short[0], f16::from_f32(1.0));
    assert_eq!(short[1], f16::from_f32(1.0 + 4.0 / 2048.0));
    assert_eq!(level.desc_rest().unwrap().unwrap()[0], f16::from_f32(0.1));
}

#[test]
fn raw_sections_are_borrowed_from_the_mapping() {
    let scene = Scene::new(1, 30, 2, &[(0, 8.0, 8, 4)]);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.sfpm");
    scene
        .writer(Codec::Raw)
        .write(&path, &sfpmap::progress::Silent)
        .unwrap();
    let map = Map::open(&path).unwrap();
    let short = map.level(0).unwrap().desc_short().unwrap();
    assert!(
        matches!(short, std::borrow::Cow::Borrowed(_)),
        "raw f16 must be zero-copy"
    );
    let range = map.bytes().unwrap().as_ptr_range();
    assert!(range.contains(&(short.as_ptr() as *const u8)));
}

#[test]
fn map_is_send_and_sync_and_shared_by_threads() {
    fn assert_send_sync<T: Send + Sync>() {}
    assert_send_sync::<Map<'static>>();
    let scene = Scene::new(2, 40, 2, &[(0, 8.0, 8, 4), (1, 4.0, 4, 4)]);
    let bytes = scene.writer(Codec::Zstd).to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    std::thread::scope(|s| {
        for _ in 0..4 {
            s.spawn(|| {
                for level in map.levels() {
                    assert_eq!(
                        level.desc_short().unwrap().len(),
                        level.len() * level.dim_short()
                    );
                }
            });
        }
    });
}

#[test]
fn write_replaces_atomically_and_leaves_no_temp_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.sfpm");
    std::fs::write(&path, b"old").unwrap();
    // A second name for the old file: a write in place (truncate + write) would change what
    // it reads; a new file renamed over `path` leaves it alone.
    let old_link = dir.path().join("old-link");
    std::fs::hard_link(&path, &old_link).unwrap();
    let scene = Scene::new(4, 5, 1, &[]);
    scene
        .writer(Codec::Raw)
        .write(&path, &sfpmap::progress::Silent)
        .unwrap();
    Map::open(&path).unwrap().verify().unwrap();
    assert_eq!(std::fs::read(&old_link).unwrap(), b"old");
    {
        use std::os::unix::fs::MetadataExt;
        let (new, old) = (
            std::fs::metadata(&path).unwrap(),
            std::fs::metadata(&old_link).unwrap(),
        );
        assert_ne!(new.ino(), old.ino(), "the map was rewritten in place");
    }
    std::fs::remove_file(&old_link).unwrap();
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names.len(), 1, "{names:?}");
    // A write into a folder that does not exist fails and creates nothing.
    let err = scene.writer(Codec::Raw).write(
        &dir.path().join("no/such/m.sfpm"),
        &sfpmap::progress::Silent,
    );
    assert!(err.is_err());
}

/// The "writing" progress ends exactly at the file's length.
#[test]
fn write_progress_reaches_the_file_length() {
    use std::sync::Mutex;
    #[derive(Default)]
    struct Record(Mutex<Vec<(String, Option<u64>, u64)>>);
    impl sfpmap::progress::Reporter for Record {
        fn start(&self, stage: &str, total: Option<u64>) {
            self.0.lock().unwrap().push((stage.to_string(), total, 0));
        }
        fn advance(&self, n: u64) {
            if let Some(last) = self.0.lock().unwrap().last_mut() {
                last.2 += n;
            }
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.sfpm");
    let scene = Scene::new(5, 40, 3, &[(0, 4.0, 16, 4), (1, 8.0, 8, 8)]);
    let record = Record::default();
    let written = scene.writer(Codec::Raw).write(&path, &record).unwrap();
    let stages = record.0.into_inner().unwrap();
    let (_, total, done) = stages.iter().find(|s| s.0 == "writing").unwrap();
    assert_eq!(*total, Some(written));
    assert_eq!(*done, written);
    assert_eq!(written, std::fs::metadata(&path).unwrap().len());
}

/// A stored zstd section that compresses past the new file's decode cap (4 MiB of zeros in
/// a few hundred bytes) is written decoded, so the map stays readable.
#[test]
fn stored_sections_past_the_decode_cap_are_written_decoded() {
    use sfpmap::format::{Dtype, SectionKind};
    let raw = vec![0u8; 4 << 20];
    // Another writer's map (crafted): the zstd section as it is, 4 MiB in a few hundred bytes,
    // readable there (20 KB of other data make the file's cap 5 MB) but past the cap of a
    // small new map.
    let kind = SectionKind::Unknown(0x7000);
    let zstd = common::Crafted::zstd(kind, u16::MAX, Dtype::U8, raw.len() as u64, 1, &raw);
    assert!((raw.len() as u64) > sfpmap::fuzzing::decode_cap(zstd.stored.len() as u64));
    let other = SectionKind::Unknown(0x7001);
    let filler = common::Crafted::raw(other, u16::MAX, Dtype::U8, 20_000, 1, vec![0; 20_000]);
    let source = common::craft(
        &common::craft_metadata(vec![]),
        &[
            common::craft_points(2),
            zstd.clone().optional(),
            filler.clone().optional(),
        ],
    );
    let source = Map::from_bytes(&source).unwrap();
    let stored = source.sections().iter().find(|s| s.kind() == kind).unwrap();
    let mut w = MapWriter::default();
    w.set_points_world(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    w.copy_section(&source, stored).unwrap();
    // A section of another map is refused, not sliced: fields are private, so that is the only
    // way to hand over a section this map did not list. Three cases: the same index with
    // the same kind but another offset (more points before it), an index naming another
    // section here, and an index past this map's table.
    let foreign = |parts: Vec<common::Crafted>| {
        Map::from_bytes(&common::craft(&common::craft_metadata(vec![]), &parts))
            .unwrap()
            .sections()
            .to_vec()
    };
    let zstd_at =
        |sections: &[sfpmap::format::Section]| *sections.iter().find(|s| s.kind() == kind).unwrap();
    let moved = zstd_at(&foreign(vec![
        common::craft_points(50),
        zstd.clone().optional(),
        filler.clone().optional(),
    ]));
    assert_eq!(moved.index(), stored.index());
    assert_ne!(moved.offset(), stored.offset());
    let renumbered = zstd_at(&foreign(vec![
        common::craft_points(2),
        filler.clone().optional(),
        zstd.clone().optional(),
    ]));
    assert_ne!(renumbered.index(), stored.index());
    let extra = common::Crafted::raw(other, 7, Dtype::U8, 64, 1, vec![0; 64]);
    let past = zstd_at(&foreign(vec![
        common::craft_points(2),
        filler.optional(),
        extra.optional(),
        zstd.optional(),
    ]));
    assert!(past.index() >= source.sections().len());
    for theirs in [moved, renumbered, past] {
        assert!(w.copy_section(&source, &theirs).is_err(), "{theirs:?}");
        assert!(source.section_bytes(&theirs).is_err(), "{theirs:?}");
        assert!(source.check_section(&theirs).is_err(), "{theirs:?}");
    }
    let bytes = w.to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    map.verify().unwrap();
    let section = map
        .sections()
        .iter()
        .find(|s| s.kind() == SectionKind::Unknown(0x7000))
        .unwrap();
    assert_eq!(section.codec(), Codec::Raw);
    assert_eq!(map.section_bytes(section).unwrap(), &raw[..]);
}

/// The scene of the conformance vectors with VLAD on level 2 (2 centroids × 2 dims).
fn vlad_scene() -> (Scene, VladData) {
    let s = Scene::new(
        7,
        24,
        3,
        &[(0, 16.0, 16, 4), (1, 8.0, 8, 4), (2, 4.0, 8, 2)],
    );
    let vlad = s.vlad(2, 2, vec![0.6, 0.8, -0.8, 0.6]);
    (s, vlad)
}

fn slice_to(bytes: &[u8], levels: &[u16], short: bool) -> (Vec<u8>, SliceSummary) {
    let map = Map::from_bytes(bytes).unwrap();
    let options = SliceOptions {
        levels: levels.to_vec(),
        short,
        codec: None,
        zstd_level: 3,
        minimal: false,
    };
    let (writer, summary) = slice(&map, &options).unwrap();
    (writer.to_bytes().unwrap(), summary)
}

/// A section as stored: level, rows, cols, `required`, stored bytes.
type Stored = (Option<u16>, u64, u64, bool, Vec<u8>);

/// The stored bytes and table fields of the section of `kind`, if any.
fn stored(map: &Map<'_>, kind: SectionKind) -> Option<Stored> {
    let s = map.sections().iter().find(|s| s.kind() == kind)?;
    let at = s.offset() as usize;
    Some((
        s.level(),
        s.rows(),
        s.cols(),
        s.required(),
        map.bytes().unwrap()[at..at + s.stored_len() as usize].to_vec(),
    ))
}

/// The header's minor version as a 1.0 reader reads it: the u16 at byte 10.
fn minor(bytes: &[u8]) -> u16 {
    u16::from_le_bytes([bytes[10], bytes[11]])
}

#[test]
fn slice_keeps_vlad_with_its_level_byte_for_byte() {
    let (s, vlad) = vlad_scene();
    for codec in [Codec::Raw, Codec::Zstd] {
        let bytes = s.writer_with_vlad(codec, &vlad).to_bytes().unwrap();
        let map = Map::from_bytes(&bytes).unwrap();
        for (levels, short) in [(&[2][..], false), (&[2][..], true), (&[1, 2][..], false)] {
            let (out, summary) = slice_to(&bytes, levels, short);
            assert!(!summary.vlad_dropped);
            let sliced = Map::from_bytes(&out).unwrap();
            sliced.verify().unwrap();
            assert_eq!(sliced.version(), "1.1");
            for kind in [SectionKind::LevelVladCentroids, SectionKind::ImageVlad] {
                let before = stored(&map, kind).unwrap();
                assert_eq!(
                    stored(&sliced, kind).unwrap(),
                    before,
                    "{kind} {levels:?} {short}"
                );
            }
            assert_eq!(sliced.metadata().retrieval(), Some(Retrieval::Vlad));
            let v = sliced.vlad().unwrap().unwrap();
            assert_eq!((v.level, v.clusters, v.dims), (2, 2, 2));
            assert_eq!(decoded_json(&sliced)["vlad"], vlad.expected_json());
        }
    }
}

#[test]
fn slice_drops_vlad_with_its_level_and_retargets_retrieval() {
    let (s, vlad) = vlad_scene();
    let bytes = s.writer_with_vlad(Codec::Raw, &vlad).to_bytes().unwrap();
    assert_eq!(minor(&bytes), 1);
    let (out, summary) = slice_to(&bytes, &[0, 1], false);
    assert!(summary.vlad_dropped);
    let sliced = Map::from_bytes(&out).unwrap();
    sliced.verify().unwrap();
    assert!(sliced.vlad().unwrap().is_none());
    assert!(stored(&sliced, SectionKind::ImageVlad).is_none());
    assert!(stored(&sliced, SectionKind::LevelVladCentroids).is_none());
    // The map still has image_global: it becomes the preference.
    assert_eq!(sliced.metadata().retrieval.as_deref(), Some("global"));
    // Nothing of 1.1 left: a 1.0 file again.
    assert_eq!(minor(&out), 0);
    assert_eq!(sliced.version(), "1.0");

    // Without image_global, no preference is left.
    let mut bare = vlad_scene().0;
    bare.global = None;
    let bytes = bare.writer_with_vlad(Codec::Raw, &vlad).to_bytes().unwrap();
    let (out, summary) = slice_to(&bytes, &[0], true);
    assert!(summary.vlad_dropped);
    let sliced = Map::from_bytes(&out).unwrap();
    assert_eq!(sliced.metadata().retrieval, None);
    assert_eq!(minor(&out), 0);

    // A preference other than "vlad" is not the slice's to change, known or not.
    for stated in ["global", "netvlad-2027"] {
        let mut w = s.writer(Codec::Raw);
        w.metadata_mut().retrieval = Some(stated.into());
        w.set_vlad(vlad.level, vlad.dims, vlad.centroids.clone(), &vlad.images)
            .unwrap();
        let bytes = w.to_bytes().unwrap();
        assert_eq!(
            Map::from_bytes(&bytes)
                .unwrap()
                .metadata()
                .retrieval
                .as_deref(),
            Some(stated),
            "set_vlad keeps a stated preference"
        );
        let (out, _) = slice_to(&bytes, &[1], false);
        let sliced = Map::from_bytes(&out).unwrap();
        assert_eq!(sliced.metadata().retrieval.as_deref(), Some(stated));
        assert_eq!(sliced.metadata().retrieval(), Retrieval::from_name(stated));
    }
}

#[test]
fn files_without_1_1_sections_stay_1_0() {
    // 1.2 adds chunk checksums, which the writer stores only with a section over 64 KiB
    // (`format_chunks`), 1.3 the image index and 1.4 its neighbours (`format_index`): none
    // of the maps below has any.
    assert_eq!(VERSION_MINOR, 4);
    let (s, vlad) = vlad_scene();
    // Every 1.0 kind, zstd or raw, an unknown optional kind, and the 1.1 metadata key
    // (which a 1.0 reader keeps as an unknown key): still minor 0.
    for codec in [Codec::Raw, Codec::Zstd] {
        let mut w = s.writer(codec);
        w.metadata_mut().retrieval = Some("global".into());
        let bytes = w.to_bytes().unwrap();
        assert_eq!(minor(&bytes), 0);
        assert_eq!(Map::from_bytes(&bytes).unwrap().version(), "1.0");
    }
    let unknown = common::with_extra_section(
        SectionKind::Unknown(0x7F01),
        sfpmap::fuzzing::NO_LEVEL,
        false,
        None,
    );
    assert_eq!(minor(&unknown), 0);
    // The same map with VLAD: minor 1, and the rest of the file is what 1.0 wrote, section
    // for section.
    let plain = s.writer(Codec::Raw).to_bytes().unwrap();
    let with = s.writer_with_vlad(Codec::Raw, &vlad).to_bytes().unwrap();
    assert_eq!(minor(&with), 1);
    let (plain, with) = (
        Map::from_bytes(&plain).unwrap(),
        Map::from_bytes(&with).unwrap(),
    );
    for section in plain.sections() {
        assert_eq!(
            stored(&with, section.kind()),
            stored(&plain, section.kind())
        );
    }
    assert_eq!(with.sections().len(), plain.sections().len() + 2);
}

#[test]
fn a_1_0_reader_skips_the_1_1_sections() {
    // A reader that knows no 1.1 kind sees kinds 20 and 38 as unknown: here they are renamed
    // to codes no version defines, which is what such a reader meets.
    let (s, vlad) = vlad_scene();
    let bytes = s.writer_with_vlad(Codec::Raw, &vlad).to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    for kind in [SectionKind::LevelVladCentroids, SectionKind::ImageVlad] {
        let (.., required, _) = stored(&map, kind).unwrap();
        assert!(!required, "{kind} must be optional so 1.0 readers skip it");
    }
    let old = patch(&bytes, |_, entries| {
        for e in entries.iter_mut() {
            e.kind = match e.kind {
                20 => 0x7F20,
                38 => 0x7F38,
                k => k,
            };
        }
    });
    let map = Map::from_bytes(&old).unwrap();
    map.verify().unwrap();
    let skipped: Vec<u16> = map.skipped_sections().map(|s| s.kind().code()).collect();
    // In file order: the shared image VLADs before the level's codebook (spec "Section order").
    assert_eq!(skipped, [0x7F38, 0x7F20]);
    assert!(map.vlad().unwrap().is_none());
    // Everything 1.0 defines reads as in the plain map.
    let plain = s.writer(Codec::Raw).to_bytes().unwrap();
    let mut expected = decoded_json(&Map::from_bytes(&plain).unwrap());
    expected["retrieval"] = "vlad".into();
    assert_eq!(decoded_json(&map), expected);
}

/// The VLAD spec/format.md describes (and tests/common computes) is the one the crate
/// computes for `convert` and queries.
#[cfg(any(feature = "colmap", feature = "localize"))]
#[test]
fn the_spec_vlad_is_the_crate_vlad() {
    use sfpmap::vlad::Codebook;
    let (s, vlad) = vlad_scene();
    let codebook = Codebook::new(vlad.centroids.clone(), vlad.dims).unwrap();
    let rows: Vec<f32> = s
        .vlad_rows(vlad.level, vlad.dims)
        .into_iter()
        .flat_map(|r| r.unwrap_or(vec![0.0; vlad.dims]))
        .collect();
    let crate_images = codebook.image_vlads(&rows, &s.vis_offsets, &s.vis_points);
    assert_eq!(crate_images.len(), vlad.images.len());
    for (a, b) in crate_images.iter().zip(&vlad.images) {
        assert!(
            (a - b).abs() < 1e-5,
            "{crate_images:?} vs {:?}",
            vlad.images
        );
    }
    // A query's VLAD from its own rows: image 0's points as the query give image 0's VLAD.
    let seen: Vec<f32> = s.vis_points[s.vis_offsets[0] as usize..s.vis_offsets[1] as usize]
        .iter()
        .flat_map(|&p| rows[p as usize * vlad.dims..(p as usize + 1) * vlad.dims].to_vec())
        .collect();
    let described: Vec<&[f32]> = seen
        .chunks(vlad.dims)
        .filter(|r| r.iter().any(|&v| v != 0.0))
        .collect();
    let query = codebook.vlad(&described.concat());
    let reference = common::reference_vlad(&described, &vlad.centroids, vlad.dims);
    for (a, b) in query.iter().zip(&reference) {
        assert!((a - b).abs() < 1e-5, "{query:?} vs {reference:?}");
    }
    for (a, b) in query.iter().zip(&vlad.images[..codebook.width()]) {
        assert!((a - b).abs() < 1e-5, "{query:?} vs {:?}", vlad.images);
    }
}

#[test]
fn set_vlad_replaces_the_previous_vlad() {
    let (s, vlad) = vlad_scene();
    let mut w = s.writer_with_vlad(Codec::Raw, &vlad);
    w.set_vlad(0, 4, vec![0.25; 8], &[0.5; 3 * 8]).unwrap();
    let bytes = w.to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    map.verify().unwrap();
    let v = map.vlad().unwrap().unwrap();
    assert_eq!((v.level, v.clusters, v.dims), (0, 2, 4));
    let codebooks = map
        .sections()
        .iter()
        .filter(|s| s.kind() == SectionKind::LevelVladCentroids)
        .count();
    assert_eq!(codebooks, 1);
}
