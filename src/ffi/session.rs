//! Localizing queries: the query's C types, `sfpm_localize` with the map's own settings, and
//! sessions (`sfpm_session_*`) with every option and a sequence's tracking.

use super::handles::{get, SfpmMap, SfpmSession, SESSIONS};
use super::map::LocalizerKey;
use super::SfpmStatus::*;
use super::{
    guard, input, non_null, put, put_opt, session_error, set_last_error, FfiError, FfiResult,
    SfpmStatus,
};
use crate::geometry::Camera;
use crate::localize::{
    FeatureSet, Localization, LocalizationPath, LocalizeOptions, QueryFeatures, RetrievalMethod,
};
use crate::session::Session;
use std::ffi::{c_char, CStr};

/// A camera in COLMAP terms, e.g. model "SIMPLE_RADIAL" with params f, cx, cy, k.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct SfpmCamera {
    /// NUL-terminated COLMAP model name ("PINHOLE", "SIMPLE_RADIAL", "OPENCV", ...).
    pub model: *const c_char,
    /// Image size in pixels, as `sfpm_camera` gives it. `sfpm_localize` takes sizes up to
    /// `UINT32_MAX` and rejects larger ones (`SFPM_ERR_ARGUMENT`).
    pub width: u64,
    /// Image height in pixels (see `width`).
    pub height: u64,
    /// `n_params` doubles in COLMAP order for the model.
    pub params: *const f64,
    /// Length of `params`.
    pub n_params: usize,
}

/// Localizer settings; pass NULL to `sfpm_localize` for the defaults (all levels, full
/// descriptors). Everything else is the map's own setting, as `sfpmap localize` uses it:
/// Lowe's ratio is 0.95 on SFP maps and 0.9 on SIFT maps (`LocalizeOptions::for_map`). A
/// session (`SfpmSessionOptions`) sets the others too.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct SfpmLocalizeOptions {
    /// Levels to match (`n_levels` ids); `n_levels == 0` (with `levels` NULL or not) means
    /// every level of the map. NULL with `n_levels > 0` is `SFPM_ERR_NULL`.
    pub levels: *const u16,
    /// Length of `levels`.
    pub n_levels: usize,
    /// Non-zero: match with the `short` descriptor block only (faster, coarser).
    pub short_only: u8,
}

/// Which stored global descriptor ranks the map's images (`SfpmSessionOptions::retrieval`,
/// a `uint32_t` holding one of these values).
#[repr(u32)]
#[allow(non_camel_case_types)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SfpmRetrieval {
    /// The map's stated preference when the query can use it, else the other kind the map
    /// stores (the default).
    SFPM_RETRIEVAL_AUTO = 0,
    /// Only VLAD.
    SFPM_RETRIEVAL_VLAD = 1,
    /// Only the extractor's global descriptor.
    SFPM_RETRIEVAL_GLOBAL = 2,
    /// No retrieval: every point of the map is a candidate.
    SFPM_RETRIEVAL_OFF = 3,
}

impl SfpmRetrieval {
    const ALL: [(SfpmRetrieval, RetrievalMethod); 4] = [
        (SfpmRetrieval::SFPM_RETRIEVAL_AUTO, RetrievalMethod::Auto),
        (SfpmRetrieval::SFPM_RETRIEVAL_VLAD, RetrievalMethod::Vlad),
        (
            SfpmRetrieval::SFPM_RETRIEVAL_GLOBAL,
            RetrievalMethod::Global,
        ),
        (SfpmRetrieval::SFPM_RETRIEVAL_OFF, RetrievalMethod::Off),
    ];

    /// The library's method for a caller's value; another value is `SFPM_ERR_ARGUMENT`, in
    /// the words of the library's option errors (`retrieval "bogus": one of "auto", ...`).
    fn method(value: u32) -> FfiResult<RetrievalMethod> {
        Self::ALL
            .iter()
            .find(|(c, _)| *c as u32 == value)
            .map(|(_, method)| *method)
            .ok_or_else(|| {
                FfiError::argument(format!(
                    "retrieval {value}: one of SFPM_RETRIEVAL_AUTO (0), SFPM_RETRIEVAL_VLAD (1), \
                     SFPM_RETRIEVAL_GLOBAL (2), SFPM_RETRIEVAL_OFF (3)"
                ))
            })
    }

