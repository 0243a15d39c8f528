//! The C ABI (feature `capi`): open a map, read its levels, descriptors, points, images and
//! visibility without copying, and localize queries, one at a time (`sfpm_localize`) or
//! through a session with every option and a sequence's tracking (`sfpm_session_*`, a
//! [`Session`] behind a handle). `include/sfpmap.h` is generated from this file by cbindgen
//! (`include/cbindgen.toml`); the doc comments below are the header's.
//!
//! Why handles are integers, not pointers: a freed pointer cannot be told apart from a live
//! one, so a use after `sfpm_close` would be undefined behaviour. A handle is a slot index
//! plus a generation counter in a process-wide registry (one for maps, one for sessions, told
//! apart by the handle's top bit); after close the generation moves on and every call with
//! the old handle returns `SFPM_ERR_INVALID_HANDLE` (double close too).
//!
//! Every entry point catches panics (`catch_unwind`) and returns `SFPM_ERR_PANIC` instead of
//! unwinding into C. The crate's other `unsafe` is the map's mmap (`format::mmap`) and the
//! SIMD kernels (`vector`, `localize::kernels`); here each block is a read of a pointer the C
//! caller passed in or a write through one (checked
//! non-null first; its validity and size are the caller's contract, stated per function).
//! Nothing here extends a lifetime: a map handle and its sessions share the map by `Arc`,
//! and each session owns its localizer beside it.

#![allow(unsafe_code)]
#![deny(unsafe_op_in_unsafe_fn)]

use crate::format::{Error as FormatError, Images, Map, SectionKind};
use crate::geometry::Camera;
use crate::localize::{
    FeatureSet, Localization, LocalizationPath, LocalizeError, LocalizeOptions, QueryFeatures,
};
use crate::session::{Session, SessionError};
use std::any::Any;
use std::borrow::Cow;
use std::cell::RefCell;
use std::collections::HashMap;
use std::ffi::{c_char, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex, MutexGuard};

/// An open map: `0` is never a valid handle. Handles are plain integers (a registry slot and a
/// generation), so a handle used after `sfpm_close` is detected, never undefined behaviour.
pub type SfpmMap = u64;

/// An open localization session (`sfpm_session_open`): a map prepared for queries with a
/// fixed set of options, and a sequence's tracking. A plain integer like `SfpmMap`, never 0,
/// never equal to a map handle; a handle used after `sfpm_session_close` is detected.
pub type SfpmSession = u64;

/// The status every function returns: `SFPM_OK`, `SFPM_NOT_LOCALIZED` (from `sfpm_localize`
/// and `sfpm_session_localize` only) or a negative error; `sfpm_last_error` gives the message
/// of the last error.
#[repr(i32)]
#[allow(non_camel_case_types)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SfpmStatus {
    /// Success.
    SFPM_OK = 0,
    /// `sfpm_localize` or `sfpm_session_localize` ran but found no pose (too few inliers,
    /// ...); `sfpm_last_error` says why.
    SFPM_NOT_LOCALIZED = 1,
    /// A required pointer argument was NULL.
    SFPM_ERR_NULL = -1,
    /// The handle is 0, was closed, never came from `sfpm_open` (`sfpm_session_open` for a
    /// session), or is a handle of the other kind.
    SFPM_ERR_INVALID_HANDLE = -2,
    /// An argument is out of range or malformed (index past the end, bad camera, not UTF-8,
    /// an option out of its range, ...).
    SFPM_ERR_ARGUMENT = -3,
    /// The file could not be read.
    SFPM_ERR_IO = -4,
    /// The file is not a valid map, or a section failed its checks on first access.
    SFPM_ERR_FORMAT = -5,
    /// The map has no such level.
    SFPM_ERR_NO_SUCH_LEVEL = -6,
    /// The map does not hold what was asked for (no images, no `rest` block, no descriptors, ...).
    SFPM_ERR_MISSING = -7,
    /// The query cannot be matched against the map (descriptor dimension mismatch, ...).
    SFPM_ERR_LOCALIZE = -8,
    /// A bug in sfpmap: a panic was caught at the boundary. The handle stays usable.
    SFPM_ERR_PANIC = -99,
}

use SfpmStatus::*;

/// Dimensions and size of one level.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default)]
pub struct SfpmLevelInfo {
    /// The level id.
    pub level: u16,
    /// Dimensions of the full descriptor (`short` + `rest`).
    pub dim_full: u32,
    /// Dimensions of the `short` block, a prefix of the full descriptor.
    pub dim_short: u32,
    /// Points (rows) the level holds.
    pub points: u64,
    /// 1 when the level has descriptors at all (0 for geometry-only maps).
    pub has_descriptors: u8,
    /// 1 when the `rest` block is present (a `--short` slice drops it).
    pub has_rest: u8,
}

