//! The on-disk cache of sections read from object storage.
//!
//! Layout: `<dir>/remote-sections/<xxh3 of the URL>/object.json` (the URL and the ETag /
//! last-modified of the object the entries came from) and one file per section,
//! `<index checksum>-<section index>.bin`, holding exactly the bytes a
//! [`Wanted`](crate::format::Wanted) names. An entry is written only after it matched its
//! checksum, through the one atomic writer (relative to the URL's open folder), so a partial
//! download is never left; it is
//! checked again when read, and a damaged one is removed. When the object's ETag or
//! last-modified differs from the recorded one, the URL's entries are dropped. Past the size
//! cap, the least recently used entries (by modification time, touched on every hit) go.
//!
//! Why file descriptors: the cache folder may be shared, or written by someone else, so a
//! folder in it may be a symbolic link planted to aim our reads, touches and unlinks at
//! another folder's files. Every open, stat, write and unlink below is relative to an open
//! folder (`openat`/`renameat`/`unlinkat`, `O_NOFOLLOW`; writes through
//! [`output::write_bytes_in`](crate::output::write_bytes_in)), so swapping a folder for a
//! link after it was opened aims nothing elsewhere. A folder that is a link, or that is not
//! safely ours (another user's, or writable by group or others, who could swap what is in
//! it), is never entered: `remote-sections` or the URL's own folder being one turns the cache
//! off for that URL, and trimming leaves such folders alone; both are counted
//! ([`Unusable::Unsafe`], [`Trimmed::links_skipped`]) for the caller to report. Off Unix the
//! cache is not used.

use crate::format::{checksum, Wanted};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The folder under the cache root that holds the sections.
const CACHE_FOLDER: &str = "remote-sections";

/// The record of the object the entries came from.
const RECORD: &str = "object.json";

/// The largest `object.json` read (a URL and two short strings).
const RECORD_MAX_BYTES: u64 = 64 << 10;

/// `<16 hex digits>-<section index>.bin`: the only files the cache trims.
fn is_entry_name(name: &str) -> bool {
    let Some((checksum, rest)) = name.split_once('-') else {
        return false;
    };
    let Some(index) = rest.strip_suffix(".bin") else {
        return false;
    };
    checksum.len() == 16
        && checksum.bytes().all(|b| b.is_ascii_hexdigit())
        && !index.is_empty()
        && index.bytes().all(|b| b.is_ascii_digit())
}

#[derive(Debug, Serialize, Deserialize, PartialEq)]
struct ObjectVersion {
    url: String,
    e_tag: Option<String>,
    last_modified: String,
}

/// Why a URL has no cache.
#[derive(Debug, PartialEq, Eq)]
pub enum Unusable {
    /// The folders could not be made or opened (read-only, off Unix): quietly no cache.
    Unavailable,
    /// The URL's folder (or the cache's own) is a symbolic link, not a folder, another
    /// user's, or writable by group or others: never used, and reported.
    Unsafe,
}

/// What [`Cache::trim`] did.
#[derive(Debug, Default, PartialEq, Eq)]
pub struct Trimmed {
    /// Entries removed.
    pub removed: u64,
    /// Per-URL folders that are symbolic links, not folders, or not safely ours, left alone.
    pub links_skipped: u64,
}

/// One URL's folder in the cache. Failures to read or write the cache never fail a read:
/// the cache is an optimisation, and the origin is always there to read from.
#[derive(Debug)]
pub struct Cache {
    /// `<root>/remote-sections/<hash>`: the URL's folder, for messages (never looked up).
    dir: PathBuf,
    #[cfg(unix)]
    root_fd: std::os::fd::OwnedFd,
    #[cfg(unix)]
    dir_fd: std::os::fd::OwnedFd,
    max_bytes: u64,
}

#[cfg(unix)]
mod at {
    //! `*at` calls relative to an open folder, never following a final symbolic link.
    use rustix::fs::{AtFlags, FileType, Mode, OFlags, Stat};
    use rustix::io::Errno;
    use std::os::fd::{AsFd, OwnedFd};