    /// The caller's value of the library's method.
    fn value(method: RetrievalMethod) -> u32 {
        Self::ALL
            .iter()
            .find(|(_, m)| *m == method)
            .map_or(SfpmRetrieval::SFPM_RETRIEVAL_AUTO, |(c, _)| *c) as u32
    }
}

/// Every setting of a session (`sfpm_session_open`). Values are taken as they are, with no
/// "0 means default": start from `sfpm_session_options_default`, which fills in the map's
/// own settings (those `sfpm_localize` and `sfpmap localize` use) and `struct_size`, and
/// change what you need. A value out of its range is refused by `sfpm_session_open` with
/// `SFPM_ERR_ARGUMENT` and the library's message in `sfpm_last_error`, e.g. "ratio 1.5: a
/// ratio in (0, 1]" (the same text the CLI and the Python package give).
///
/// Versioned by its size: a later library appends fields and takes the struct of an earlier
/// header by its `struct_size`, the fields it lacks at their defaults. This one takes its own
/// size and that of the struct before `retrieval_probe` (`offsetof(SfpmSessionOptions,
/// retrieval_probe)`).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct SfpmSessionOptions {
    /// `sizeof(SfpmSessionOptions)` of the header the caller was built with, as
    /// `sfpm_session_options_default` writes it; `sfpm_session_open` refuses a size it does
    /// not know (`SFPM_ERR_ARGUMENT`, naming the size it expects).
    pub struct_size: usize,
    /// Levels to match (`n_levels` ids, read during `sfpm_session_open` only); `n_levels ==
    /// 0` (with `levels` NULL or not) means every level of the map. NULL with `n_levels > 0`
    /// is `SFPM_ERR_NULL`.
    pub levels: *const u16,
    /// Length of `levels`.
    pub n_levels: usize,
    /// Non-zero: match with the `short` descriptor block only (faster, coarser).
    pub short_only: u8,
    /// Database images retrieval keeps (1 to 100000).
    pub top_k: usize,
    /// Lowe's ratio, in (0, 1]: 1 turns the test off. The map's default is 0.95 on SFP maps
    /// and 0.9 on SIFT maps.
    pub ratio: f32,
    /// Matches below this cosine similarity are dropped, in [-1, 1].
    pub min_similarity: f32,
    /// Non-zero: keep mutual nearest neighbours only.
    pub mutual: u8,
    /// Coarse RANSAC threshold in pixels (finite, > 0).
    pub coarse_error_px: f64,
    /// Gate radius of guided matching around projected points in pixels (finite, > 0).
    pub gate_px: f64,
    /// Ratio test among the gated candidates, in (0, 1].
    pub gate_ratio: f32,
    /// Final RANSAC threshold in pixels (finite, > 0).
    pub fine_error_px: f64,
    /// Fewer final inliers is "not localized" (4 to 1000000).
    pub min_inliers: usize,
    /// Non-zero: the queries are an ordered sequence (a moving camera). Each is localized by
    /// guided matching around the pose predicted from the last ones (the tracking path) and
    /// through retrieval only when tracking is lost; queries then run one at a time, in the
    /// order of the calls. Needs a map with images and visibility to track.
    pub sequence: u8,
    /// How the map's images are ranked for a query: one of `SfpmRetrieval`'s values
    /// (`SFPM_RETRIEVAL_AUTO`, the default; `SFPM_RETRIEVAL_VLAD`, `SFPM_RETRIEVAL_GLOBAL`,
    /// `SFPM_RETRIEVAL_OFF`: every point a candidate). Another value is `SFPM_ERR_ARGUMENT`.
    pub retrieval: u32,
    /// Lists of the map's image index (format 1.3) a query scores: -1, the map's own probe
    /// (the default); 0, no index (every image scored, as `sfpmap localize
    /// --retrieval-probe 0`); n > 0, n lists. Another negative value is `SFPM_ERR_ARGUMENT`.
    pub retrieval_probe: i64,
}