/// A product-quantised level's descriptors (format 1.1; see `spec/format.md`, kinds 21 to
/// 23): `points × subspaces` one-byte codes, the `subspaces × centroids` codebook rows of
/// `sub_dims` floats (subspace s's centroid k is row `s·centroids + k`) and the order of the
/// quantised dimensions (`order[j]` is the level dimension at position j, checked a
/// permutation; NULL and 0 when the level has no `level_pq_order`, i.e. the identity).
/// Zero-copy for raw sections; valid until `sfpm_close`.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct SfpmLevelPq {
    /// Codes per point (`M`).
    pub subspaces: u32,
    /// Centroids per subspace (`K`).
    pub centroids: u32,
    /// Dimensions per subspace.
    pub sub_dims: u32,
    /// `points × subspaces` codes, row-major.
    pub codes: *const u8,
    /// Length of `codes`.
    pub codes_len: usize,
    /// `subspaces × centroids` rows of `sub_dims` floats.
    pub codebook: *const f32,
    /// Length of `codebook`, in floats.
    pub codebook_len: usize,
    /// The quantised dimensions' order; NULL for the identity.
    pub order: *const u16,
    /// Length of `order` (0 for the identity).
    pub order_len: usize,
}

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

/// Every setting of a session (`sfpm_session_open`). Values are taken as they are, with no
/// "0 means default": start from `sfpm_session_options_default`, which fills in the map's
/// own settings (those `sfpm_localize` and `sfpmap localize` use), and change what you need.
/// A value out of its range is refused by `sfpm_session_open` with `SFPM_ERR_ARGUMENT` and
/// the library's message in `sfpm_last_error`, e.g. "ratio 1.5: a ratio in (0, 1]" (the
/// same text the CLI and the Python package give).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct SfpmSessionOptions {
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
}

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

struct FfiError {
    code: SfpmStatus,
    message: String,
}

impl FfiError {
    fn new(code: SfpmStatus, message: impl Into<String>) -> Self {
        FfiError {
            code,
            message: message.into(),
        }
    }

    fn null(what: &str) -> Self {
        FfiError::new(SFPM_ERR_NULL, format!("{what} is NULL"))
    }

    fn argument(message: impl Into<String>) -> Self {
        FfiError::new(SFPM_ERR_ARGUMENT, message)
    }
}

impl From<FormatError> for FfiError {
    fn from(e: FormatError) -> Self {
        let code = match &e {
            FormatError::Io { .. } | FormatError::NotARegularFile { .. } => SFPM_ERR_IO,
            FormatError::NoSuchLevel { .. } => SFPM_ERR_NO_SUCH_LEVEL,
            FormatError::MissingSection { .. } => SFPM_ERR_MISSING,
            _ => SFPM_ERR_FORMAT,
        };
        FfiError::new(code, e.to_string())
    }
}

type FfiResult<T = ()> = Result<T, FfiError>;

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

fn set_last_error(message: &str) {
    // Interior NULs cannot be in a C string; they never occur in our messages, but a file
    // name could hold one.
    let c = CString::new(message.replace('\0', "\\0")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = c);
}

/// Runs an entry point: panics become `SFPM_ERR_PANIC`, errors set the thread's last error.
fn guard(f: impl FnOnce() -> FfiResult<SfpmStatus>) -> SfpmStatus {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(code)) => code,
        Ok(Err(e)) => {
            set_last_error(&e.message);
            e.code
        }
        Err(panic) => {
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            set_last_error(&format!("internal error (panic): {what}"));
            SFPM_ERR_PANIC
        }
    }
}

/// Owns the map and whatever the handle lends out.
struct MapHandle {
    /// Shared with the handle's sessions (`sfpm_session_open`), which keep it open after
    /// `sfpm_close`.
    map: Arc<Map<'static>>,
    /// The path it was opened from: the name sessions give it.
    path: String,
    /// `sfpm_localize`'s sessions, one per set of options, built on first use (each indexes
    /// the levels it matches: projections, retrieval, viewpoints) and kept until close.
    sessions: Mutex<Vec<(LocalizerKey, Arc<Session>)>>,
    /// Arrays the map could only give as owned copies (a buffer not aligned for the type),
    /// kept so their pointers stay valid until close. With `sfpm_open` (mmap, page-aligned)
    /// every section is borrowed and this stays empty.
    pinned: Mutex<HashMap<(SectionKind, u16), Box<dyn Any + Send + Sync>>>,
}

