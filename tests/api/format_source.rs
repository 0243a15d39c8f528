//! `Map::open_source`: a map read by range through a `RangeSource` the test controls (no
//! network): what is read, a damaged read retried once, damage that persists, short reads,
//! and an index longer than the first read.

use crate::common;

use sfpmap::format::{Error, Map, MapWriter, RangeSource, SectionKind, SourceStats, Wanted};
use sfpmap::fuzzing::HEAD_READ;
use std::ops::Range;
use std::sync::Mutex;

/// Serves `bytes`; damages the section at `damage` (table index) on its first `times` reads,
/// and logs every range.
struct Fake {
    bytes: Vec<u8>,
    damage: Option<(usize, usize)>,
    short: bool,
    log: Mutex<Vec<(Range<u64>, bool)>>,
    heads: Mutex<usize>,
    batches: Mutex<usize>,
}

impl Fake {
    fn new(bytes: Vec<u8>) -> Fake {
        Fake {
            bytes,
            damage: None,
            short: false,
            log: Mutex::new(Vec::new()),
            heads: Mutex::new(0),
            batches: Mutex::new(0),
        }
    }
}

impl RangeSource for Fake {
    fn name(&self) -> &str {
        "fake://map"
    }
    fn len(&self) -> u64 {
        self.bytes.len() as u64
    }
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, Error> {
        *self.heads.lock().unwrap() += 1;
        Ok(self.bytes[range.start as usize..range.end as usize].to_vec())
    }
    fn read_sections(
        &self,
        _index_checksum: u64,
        wanted: &[Wanted],
        fresh: bool,
    ) -> Result<Vec<Vec<u8>>, Error> {
        *self.batches.lock().unwrap() += 1;
        let mut out = Vec::new();
        for w in wanted {
            let mut log = self.log.lock().unwrap();
            let seen = log.iter().filter(|(r, _)| *r == w.range).count();
            log.push((w.range.clone(), fresh));
            let mut b = self.bytes[w.range.start as usize..w.range.end as usize].to_vec();
            if let Some((index, times)) = self.damage {
                if index == w.index && seen < times {
                    let last = b.len() - 1;
                    b[last] ^= 1;
                }
            }
            if self.short {
                b.pop();
            }
            out.push(b);
        }
        Ok(out)
    }
    /// Reads of the head and batches of sections, as `requests`.
    fn stats(&self) -> SourceStats {
        let heads = *self.heads.lock().unwrap();
        let mut stats = SourceStats::default();
        stats.requests = (heads + *self.batches.lock().unwrap()) as u64;
        stats
    }
}

fn map_bytes() -> Vec<u8> {
    let mut w = MapWriter::default();
    let points: Vec<[f64; 3]> = (0..200).map(|i| [i as f64, 1.0, 2.0]).collect();
    w.set_points_world(&points);
    let ids: Vec<u32> = (0..200).collect();
    let descs: Vec<Vec<f32>> = (0..3)
        .map(|level| {
            (0..200 * 16)
                .map(|i| ((i * 7 + level) % 13) as f32)
                .collect()
        })
        .collect();
    for level in 0..3u16 {
        let desc = &descs[level as usize];
        w.add_level(
            common::level_info(level, 1.0, 16, 8),
            &ids,
            Some(sfpmap::format::Descriptors::F32(desc)),
            true,
        )
        .unwrap();
    }
    w.to_bytes().unwrap()
}

fn index_of(map: &Map<'_>, kind: SectionKind, level: u16) -> usize {
    map.find(kind, Some(level)).unwrap().index()
}

#[test]
fn reads_the_index_once_and_a_level_in_one_batch_and_agrees_with_memory() {
    let bytes = map_bytes();
    let local = Map::from_bytes(&bytes).unwrap();
    let fake = Fake::new(bytes.clone());
    let map = Map::open_source(Box::new(fake)).unwrap();
    assert!(map.bytes().is_none());
    map.prefetch(|s| s.level() == Some(1)).unwrap();
    let fake = map.source().unwrap();
    // One read of the head (the whole index), one batch for level 1.
    assert_eq!(fake.stats().requests, 2, "{:?}", fake.stats());
    let level = map.level(1).unwrap();
    assert_eq!(
        level.desc_short().unwrap().as_ref(),
        local.level(1).unwrap().desc_short().unwrap().as_ref()
    );
    map.verify().unwrap();
    // Level 1 is one contiguous run of the table, `rest` last (spec "Section order").
    let level_1: Vec<usize> = map
        .sections()
        .iter()
        .filter(|s| s.level() == Some(1))
        .map(|s| s.index())
        .collect();
    assert!(level_1.windows(2).all(|w| w[1] == w[0] + 1), "{level_1:?}");
    assert_eq!(
        *level_1.last().unwrap(),
        index_of(&map, SectionKind::LevelDescRest, 1)
    );
}

#[test]
fn a_damaged_read_is_read_again_once_from_the_origin() {
    let bytes = map_bytes();
    let probe = Map::from_bytes(&bytes).unwrap();
    let damaged = index_of(&probe, SectionKind::LevelDescShort, 2);
    let mut fake = Fake::new(bytes.clone());
    fake.damage = Some((damaged, 1));
    let map = Map::open_source(Box::new(fake)).unwrap();
    map.verify().unwrap();
    let source = map.source().unwrap();
    assert_eq!(source.name(), "fake://map");

    let mut fake = Fake::new(bytes.clone());
    fake.damage = Some((damaged, 2));
    let map = Map::open_source(Box::new(fake)).unwrap();
    match map.level(2).unwrap().desc_short() {
        Err(Error::ChecksumMismatch { section, .. }) => assert_eq!(section.index, damaged),
        other => panic!("expected a checksum mismatch, got {other:?}"),
    }
}

#[test]
fn a_short_read_is_an_error_naming_the_source() {
    let mut fake = Fake::new(map_bytes());
    fake.short = true;
    let map = Map::open_source(Box::new(fake)).unwrap();
    let err = map.verify().unwrap_err().to_string();
    assert!(
        err.contains("fake://map") && err.contains("bytes for a range of"),
        "{err}"
    );
}

#[test]
fn an_index_longer_than_the_first_read_takes_a_second_read() {
    // Metadata past HEAD_READ: a long provenance note.
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0, 0.0, 0.0]]);
    let mut meta = w.metadata().clone();
    meta.provenance
        .parameters
        .insert("note".into(), "x".repeat(HEAD_READ as usize + 1000).into());
    let mut w = MapWriter::new(meta);
    w.set_points_world(&[[0.0, 0.0, 0.0]]);
    let bytes = w.to_bytes().unwrap();
    let fake = Fake::new(bytes);
    let map = Map::open_source(Box::new(fake)).unwrap();
    // The first read, then the rest of the index.
    assert_eq!(map.source().unwrap().stats().requests, 2);
    map.verify().unwrap();
}

#[test]
fn hostile_heads_fail_like_files() {
    for bytes in [
        Vec::new(),
        b"not a map".to_vec(),
        common::minimal()[..100].to_vec(),
    ] {
        let local = Map::from_bytes(&bytes).unwrap_err();
        let remote = Map::open_source(Box::new(Fake::new(bytes.clone()))).unwrap_err();
        assert_eq!(local.kind_name(), remote.kind_name(), "{local} vs {remote}");
    }
}