/// `sizeof` the options before `retrieval_probe` was appended: `sfpm_session_open` takes a
/// struct of this size too, `retrieval_probe` then at its default.
pub const SFPM_SESSION_OPTIONS_SIZE_1: usize =
    std::mem::offset_of!(SfpmSessionOptions, retrieval_probe);

// The earlier header's `sizeof` on 64-bit targets: a field reordered before the appended ones
// would break old callers, and fails to build here instead.
#[cfg(target_pointer_width = "64")]
const _: () = assert!(SFPM_SESSION_OPTIONS_SIZE_1 == 104);

/// What `sfpm_localize` found.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct SfpmLocalization {
    /// `cam_from_world` as qw qx qy qz tx ty tz (COLMAP convention); zeros if not localized.
    pub cam_from_world: [f64; 7],
    /// Inliers of the final estimate (all levels).
    pub inliers: u64,
    /// Tentative matches the estimate was drawn from.
    pub matches: u64,
}

/// A query as the caller passed it: `2n` keypoint coordinates, `n × dim` descriptor values
/// and the camera, checked.
struct QueryInput<'a> {
    xy: &'a [f64],
    desc: &'a [f32],
    dim: usize,
    camera: Camera,
}

/// Reads the query arguments of `sfpm_localize` and `sfpm_session_localize`.
///
/// # Safety
/// `keypoints` must be valid for `2 × n` doubles and `descriptors` for `n × dim` floats for
/// the call (both may be NULL when `n == 0`); `camera` must be NULL (an error) or point to a
/// valid `SfpmCamera`.
unsafe fn read_query<'a>(
    keypoints: *const f64,
    descriptors: *const f32,
    n: usize,
    dim: usize,
    camera: *const SfpmCamera,
) -> FfiResult<QueryInput<'a>> {
    non_null(&[(camera.is_null(), "camera")])?;
    if dim == 0 {
        return Err(FfiError::argument("dim is 0"));
    }
    let n2 = n
        .checked_mul(2)
        .ok_or_else(|| FfiError::argument("n too large"))?;
    let nd = n
        .checked_mul(dim)
        .ok_or_else(|| FfiError::argument("n × dim too large"))?;
    // SAFETY: per contract: `2n` doubles.
    let xy = unsafe { input(keypoints, n2, "keypoints")? };
    // SAFETY: per contract: `n × dim` floats.
    let desc = unsafe { input(descriptors, nd, "descriptors")? };
    // SAFETY: non-null (checked), points to a valid SfpmCamera per contract.
    let cam = unsafe { &*camera };
    non_null(&[(cam.model.is_null(), "camera.model")])?;
    // SAFETY: non-null, NUL-terminated per contract.
    let model = unsafe { CStr::from_ptr(cam.model) }
        .to_str()
        .map_err(|_| FfiError::argument("camera.model is not UTF-8"))?;
    // SAFETY: per contract: `n_params` doubles.
    let params = unsafe { input(cam.params, cam.n_params, "camera.params")? };
    let too_large = |what| FfiError::argument(format!("camera.{what} is above {}", u32::MAX));
    let width = u32::try_from(cam.width).map_err(|_| too_large("width"))?;
    let height = u32::try_from(cam.height).map_err(|_| too_large("height"))?;
    let camera = Camera::from_model_name(model, width, height, params)
        .map_err(|e| FfiError::argument(format!("camera: {e}")))?;
    Ok(QueryInput {
        xy,
        desc,
        dim,
        camera,
    })
}

impl QueryInput<'_> {
    /// The features, one set for every level (the session refuses NaN and infinity,
    /// `SFPM_ERR_ARGUMENT`).
    fn features(&self) -> QueryFeatures {
        QueryFeatures {
            sets: vec![FeatureSet {
                level: None,
                keypoints: self.xy.chunks_exact(2).map(|p| [p[0], p[1]]).collect(),
                descriptors: self.desc.to_vec(),
                dim: self.dim,
            }],
            global: None,
            model: None,
        }
    }
}