#[derive(PartialEq, Eq, Default)]
struct LocalizerKey {
    levels: Vec<u16>,
    short: bool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic while holding the lock was already reported; the data is still consistent
    // (every critical section here is a single insert or lookup).
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl MapHandle {
    /// Writes pointer and length of a map array, valid until close, to the caller's `ptr` and
    /// `len`. `U` is the element type the caller sees (`u16` for `f16`, `f32` for `[f32; 3]`).
    ///
    /// # Safety
    /// `ptr` and `len` must be non-null (callers check with [`non_null`] first) and writable.
    unsafe fn lend<T: bytemuck::Pod + Send + Sync, U>(
        &self,
        key: (SectionKind, u16),
        data: Cow<'_, [T]>,
        ptr: *mut *const U,
        len: *mut usize,
    ) {
        let (p, n) = match data {
            // Borrowed from the mmap or from the map's decoded-section cache: both live as
            // long as `map`, which outlives the handle.
            Cow::Borrowed(s) => (s.as_ptr(), s.len()),
            Cow::Owned(v) => {
                let mut pinned = lock(&self.pinned);
                let entry = pinned.entry(key).or_insert_with(|| Box::new(v));
                match entry.downcast_ref::<Vec<T>>() {
                    Some(v) => (v.as_ptr(), v.len()),
                    None => (std::ptr::null(), 0),
                }
            }
        };
        // SAFETY: non-null and writable per this function's contract.
        unsafe {
            ptr.write(p.cast());
            len.write(n);
        }
    }

    /// `sfpm_localize`'s session for these options: the map's own settings with `key`'s
    /// levels and block, built on first use and kept until close.
    fn session(&self, key: LocalizerKey) -> FfiResult<Arc<Session>> {
        let mut cache = lock(&self.sessions);
        if let Some((_, s)) = cache.iter().find(|(k, _)| *k == key) {
            return Ok(s.clone());
        }
        let options = LocalizeOptions {
            levels: key.levels.clone(),
            short: key.short,
            ..LocalizeOptions::for_map(&self.map)
        };
        let session = Session::builder(self.map.clone(), self.path.clone())
            .options(options)
            .build(&crate::progress::Silent)
            .map_err(session_error)?;
        let session = Arc::new(session);
        cache.push((key, session.clone()));
        Ok(session)
    }
}

fn localize_error_code(e: &LocalizeError) -> SfpmStatus {
    use LocalizeError as E;
    match e {
        E::Format(FormatError::NoSuchLevel { .. }) => SFPM_ERR_NO_SUCH_LEVEL,
        E::Format(_) => SFPM_ERR_FORMAT,
        E::Option(_) => SFPM_ERR_ARGUMENT,
        E::NoDescriptors => SFPM_ERR_MISSING,
        _ => SFPM_ERR_LOCALIZE,
    }
}

/// A session's error as C sees it: the localizer's own message (an option's "ratio 1.5: a
/// ratio in (0, 1]", a query's dimension mismatch) without the map's path in front, as
/// `sfpm_localize` always gave it.
fn session_error(e: SessionError) -> FfiError {
    match e {
        SessionError::Localize { source, .. } | SessionError::Query { source, .. } => {
            FfiError::new(localize_error_code(&source), source.to_string())
        }
        SessionError::Map { source, .. } => source.into(),
        other => FfiError::new(SFPM_ERR_LOCALIZE, other.to_string()),
    }
}

struct Slot<T> {
    generation: u32,
    value: Option<Arc<T>>,
}

/// The live handles of one kind. A handle is `kind << 63 | generation << 32 | (slot + 1)`:
/// never 0, and a map handle is never a session handle.
struct Registry<T> {
    slots: Mutex<Vec<Slot<T>>>,
    /// The handle's top bit.
    kind: u64,
    /// "map" or "session", in errors.
    what: &'static str,
    /// The function that makes a handle of this kind, in errors.
    opener: &'static str,
}

/// Generations run from 1 to this and wrap to 1, so they fit beside the kind bit.
const MAX_GENERATION: u32 = (1 << 31) - 1;

static MAPS: Registry<MapHandle> = Registry::new(0, "map", "sfpm_open");
static SESSIONS: Registry<Session> = Registry::new(1, "session", "sfpm_session_open");

impl<T> Registry<T> {
    const fn new(kind: u64, what: &'static str, opener: &'static str) -> Self {
        Registry {
            slots: Mutex::new(Vec::new()),
            kind,
            what,
            opener,
        }
    }

    fn register(&self, value: T) -> u64 {
        let mut slots = lock(&self.slots);
        let index = match slots.iter().position(|s| s.value.is_none()) {
            Some(i) => i,
            None => {
                slots.push(Slot {
                    generation: 1,
                    value: None,
                });
                slots.len() - 1
            }
        };
        slots[index].value = Some(Arc::new(value));
        (self.kind << 63) | (u64::from(slots[index].generation) << 32) | (index as u64 + 1)
    }

    /// The slot and generation of `handle`, or why it cannot be one of this registry's.
    fn split(&self, handle: u64) -> FfiResult<(usize, u32)> {
        let what = self.what;
        if handle >> 63 != self.kind {
            let other = if self.kind == 0 { "a session" } else { "a map" };
            return Err(FfiError::new(
                SFPM_ERR_INVALID_HANDLE,
                format!("invalid {what} handle {handle:#x} ({other} handle?)"),
            ));
        }
        let index = (handle & 0xffff_ffff).checked_sub(1).ok_or_else(|| {
            FfiError::new(
                SFPM_ERR_INVALID_HANDLE,
                format!("invalid {what} handle {handle:#x}"),
            )
        })?;
        Ok((index as usize, ((handle >> 32) as u32) & MAX_GENERATION))
    }

