//! (1.3) The image index: what open and first access refuse, and what a slice keeps. The
//! conformance vectors (`image_index`, `image_index_image_twice`, `image_index_wrong_width`)
//! cover the valid layout and one error of each stage; these cover the other rules.

use crate::common::{Scene, VladData};
use sfpmap::format::{
    slice, Codec, Dtype, ImageIndexInfo, Map, MapWriter, Retrieval, SectionKind, SliceOptions,
};
use sfpmap::fuzzing::NO_LEVEL;
use std::borrow::Cow;

const CENTROIDS: [f32; 8] = [0.5, 0.5, 0.5, 0.5, -0.5, 0.5, -0.5, 0.5];

fn scene() -> Scene {
    Scene::new(
        7,
        24,
        3,
        &[(0, 16.0, 16, 4), (1, 8.0, 8, 4), (2, 4.0, 8, 2)],
    )
}

fn info(of: &str, probe: u32) -> ImageIndexInfo {
    ImageIndexInfo {
        of: of.into(),
        probe,
        extra: Default::default(),
    }
}

/// The scene with VLAD on level 2 (4 values an image) and an index of 2 lists over `of`.
fn indexed<'s>(s: &'s Scene, vlad: &VladData, of: &str) -> MapWriter<'s> {
    let mut w = s.writer_with_vlad(Codec::Raw, vlad);
    w.set_image_index(info(of, 1), CENTROIDS.to_vec(), 4, &[0, 1, 0])
        .unwrap();
    w
}

fn vlad(s: &Scene) -> VladData {
    s.vlad(2, 2, vec![0.6, 0.8, -0.8, 0.6])
}

/// The error kind `bytes` fail to open with.
fn open_error(bytes: &[u8]) -> &'static str {
    Map::from_bytes(bytes).expect_err("refused").kind_name()
}

#[test]
fn an_index_opens_and_reads_back_its_lists() {
    let s = scene();
    let v = vlad(&s);
    let bytes = indexed(&s, &v, "vlad").to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    assert_eq!(map.version(), "1.3");
    map.verify().unwrap();
    let index = map.image_index().unwrap().unwrap();
    assert_eq!(
        (index.of, index.probe, index.width),
        (Retrieval::Vlad, 1, 4)
    );
    assert_eq!((index.list(0), index.list(1)), (&[0, 2][..], &[1][..]));
    // The same index over the scene's 4-dimensional global descriptors opens too.
    let bytes = indexed(&s, &v, "global").to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    assert_eq!(map.image_index().unwrap().unwrap().of, Retrieval::Global);
    // Over rows this version does not know: opened, and not used.
    let bytes = indexed(&s, &v, "netvlad-pca").to_bytes().unwrap();
    assert!(Map::from_bytes(&bytes)
        .unwrap()
        .image_index()
        .unwrap()
        .is_none());
}

#[test]
fn an_index_with_a_part_missing_is_no_index() {
    let s = scene();
    let v = vlad(&s);
    // The metadata without the sections (a 1.2 slice of a 1.3 map drops sections it does
    // not know and keeps the key), the sections without the metadata, an index over global
    // descriptors the map does not have: each opens, without an index, and slices to a map
    // without one.
    let mut key_only = s.writer_with_vlad(Codec::Raw, &v);
    key_only.metadata_mut().image_index = Some(info("vlad", 1));
    let mut sections_only = indexed(&s, &v, "vlad");
    sections_only.metadata_mut().image_index = None;
    let plain = s.writer_with_vlad(Codec::Raw, &v).to_bytes().unwrap();
    let map = Map::from_bytes(&plain).unwrap();
    let mut no_global = MapWriter::default();
    for section in map.sections() {
        if section.kind() != SectionKind::ImageGlobal {
            no_global.copy_section(&map, section).unwrap();
        }
    }
    *no_global.metadata_mut() = map.metadata().clone();
    no_global
        .set_image_index(info("global", 1), CENTROIDS.to_vec(), 4, &[0, 1, 0])
        .unwrap();
    for (what, w) in [
        ("key only", key_only),
        ("sections only", sections_only),
        ("no global rows", no_global),
    ] {
        let bytes = w.to_bytes().unwrap();
        let map = Map::from_bytes(&bytes).unwrap_or_else(|e| panic!("{what}: {e}"));
        map.verify().unwrap();
        assert!(map.image_index().unwrap().is_none(), "{what}");
        let (sliced, _) = sliced(&bytes, &[2], false);
        let sliced = Map::from_bytes(&sliced).unwrap();
        assert!(sliced.metadata().image_index.is_none(), "{what}");
        assert!(
            sliced.find(SectionKind::ImageIndexImages, None).is_none(),
            "{what}"
        );
    }
}

