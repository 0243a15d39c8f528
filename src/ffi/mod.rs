//! The C ABI (feature `capi`): open a map, read its levels, descriptors, points, images and
//! visibility without copying, and localize queries, one at a time (`sfpm_localize`) or
//! through a session with every option and a sequence's tracking (`sfpm_session_*`, a
//! [`Session`](crate::session::Session) behind a handle). `include/sfpmap.h` is generated
//! from this module by cbindgen (`include/cbindgen.toml`); the doc comments of its C items
//! are the header's.
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
//!
//! The files: this one holds the status codes, the error plumbing (the thread's last error,
//! `guard`) and the reads and writes of the caller's pointers; `handles.rs` the registry
//! behind both kinds of handle; `map.rs` opening a map and reading it; `session.rs` the
//! query's C types, `sfpm_localize` and the sessions. cbindgen reads them in that order (this
//! file, then its `mod`s as declared), which is the order of the header's functions.

#![allow(unsafe_code)]
#![deny(unsafe_op_in_unsafe_fn)]

mod handles;
mod map;
mod session;

pub use handles::{SfpmMap, SfpmSession};
pub use map::{
    sfpm_camera, sfpm_camera_count, sfpm_close, sfpm_image_count, sfpm_image_name, sfpm_image_pose,
    sfpm_level_count, sfpm_level_desc_rest, sfpm_level_desc_short, sfpm_level_ids, sfpm_level_info,
    sfpm_level_points, sfpm_level_pq, sfpm_open, sfpm_point_count, sfpm_point_positions,
    sfpm_visibility, SfpmLevelInfo, SfpmLevelPq,
};
pub use session::{
    sfpm_localize, sfpm_session_close, sfpm_session_is_tracking, sfpm_session_localize,
    sfpm_session_localize_global, sfpm_session_open, sfpm_session_options_default,
    sfpm_session_reset_tracking, SfpmCamera, SfpmLocalization, SfpmLocalizeOptions, SfpmRetrieval,
    SfpmSessionOptions, SFPM_SESSION_OPTIONS_SIZE_1,
};

use crate::format::Error as FormatError;
use crate::session::SessionError;
use crate::ErrorKind;
use std::cell::RefCell;
use std::ffi::{c_char, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Mutex, MutexGuard};

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

/// The status of a library error: the one place C's codes are made from the library's
/// [`ErrorKind`]s (which the Python package's exception classes are made from too).
fn status(kind: ErrorKind) -> SfpmStatus {
    match kind {
        ErrorKind::Io => SFPM_ERR_IO,
        ErrorKind::Format => SFPM_ERR_FORMAT,
        ErrorKind::NoSuchLevel => SFPM_ERR_NO_SUCH_LEVEL,
        ErrorKind::Missing | ErrorKind::NoDescriptors => SFPM_ERR_MISSING,
        ErrorKind::InvalidArgument | ErrorKind::Input => SFPM_ERR_ARGUMENT,
        // What stops a query (C sessions neither extract nor convert; were they to, the
        // query could not run either).
        ErrorKind::Mismatch
        | ErrorKind::Localize
        | ErrorKind::Extract
        | ErrorKind::Convert
        | ErrorKind::Other => SFPM_ERR_LOCALIZE,
    }
}

impl From<FormatError> for FfiError {
    fn from(e: FormatError) -> Self {
        let e = crate::Error::from(e);
        FfiError::new(status(e.kind()), e.to_string())
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

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic while holding the lock was already reported; the data is still consistent
    // (every critical section here is a single insert or lookup).
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A session's error as C sees it: the code of its [`ErrorKind`], and the localizer's own
/// message (an option's "ratio 1.5: a ratio in (0, 1]", a query's dimension mismatch) without
/// the map's path in front, as `sfpm_localize` always gave it.
fn session_error(e: SessionError) -> FfiError {
    let code = status(e.kind());
    match e {
        SessionError::Localize { source, .. } | SessionError::Query { source, .. } => {
            FfiError::new(code, source.to_string())
        }
        SessionError::Map { source, .. } => FfiError::new(code, source.to_string()),
        other => FfiError::new(code, other.to_string()),
    }
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
