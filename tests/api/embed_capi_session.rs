//! The C ABI's sessions (`sfpm_session_*`) called from Rust as C would: the same pose as
//! `sfpm_localize`, options checked, a moving sequence tracked, handles that outlive the map.
#![cfg(feature = "capi")]
// Every call here passes valid pointers (or deliberately NULL ones, which the API reports).
#![allow(clippy::undocumented_unsafe_blocks)]

use crate::embed_capi::{last_error, open, vector_path};
use crate::embed_capi_localize::{
    assert_near, assert_near_truth, localize, query, query_at, synthetic_map, synthetic_map_with,
    DIM,
};
use crate::synthetic_scene::truth;

use sfpmap::ffi::*;
use sfpmap::geometry::Pose;
use std::ffi::CString;
use std::ptr::{null, null_mut};

/// The synthetic query's camera, for `f` to use.
fn with_camera<R>(f: impl FnOnce(&SfpmCamera) -> R) -> R {
    let model = CString::new("PINHOLE").unwrap();
    let params = [500.0, 500.0, 320.0, 240.0];
    f(&SfpmCamera {
        model: model.as_ptr(),
        width: 640,
        height: 480,
        params: params.as_ptr(),
        n_params: params.len(),
    })
}

/// `sfpm_session_localize`: its status, what it found and its path (1: tracking).
fn session_localize(
    session: SfpmSession,
    xy: &[f64],
    desc: &[f32],
) -> (SfpmStatus, SfpmLocalization, u8) {
    let mut out = SfpmLocalization::default();
    let mut tracked = 9u8;
    let status = with_camera(|camera| unsafe {
        sfpm_session_localize(
            session,
            xy.as_ptr(),
            desc.as_ptr(),
            xy.len() / 2,
            DIM,
            camera,
            &mut out,
            &mut tracked,
        )
    });
    (status, out, tracked)
}