/// Writes what a query found to `*out` (and its path to `*tracked` if not NULL): `SFPM_OK`
/// with the pose, or `SFPM_NOT_LOCALIZED` with the reason as the last error.
///
/// # Safety
/// `out` must be NULL (an error) or writable; `tracked` NULL or writable.
unsafe fn report(
    found: &Localization,
    out: *mut SfpmLocalization,
    tracked: *mut u8,
) -> FfiResult<SfpmStatus> {
    let mut value = SfpmLocalization {
        matches: found.matches as u64,
        inliers: found.inliers as u64,
        ..SfpmLocalization::default()
    };
    let code = match &found.outcome {
        Ok(pose) => {
            value.cam_from_world = pose.to_colmap();
            SFPM_OK
        }
        Err(failure) => {
            value.inliers = 0;
            set_last_error(&failure.to_string());
            SFPM_NOT_LOCALIZED
        }
    };
    // SAFETY: per this function's contract.
    unsafe {
        put(out, value, "out")?;
        put_opt(tracked, u8::from(found.path == LocalizationPath::Tracking));
    }
    Ok(code)
}

/// Localizes one query image against the map.
///
/// `keypoints` holds `n` pixel positions as x, y doubles (COLMAP convention: the top-left
/// pixel's centre is (0.5, 0.5)); `descriptors` holds `n × dim` floats, row-major, in the
/// extractor's space (the map's level projection is applied here; they need not be
/// normalised). The same features serve every level. `options` may be NULL (defaults).
///
/// Returns `SFPM_OK` with the pose in `*out`, `SFPM_NOT_LOCALIZED` when the query ran but no
/// pose was found (reason in `sfpm_last_error`; `*out` holds zeros and the match count), or
/// an error code. The first call for a given set of options prepares the levels (decodes
/// descriptors to f32, noticeable on a large map); later calls reuse that until close, for
/// the 4 sets of options used last (a fifth prepares its levels in place of the least
/// recently used).
/// Thread-safe: any number of threads may localize with the same handle at once. For the
/// other options, or a sequence's tracking, open a session (`sfpm_session_open`).
///
/// # Safety
/// `keypoints` must be valid for `2 × n` doubles, `descriptors` for `n × dim` floats (both
/// may be NULL when `n == 0`), `camera` must point to a valid `SfpmCamera`, `options` to a
/// valid `SfpmLocalizeOptions` or be NULL, and `out` must be writable.
#[no_mangle]
pub unsafe extern "C" fn sfpm_localize(
    map: SfpmMap,
    keypoints: *const f64,
    descriptors: *const f32,
    n: usize,
    dim: usize,
    camera: *const SfpmCamera,
    options: *const SfpmLocalizeOptions,
    out: *mut SfpmLocalization,
) -> SfpmStatus {
    guard(|| {
        let h = get(map)?;
        non_null(&[(out.is_null(), "out"), (camera.is_null(), "camera")])?;
        // SAFETY: the arrays and the camera per this function's contract.
        let query = unsafe { read_query(keypoints, descriptors, n, dim, camera)? };
        let key = if options.is_null() {
            LocalizerKey::default()
        } else {
            // SAFETY: non-null, points to a valid SfpmLocalizeOptions per contract.
            let o = unsafe { &*options };
            LocalizerKey {
                // SAFETY: per contract: `n_levels` ids (NULL allowed when 0).
                levels: unsafe { read_levels(o.levels, o.n_levels)? },
                short: o.short_only != 0,
            }
        };
        let features = query.features();
        let session = h.session(key)?;
        let found = session
            .localize_features(&features, &query.camera, "query")
            .map_err(session_error)?;
        // SAFETY: checked non-null; writable per contract.
        unsafe { report(&found, out, std::ptr::null_mut()) }
    })
}