    /// The live value, or `SFPM_ERR_INVALID_HANDLE`. The `Arc` keeps it alive for the call
    /// even if another thread closes the handle meanwhile.
    fn get(&self, handle: u64) -> FfiResult<Arc<T>> {
        let (index, generation) = self.split(handle)?;
        let slots = lock(&self.slots);
        match slots.get(index) {
            Some(Slot {
                generation: g,
                value: Some(v),
            }) if *g == generation => Ok(v.clone()),
            _ => Err(FfiError::new(
                SFPM_ERR_INVALID_HANDLE,
                format!(
                    "invalid {} handle {handle:#x} (closed, or not from {})",
                    self.what, self.opener
                ),
            )),
        }
    }

    /// Ends `handle`: its slot's generation moves on, so it is invalid from now on. The value
    /// is dropped outside the registry's lock (unmapping may take a moment), once the calls
    /// still running with it have returned.
    fn close(&self, handle: u64) -> FfiResult {
        let (index, generation) = self.split(handle)?;
        let taken = {
            let mut slots = lock(&self.slots);
            match slots.get_mut(index) {
                Some(slot) if slot.generation == generation && slot.value.is_some() => {
                    slot.generation = if slot.generation >= MAX_GENERATION {
                        1
                    } else {
                        slot.generation + 1
                    };
                    slot.value.take()
                }
                _ => None,
            }
        };
        match taken {
            Some(value) => {
                drop(value);
                Ok(())
            }
            None => Err(FfiError::new(
                SFPM_ERR_INVALID_HANDLE,
                format!("invalid {} handle {handle:#x} (already closed?)", self.what),
            )),
        }
    }
}

fn get(map: SfpmMap) -> FfiResult<Arc<MapHandle>> {
    MAPS.get(map)
}

/// Checks every out pointer of a call before anything is written, so a call that fails for
/// a NULL leaves the caller's other variables untouched.
fn non_null(pointers: &[(bool, &str)]) -> FfiResult {
    match pointers.iter().find(|(is_null, _)| *is_null) {
        Some((_, what)) => Err(FfiError::null(what)),
        None => Ok(()),
    }
}

/// Writes `value` to a caller's out pointer.
///
/// # Safety
/// `ptr` must be NULL (an error is returned) or valid for a write of one `T`.
unsafe fn put<T>(ptr: *mut T, value: T, what: &str) -> FfiResult {
    non_null(&[(ptr.is_null(), what)])?;
    // SAFETY: non-null, and valid for writes per this function's contract.
    unsafe { ptr.write(value) };
    Ok(())
}

/// Borrows `n` elements of a caller's input array (`n == 0` allows NULL).
///
/// # Safety
/// `ptr` must be NULL or valid for reads of `n` elements of `T` for the call's duration.
unsafe fn input<'a, T>(ptr: *const T, n: usize, what: &str) -> FfiResult<&'a [T]> {
    if n == 0 {
        return Ok(&[]);
    }
    non_null(&[(ptr.is_null(), what)])?;
    if n.checked_mul(std::mem::size_of::<T>())
        .is_none_or(|b| b > isize::MAX as usize)
    {
        return Err(FfiError::argument(format!("{what}: length {n} too large")));
    }
    // SAFETY: non-null, size checked against isize::MAX, valid for `n` reads per contract.
    Ok(unsafe { std::slice::from_raw_parts(ptr, n) })
}

/// Writes `value` to an out pointer the caller may pass as NULL to skip it.
///
/// # Safety
/// `ptr` must be NULL or valid for a write of one `T`.
unsafe fn put_opt<T>(ptr: *mut T, value: T) {
    if !ptr.is_null() {
        // SAFETY: non-null, and valid for writes per this function's contract.
        unsafe { ptr.write(value) };
    }
}

/// Copies up to `capacity` elements of `src` to a caller's array; returns how many.
///
/// # Safety
/// `dst` must be valid for `capacity` writes of `T` (NULL is allowed when `capacity == 0`).
unsafe fn copy_out<T: Copy>(src: &[T], dst: *mut T, capacity: usize) -> usize {
    let n = src.len().min(capacity);
    if n > 0 {
        // SAFETY: `0 < n <= capacity`: `dst` is valid for `n` writes per this function's
        // contract; `src` is ours and cannot overlap a caller's buffer.
        unsafe { std::ptr::copy_nonoverlapping(src.as_ptr(), dst, n) };
    }
    n
}

/// Copies `s` NUL-terminated into a caller's buffer of `capacity` bytes, truncated to fit.
///
/// # Safety
/// `buf` must be NULL (an error unless `capacity == 0`) or valid for `capacity` writes.
unsafe fn put_str(s: &str, buf: *mut c_char, capacity: usize, what: &str) -> FfiResult {
    if capacity == 0 {
        return Ok(());
    }
    non_null(&[(buf.is_null(), what)])?;
    // SAFETY: non-null and valid for `capacity` bytes per contract; `n < capacity`.
    unsafe {
        let n = copy_out(s.as_bytes(), buf.cast::<u8>(), capacity - 1);
        buf.add(n).write(0);
    }
    Ok(())
}

/// The `sfpm_*_count` functions: `count` of the map written to `*out`.
///
/// # Safety
/// `out` must be NULL (an error) or valid for one write.
unsafe fn put_count(
    map: SfpmMap,
    out: *mut usize,
    count: impl FnOnce(&Map) -> FfiResult<usize>,
) -> SfpmStatus {
    guard(|| {
        let n = count(&get(map)?.map)?;
        // SAFETY: per this function's contract.
        unsafe { put(out, n, "out") }.map(|()| SFPM_OK)
    })
}

/// The library version, e.g. "0.1.0". Static storage: never free it.
#[no_mangle]
pub extern "C" fn sfpm_version() -> *const c_char {
    concat!(env!("CARGO_PKG_VERSION"), "\0").as_ptr().cast()
}

/// The message of the last failed call on this thread (UTF-8, NUL-terminated; "" if none).
/// The pointer is owned by the library and valid until the next failing call on the same
/// thread. Each thread has its own last error, so threads never see each other's messages.
#[no_mangle]
pub extern "C" fn sfpm_last_error() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}