#[test]
fn an_index_that_disagrees_with_its_images_is_refused_at_open() {
    let s = scene();
    let v = vlad(&s);
    // A probe past the 2 lists, and 0.
    for probe in [0, 3] {
        let mut w = indexed(&s, &v, "vlad");
        w.metadata_mut().image_index.as_mut().unwrap().probe = probe;
        assert_eq!(
            open_error(&w.to_bytes().unwrap()),
            "inconsistent",
            "{probe}"
        );
    }
    // Two images listed for the map's three; list offsets for 3 lists of 2 centroids.
    let u32s = |v: &[u32]| Cow::Owned(bytemuck::cast_slice(v).to_vec());
    for (kind, rows, values) in [
        (SectionKind::ImageIndexImages, 2, vec![0u32, 1]),
        (SectionKind::ImageIndexOffsets, 4, vec![0u32, 1, 2, 3]),
    ] {
        let mut w = indexed(&s, &v, "vlad");
        w.add_raw_section(
            kind,
            NO_LEVEL,
            Dtype::U32,
            rows,
            1,
            false,
            u32s(&values),
            None,
        )
        .unwrap();
        assert_eq!(open_error(&w.to_bytes().unwrap()), "inconsistent", "{kind}");
    }
    // More lists (4) than images (3); centroids of no value over rows of none (a map whose
    // global descriptors have 0 columns).
    let mut w = indexed(&s, &v, "vlad");
    let four: Vec<f32> = CENTROIDS.iter().chain(&CENTROIDS).copied().collect();
    w.add_raw_section(
        SectionKind::ImageIndexCentroids,
        NO_LEVEL,
        Dtype::F32,
        4,
        4,
        false,
        Cow::Owned(bytemuck::cast_slice(&four).to_vec()),
        None,
    )
    .unwrap();
    w.add_raw_section(
        SectionKind::ImageIndexOffsets,
        NO_LEVEL,
        Dtype::U32,
        5,
        1,
        false,
        u32s(&[0, 1, 2, 3, 3]),
        None,
    )
    .unwrap();
    assert_eq!(open_error(&w.to_bytes().unwrap()), "inconsistent");
    let mut w = indexed(&s, &v, "global");
    for (kind, rows) in [
        (SectionKind::ImageGlobal, 3),
        (SectionKind::ImageIndexCentroids, 2),
    ] {
        let dtype = if kind == SectionKind::ImageGlobal {
            Dtype::F16
        } else {
            Dtype::F32
        };
        w.add_raw_section(
            kind,
            NO_LEVEL,
            dtype,
            rows,
            0,
            false,
            Cow::Owned(Vec::new()),
            None,
        )
        .unwrap();
    }
    assert_eq!(open_error(&w.to_bytes().unwrap()), "inconsistent");
}