/// Level ids from a caller's array, ascending, each once.
///
/// # Safety
/// `levels` must be NULL or valid for `n` reads (NULL is allowed when `n == 0`).
unsafe fn read_levels(levels: *const u16, n: usize) -> FfiResult<Vec<u16>> {
    // SAFETY: per this function's contract.
    let mut levels = unsafe { input(levels, n, "options.levels")? }.to_vec();
    levels.sort_unstable();
    levels.dedup();
    Ok(levels)
}

/// Writes the map's own settings to `*out`: every level, full descriptors, and the values
/// `sfpm_localize` and `sfpmap localize` use (Lowe's ratio 0.95 on SFP maps, 0.9 on SIFT
/// maps, `SFPM_RETRIEVAL_AUTO`), not a sequence; and `struct_size`. Start a session's options
/// from these and change what you need.
///
/// # Safety
/// `out` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_session_options_default(
    map: SfpmMap,
    out: *mut SfpmSessionOptions,
) -> SfpmStatus {
    guard(|| {
        non_null(&[(out.is_null(), "out")])?;
        let h = get(map)?;
        let o = LocalizeOptions::for_map(&h.map);
        let value = SfpmSessionOptions {
            struct_size: std::mem::size_of::<SfpmSessionOptions>(),
            levels: std::ptr::null(),
            n_levels: 0,
            short_only: u8::from(o.short),
            top_k: o.top_k,
            ratio: o.matching.ratio,
            min_similarity: o.matching.min_similarity,
            mutual: u8::from(o.matching.mutual),
            coarse_error_px: o.coarse_error_px,
            gate_px: o.gate_px,
            gate_ratio: o.gate_ratio,
            fine_error_px: o.fine_error_px,
            min_inliers: o.min_inliers,
            sequence: 0,
            retrieval: SfpmRetrieval::value(o.retrieval),
            retrieval_probe: -1,
        };
        // SAFETY: checked non-null above; writable per contract.
        unsafe { put(out, value, "out") }?;
        Ok(SFPM_OK)
    })
}

