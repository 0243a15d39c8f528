//! The localizer end to end on a synthetic map the test builds itself: known query pose,
//! projected keypoints with noise, descriptor noise and outliers.
#![cfg(feature = "localize")]

use crate::synthetic_scene;

use sfpmap::format::{slice, Descriptors, Map, MapWriter, SliceOptions};
use sfpmap::geometry::{Camera, Pose};
use sfpmap::localize::{
    FeatureSet, LocalizeError, LocalizeOptions, Localizer, QueryFailure, QueryFeatures,
};
use synthetic_scene::{level_info, points_and_descriptors, truth, unit, Rng};

pub(crate) const DIM: usize = 32;
const N: usize = 3000;

pub(crate) struct Scene {
    points: Vec<[f64; 3]>,
    descriptors: Vec<f32>,
    pub(crate) camera: Camera,
}

pub(crate) fn scene() -> Scene {
    let (points, descriptors) = points_and_descriptors(N, DIM);
    let camera = Camera::parse("SIMPLE_RADIAL 640 480 500 320 240 0.01").unwrap();
    Scene {
        points,
        descriptors,
        camera,
    }
}

pub(crate) fn map_bytes(s: &Scene) -> Vec<u8> {
    let levels: Vec<Vec<u32>> = (0..3)
        .map(|l| (l * 1000..(l + 1) * 1000).map(|p| p as u32).collect())
        .collect();
    map_bytes_with(s, &levels)
}

/// The scene's map with level `l` holding the points `levels[l]`.
fn map_bytes_with(s: &Scene, levels: &[Vec<u32>]) -> Vec<u8> {
    map_bytes_global(s, levels, None)
}

/// [`map_bytes_with`], with `(dim, values)` as its two images' global descriptors.
fn map_bytes_global(s: &Scene, levels: &[Vec<u32>], global: Option<(usize, &[f32])>) -> Vec<u8> {
    let mut w = MapWriter::default();
    w.add_camera(sfpmap::format::CameraInfo {
        id: Some(1),
        model: "SIMPLE_RADIAL".into(),
        width: 640,
        height: 480,
        params: vec![500.0, 320.0, 240.0, 0.01],
    });
    w.set_points_world(&s.points);
    let names = ["db0.jpg", "db1.jpg"];
    let cams = [0u32, 0];
    let poses = [
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
    ];
    w.set_images(&names, &cams, &poses, None).unwrap();
    let all: Vec<u32> = (0..N as u32).collect();
    let offsets = [0u64, N as u64, 2 * N as u64];
    let vis: Vec<u32> = all.iter().chain(all.iter()).copied().collect();
    let identity: Vec<f32> = (0..DIM * DIM)
        .map(|i| if i % (DIM + 1) == 0 { 1.0 } else { 0.0 })
        .collect();
    let mut w2 = w;
    for (l, pts) in levels.iter().enumerate() {
        let desc: Vec<f32> = pts
            .iter()
            .flat_map(|&p| s.descriptors[p as usize * DIM..(p as usize + 1) * DIM].to_vec())
            .collect();
        let info = level_info(l as u16, DIM);
        w2.add_level(info, pts, Some(Descriptors::F32(&desc)), true)
            .unwrap();
        w2.set_level_projection(l as u16, DIM, identity.clone())
            .unwrap();
    }
    w2.set_visibility(&offsets, &vis, None).unwrap();
    if let Some((dim, values)) = global {
        w2.set_image_global(dim, values).unwrap();
    }
    w2.to_bytes().unwrap()
}