    /// Opens the folder `name` in `dir`: `Err(None)` when it is a link, not a folder, or
    /// not [`safe`], `Err(Some(errno))` for any other failure.
    pub fn open_folder(dir: impl AsFd, name: &str) -> Result<OwnedFd, Option<Errno>> {
        let flags = OFlags::RDONLY | OFlags::DIRECTORY | OFlags::NOFOLLOW | OFlags::CLOEXEC;
        match rustix::fs::openat(dir, name, flags, Mode::empty()) {
            Ok(fd) if safe(&fd) => Ok(fd),
            Ok(_) | Err(Errno::LOOP | Errno::NOTDIR) => Err(None),
            Err(e) => Err(Some(e)),
        }
    }

    /// Whether the open folder is ours alone: owned by this process's user and writable by
    /// neither group nor others (who could otherwise swap what is in it, or have planted it).
    pub fn safe(fd: impl AsFd) -> bool {
        rustix::fs::fstat(fd).is_ok_and(|st| {
            st.st_uid == rustix::process::geteuid().as_raw()
                && Mode::from_raw_mode(st.st_mode).intersection(Mode::WGRP | Mode::WOTH)
                    == Mode::empty()
        })
    }

    /// [`open_folder`], making the folder first when it is missing.
    pub fn open_or_make_folder(dir: impl AsFd, name: &str) -> Result<OwnedFd, Option<Errno>> {
        match open_folder(dir.as_fd(), name) {
            Err(Some(Errno::NOENT)) => {
                match rustix::fs::mkdirat(dir.as_fd(), name, Mode::from_raw_mode(0o755)) {
                    Ok(()) | Err(Errno::EXIST) => open_folder(dir, name),
                    Err(e) => Err(Some(e)),
                }
            }
            other => other,
        }
    }

    /// A regular file `name` in `dir`, opened for reading (a link is refused).
    pub fn open_file(dir: impl AsFd, name: &str) -> Option<std::fs::File> {
        let flags = OFlags::RDONLY | OFlags::NOFOLLOW | OFlags::NONBLOCK | OFlags::CLOEXEC;
        let fd = rustix::fs::openat(dir, name, flags, Mode::empty()).ok()?;
        let file = std::fs::File::from(fd);
        file.metadata().ok()?.is_file().then_some(file)
    }

    /// `name` in `dir`, not followed if it is a link.
    pub fn stat(dir: impl AsFd, name: &str) -> Option<Stat> {
        rustix::fs::statat(dir, name, AtFlags::SYMLINK_NOFOLLOW).ok()
    }

    pub fn is_regular(stat: &Stat) -> bool {
        FileType::from_raw_mode(stat.st_mode) == FileType::RegularFile
    }

    /// Modification time and length.
    #[allow(clippy::unnecessary_cast)] // the field types differ between targets
    pub fn used_and_len(stat: &Stat) -> ((i64, i64), u64) {
        (
            (stat.st_mtime as i64, stat.st_mtime_nsec as i64),
            stat.st_size as u64,
        )
    }

    /// Removes `name` from `dir` (a link is removed, not what it points to).
    pub fn unlink(dir: impl AsFd, name: &str) -> bool {
        rustix::fs::unlinkat(dir, name, AtFlags::empty()).is_ok()
    }

    /// The names in folder `dir` (`.` and `..` left out), as UTF-8 (others are not ours).
    pub fn names(dir: impl AsFd) -> Vec<String> {
        let Ok(listing) = rustix::fs::Dir::read_from(dir) else {
            return Vec::new();
        };
        listing
            .flatten()
            .filter_map(|e| e.file_name().to_str().ok().map(str::to_string))
            .filter(|n| n != "." && n != "..")
            .collect()
    }
}