/// Opens a session on `map`: the localizer prepared with `options` (NULL: the map's own
/// settings, as `sfpm_session_options_default` gives them), its handle written to `*out`.
/// Options out of range are refused (`SFPM_ERR_ARGUMENT`, and `sfpm_last_error` names the
/// option, e.g. "ratio 1.5: a ratio in (0, 1]"), as are a `struct_size` this library does
/// not know (`SFPM_ERR_ARGUMENT`) and levels the map lacks (`SFPM_ERR_NO_SUCH_LEVEL`).
/// Opening prepares the levels (decodes descriptors to f32, noticeable on a large map).
///
/// The session holds the map: closing the map handle first is allowed, and the session goes
/// on working until `sfpm_session_close` (the file is unmapped when both are closed). Close
/// every session with `sfpm_session_close`.
///
/// # Safety
/// `options` must be NULL or point to a valid `SfpmSessionOptions` of `options->struct_size`
/// bytes (its `levels` valid for `n_levels` ids during the call); `out` must be writable or
/// NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_session_open(
    map: SfpmMap,
    options: *const SfpmSessionOptions,
    out: *mut SfpmSession,
) -> SfpmStatus {
    guard(|| {
        non_null(&[(out.is_null(), "out")])?;
        let h = get(map)?;
        let mut settings = LocalizeOptions::for_map(&h.map);
        let mut sequence = false;
        if !options.is_null() {
            // SAFETY: non-null, and per contract the caller's struct, which starts with its
            // size whatever header it was built with: the first field is readable (and
            // aligned for a `usize`, the struct's first field).
            let size = unsafe { options.cast::<usize>().read() };
            let expected = std::mem::size_of::<SfpmSessionOptions>();
            if size != expected && size != SFPM_SESSION_OPTIONS_SIZE_1 {
                return Err(FfiError::argument(format!(
                    "struct_size {size}: {expected}, sizeof(SfpmSessionOptions) of this library, \
                     or {SFPM_SESSION_OPTIONS_SIZE_1} of the header before retrieval_probe \
                     (fill the options with sfpm_session_options_default)"
                )));
            }
            // An earlier header's struct: its fields over this one's, the rest (appended
            // since) at their defaults.
            let mut read = SfpmSessionOptions {
                struct_size: expected,
                levels: std::ptr::null(),
                n_levels: 0,
                short_only: 0,
                top_k: 0,
                ratio: 0.0,
                min_similarity: 0.0,
                mutual: 0,
                coarse_error_px: 0.0,
                gate_px: 0.0,
                gate_ratio: 0.0,
                fine_error_px: 0.0,
                min_inliers: 0,
                sequence: 0,
                retrieval: 0,
                retrieval_probe: -1,
            };
            // SAFETY: per contract the caller's struct is `size` readable bytes, and `size` is
            // at most this struct's (checked above); the prefix of an earlier header has this
            // one's layout (fields are only appended).
            unsafe {
                std::ptr::copy_nonoverlapping(
                    options.cast::<u8>(),
                    (&mut read as *mut SfpmSessionOptions).cast::<u8>(),
                    size,
                )
            };
            let o = &read;
            // SAFETY: per contract: `n_levels` ids (NULL allowed when 0).
            settings.levels = unsafe { read_levels(o.levels, o.n_levels)? };
            settings.short = o.short_only != 0;
            settings.top_k = o.top_k;
            settings.matching.ratio = o.ratio;
            settings.matching.min_similarity = o.min_similarity;
            settings.matching.mutual = o.mutual != 0;
            settings.coarse_error_px = o.coarse_error_px;
            settings.gate_px = o.gate_px;
            settings.gate_ratio = o.gate_ratio;
            settings.fine_error_px = o.fine_error_px;
            settings.min_inliers = o.min_inliers;
            settings.retrieval = SfpmRetrieval::method(o.retrieval)?;
            settings.retrieval_probe = match o.retrieval_probe {
                -1 => None,
                n if n >= 0 => Some(usize::try_from(n).unwrap_or(usize::MAX)),
                n => {
                    return Err(FfiError::argument(format!(
                        "retrieval_probe {n}: -1 (the map's own), 0 (no index) or a number of lists"
                    )))
                }
            };
            sequence = o.sequence != 0;
        }
        let session = Session::builder(h.map.clone(), h.path.clone())
            .options(settings)
            .sequence(sequence)
            .build(&crate::progress::Silent)
            .map_err(session_error)?;
        let handle = SESSIONS.register(session);
        // SAFETY: checked non-null above; writable per contract.
        unsafe { put(out, handle, "out") }?;
        Ok(SFPM_OK)
    })
}

/// Localizes one query image with the session's options: the arguments, results and status
/// of `sfpm_localize`. In a sequence (`SfpmSessionOptions::sequence`), each call is the next
/// frame: it is localized around the pose predicted from the last ones when the session is
/// tracking, through retrieval otherwise, and calls run one at a time in the order they are
/// made. `tracked`, when not NULL, receives 1 when the query was localized (or last tried) on
/// the tracking path, 0 when through retrieval. Thread-safe; outside a sequence any number of
/// threads may localize with one session at once.
///
/// # Safety
/// `keypoints` must be valid for `2 × n` doubles, `descriptors` for `n × dim` floats (both
/// may be NULL when `n == 0`), `camera` must point to a valid `SfpmCamera`, `out` must be
/// writable and `tracked` writable or NULL.
#[no_mangle]
pub unsafe extern "C" fn sfpm_session_localize(
    session: SfpmSession,
    keypoints: *const f64,
    descriptors: *const f32,
    n: usize,
    dim: usize,
    camera: *const SfpmCamera,
    out: *mut SfpmLocalization,
    tracked: *mut u8,
) -> SfpmStatus {
    // SAFETY: this function's contract is that one's with no global descriptor.
    unsafe {
        sfpm_session_localize_global(
            session,
            keypoints,
            descriptors,
            n,
            dim,
            std::ptr::null(),
            0,
            camera,
            out,
            tracked,
        )
    }
}