/// Opens (memory-maps) and validates the map at `path` (NUL-terminated, UTF-8) and writes its
/// handle to `*out`. Only the header, section table and metadata are read; sections are
/// checked on first access. Close the handle with `sfpm_close`.
///
/// # Safety
/// `path` must be a NUL-terminated string and `out` writable, or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_open(path: *const c_char, out: *mut SfpmMap) -> SfpmStatus {
    guard(|| {
        non_null(&[(path.is_null(), "path"), (out.is_null(), "out")])?;
        // SAFETY: non-null and NUL-terminated per contract.
        let path = unsafe { CStr::from_ptr(path) }
            .to_str()
            .map_err(|_| FfiError::argument("path is not UTF-8"))?;
        let map = Map::open(path)?;
        let handle = MAPS.register(MapHandle {
            map: Arc::new(map),
            path: path.to_string(),
            sessions: Mutex::new(Vec::new()),
            pinned: Mutex::new(HashMap::new()),
        });
        // SAFETY: checked non-null above; writable per contract.
        unsafe { put(out, handle, "out") }?;
        Ok(SFPM_OK)
    })
}

/// Closes a map: frees what the handle lent out, and unmaps the file unless a session still
/// holds it. Every pointer obtained from this handle becomes invalid; the handle itself
/// becomes invalid, and using it again (including a second close) returns
/// `SFPM_ERR_INVALID_HANDLE`. Sessions opened on the map (`sfpm_session_open`) keep working:
/// each holds the map until `sfpm_session_close`. A call running on another thread with the
/// same handle finishes safely first (the map is freed after it), but the pointers it returns
/// are dangling once close has returned: do not close a map other threads still read.
#[no_mangle]
pub extern "C" fn sfpm_close(map: SfpmMap) -> SfpmStatus {
    guard(|| {
        MAPS.close(map)?;
        Ok(SFPM_OK)
    })
}

/// Number of levels in the map.
///
/// # Safety
/// `out` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_level_count(map: SfpmMap, out: *mut usize) -> SfpmStatus {
    // SAFETY: `out` per contract.
    unsafe { put_count(map, out, |m| Ok(m.metadata().levels.len())) }
}

/// Writes up to `capacity` level ids (ascending) to `ids` and the number of levels to
/// `*count`. Call with `ids == NULL, capacity == 0` to get the count first.
///
/// # Safety
/// `ids` must be valid for `capacity` writes (or NULL with `capacity == 0`); `count` writable.
#[no_mangle]
pub unsafe extern "C" fn sfpm_level_ids(
    map: SfpmMap,
    ids: *mut u16,
    capacity: usize,
    count: *mut usize,
) -> SfpmStatus {
    guard(|| {
        non_null(&[
            (capacity > 0 && ids.is_null(), "ids"),
            (count.is_null(), "count"),
        ])?;
        let h = get(map)?;
        let all = h.map.level_ids();
        // SAFETY: `ids` is valid for `capacity` writes and `count` writable per contract.
        unsafe {
            copy_out(&all, ids, capacity);
            put(count, all.len(), "count")?;
        }
        Ok(SFPM_OK)
    })
}

/// Dimensions and point count of `level`.
///
/// # Safety
/// `out` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_level_info(
    map: SfpmMap,
    level: u16,
    out: *mut SfpmLevelInfo,
) -> SfpmStatus {
    guard(|| {
        let h = get(map)?;
        let l = h.map.level(level)?;
        let info = SfpmLevelInfo {
            level,
            dim_full: l.dim_full() as u32,
            dim_short: l.dim_short() as u32,
            points: l.len() as u64,
            has_descriptors: u8::from(l.has_descriptors()),
            has_rest: u8::from(l.has_rest()),
        };
        // SAFETY: per contract.
        unsafe { put(out, info, "out") }?;
        Ok(SFPM_OK)
    })
}

