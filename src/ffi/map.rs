//! Opening a map (`sfpm_open`, `sfpm_close`) and reading it: levels, descriptors (f16 blocks
//! and PQ codes), points, cameras, images and visibility, lent without copying.

use super::handles::{get, SfpmMap, MAPS};
use super::SfpmStatus::*;
use super::{
    copy_out, guard, lock, non_null, put, put_opt, put_str, session_error, FfiError, FfiResult,
    SfpmStatus,
};
use crate::format::{Images, Map, SectionKind};
use crate::localize::LocalizeOptions;
use crate::session::Session;
use std::any::Any;
use std::borrow::Cow;
use std::collections::HashMap;
use std::ffi::{c_char, CStr};
use std::sync::{Arc, Mutex};

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

/// Owns the map and whatever the handle lends out.
pub(super) struct MapHandle {
    /// Shared with the handle's sessions (`sfpm_session_open`), which keep it open after
    /// `sfpm_close`.
    pub(super) map: Arc<Map<'static>>,
    /// The path it was opened from: the name sessions give it.
    pub(super) path: String,
    /// `sfpm_localize`'s sessions, one per set of options, built on first use (each indexes
    /// the levels it matches: projections, retrieval, viewpoints): the [`SESSION_CACHE`] most
    /// recently used, least recently used first.
    sessions: Mutex<Vec<(LocalizerKey, Arc<Session>)>>,
    /// Arrays the map could only give as owned copies (a buffer not aligned for the type),
    /// kept so their pointers stay valid until close. With `sfpm_open` (mmap, page-aligned)
    /// every section is borrowed and this stays empty.
    pinned: Mutex<HashMap<(SectionKind, u16), Box<dyn Any + Send + Sync>>>,
}

/// How many of `sfpm_localize`'s sessions a map handle keeps (its last sets of options). Each
/// holds its own index of the levels it matches, the retrieval index and the viewpoints
/// (descriptors stay views of the map): a caller cycling through more sets of options pays
/// for preparing them again (about 3 to 7 ms on a 1 M-point map), never for memory without
/// bound. An application with more settings opens sessions (`sfpm_session_open`).
/// `sfpm_localize`'s doc (the header's) states the number.
pub(super) const SESSION_CACHE: usize = 4;