/// Keypoints where the map's points project (0.5 px noise, descriptor noise) plus outliers.
pub(crate) fn query(s: &Scene, pose: &Pose, outliers: usize, dim: usize) -> QueryFeatures {
    let mut rng = Rng(7);
    let mut set = FeatureSet {
        level: None,
        keypoints: Vec::new(),
        descriptors: Vec::new(),
        dim,
    };
    for (p, xyz) in s.points.iter().enumerate() {
        let pc = pose.transform(&nalgebra::Vector3::from(*xyz));
        let Some(px) = s.camera.project(&pc) else {
            continue;
        };
        if !(px.x > 0.0 && px.y > 0.0 && px.x < 640.0 && px.y < 480.0) || rng.next() < 0.3 {
            continue;
        }
        set.keypoints
            .push([px.x + 0.5 * rng.normal(), px.y + 0.5 * rng.normal()]);
        let mut d: Vec<f32> = (0..dim)
            .map(|k| s.descriptors[p * DIM + k % DIM] + 0.08 * rng.normal() as f32)
            .collect();
        unit(&mut d);
        set.descriptors.extend(d);
    }
    for _ in 0..outliers {
        set.keypoints.push([rng.next() * 640.0, rng.next() * 480.0]);
        let mut d: Vec<f32> = (0..dim).map(|_| rng.normal() as f32).collect();
        unit(&mut d);
        set.descriptors.extend(d);
    }
    QueryFeatures {
        sets: vec![set],
        global: None,
        model: None,
    }
}

#[test]
fn recovers_the_pose_with_all_levels_and_with_a_level_2_short_slice() {
    let s = scene();
    let bytes = map_bytes(&s);
    let map = Map::from_bytes(&bytes).unwrap();
    let q = query(&s, &truth(), 800, DIM);
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    assert_eq!(localizer.level_order(), vec![2, 1, 0]);
    let r = localizer.localize(&q, &s.camera).unwrap();
    let pose = *r
        .pose()
        .unwrap_or_else(|| panic!("failed: {:?}", r.failure()));
    assert!(
        pose.rotation_error_deg(&truth()) < 0.1,
        "{}",
        pose.rotation_error_deg(&truth())
    );
    assert!(
        pose.center_distance(&truth()) < 0.02,
        "{}",
        pose.center_distance(&truth())
    );
    assert!(
        r.inliers_per_level.iter().all(|&(_, n)| n > 50),
        "{:?}",
        r.inliers_per_level
    );

    let options = SliceOptions {
        levels: vec![2],
        short: true,
        codec: None,
        zstd_level: 3,
        minimal: false,
    };
    let sliced = slice(&map, &options).unwrap().0.to_bytes().unwrap();
    let small = Map::from_bytes(&sliced).unwrap();
    let localizer = Localizer::new(
        &small,
        LocalizeOptions {
            short: true,
            ..LocalizeOptions::default()
        },
    )
    .unwrap();
    let r = localizer.localize(&q, &s.camera).unwrap();
    let pose = *r
        .pose()
        .unwrap_or_else(|| panic!("failed: {:?}", r.failure()));
    assert!(pose.rotation_error_deg(&truth()) < 0.2);
    assert_eq!(r.inliers_per_level.len(), 1);
}

/// (1.1) The map's levels product-quantised (`slice --pq`): 8 one-byte codes per point in
/// place of 32 (or, short, 16) f16 values, matched by asymmetric distance, still give the
/// pose.
#[cfg(feature = "colmap-model")]
#[test]
fn recovers_the_pose_from_product_quantised_levels() {
    use sfpmap::build::pq::{quantise_levels, PqOptions};
    let s = scene();
    let bytes = map_bytes(&s);
    let map = Map::from_bytes(&bytes).unwrap();
    let q = query(&s, &truth(), 800, DIM);
    for (levels, short) in [(vec![0, 1, 2], false), (vec![2], true)] {
        let options = SliceOptions {
            levels: levels.clone(),
            short,
            codec: None,
            zstd_level: 3,
            minimal: false,
        };
        let (mut writer, _) = slice(&map, &options).unwrap();
        let summary = quantise_levels(
            &map,
            &mut writer,
            &levels,
            &PqOptions {
                subspaces: 8,
                short,
            },
        )
        .unwrap();
        let dims = if short { 16 } else { DIM };
        assert!(
            summary.iter().all(|l| l.centroids == 64 && l.dims == dims),
            "{summary:?}"
        );
        let pq_bytes = writer.to_bytes().unwrap();
        let pq_map = Map::from_bytes(&pq_bytes).unwrap();
        pq_map.verify().unwrap();
        assert!(pq_map.levels().all(|l| l.is_pq()));
        let localizer = Localizer::new(&pq_map, LocalizeOptions::default()).unwrap();
        let r = localizer.localize(&q, &s.camera).unwrap();
        let pose = *r
            .pose()
            .unwrap_or_else(|| panic!("{levels:?}: failed: {:?}", r.failure()));
        assert!(pose.rotation_error_deg(&truth()) < 0.3, "{levels:?}");
        assert!(pose.center_distance(&truth()) < 0.05, "{levels:?}");
        assert!(
            r.inliers_per_level.iter().all(|&(_, n)| n > 30),
            "{:?}",
            r.inliers_per_level
        );
    }
    // A PQ level is not quantised twice, and M must divide the dims.
    let (mut writer, _) = slice(
        &map,
        &SliceOptions {
            levels: vec![1],
            ..Default::default()
        },
    )
    .unwrap();
    let err = quantise_levels(
        &map,
        &mut writer,
        &[1],
        &PqOptions {
            subspaces: 5,
            short: false,
        },
    )
    .unwrap_err();
    assert!(
        err.to_string()
            .contains("32 dimensions, which 5 subspaces do not divide"),
        "{err}"
    );
}