impl Cache {
    /// The cache for `url` in `root`, emptied first if the object changed since its entries
    /// were written. [`Unusable::Unsafe`] when the URL's folder (or `remote-sections`) is a
    /// symbolic link, not a folder, another user's or writable by others: it is never used.
    pub fn open(
        root: &Path,
        url: &str,
        e_tag: Option<&str>,
        last_modified: impl std::fmt::Display,
        max_bytes: u64,
    ) -> Result<Cache, Unusable> {
        let name = format!("{:016x}", checksum(url.as_bytes()));
        let dir = root.join(CACHE_FOLDER).join(&name);
        let version = ObjectVersion {
            url: url.to_string(),
            e_tag: e_tag.map(str::to_string),
            last_modified: last_modified.to_string(),
        };
        #[cfg(unix)]
        {
            // The root itself is the user's choice (it may be reached through links); what
            // is inside it is not.
            std::fs::create_dir_all(root).map_err(|_| Unusable::Unavailable)?;
            let base = std::fs::File::open(root).map_err(|_| Unusable::Unavailable)?;
            let folder = |dir: &dyn std::os::fd::AsFd, name: &str| {
                at::open_or_make_folder(dir.as_fd(), name).map_err(|e| match e {
                    None => Unusable::Unsafe,
                    Some(_) => Unusable::Unavailable,
                })
            };
            let root_fd = folder(&base, CACHE_FOLDER)?;
            let dir_fd = folder(&root_fd, &name)?;
            let cache = Cache {
                dir,
                root_fd,
                dir_fd,
                max_bytes,
            };
            if cache.recorded().as_ref() != Some(&version) {
                cache.empty();
                if let Ok(json) = serde_json::to_vec(&version) {
                    cache.write(RECORD, &json);
                }
            }
            Ok(cache)
        }
        #[cfg(not(unix))]
        {
            let _ = (dir, version, max_bytes);
            Err(Unusable::Unavailable)
        }
    }

    fn entry_name(index_checksum: u64, want: &Wanted) -> String {
        format!("{index_checksum:016x}-{}.bin", want.index)
    }

    /// The path of an entry (tests, messages).
    #[cfg(test)]
    fn entry(&self, index_checksum: u64, want: &Wanted) -> PathBuf {
        self.dir.join(Cache::entry_name(index_checksum, want))
    }

    /// The cached bytes of `want`, if present and still what the table says.
    pub fn get(&self, index_checksum: u64, want: &Wanted) -> Option<Vec<u8>> {
        #[cfg(unix)]
        {
            use std::io::Read;
            let name = Cache::entry_name(index_checksum, want);
            let file = at::open_file(&self.dir_fd, &name)?;
            // At most one byte more than wanted: a longer file is damaged, whatever its length.
            let len = want.range.end.saturating_sub(want.range.start);
            let mut bytes = Vec::new();
            (&file).take(len + 1).read_to_end(&mut bytes).ok()?;
            if !want.matches(&bytes) {
                at::unlink(&self.dir_fd, &name);
                return None;
            }
            // Least recently used goes first: a hit counts as a use (on the file we opened).
            let _ = file.set_modified(std::time::SystemTime::now());
            Some(bytes)
        }
        #[cfg(not(unix))]
        {
            let _ = (index_checksum, want);
            None
        }
    }

    /// Keeps `bytes` (which matched `want`); [`Cache::trim`] after a batch.
    pub fn put(&self, index_checksum: u64, want: &Wanted, bytes: &[u8]) {
        if bytes.len() as u64 > self.max_bytes {
            return;
        }
        self.write(&Cache::entry_name(index_checksum, want), bytes);
    }

    /// Writes `name` in the URL's folder through the one atomic writer, relative to the folder
    /// we opened: its path is never looked up again (it may lead elsewhere by now).
    fn write(&self, name: &str, bytes: &[u8]) {
        #[cfg(unix)]
        {
            use std::os::fd::AsFd;
            let _ = crate::output::write_bytes_in(self.dir_fd.as_fd(), &self.dir, name, bytes);
        }
        #[cfg(not(unix))]
        let _ = (name, bytes);
    }