#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub(super) struct LocalizerKey {
    pub(super) levels: Vec<u16>,
    pub(super) short: bool,
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
    /// levels and block, built on first use (outside the lock: preparing the levels takes a
    /// while, and other options' queries go on meanwhile) and kept among the
    /// [`SESSION_CACHE`] most recently used. Two threads that build the same session at once
    /// both use the first one kept; the other is dropped.
    pub(super) fn session(&self, key: LocalizerKey) -> FfiResult<Arc<Session>> {
        if let Some(session) = self.cached(&key) {
            return Ok(session);
        }
        let options = LocalizeOptions {
            levels: key.levels.clone(),
            short: key.short,
            ..LocalizeOptions::for_map(&self.map)
        };
        let built = Session::builder(self.map.clone(), self.path.clone())
            .options(options)
            .build(&crate::progress::Silent)
            .map_err(session_error)?;
        let mut cache = lock(&self.sessions);
        if let Some(i) = cache.iter().position(|(k, _)| *k == key) {
            // Another thread built it meanwhile: that one is kept, this one dropped (after
            // the lock, as `built` was made before the guard).
            let entry = cache.remove(i);
            let session = entry.1.clone();
            cache.push(entry);
            return Ok(session);
        }
        // The least recently used goes, freed outside the lock (a call still running with
        // it holds its `Arc`).
        let evicted = (cache.len() >= SESSION_CACHE).then(|| cache.remove(0));
        let session = Arc::new(built);
        cache.push((key, session.clone()));
        drop(cache);
        drop(evicted);
        Ok(session)
    }

    /// The kept session for `key`, now the most recently used.
    fn cached(&self, key: &LocalizerKey) -> Option<Arc<Session>> {
        let mut cache = lock(&self.sessions);
        let i = cache.iter().position(|(k, _)| k == key)?;
        let entry = cache.remove(i);
        let session = entry.1.clone();
        cache.push(entry);
        Some(session)
    }

    /// The options of the kept sessions, least recently used first (for the tests).
    #[cfg(test)]
    fn cached_keys(&self) -> Vec<LocalizerKey> {
        lock(&self.sessions)
            .iter()
            .map(|(k, _)| k.clone())
            .collect()
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    fn levels_map() -> MapHandle {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/spec/vectors/valid/levels.sfpm"
        );
        MapHandle {
            map: Arc::new(Map::open(path).unwrap()),
            path: path.to_string(),
            sessions: Mutex::default(),
            pinned: Mutex::default(),
        }
    }

    fn key(levels: &[u16], short: bool) -> LocalizerKey {
        LocalizerKey {
            levels: levels.to_vec(),
            short,
        }
    }

    fn session(handle: &MapHandle, key: &LocalizerKey) -> Arc<Session> {
        match handle.session(key.clone()) {
            Ok(s) => s,
            Err(e) => panic!("{}", e.message),
        }
    }

    /// `sfpm_localize`'s sessions: at most `SESSION_CACHE` kept, the least recently used
    /// dropped first, a kept one reused (the same session), a dropped one built again.
    #[test]
    fn the_session_cache_keeps_the_most_recently_used() {
        let handle = levels_map();
        let keys = [
            key(&[], false),
            key(&[0], false),
            key(&[1], false),
            key(&[2], false),
            key(&[0], true),
            key(&[1], true),
        ];
        assert!(keys.len() > SESSION_CACHE + 1);
        let first = session(&handle, &keys[0]);
        for k in &keys[1..SESSION_CACHE] {
            session(&handle, k);
        }
        assert_eq!(handle.cached_keys(), keys[..SESSION_CACHE]);
        // Used again: the same session, now the most recently used.
        assert!(Arc::ptr_eq(&first, &session(&handle, &keys[0])));
        for k in &keys[SESSION_CACHE..] {
            session(&handle, k);
        }
        let kept = handle.cached_keys();
        assert_eq!(kept.len(), SESSION_CACHE, "{kept:?}");
        assert!(kept.contains(&keys[0]), "used recently: kept");
        let dropped = &keys[1..=keys.len() - SESSION_CACHE];
        assert!(dropped.iter().all(|k| !kept.contains(k)), "{kept:?}");
        assert_eq!(kept.last(), keys.last());
        assert!(Arc::ptr_eq(&first, &session(&handle, &keys[0])));
        // A dropped one is made again, and evicts the least recently used in turn.
        session(&handle, &keys[1]);
        let again = handle.cached_keys();
        assert_eq!(again.len(), SESSION_CACHE);
        assert_eq!(again.last(), Some(&keys[1]));
        assert!(!again.contains(&kept[0]), "{again:?}");
    }

    /// Threads asking for the same new options at once each get a session, all the one
    /// kept: a duplicate built meanwhile is dropped, not cached beside it.
    #[test]
    fn threads_building_the_same_session_share_the_one_kept() {
        let handle = levels_map();
        let k = key(&[2], true);
        let barrier = std::sync::Barrier::new(4);
        let sessions: Vec<Arc<Session>> = std::thread::scope(|s| {
            let threads: Vec<_> = (0..4)
                .map(|_| {
                    s.spawn(|| {
                        barrier.wait();
                        session(&handle, &k)
                    })
                })
                .collect();
            threads.into_iter().map(|t| t.join().unwrap()).collect()
        });
        assert!(sessions.iter().all(|s| Arc::ptr_eq(s, &sessions[0])));
        assert_eq!(handle.cached_keys(), [k]);
    }
}