pub(crate) fn default_options(map: SfpmMap) -> SfpmSessionOptions {
    let mut out = std::mem::MaybeUninit::<SfpmSessionOptions>::zeroed();
    let status = unsafe { sfpm_session_options_default(map, out.as_mut_ptr()) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    unsafe { out.assume_init() }
}

fn open_session(map: SfpmMap, options: Option<&SfpmSessionOptions>) -> SfpmSession {
    let mut session = 0;
    let options = options.map_or(null(), |o| o as *const _);
    let status = unsafe { sfpm_session_open(map, options, &mut session) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_ne!(session, 0);
    session
}

fn is_tracking(session: SfpmSession) -> u8 {
    let mut tracking = 9u8;
    let status = unsafe { sfpm_session_is_tracking(session, &mut tracking) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    tracking
}

/// A session with the map's own settings (NULL options, or `sfpm_session_options_default`'s
/// written out) finds what `sfpm_localize` finds, to the last bit; so does one on level 2's
/// short block, and one shared by four threads.
#[test]
fn a_session_localizes_like_sfpm_localize() {
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map(tmp.path());
    let (xy, desc) = query(&points, &descriptors);
    let map = open(&path);
    let (status, plain) = localize(map, &xy, &desc, None);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());

    // The map's settings: `LocalizeOptions::for_map` (a "test" descriptor, taken for an SFP
    // model's: ratio 0.95).
    let defaults = default_options(map);
    let want = sfpmap::localize::LocalizeOptions::for_map(
        &sfpmap::format::Map::open(path.to_str().unwrap()).unwrap(),
    );
    assert_eq!((defaults.levels, defaults.n_levels), (null(), 0));
    assert_eq!((defaults.short_only, defaults.sequence), (0, 0));
    assert_eq!(defaults.ratio, 0.95);
    assert_eq!(defaults.ratio, want.matching.ratio);
    assert_eq!(defaults.mutual, u8::from(want.matching.mutual));
    assert_eq!(defaults.min_similarity, want.matching.min_similarity);
    assert_eq!(defaults.top_k, want.top_k);
    assert_eq!(defaults.min_inliers, want.min_inliers);
    assert_eq!(
        (
            defaults.coarse_error_px,
            defaults.gate_px,
            defaults.gate_ratio,
            defaults.fine_error_px
        ),
        (
            want.coarse_error_px,
            want.gate_px,
            want.gate_ratio,
            want.fine_error_px
        )
    );

    for options in [None, Some(&defaults)] {
        let session = open_session(map, options);
        let (status, out, tracked) = session_localize(session, &xy, &desc);
        assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
        assert_eq!(out.cam_from_world, plain.cam_from_world);
        assert_eq!((out.inliers, out.matches), (plain.inliers, plain.matches));
        assert_eq!(tracked, 0, "not a sequence: retrieval");
        assert_eq!(is_tracking(session), 0);
        assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    }

    // Level 2, short block only, both ways.
    let level = [2u16];
    let short = SfpmLocalizeOptions {
        levels: level.as_ptr(),
        n_levels: 1,
        short_only: 1,
    };
    let (status, plain) = localize(map, &xy, &desc, Some(&short));
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    let session = open_session(
        map,
        Some(&SfpmSessionOptions {
            levels: level.as_ptr(),
            n_levels: 1,
            short_only: 1,
            ..defaults
        }),
    );
    let (status, out, _) = session_localize(session, &xy, &desc);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_eq!(out.cam_from_world, plain.cam_from_world);
    assert_eq!(out.inliers, plain.inliers);

    // One session, four threads.
    std::thread::scope(|s| {
        for _ in 0..4 {
            s.spawn(|| {
                let (status, out, _) = session_localize(session, &xy, &desc);
                assert_eq!(status, SfpmStatus::SFPM_OK);
                assert_near_truth(&out);
            });
        }
    });

    // Too few features: runs, no pose, a reason; bad input: the codes of sfpm_localize.
    let (status, out, _) = session_localize(session, &xy[..10], &desc[..5 * DIM]);
    assert_eq!(status, SfpmStatus::SFPM_NOT_LOCALIZED);
    assert_eq!((out.cam_from_world, out.inliers), ([0.0; 7], 0));
    assert!(!last_error().is_empty());
    let mut bad = xy.clone();
    bad[3] = f64::NAN;
    assert_eq!(
        session_localize(session, &bad, &desc).0,
        SfpmStatus::SFPM_ERR_ARGUMENT
    );
    let mut out = SfpmLocalization::default();
    let status = with_camera(|camera| unsafe {
        sfpm_session_localize(
            session,
            xy.as_ptr(),
            desc.as_ptr(),
            1,
            16,
            camera,
            &mut out,
            null_mut(),
        )
    });
    assert_eq!(
        status,
        SfpmStatus::SFPM_ERR_LOCALIZE,
        "16 dimensions against 32"
    );
    assert!(last_error().contains("dimensions"), "{}", last_error());
    unsafe {
        let status = sfpm_session_localize(
            session,
            null(),
            null(),
            0,
            DIM,
            null(),
            &mut out,
            null_mut(),
        );
        assert_eq!(status, SfpmStatus::SFPM_ERR_NULL);
        assert!(last_error().contains("camera is NULL"), "{}", last_error());
        let status = with_camera(|camera| {
            sfpm_session_localize(
                session,
                null(),
                null(),
                0,
                DIM,
                camera,
                null_mut(),
                null_mut(),
            )
        });
        assert_eq!(status, SfpmStatus::SFPM_ERR_NULL);
        assert!(last_error().contains("out is NULL"), "{}", last_error());
    }
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// Options out of range are refused when the session opens, with the library's own message
/// (`LocalizeOptions::validate`, the CLI's and Python's text) and `SFPM_ERR_ARGUMENT`; values
/// are taken as they are, so a zeroed struct is refused too (0 never means "default").
#[test]
fn session_options_out_of_range_are_refused_with_the_library_message() {
    let path = vector_path("levels");
    let map = open(&path);
    let defaults = default_options(map);
    let cases: [(SfpmSessionOptions, &str); 7] = [
        (
            SfpmSessionOptions {
                ratio: 1.5,
                ..defaults
            },
            "ratio 1.5: a ratio in (0, 1]",
        ),
        (
            SfpmSessionOptions {
                ratio: 0.0,
                ..defaults
            },
            "ratio 0: a ratio in (0, 1]",
        ),
        (
            SfpmSessionOptions {
                gate_ratio: -0.5,
                ..defaults
            },
            "gate_ratio -0.5: a ratio in (0, 1]",
        ),
        (
            SfpmSessionOptions {
                top_k: 0,
                ..defaults
            },
            "top_k 0: 1 to 100000 images",
        ),
        (
            SfpmSessionOptions {
                min_similarity: 2.0,
                ..defaults
            },
            "min_similarity 2: a cosine similarity in [-1, 1]",
        ),
        (
            SfpmSessionOptions {
                fine_error_px: f64::NAN,
                ..defaults
            },
            "fine_error_px NaN: a finite number of pixels > 0",
        ),
        (
            SfpmSessionOptions {
                min_inliers: 3,
                ..defaults
            },
            "min_inliers 3: 4 to 1000000 inliers",
        ),
    ];
    for (options, message) in cases {
        let mut session: SfpmSession = 77;
        let status = unsafe { sfpm_session_open(map, &options, &mut session) };
        assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT, "{message}");
        assert_eq!(last_error(), message);
        assert_eq!(session, 77, "nothing written");
    }
    // Zeroed but for the struct's size (a zeroed size is refused first: see
    // `session_options_are_versioned_by_their_size`).
    let zeroed = SfpmSessionOptions {
        struct_size: std::mem::size_of::<SfpmSessionOptions>(),
        ..unsafe { std::mem::MaybeUninit::<SfpmSessionOptions>::zeroed().assume_init() }
    };
    let mut session: SfpmSession = 0;
    assert_eq!(
        unsafe { sfpm_session_open(map, &zeroed, &mut session) },
        SfpmStatus::SFPM_ERR_ARGUMENT
    );
    assert_eq!(last_error(), "top_k 0: 1 to 100000 images");
    // A level the map lacks, and NULL pointers.
    let level = [7u16];
    let options = SfpmSessionOptions {
        levels: level.as_ptr(),
        n_levels: 1,
        ..defaults
    };
    assert_eq!(
        unsafe { sfpm_session_open(map, &options, &mut session) },
        SfpmStatus::SFPM_ERR_NO_SUCH_LEVEL
    );
    assert!(last_error().contains("no level 7"), "{}", last_error());
    let options = SfpmSessionOptions {
        levels: null(),
        n_levels: 2,
        ..defaults
    };
    assert_eq!(
        unsafe { sfpm_session_open(map, &options, &mut session) },
        SfpmStatus::SFPM_ERR_NULL
    );
    assert!(
        last_error().contains("options.levels is NULL"),
        "{}",
        last_error()
    );
    assert_eq!(
        unsafe { sfpm_session_open(map, null(), null_mut()) },
        SfpmStatus::SFPM_ERR_NULL
    );
    assert_eq!(
        unsafe { sfpm_session_options_default(map, null_mut()) },
        SfpmStatus::SFPM_ERR_NULL
    );
    assert_eq!(session, 0);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// `struct_size` versions the options: `sfpm_session_options_default` writes this library's
/// `sizeof(SfpmSessionOptions)`; `sfpm_session_open` takes it and the size before
/// `retrieval_probe` (that field then at its default), and refuses any other size (a newer
/// header's, a struct never filled in) with `SFPM_ERR_ARGUMENT`, naming the size it expects,
/// before reading anything past the size.
#[test]
fn session_options_are_versioned_by_their_size() {
    let map = open(&vector_path("levels"));
    let defaults = default_options(map);
    let size = std::mem::size_of::<SfpmSessionOptions>();
    assert_eq!(defaults.struct_size, size);
    assert_eq!(defaults.retrieval_probe, -1);
    for wrong in [0, SFPM_SESSION_OPTIONS_SIZE_1 - 8, size + 8, usize::MAX] {
        let options = SfpmSessionOptions {
            struct_size: wrong,
            ..defaults
        };
        let mut session: SfpmSession = 77;
        let status = unsafe { sfpm_session_open(map, &options, &mut session) };
        assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT, "struct_size {wrong}");
        assert_eq!(session, 77, "nothing written");
        assert!(
            last_error().starts_with(&format!(
                "struct_size {wrong}: {size}, sizeof(SfpmSessionOptions)"
            )),
            "{}",
            last_error()
        );
    }
    // Only the size is read of a struct of another size: a caller's struct of just a
    // `size_t` is refused, not read past its end.
    let only_a_size: usize = 8;
    let mut session: SfpmSession = 0;
    let status = unsafe {
        sfpm_session_open(
            map,
            (&only_a_size as *const usize).cast::<SfpmSessionOptions>(),
            &mut session,
        )
    };
    assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT);
    assert_eq!(session, 0);
    let session = open_session(map, Some(&defaults));
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    // The header before `retrieval_probe`: the fields it has are read, the probe is the
    // map's own, whatever follows the caller's struct in memory.
    let old = SfpmSessionOptions {
        struct_size: SFPM_SESSION_OPTIONS_SIZE_1,
        top_k: 2,
        retrieval_probe: -7,
        ..defaults
    };
    let session = open_session(map, Some(&old));
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    // This header's: a negative probe other than -1 is refused, 0 and a count are taken.
    let mut session: SfpmSession = 77;
    let bad = SfpmSessionOptions {
        retrieval_probe: -7,
        ..defaults
    };
    let status = unsafe { sfpm_session_open(map, &bad, &mut session) };
    assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT);
    assert!(
        last_error().starts_with("retrieval_probe -7:"),
        "{}",
        last_error()
    );
    for probe in [0, 3, i64::MAX] {
        let options = SfpmSessionOptions {
            retrieval_probe: probe,
            ..defaults
        };
        let session = open_session(map, Some(&options));
        assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    }
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// `retrieval` reaches the session's localizer. On the `vlad` vector with its images' VLAD
/// damaged, the methods that read VLAD (`SFPM_RETRIEVAL_AUTO`, the default, and
/// `SFPM_RETRIEVAL_VLAD`) meet the damage when the session opens (`SFPM_ERR_FORMAT`, the
/// section's checksum), those that do not (`SFPM_RETRIEVAL_GLOBAL`: the map stores no global
/// descriptors; `SFPM_RETRIEVAL_OFF`) open. A value past them is
/// `SFPM_ERR_ARGUMENT`, in the words of the library's option errors.
#[test]
fn session_retrieval_is_passed_through_and_checked() {
    use sfpmap::format::{Map, SectionKind};
    use SfpmRetrieval::*;
    let intact = vector_path("vlad");
    let intact = intact.to_str().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let damaged = tmp.path().join("damaged-vlad.sfpm");
    let mut bytes = std::fs::read(intact).unwrap();
    let section = *Map::open(intact)
        .unwrap()
        .find(SectionKind::ImageVlad, None)
        .expect("the vlad vector stores its images' VLAD");
    let at = usize::try_from(section.offset() + section.stored_len() / 2).unwrap();
    bytes[at] ^= 0x55;
    std::fs::write(&damaged, bytes).unwrap();

    let map = open(&CString::new(damaged.to_str().unwrap()).unwrap());
    let defaults = default_options(map);
    assert_eq!(defaults.retrieval, SFPM_RETRIEVAL_AUTO as u32);
    let with = |retrieval: u32| SfpmSessionOptions {
        retrieval,
        ..defaults
    };
    for (retrieval, opens) in [
        (SFPM_RETRIEVAL_AUTO, false),
        (SFPM_RETRIEVAL_VLAD, false),
        (SFPM_RETRIEVAL_GLOBAL, true),
        (SFPM_RETRIEVAL_OFF, true),
    ] {
        let mut session: SfpmSession = 0;
        let status = unsafe { sfpm_session_open(map, &with(retrieval as u32), &mut session) };
        if opens {
            assert_eq!(
                status,
                SfpmStatus::SFPM_OK,
                "{retrieval:?}: {}",
                last_error()
            );
            assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
        } else {
            assert_eq!(status, SfpmStatus::SFPM_ERR_FORMAT, "{retrieval:?}");
            assert!(last_error().contains("checksum"), "{}", last_error());
            assert_eq!(session, 0);
        }
    }
    // NULL options are the defaults: AUTO, which reads the damaged VLAD.
    let mut session: SfpmSession = 0;
    assert_eq!(
        unsafe { sfpm_session_open(map, null(), &mut session) },
        SfpmStatus::SFPM_ERR_FORMAT
    );
    for bad in [SFPM_RETRIEVAL_OFF as u32 + 1, 42, u32::MAX] {
        let mut session: SfpmSession = 77;
        let status = unsafe { sfpm_session_open(map, &with(bad), &mut session) };
        assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT, "{bad}");
        assert_eq!(session, 77);
        assert_eq!(
            last_error(),
            format!(
                "retrieval {bad}: one of SFPM_RETRIEVAL_AUTO (0), SFPM_RETRIEVAL_VLAD (1), \
                 SFPM_RETRIEVAL_GLOBAL (2), SFPM_RETRIEVAL_OFF (3)"
            )
        );
    }
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// A sequence session on a map whose image sees every point: the first frame goes through
/// retrieval, the next ones are tracked around the predicted pose, a reset (or a frame that
/// is not localized) sends the next one through retrieval again. A session that is not a
/// sequence never tracks.
#[test]
fn a_sequence_session_tracks_a_moving_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map_with(tmp.path(), true);
    let map = open(&path);
    let options = SfpmSessionOptions {
        sequence: 1,
        ..default_options(map)
    };
    let session = open_session(map, Some(&options));
    // The camera moves 5 cm sideways a frame.
    let t = truth();
    let frame = |k: usize| {
        let pose = Pose::new(
            t.rotation,
            t.translation + nalgebra::Vector3::new(0.05 * k as f64, 0.0, 0.0),
        );
        let (xy, desc) = query_at(&points, &descriptors, &pose);
        (pose, xy, desc)
    };
    assert_eq!(is_tracking(session), 0, "nothing to predict from yet");
    for k in 0..4 {
        let (pose, xy, desc) = frame(k);
        let (status, out, tracked) = session_localize(session, &xy, &desc);
        assert_eq!(status, SfpmStatus::SFPM_OK, "frame {k}: {}", last_error());
        assert_near(&out, &pose);
        assert_eq!(
            tracked,
            u8::from(k > 0),
            "frame {k}: the tracking path after the first"
        );
        assert_eq!(is_tracking(session), 1, "frame {k}");
    }
    assert_eq!(sfpm_session_reset_tracking(session), SfpmStatus::SFPM_OK);
    assert_eq!(is_tracking(session), 0);
    for (k, want) in [(4, 0), (5, 1)] {
        let (pose, xy, desc) = frame(k);
        let (status, out, tracked) = session_localize(session, &xy, &desc);
        assert_eq!(status, SfpmStatus::SFPM_OK, "frame {k}: {}", last_error());
        assert_near(&out, &pose);
        assert_eq!(tracked, want, "frame {k} after the reset");
    }
    // A frame that is not localized ends the track.
    let (_, xy, desc) = frame(6);
    let (status, _, _) = session_localize(session, &xy[..10], &desc[..5 * DIM]);
    assert_eq!(status, SfpmStatus::SFPM_NOT_LOCALIZED);
    assert_eq!(is_tracking(session), 0);
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);

    let plain = open_session(map, None);
    for k in 0..2 {
        let (pose, xy, desc) = frame(k);
        let (status, out, tracked) = session_localize(plain, &xy, &desc);
        assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
        assert_near(&out, &pose);
        assert_eq!((tracked, is_tracking(plain)), (0, 0), "not a sequence");
    }
    assert_eq!(sfpm_session_reset_tracking(plain), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_session_close(plain), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// A session holds its map: it keeps localizing after `sfpm_close` of the map handle. Closed
/// sessions and maps, second closes, 0 and handles of the other kind are
/// `SFPM_ERR_INVALID_HANDLE`, never a crash; a map's close does not close a session.
#[test]
fn sessions_outlive_their_map_handle_and_closed_handles_are_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map(tmp.path());
    let (xy, desc) = query(&points, &descriptors);
    let map = open(&path);
    let session = open_session(map, None);
    assert_ne!(session, map);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
    let (status, out, _) = session_localize(session, &xy, &desc);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_near_truth(&out);

    // The closed map opens no session and gives no defaults.
    let mut other: SfpmSession = 0;
    assert_eq!(
        unsafe { sfpm_session_open(map, null(), &mut other) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(other, 0);
    let mut options = std::mem::MaybeUninit::<SfpmSessionOptions>::zeroed();
    assert_eq!(
        unsafe { sfpm_session_options_default(map, options.as_mut_ptr()) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );

    // A session handle is not a map handle: map calls refuse it, and sfpm_close leaves it.
    let mut n = 0usize;
    assert_eq!(
        unsafe { sfpm_level_count(session, &mut n) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert!(last_error().contains("session handle?"), "{}", last_error());
    assert_eq!(sfpm_close(session), SfpmStatus::SFPM_ERR_INVALID_HANDLE);
    assert_eq!(is_tracking(session), 0, "still open");

    // Nor the reverse.
    let live = open(&path);
    assert_eq!(
        sfpm_session_close(live),
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert!(last_error().contains("map handle?"), "{}", last_error());
    assert_eq!(
        session_localize(live, &xy, &desc).0,
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );

    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    assert_eq!(
        sfpm_session_close(session),
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(
        session_localize(session, &xy, &desc).0,
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert!(last_error().contains("closed"), "{}", last_error());
    let mut tracking = 9u8;
    assert_eq!(
        unsafe { sfpm_session_is_tracking(session, &mut tracking) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(tracking, 9);
    assert_eq!(
        sfpm_session_reset_tracking(session),
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(sfpm_session_close(0), SfpmStatus::SFPM_ERR_INVALID_HANDLE);
    assert_eq!(
        unsafe { sfpm_session_is_tracking(0, &mut tracking) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );

    // A new session in the freed slot gets a new generation: the old handle stays dead.
    let again = open_session(live, None);
    assert_ne!(again, session);
    assert_eq!(
        sfpm_session_reset_tracking(session),
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );

    // Closing a session while other threads localize with it: each call completes or sees
    // an invalid handle.
    std::thread::scope(|s| {
        for _ in 0..2 {
            s.spawn(|| loop {
                match session_localize(again, &xy, &desc).0 {
                    SfpmStatus::SFPM_OK => {}
                    SfpmStatus::SFPM_ERR_INVALID_HANDLE => break,
                    other => panic!("{other:?}: {}", last_error()),
                }
            });
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
        assert_eq!(sfpm_session_close(again), SfpmStatus::SFPM_OK);
    });
    assert_eq!(sfpm_close(live), SfpmStatus::SFPM_OK);
}