/// Global point indices of `level`'s rows (strictly increasing): `*len` `uint32_t`s at
/// `*points`. Zero-copy; valid until `sfpm_close`.
///
/// # Safety
/// `points` and `len` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_level_points(
    map: SfpmMap,
    level: u16,
    points: *mut *const u32,
    len: *mut usize,
) -> SfpmStatus {
    guard(|| {
        non_null(&[(points.is_null(), "points"), (len.is_null(), "len")])?;
        let h = get(map)?;
        let l = h.map.level(level)?;
        // SAFETY: checked non-null above; writable per contract.
        unsafe { h.lend((SectionKind::LevelPoints, level), l.points()?, points, len) };
        Ok(SFPM_OK)
    })
}

/// The `short` descriptor block of `level`: `points × dim_short` IEEE half floats (binary16
/// bit patterns as `uint16_t`), row-major, `*len` elements. Raw sections point into the
/// mapped file; zstd sections are decoded once into a buffer owned by the handle. Either way
/// the pointer is valid until `sfpm_close`. `SFPM_ERR_MISSING` for a geometry-only level.
///
/// # Safety
/// `data` and `len` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_level_desc_short(
    map: SfpmMap,
    level: u16,
    data: *mut *const u16,
    len: *mut usize,
) -> SfpmStatus {
    guard(|| {
        non_null(&[(data.is_null(), "data"), (len.is_null(), "len")])?;
        let h = get(map)?;
        let l = h.map.level(level)?;
        let desc = l.desc_short()?;
        // SAFETY: checked non-null above; writable per contract.
        unsafe { h.lend((SectionKind::LevelDescShort, level), desc, data, len) };
        Ok(SFPM_OK)
    })
}

/// The `rest` descriptor block of `level`: `points × (dim_full − dim_short)` half floats,
/// row-major; row r's full descriptor is short row r followed by rest row r. Same lifetime
/// as `sfpm_level_desc_short`. `SFPM_ERR_MISSING` when the level has no `rest` block.
///
/// # Safety
/// `data` and `len` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_level_desc_rest(
    map: SfpmMap,
    level: u16,
    data: *mut *const u16,
    len: *mut usize,
) -> SfpmStatus {
    guard(|| {
        non_null(&[(data.is_null(), "data"), (len.is_null(), "len")])?;
        let h = get(map)?;
        let l = h.map.level(level)?;
        let desc = l.desc_rest()?.ok_or_else(|| {
            FfiError::new(SFPM_ERR_MISSING, format!("level {level} has no rest block"))
        })?;
        // SAFETY: checked non-null above; writable per contract.
        unsafe { h.lend((SectionKind::LevelDescRest, level), desc, data, len) };
        Ok(SFPM_OK)
    })
}

/// The PQ codes and codebook of a product-quantised `level` into `*out`. `SFPM_ERR_MISSING`
/// when the level stores f16 blocks (see `sfpm_level_desc_short`).
///
/// # Safety
/// `out` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_level_pq(
    map: SfpmMap,
    level: u16,
    out: *mut SfpmLevelPq,
) -> SfpmStatus {
    guard(|| {
        non_null(&[(out.is_null(), "out")])?;
        let h = get(map)?;
        let pq = h.map.level(level)?.pq()?.ok_or_else(|| {
            FfiError::new(
                SFPM_ERR_MISSING,
                format!("level {level} is not product-quantised"),
            )
        })?;
        let (mut codes, mut codes_len) = (std::ptr::null::<u8>(), 0usize);
        let (mut codebook, mut codebook_len) = (std::ptr::null::<f32>(), 0usize);
        // SAFETY: locals, writable.
        unsafe {
            h.lend(
                (SectionKind::LevelPqCodes, level),
                pq.codes,
                &mut codes,
                &mut codes_len,
            );
            h.lend(
                (SectionKind::LevelPqCodebook, level),
                pq.codebook,
                &mut codebook,
                &mut codebook_len,
            );
        }
        let (mut order, mut order_len) = (std::ptr::null::<u16>(), 0usize);
        if let Some(o) = pq.order {
            // SAFETY: locals, writable.
            unsafe {
                h.lend(
                    (SectionKind::LevelPqOrder, level),
                    o,
                    &mut order,
                    &mut order_len,
                )
            };
        }
        let value = SfpmLevelPq {
            subspaces: pq.subspaces as u32,
            centroids: pq.centroids as u32,
            sub_dims: pq.sub_dims as u32,
            codes,
            codes_len,
            codebook,
            codebook_len,
            order,
            order_len,
        };
        // SAFETY: per contract.
        unsafe { put(out, value, "out") }?;
        Ok(SFPM_OK)
    })
}

/// Number of 3D points in the map.
///
/// # Safety
/// `out` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_point_count(map: SfpmMap, out: *mut usize) -> SfpmStatus {
    // SAFETY: `out` per contract.
    unsafe { put_count(map, out, |m| Ok(m.n_points() as usize)) }
}