#[test]
fn index_contents_are_checked_where_they_are_read() {
    let s = scene();
    let v = vlad(&s);
    let u32s = |v: &[u32]| Cow::Owned(bytemuck::cast_slice(v).to_vec());
    let f32s = |v: &[f32]| Cow::Owned(bytemuck::cast_slice(v).to_vec());
    let offsets = |v: &[u32]| (SectionKind::ImageIndexOffsets, Dtype::U32, 3, u32s(v));
    let cases: [(SectionKind, Dtype, u64, Cow<'static, [u8]>); 5] = [
        // Offsets ending at 2 of the 3 images; decreasing; not starting at 0.
        offsets(&[0, 2, 2]),
        offsets(&[0, 4, 3]),
        offsets(&[1, 2, 3]),
        // Image 3 of 3.
        (
            SectionKind::ImageIndexImages,
            Dtype::U32,
            3,
            u32s(&[0, 3, 1]),
        ),
        // A NaN centroid.
        (
            SectionKind::ImageIndexCentroids,
            Dtype::F32,
            2,
            f32s(&[f32::NAN, 0.5, 0.5, 0.5, -0.5, 0.5, -0.5, 0.5]),
        ),
    ];
    for (kind, dtype, rows, bytes) in cases {
        let cols = if dtype == Dtype::F32 { 4 } else { 1 };
        let mut w = indexed(&s, &v, "vlad");
        w.add_raw_section(kind, NO_LEVEL, dtype, rows, cols, false, bytes, None)
            .unwrap();
        let bytes = w.to_bytes().unwrap();
        let map = Map::from_bytes(&bytes).unwrap();
        let err = map.image_index().expect_err("refused on access");
        assert_eq!(err.kind_name(), "inconsistent", "{kind}: {err}");
        // Named by the section and the rule.
        let rule = match kind {
            SectionKind::ImageIndexOffsets => "list offsets do not run from 0",
            SectionKind::ImageIndexImages => "past the 3 images or in two lists",
            _ => "not finite",
        };
        let text = err.to_string();
        assert!(text.contains(kind.name()) && text.contains(rule), "{text}");
        assert_eq!(map.verify().unwrap_err().kind_name(), "inconsistent");
    }
}

fn sliced(bytes: &[u8], levels: &[u16], minimal: bool) -> (Vec<u8>, sfpmap::format::SliceSummary) {
    let map = Map::from_bytes(bytes).unwrap();
    let options = SliceOptions {
        levels: levels.to_vec(),
        minimal,
        zstd_level: 3,
        ..SliceOptions::default()
    };
    let (w, summary) = slice(&map, &options).unwrap();
    (w.to_bytes().unwrap(), summary)
}

#[test]
fn a_slice_keeps_the_index_with_the_rows_it_indexes() {
    let s = scene();
    let v = vlad(&s);
    let bytes = indexed(&s, &v, "vlad").to_bytes().unwrap();
    let before = Map::from_bytes(&bytes).unwrap();
    let before = before.image_index().unwrap().unwrap();
    // Level 2 holds the VLAD: kept, and the index with it, unchanged.
    let (kept, summary) = sliced(&bytes, &[2], false);
    assert!(!summary.index_dropped);
    let map = Map::from_bytes(&kept).unwrap();
    map.verify().unwrap();
    let after = map.image_index().unwrap().unwrap();
    assert_eq!(
        (
            &*after.centroids,
            &*after.offsets,
            &*after.images,
            after.probe
        ),
        (
            &*before.centroids,
            &*before.offsets,
            &*before.images,
            before.probe
        )
    );
    // Level 0 alone: the VLAD goes, and the index and its metadata with it (a 1.0 file).
    let (dropped, summary) = sliced(&bytes, &[0], false);
    assert!(summary.vlad_dropped && summary.index_dropped);
    let map = Map::from_bytes(&dropped).unwrap();
    assert!(map.metadata().image_index.is_none());
    assert!(map.find(SectionKind::ImageIndexImages, None).is_none());
    assert_eq!(map.version(), "1.0");
    // An index over global descriptors stays when the VLAD level goes.
    let global = indexed(&s, &v, "global").to_bytes().unwrap();
    let (kept, summary) = sliced(&global, &[0], false);
    assert!(summary.vlad_dropped && !summary.index_dropped);
    let map = Map::from_bytes(&kept).unwrap();
    assert_eq!(map.image_index().unwrap().unwrap().of, Retrieval::Global);
    // Over rows this version does not know: dropped, key and all.
    let unknown = indexed(&s, &v, "netvlad-pca").to_bytes().unwrap();
    let (sliced_unknown, summary) = sliced(&unknown, &[2], false);
    assert!(summary.index_dropped);
    let map = Map::from_bytes(&sliced_unknown).unwrap();
    assert!(map.metadata().image_index.is_none());
    assert!(map.find(SectionKind::ImageIndexCentroids, None).is_none());
    // --minimal on 3 images keeps no retrieval data, so no index.
    let (minimal, summary) = sliced(&bytes, &[2], true);
    assert!(summary.index_dropped);
    assert!(Map::from_bytes(&minimal)
        .unwrap()
        .image_index()
        .unwrap()
        .is_none());
}

/// (1.4) Each image's neighbours: a map with them is 1.4, reads them back (a row ends at
/// `NO_NEIGHBOUR`), and a slice keeps them with the index and drops them with it; a shape
/// that is not one row per image of 1 to `MAX_NEIGHBOURS` is refused at open, a neighbour
/// past the images where the index is read, and the writer refuses both.
#[test]
fn image_neighbours_are_part_of_the_index() {
    use sfpmap::format::{MAX_NEIGHBOURS, NO_NEIGHBOUR};
    let s = scene();
    let v = vlad(&s);
    let mut w = indexed(&s, &v, "vlad");
    w.set_image_neighbours(vec![2, 1, 0, NO_NEIGHBOUR, 1, 0], 2)
        .unwrap();
    let bytes = w.to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    assert_eq!(map.version(), "1.4");
    map.verify().unwrap();
    let index = map.image_index().unwrap().unwrap();
    let neighbours = index.neighbours.as_ref().expect("stored");
    assert_eq!(neighbours.per_image, 2);
    assert_eq!(
        (
            neighbours.of(0),
            neighbours.of(1),
            neighbours.of(2),
            neighbours.of(3)
        ),
        (&[2, 1][..], &[0][..], &[1, 0][..], &[][..])
    );
    let (kept, summary) = sliced(&bytes, &[2], false);
    assert!(!summary.index_dropped);
    let kept = Map::from_bytes(&kept).unwrap();
    let after = kept.image_index().unwrap().unwrap();
    assert_eq!(after.neighbours.unwrap().rows, neighbours.rows);
    let (dropped, _) = sliced(&bytes, &[0], false);
    let dropped = Map::from_bytes(&dropped).unwrap();
    assert!(dropped
        .find(SectionKind::ImageIndexNeighbours, None)
        .is_none());
    assert_eq!(dropped.version(), "1.0");

    // Two rows for three images; rows of no neighbour; rows past MAX_NEIGHBOURS.
    for (rows, cols) in [(2u64, 2u64), (3, 0), (3, MAX_NEIGHBOURS as u64 + 1)] {
        let mut w = indexed(&s, &v, "vlad");
        let values = vec![0u32; (rows * cols) as usize];
        w.add_raw_section(
            SectionKind::ImageIndexNeighbours,
            NO_LEVEL,
            Dtype::U32,
            rows,
            cols,
            false,
            Cow::Owned(bytemuck::cast_slice(&values).to_vec()),
            None,
        )
        .unwrap();
        assert_eq!(
            open_error(&w.to_bytes().unwrap()),
            "inconsistent",
            "{rows} x {cols}"
        );
    }
    // Image 3 of 3 as a neighbour: opens, refused where the index is read, and by verify.
    let mut w = indexed(&s, &v, "vlad");
    w.add_raw_section(
        SectionKind::ImageIndexNeighbours,
        NO_LEVEL,
        Dtype::U32,
        3,
        1,
        false,
        Cow::Owned(bytemuck::cast_slice(&[1u32, 3, 0]).to_vec()),
        None,
    )
    .unwrap();
    let bytes = w.to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    let err = map.image_index().expect_err("refused on access");
    let text = err.to_string();
    assert_eq!(err.kind_name(), "inconsistent", "{text}");
    assert!(
        text.contains("image_index_neighbours")
            && text.contains("neighbour 3 is past the 3 images"),
        "{text}"
    );
    assert_eq!(map.verify().unwrap_err().kind_name(), "inconsistent");
    // The writer: a neighbour past the rows' images, rows of 0 or 257.
    let mut w = indexed(&s, &v, "vlad");
    assert!(w.set_image_neighbours(vec![1, 3, 0], 1).is_err());
    assert!(w.set_image_neighbours(vec![], 0).is_err());
    assert!(w
        .set_image_neighbours(vec![0; MAX_NEIGHBOURS + 1], MAX_NEIGHBOURS + 1)
        .is_err());
}

/// (1.4) A row whose neighbours go on after an end mark is refused where the index is read.
#[test]
fn neighbours_after_an_end_mark_are_refused() {
    use sfpmap::format::NO_NEIGHBOUR;
    let s = scene();
    let v = vlad(&s);
    let mut w = indexed(&s, &v, "vlad");
    let rows = [1u32, 2, NO_NEIGHBOUR, 0, 0, 1];
    w.add_raw_section(
        SectionKind::ImageIndexNeighbours,
        NO_LEVEL,
        Dtype::U32,
        3,
        2,
        false,
        Cow::Owned(bytemuck::cast_slice(&rows).to_vec()),
        None,
    )
    .unwrap();
    let bytes = w.to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    let text = map.image_index().expect_err("refused").to_string();
    assert!(
        text.contains("image 1's neighbours go on after their end mark"),
        "{text}"
    );
}