    /// The recorded object version, if `object.json` is a regular file that parses.
    #[cfg(unix)]
    fn recorded(&self) -> Option<ObjectVersion> {
        use std::io::Read;
        let file = at::open_file(&self.dir_fd, RECORD)?;
        let mut bytes = Vec::new();
        (&file)
            .take(RECORD_MAX_BYTES)
            .read_to_end(&mut bytes)
            .ok()?;
        serde_json::from_slice(&bytes).ok()
    }

    /// Removes every file (and link) in the URL's folder; folders in it stay.
    #[cfg(unix)]
    fn empty(&self) {
        for name in at::names(&self.dir_fd) {
            if at::stat(&self.dir_fd, &name).is_some_and(|st| {
                rustix::fs::FileType::from_raw_mode(st.st_mode) != rustix::fs::FileType::Directory
            }) {
                at::unlink(&self.dir_fd, &name);
            }
        }
    }

    /// Removes the least recently used entries (of every URL) until the cache holds at most
    /// `max_bytes`. Only regular files named as entries, in folders (not links to folders)
    /// that hold a regular `object.json`, count or go.
    pub fn trim(&self) -> Trimmed {
        let mut trimmed = Trimmed::default();
        #[cfg(unix)]
        {
            // (last use, length, folder, file)
            let mut entries: Vec<((i64, i64), u64, String, String)> = Vec::new();
            for object in at::names(&self.root_fd) {
                let fd = match at::open_folder(&self.root_fd, &object) {
                    Ok(fd) => fd,
                    Err(None) => {
                        trimmed.links_skipped += 1;
                        continue;
                    }
                    Err(Some(_)) => continue,
                };
                if !at::stat(&fd, RECORD).is_some_and(|st| at::is_regular(&st)) {
                    continue;
                }
                for file in at::names(&fd) {
                    if !is_entry_name(&file) {
                        continue;
                    }
                    if let Some(st) = at::stat(&fd, &file).filter(at::is_regular) {
                        let (used, len) = at::used_and_len(&st);
                        entries.push((used, len, object.clone(), file));
                    }
                }
            }
            let mut total: u64 = entries.iter().map(|e| e.1).sum();
            entries.sort();
            for (_, len, object, file) in entries {
                if total <= self.max_bytes {
                    break;
                }
                // Opened again, not followed: the folder may have been swapped for a link.
                let Ok(fd) = at::open_folder(&self.root_fd, &object) else {
                    continue;
                };
                if at::unlink(&fd, &file) {
                    total -= len;
                    trimmed.removed += 1;
                }
            }
        }
        trimmed
    }
}

#[cfg(all(test, unix))]
mod tests {
    use super::*;

    fn wanted(index: usize, bytes: &[u8]) -> Wanted {
        Wanted {
            index,
            range: 0..bytes.len() as u64,
            offset: 0,
            checksum: checksum(bytes),
        }
    }

    #[test]
    fn entries_round_trip_and_damaged_ones_are_dropped() {
        let root = tempfile::tempdir().unwrap();
        let cache =
            Cache::open(root.path(), "http://h/m.sfpm", Some("\"a\""), "t", 1 << 20).unwrap();
        let want = wanted(3, b"abc");
        assert_eq!(cache.get(7, &want), None);
        cache.put(7, &want, b"abc");
        assert_eq!(cache.get(7, &want).as_deref(), Some(&b"abc"[..]));
        // Another index checksum is another map: no hit.
        assert_eq!(cache.get(8, &want), None);
        std::fs::write(cache.entry(7, &want), b"abd").unwrap();
        assert_eq!(cache.get(7, &want), None);
        assert!(!cache.entry(7, &want).exists());
    }

    #[test]
    fn a_changed_object_empties_its_entries() {
        let root = tempfile::tempdir().unwrap();
        let want = wanted(0, b"xyz");
        Cache::open(root.path(), "s3://b/k", Some("\"1\""), "t", 1 << 20)
            .unwrap()
            .put(1, &want, b"xyz");
        let same = Cache::open(root.path(), "s3://b/k", Some("\"1\""), "t", 1 << 20).unwrap();
        assert!(same.get(1, &want).is_some());
        let changed = Cache::open(root.path(), "s3://b/k", Some("\"2\""), "t", 1 << 20).unwrap();
        assert!(changed.get(1, &want).is_none());
    }