/// Point positions: `*n_points` rows of 3 floats (x y z) relative to the map origin, which is
/// written to `origin[0..3]` as doubles: world = origin + position (f32 keeps ~7 digits
/// relative to the origin, f64 the rest). Zero-copy; valid until `sfpm_close`.
///
/// # Safety
/// `positions` and `n_points` must be writable; `origin` must be valid for 3 doubles, or NULL
/// to skip it.
#[no_mangle]
pub unsafe extern "C" fn sfpm_point_positions(
    map: SfpmMap,
    positions: *mut *const f32,
    n_points: *mut usize,
    origin: *mut f64,
) -> SfpmStatus {
    guard(|| {
        non_null(&[
            (positions.is_null(), "positions"),
            (n_points.is_null(), "n_points"),
        ])?;
        let h = get(map)?;
        let data = h.map.point_positions()?;
        // SAFETY: `positions` and `n_points` checked non-null above and writable, `origin` NULL
        // or valid for 3 doubles, i.e. one `[f64; 3]` (alignment of `f64`), per contract.
        unsafe {
            h.lend((SectionKind::PointPositions, 0), data, positions, n_points);
            put_opt(origin.cast::<[f64; 3]>(), h.map.metadata().origin);
        }
        Ok(SFPM_OK)
    })
}

/// Number of cameras in the map's metadata (what `sfpm_image_pose`'s `camera` indexes).
///
/// # Safety
/// `out` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_camera_count(map: SfpmMap, out: *mut usize) -> SfpmStatus {
    // SAFETY: `out` per contract.
    unsafe { put_count(map, out, |m| Ok(m.metadata().cameras.len())) }
}

/// Camera `index`: its COLMAP model name copied into `model` (NUL-terminated, truncated to
/// `model_capacity` bytes; 32 always suffice), width and height, and up to `params_capacity`
/// parameters in COLMAP order into `params`, with their full count in `*n_params`.
/// `model`/`params` may be NULL with a zero capacity; the other out pointers may be NULL
/// to skip them.
///
/// # Safety
/// `model` must be valid for `model_capacity` bytes and `params` for `params_capacity`
/// doubles; `width`, `height` and `n_params` writable or NULL.
#[no_mangle]
pub unsafe extern "C" fn sfpm_camera(
    map: SfpmMap,
    index: usize,
    model: *mut c_char,
    model_capacity: usize,
    width: *mut u64,
    height: *mut u64,
    params: *mut f64,
    params_capacity: usize,
    n_params: *mut usize,
) -> SfpmStatus {
    guard(|| {
        non_null(&[
            (model_capacity > 0 && model.is_null(), "model"),
            (params_capacity > 0 && params.is_null(), "params"),
        ])?;
        let h = get(map)?;
        let cameras = &h.map.metadata().cameras;
        let camera = cameras
            .get(index)
            .ok_or_else(|| out_of_range("camera", index, cameras.len()))?;
        // SAFETY: `model` and `params` are valid for their capacities (checked non-null unless
        // 0), `width`, `height` and `n_params` NULL or writable, per contract.
        unsafe {
            put_str(&camera.model, model, model_capacity, "model")?;
            copy_out(&camera.params, params, params_capacity);
            put_opt(width, camera.width);
            put_opt(height, camera.height);
            put_opt(n_params, camera.params.len());
        }
        Ok(SFPM_OK)
    })
}

/// Number of database images (0 when the map stores none).
///
/// # Safety
/// `out` must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_image_count(map: SfpmMap, out: *mut usize) -> SfpmStatus {
    // SAFETY: `out` per contract.
    unsafe { put_count(map, out, |m| Ok(m.images()?.map_or(0, |i| i.len()))) }
}

/// Copies image `index`'s name into `buf` (at most `capacity` bytes including the NUL,
/// truncated if needed) and writes the name's full length in bytes (without NUL) to
/// `*needed` when `needed` is not NULL, like `snprintf`. `buf` may be NULL with
/// `capacity == 0` to query the length.
///
/// # Safety
/// `buf` must be valid for `capacity` writes (or NULL with `capacity == 0`); `needed` must be
/// writable or NULL.
#[no_mangle]
pub unsafe extern "C" fn sfpm_image_name(
    map: SfpmMap,
    index: usize,
    buf: *mut c_char,
    capacity: usize,
    needed: *mut usize,
) -> SfpmStatus {
    guard(|| {
        let h = get(map)?;
        let images = images_at(&h.map, index)?;
        let name = images.name(index)?;
        // SAFETY: `buf` NULL or valid for `capacity` bytes, `needed` NULL or writable (contract).
        unsafe {
            put_str(name, buf, capacity, "buf")?;
            put_opt(needed, name.len());
        }
        Ok(SFPM_OK)
    })
}