/// `sfpm_session_localize` with the query's global descriptor (`global_dim` floats), for a
/// map whose retrieval ranks images by global descriptors (an hloc `global-feats.h5` given to
/// `sfpmap convert --global-features`, or the SFP network's): the query's must have the
/// map's dimensions: another size, or a map without global descriptors (it ranks by VLAD),
/// is `SFPM_ERR_ARGUMENT`, checked before `global` is read. A NULL `global` with
/// `global_dim == 0` is `sfpm_session_localize`. NaN or infinity in it is
/// `SFPM_ERR_ARGUMENT`. On any error `*out` and `*tracked` are left as they were.
///
/// # Safety
/// As `sfpm_session_localize`, and `global` must be valid for `global_dim` floats (NULL when
/// `global_dim == 0`).
#[no_mangle]
pub unsafe extern "C" fn sfpm_session_localize_global(
    session: SfpmSession,
    keypoints: *const f64,
    descriptors: *const f32,
    n: usize,
    dim: usize,
    global: *const f32,
    global_dim: usize,
    camera: *const SfpmCamera,
    out: *mut SfpmLocalization,
    tracked: *mut u8,
) -> SfpmStatus {
    guard(|| {
        let s = SESSIONS.get(session)?;
        non_null(&[(out.is_null(), "out"), (camera.is_null(), "camera")])?;
        // SAFETY: the arrays and the camera per this function's contract.
        let query = unsafe { read_query(keypoints, descriptors, n, dim, camera)? };
        let mut features = query.features();
        if global_dim > 0 {
            // Another size than the map's (or a map without global descriptors) would make
            // retrieval fall back in silence: a caller who hands one in wants to know. Checked
            // from the section table before a value is read, so a length past the caller's
            // buffer is refused, not read.
            let why = crate::session::global_mismatch(global_dim, s.global_dim(), s.map_name());
            if let Some(why) = why {
                return Err(FfiError::argument(format!("global: {why}")));
            }
            // SAFETY: per contract: `global_dim` floats.
            let global = unsafe { input(global, global_dim, "global")? };
            if let Some(i) = global.iter().position(|v| !v.is_finite()) {
                return Err(FfiError::argument(format!(
                    "global: value {i} is {}",
                    global[i]
                )));
            }
            features.global = Some(global.to_vec());
        }
        let found = s
            .localize_features(&features, &query.camera, "query")
            .map_err(session_error)?;
        // SAFETY: `out` checked non-null, writable; `tracked` NULL or writable (contract).
        unsafe { report(&found, out, tracked) }
    })
}

/// Writes 1 to `*out` when the session predicts the next query's pose (a sequence that
/// localized its last query), so that the next `sfpm_session_localize` tries the tracking
/// path first; 0 otherwise, and always outside a sequence.
///
/// # Safety
/// `out` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_session_is_tracking(
    session: SfpmSession,
    out: *mut u8,
) -> SfpmStatus {
    guard(|| {
        non_null(&[(out.is_null(), "out")])?;
        let s = SESSIONS.get(session)?;
        let tracking = s.is_sequence() && s.is_tracking();
        // SAFETY: checked non-null above; writable per contract.
        unsafe { put(out, u8::from(tracking), "out") }?;
        Ok(SFPM_OK)
    })
}

/// Forgets a sequence's motion (a frame that could not be read, a cut): the next query goes
/// through retrieval, and tracking resumes from it. Does nothing outside a sequence.
#[no_mangle]
pub extern "C" fn sfpm_session_reset_tracking(session: SfpmSession) -> SfpmStatus {
    guard(|| {
        SESSIONS.get(session)?.reset_tracking();
        Ok(SFPM_OK)
    })
}

/// Closes a session and releases the map if its handle was closed already. The handle
/// becomes invalid: using it again, including a second close, returns
/// `SFPM_ERR_INVALID_HANDLE`. A call running on another thread with it finishes first.
#[no_mangle]
pub extern "C" fn sfpm_session_close(session: SfpmSession) -> SfpmStatus {
    guard(|| {
        SESSIONS.close(session)?;
        Ok(SFPM_OK)
    })
}