/// (1.2) A map whose blocks span several chunks carries chunk checksums, which the localizer
/// checks where it reads: the pose as from any map, and a damaged chunk of a block a query
/// reads makes that query an error (not a pose, not a panic), though the map opened.
#[test]
fn chunks_are_checked_where_the_localizer_reads_them() {
    use sfpmap::format::{Error as FormatError, SectionKind};
    use sfpmap::fuzzing::CHUNK_LEN;
    let s = scene();
    let all: Vec<u32> = (0..N as u32).collect();
    let bytes = map_bytes_with(&s, &[all]);
    let map = Map::from_bytes(&bytes).unwrap();
    assert_eq!(map.version(), "1.2");
    let short = *map.find(SectionKind::LevelDescShort, Some(0)).unwrap();
    assert!(short.stored_len() > CHUNK_LEN);
    let q = query(&s, &truth(), 300, DIM);
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    let r = localizer.localize(&q, &s.camera).unwrap();
    let pose = *r
        .pose()
        .unwrap_or_else(|| panic!("failed: {:?}", r.failure()));
    assert!(pose.rotation_error_deg(&truth()) < 0.1);

    let mut bad = bytes.clone();
    bad[(short.offset() + CHUNK_LEN + 10) as usize] ^= 0x40;
    let map = Map::from_bytes(&bad).unwrap();
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    let err = localizer.localize(&q, &s.camera).unwrap_err();
    assert!(
        matches!(
            err,
            LocalizeError::Format(FormatError::ChunkChecksumMismatch { chunk: 1, .. })
        ),
        "{err}"
    );
    assert!(err.to_string().contains("level_desc_short"), "{err}");
}

#[test]
fn a_query_of_noise_fails_with_a_reason_not_a_panic() {
    let s = scene();
    let bytes = map_bytes(&s);
    let map = Map::from_bytes(&bytes).unwrap();
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    let mut q = query(&s, &truth(), 300, DIM);
    // Keep only the outliers.
    let n = q.sets[0].keypoints.len();
    q.sets[0].keypoints.drain(..n - 300);
    q.sets[0].descriptors.drain(..(n - 300) * DIM);
    let r = localizer.localize(&q, &s.camera).unwrap();
    // Noise has no consistent subset: no coarse pose, with the matches it had.
    assert!(r.pose().is_none());
    assert!(
        matches!(r.failure(), Some(QueryFailure::NoCoarsePose { matches, .. }) if *matches > 0),
        "{:?}",
        r.failure()
    );
    assert!(r
        .failure()
        .unwrap()
        .to_string()
        .starts_with("coarse pose: "));
    let empty = QueryFeatures {
        sets: vec![FeatureSet {
            level: None,
            keypoints: vec![],
            descriptors: vec![],
            dim: DIM,
        }],
        global: None,
        model: None,
    };
    assert!(localizer
        .localize(&empty, &s.camera)
        .unwrap()
        .pose()
        .is_none());
}

/// A camera claiming a huge image (any u32 size is valid input) still localizes: the
/// guided-matching grid is bounded, not sized by the image.
#[test]
fn a_huge_camera_does_not_size_the_matching_grid() {
    let s = scene();
    let bytes = map_bytes(&s);
    let map = Map::from_bytes(&bytes).unwrap();
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    let q = query(&s, &truth(), 0, DIM);
    let huge = Camera::parse("SIMPLE_RADIAL 4294967295 4294967295 500 320 240 0.01").unwrap();
    let r = localizer.localize(&q, &huge).unwrap();
    let pose = *r
        .pose()
        .unwrap_or_else(|| panic!("failed: {:?}", r.failure()));
    assert!(pose.rotation_error_deg(&truth()) < 0.2);
}