/// Image `index`'s pose `cam_from_world` as qw qx qy qz tx ty tz into `pose[0..7]`, and its
/// camera's index in the map's camera list into `*camera` (if not NULL).
///
/// # Safety
/// `pose` must be valid for 7 doubles; `camera` writable or NULL.
#[no_mangle]
pub unsafe extern "C" fn sfpm_image_pose(
    map: SfpmMap,
    index: usize,
    pose: *mut f64,
    camera: *mut u32,
) -> SfpmStatus {
    guard(|| {
        let h = get(map)?;
        let images = images_at(&h.map, index)?;
        // SAFETY: `pose` is NULL (reported) or valid for 7 doubles, one `[f64; 7]` (same
        // alignment as `f64`); `camera` NULL or writable; per contract.
        unsafe {
            put(pose.cast::<[f64; 7]>(), images.poses[index], "pose")?;
            put_opt(camera, images.cameras[index]);
        }
        Ok(SFPM_OK)
    })
}

/// The image → point visibility in CSR form: image i sees
/// `points[offsets[i] .. offsets[i + 1]]` (global point indices). `*n_offsets` is
/// images + 1 and `*n_points` the total entries. Zero-copy; valid until `sfpm_close`.
/// `SFPM_ERR_MISSING` when the map stores no visibility.
///
/// # Safety
/// All four out pointers must be writable or NULL (an error).
#[no_mangle]
pub unsafe extern "C" fn sfpm_visibility(
    map: SfpmMap,
    offsets: *mut *const u64,
    n_offsets: *mut usize,
    points: *mut *const u32,
    n_points: *mut usize,
) -> SfpmStatus {
    guard(|| {
        non_null(&[
            (offsets.is_null(), "offsets"),
            (n_offsets.is_null(), "n_offsets"),
            (points.is_null(), "points"),
            (n_points.is_null(), "n_points"),
        ])?;
        let h = get(map)?;
        let vis = h
            .map
            .visibility()?
            .ok_or_else(|| FfiError::new(SFPM_ERR_MISSING, "the map stores no visibility"))?;
        // SAFETY: checked non-null above; writable per contract.
        unsafe {
            h.lend(
                (SectionKind::VisibilityOffsets, 0),
                vis.offsets,
                offsets,
                n_offsets,
            );
            h.lend(
                (SectionKind::VisibilityPoints, 0),
                vis.points,
                points,
                n_points,
            );
        }
        Ok(SFPM_OK)
    })
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
    /// The features, one set for every level; NaN and infinity refused.
    fn features(&self) -> FfiResult<QueryFeatures> {
        if self.xy.iter().any(|v| !v.is_finite()) || self.desc.iter().any(|v| !v.is_finite()) {
            return Err(FfiError::argument(
                "keypoints or descriptors hold NaN or infinity",
            ));
        }
        Ok(QueryFeatures {
            sets: vec![FeatureSet {
                level: None,
                keypoints: self.xy.chunks_exact(2).map(|p| [p[0], p[1]]).collect(),
                descriptors: self.desc.to_vec(),
                dim: self.dim,
            }],
            global: None,
            model: None,
        })
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
/// descriptors to f32, noticeable on a large map); later calls reuse that until close.
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
        let features = query.features()?;
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
/// maps), not a sequence. Start a session's options from these and change what you need.
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
        };
        // SAFETY: checked non-null above; writable per contract.
        unsafe { put(out, value, "out") }?;
        Ok(SFPM_OK)
    })
}

/// Opens a session on `map`: the localizer prepared with `options` (NULL: the map's own
/// settings, as `sfpm_session_options_default` gives them), its handle written to `*out`.
/// Options out of range are refused (`SFPM_ERR_ARGUMENT`, and `sfpm_last_error` names the
/// option, e.g. "ratio 1.5: a ratio in (0, 1]"), as are levels the map lacks
/// (`SFPM_ERR_NO_SUCH_LEVEL`). Opening prepares the levels (decodes descriptors to f32,
/// noticeable on a large map).
///
/// The session holds the map: closing the map handle first is allowed, and the session goes
/// on working until `sfpm_session_close` (the file is unmapped when both are closed). Close
/// every session with `sfpm_session_close`.
///
/// # Safety
/// `options` must be NULL or point to a valid `SfpmSessionOptions` (its `levels` valid for
/// `n_levels` ids during the call); `out` must be writable or NULL (an error).
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
            // SAFETY: non-null, points to a valid SfpmSessionOptions per contract.
            let o = unsafe { &*options };
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
    guard(|| {
        let s = SESSIONS.get(session)?;
        non_null(&[(out.is_null(), "out"), (camera.is_null(), "camera")])?;
        // SAFETY: the arrays and the camera per this function's contract.
        let query = unsafe { read_query(keypoints, descriptors, n, dim, camera)? };
        let features = query.features()?;
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

/// The map's images, `index` checked against them.
fn images_at<'m>(map: &'m Map<'_>, index: usize) -> FfiResult<Images<'m>> {
    let images = map
        .images()?
        .ok_or_else(|| FfiError::new(SFPM_ERR_MISSING, "the map stores no images"))?;
    if index >= images.len() {
        return Err(out_of_range("image", index, images.len()));
    }
    Ok(images)
}

fn out_of_range(what: &str, index: usize, len: usize) -> FfiError {
    FfiError::argument(format!(
        "{what} index {index} out of range (the map has {len})"
    ))
}