    #[test]
    fn the_cap_evicts_the_least_recently_used() {
        let root = tempfile::tempdir().unwrap();
        let cache = Cache::open(root.path(), "http://h/m", None, "t", 10).unwrap();
        let a = wanted(0, b"aaaaaa");
        let b = wanted(1, b"bbbbbb");
        cache.put(1, &a, b"aaaaaa");
        // Older mtime for `a`, so it goes first.
        let old = std::time::SystemTime::now() - std::time::Duration::from_secs(60);
        let f = std::fs::File::options()
            .append(true)
            .open(cache.entry(1, &a))
            .unwrap();
        f.set_modified(old).unwrap();
        // Another file in the folder is not the cache's: never counted, never removed.
        std::fs::write(cache.dir.join("notes.bin"), b"mine, twenty bytes..").unwrap();
        cache.put(1, &b, b"bbbbbb");
        cache.trim();
        assert!(cache.dir.join("notes.bin").exists());
        assert!(cache.get(1, &a).is_none());
        assert!(cache.get(1, &b).is_some());
    }

    /// A victim folder outside the cache that looks like a URL's folder: a record and an entry.
    fn victim() -> (tempfile::TempDir, PathBuf) {
        let outside = tempfile::tempdir().unwrap();
        std::fs::write(outside.path().join(RECORD), b"{}").unwrap();
        let entry = outside.path().join("0123456789abcdef-0.bin");
        std::fs::write(&entry, vec![7u8; 100]).unwrap();
        (outside, entry)
    }

    #[test]
    fn trimming_never_follows_a_folder_that_is_a_link() {
        let root = tempfile::tempdir().unwrap();
        let cache = Cache::open(root.path(), "http://h/m", None, "t", 0).unwrap();
        let (outside, entry) = victim();
        std::os::unix::fs::symlink(
            outside.path(),
            root.path().join(CACHE_FOLDER).join("00000000000000aa"),
        )
        .unwrap();
        let trimmed = cache.trim();
        assert!(entry.exists(), "an entry behind a link was unlinked");
        assert_eq!(trimmed.links_skipped, 1);
        assert_eq!(trimmed.removed, 0);
    }

    #[test]
    fn a_urls_folder_that_is_a_link_turns_the_cache_off_for_it() {
        let root = tempfile::tempdir().unwrap();
        let (outside, entry) = victim();
        let url = "http://h/m";
        let name = format!("{:016x}", checksum(url.as_bytes()));
        std::fs::create_dir(root.path().join(CACHE_FOLDER)).unwrap();
        let link = root.path().join(CACHE_FOLDER).join(name);
        std::os::unix::fs::symlink(outside.path(), &link).unwrap();
        let opened = Cache::open(root.path(), url, Some("\"e\""), "t", 1 << 20);
        assert_eq!(opened.unwrap_err(), Unusable::Unsafe);
        assert!(entry.exists());
        assert_eq!(std::fs::read(outside.path().join(RECORD)).unwrap(), b"{}");
        assert!(std::fs::symlink_metadata(&link).unwrap().is_symlink());
    }

    #[test]
    fn an_entry_that_is_a_link_is_neither_read_nor_touched_nor_its_target_removed() {
        let root = tempfile::tempdir().unwrap();
        let cache = Cache::open(root.path(), "http://h/m", None, "t", 1 << 20).unwrap();
        let (_outside, target) = victim();
        let want = wanted(0, &[7u8; 100]);
        std::os::unix::fs::symlink(&target, cache.entry(1, &want)).unwrap();
        assert_eq!(cache.get(1, &want), None);
        assert!(target.exists());
    }