#[test]
fn wrong_descriptor_kind_and_geometry_only_maps_are_errors() {
    let s = scene();
    let bytes = map_bytes(&s);
    let map = Map::from_bytes(&bytes).unwrap();
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    let q = query(&s, &truth(), 0, 16);
    assert!(matches!(
        localizer.localize(&q, &s.camera),
        Err(LocalizeError::DescriptorMismatch {
            expected: 32,
            found: 16,
            ..
        })
    ));

    // Descriptors that are not keypoints × dim values: an error, not a panic.
    let mut bad = query(&s, &truth(), 0, 32);
    bad.sets[0].descriptors.pop();
    assert!(matches!(
        localizer.localize(&bad, &s.camera),
        Err(LocalizeError::FeatureShape { dim: 32, .. })
    ));

    let mut w = MapWriter::default();
    w.metadata_mut().geometry_only = true;
    w.set_points_world(&s.points);
    let geo = w.to_bytes().unwrap();
    let geo = Map::from_bytes(&geo).unwrap();
    assert!(matches!(
        Localizer::new(&geo, LocalizeOptions::default()),
        Err(LocalizeError::NoDescriptors)
    ));
}

#[test]
fn threads_share_one_localizer() {
    let s = scene();
    let bytes = map_bytes(&s);
    let map = Map::from_bytes(&bytes).unwrap();
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    let q = query(&s, &truth(), 200, DIM);
    let poses: Vec<_> = std::thread::scope(|sc| {
        let handles: Vec<_> = (0..3)
            .map(|_| sc.spawn(|| *localizer.localize(&q, &s.camera).unwrap().pose().unwrap()))
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    assert!(
        poses.windows(2).all(|w| w[0] == w[1]),
        "deterministic across threads"
    );
}

/// (1.1) `slice --budget`: budgets from above the whole map down to below its smallest cut.
/// Each choice is the first candidate of the ladder that fits, is no larger than its budget,
/// and localizes the query; a budget below every candidate names the smallest.
#[cfg(feature = "colmap-model")]
#[test]
fn budget_slices_fit_and_localize() {
    use sfpmap::build::budget::{ladder, slice_to_budget};
    let s = scene();
    let bytes = map_bytes(&s);
    let map = Map::from_bytes(&bytes).unwrap();
    let q = query(&s, &truth(), 800, DIM);
    let rungs = ladder(&map, None).unwrap();
    assert_eq!(rungs[0].levels, map.level_ids(), "all levels first");
    assert!(rungs
        .iter()
        .any(|c| c.levels == [2] && c.dims_per_code == Some(8)));
    let mut chosen = Vec::new();
    let mut budget = bytes.len() as u64 * 2;
    let smallest = loop {
        match slice_to_budget(&map, budget, None) {
            Ok(b) => {
                assert!(b.bytes <= budget);
                let written = b.sliced.writer.to_bytes().unwrap();
                assert_eq!(written.len() as u64, b.bytes);
                // Every candidate sized before the chosen one is larger than the budget.
                let (last, before) = b.sized.split_last().unwrap();
                assert!(before.iter().all(|c| c.bytes > budget), "{budget}");
                assert_eq!(last.candidate, b.chosen);
                let small = Map::from_bytes(&written).unwrap();
                small.verify().unwrap();
                let r = Localizer::new(&small, LocalizeOptions::default())
                    .unwrap()
                    .localize(&q, &s.camera)
                    .unwrap();
                let pose = *r
                    .pose()
                    .unwrap_or_else(|| panic!("{budget}: {:?}", r.failure()));
                assert!(pose.rotation_error_deg(&truth()) < 0.5, "{budget}");
                chosen.push(b.chosen);
                budget = b.bytes - 1;
            }
            Err(e) => break e.to_string(),
        }
    };
    assert!(chosen.len() >= 4, "{chosen:?}");
    assert!(chosen.windows(2).all(|w| w[0] != w[1]));
    assert!(chosen.last().unwrap().dims_per_code.is_some(), "{chosen:?}");
    assert!(
        smallest.contains("no slice fits in") && smallest.contains("the smallest is"),
        "{smallest}"
    );
}

/// A prior's wide first round looks at every 4th keypoint; a query whose 40 keypoints leave
/// that round 10, fewer than `min_inliers` (12), is tracked all the same: the round is run
/// again on every keypoint.
#[test]
fn a_prior_whose_strided_round_is_too_thin_still_tracks() {
    let s = scene();
    let bytes = map_bytes(&s);
    let map = Map::from_bytes(&bytes).unwrap();
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    let mut q = query(&s, &truth(), 0, DIM);
    let set = &mut q.sets[0];
    set.keypoints.truncate(40);
    set.descriptors.truncate(40 * DIM);
    // The prior: the truth moved 2 cm sideways (a few pixels at these depths).
    let t = truth();
    let prior = Pose::new(
        t.rotation,
        t.translation + nalgebra::Vector3::new(0.02, 0.0, 0.0),
    );
    let r = localizer
        .localize_with_prior(&q, &s.camera, Some(&prior))
        .unwrap();
    assert_eq!(
        r.path,
        sfpmap::localize::LocalizationPath::Tracking,
        "{:?}",
        r.tracking_lost
    );
    assert!(r.inliers > 10, "{} inliers", r.inliers);
    let pose = *r.pose().unwrap();
    assert!(pose.rotation_error_deg(&t) < 0.5);
}

/// A sequence's frame extracted without its global descriptor (tracked frames need none):
/// when tracking is lost, the localizer asks for it once and retrieves with it; a frame that
/// tracks never asks; without one it retrieves without it, and says so.
#[test]
fn a_frame_that_loses_tracking_asks_for_its_global_descriptor() {
    use sfpmap::localize::{LocalizationPath, RetrievalFallback};
    let s = scene();
    let levels: Vec<Vec<u32>> = (0..3)
        .map(|l| (l * 1000..(l + 1) * 1000).map(|p| p as u32).collect())
        .collect();
    let bytes = map_bytes_global(&s, &levels, Some((2, &[1.0, 0.0, 0.0, 1.0])));
    let map = Map::from_bytes(&bytes).unwrap();
    let options = LocalizeOptions {
        retrieval: sfpmap::localize::RetrievalMethod::Global,
        ..LocalizeOptions::default()
    };
    let localizer = Localizer::new(&map, options).unwrap();
    let q = query(&s, &truth(), 0, DIM);
    assert!(q.global.is_none());
    let t = truth();
    // Turned around: no database image looks its way, tracking is lost.
    let lost = Pose::new(
        nalgebra::UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0) * t.rotation,
        t.translation,
    );
    let mut asked = 0;
    let r = localizer
        .localize_with_prior_then_global(&q, &s.camera, Some(&lost), &mut || {
            asked += 1;
            Some(vec![1.0, 0.0])
        })
        .unwrap();
    assert_eq!(asked, 1, "{:?} {:?}", r.path, r.tracking_lost);
    assert_eq!(r.path, LocalizationPath::Retrieval);
    assert!(r.tracking_lost.is_some());
    // Both images see every point, so retrieval cannot narrow them; it ran with the global
    // descriptor given (without one, the fallback below says so instead).
    assert_eq!(
        r.retrieval_fallback,
        Some(RetrievalFallback::EveryPointSeen)
    );
    assert!(r.pose().unwrap().rotation_error_deg(&t) < 0.5);

    let mut asked = 0;
    let r = localizer
        .localize_with_prior_then_global(&q, &s.camera, Some(&lost), &mut || {
            asked += 1;
            None
        })
        .unwrap();
    assert_eq!(asked, 1);
    assert_eq!(
        r.retrieval_fallback,
        Some(RetrievalFallback::NoQueryDescriptor)
    );

    let r = localizer
        .localize_with_prior_then_global(&q, &s.camera, Some(&t), &mut || {
            panic!("a tracked frame needs no global descriptor")
        })
        .unwrap();
    assert_eq!(r.path, LocalizationPath::Tracking, "{:?}", r.tracking_lost);
}