    #[test]
    fn a_folder_swapped_for_a_link_after_opening_gets_no_write_outside() {
        let root = tempfile::tempdir().unwrap();
        let cache = Cache::open(root.path(), "http://h/m", None, "t", 1 << 20).unwrap();
        let (outside, entry) = victim();
        let before = std::fs::read_dir(outside.path()).unwrap().count();
        // The race the review ran, made deterministic: between the open and the write, the
        // URL's folder moves aside and a link to another folder takes its path.
        let moved = root.path().join(CACHE_FOLDER).join("moved");
        std::fs::rename(&cache.dir, &moved).unwrap();
        std::os::unix::fs::symlink(outside.path(), &cache.dir).unwrap();
        let want = wanted(7, b"server-chosen bytes");
        cache.put(1, &want, b"server-chosen bytes");
        // Nothing new outside (no entry, no temp file), the victim's files untouched.
        assert_eq!(std::fs::read_dir(outside.path()).unwrap().count(), before);
        assert!(!outside.path().join(Cache::entry_name(1, &want)).exists());
        assert_eq!(std::fs::read(&entry).unwrap(), vec![7u8; 100]);
        assert_eq!(std::fs::read(outside.path().join(RECORD)).unwrap(), b"{}");
        // It went to the folder the cache opened, and reads back from there.
        let name = Cache::entry_name(1, &want);
        assert_eq!(
            std::fs::read(moved.join(&name)).unwrap(),
            b"server-chosen bytes"
        );
        assert_eq!(
            cache.get(1, &want).as_deref(),
            Some(&b"server-chosen bytes"[..])
        );
        let mut names = at::names(&cache.dir_fd);
        names.sort();
        assert_eq!(names, [name.as_str(), RECORD]);
    }

    #[test]
    fn a_folder_writable_by_group_or_others_is_refused() {
        use std::os::unix::fs::PermissionsExt;
        let url = "http://h/m";
        let name = format!("{:016x}", checksum(url.as_bytes()));
        let mode = |p: &Path, m: u32| {
            std::fs::set_permissions(p, std::fs::Permissions::from_mode(m)).unwrap();
        };
        // The URL's folder, made in advance and group-writable (or others-writable).
        for loose in [0o775, 0o757] {
            let root = tempfile::tempdir().unwrap();
            let folder = root.path().join(CACHE_FOLDER).join(&name);
            std::fs::create_dir_all(&folder).unwrap();
            mode(&root.path().join(CACHE_FOLDER), 0o755);
            mode(&folder, loose);
            let opened = Cache::open(root.path(), url, Some("\"e\""), "t", 1 << 20);
            assert_eq!(opened.unwrap_err(), Unusable::Unsafe);
            assert_eq!(std::fs::read_dir(&folder).unwrap().count(), 0, "written in");
            // Once it is ours alone, it is used.
            mode(&folder, 0o755);
            assert!(Cache::open(root.path(), url, Some("\"e\""), "t", 1 << 20).is_ok());
        }
        // `remote-sections` itself group-writable: nothing made or written in it.
        let root = tempfile::tempdir().unwrap();
        let sections = root.path().join(CACHE_FOLDER);
        std::fs::create_dir(&sections).unwrap();
        mode(&sections, 0o770);
        let opened = Cache::open(root.path(), url, None, "t", 1 << 20);
        assert_eq!(opened.unwrap_err(), Unusable::Unsafe);
        assert_eq!(std::fs::read_dir(&sections).unwrap().count(), 0);
        // Trimming leaves a group-writable URL folder alone, and counts it.
        mode(&sections, 0o755);
        let cache = Cache::open(root.path(), url, None, "t", 0).unwrap();
        let other = sections.join("00000000000000aa");
        std::fs::create_dir(&other).unwrap();
        std::fs::write(other.join(RECORD), b"{}").unwrap();
        std::fs::write(other.join("0123456789abcdef-0.bin"), [7u8; 100]).unwrap();
        mode(&other, 0o775);
        let trimmed = cache.trim();
        assert!(other.join("0123456789abcdef-0.bin").exists());
        assert_eq!(trimmed.links_skipped, 1);
    }
}
