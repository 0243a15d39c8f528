//! The on-disk cache of sections read from object storage.
//!
//! Layout: `<dir>/<xxh3 of the URL>/object.json` (the URL and the ETag / last-modified of the
//! object the entries came from) and one file per section,
//! `<index checksum>-<section index>.bin`, holding exactly the bytes a
//! [`Wanted`](crate::format::Wanted) names. An entry is written only after it matched its
//! checksum, through the one atomic writer, so a partial download is never left; it is
//! checked again when read, and a damaged one is removed. When the object's ETag or
//! last-modified differs from the recorded one, the URL's entries are dropped. Past the size
//! cap, the least recently used entries (by modification time, touched on every hit) go.

use crate::format::{checksum, Wanted};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// One URL's folder in the cache. Failures to read or write the cache never fail a read:
/// the cache is an optimisation, and the origin is always there to read from.
#[derive(Debug)]
pub struct Cache {
    root: PathBuf,
    dir: PathBuf,
    max_bytes: u64,
}

/// The folder under the cache root that holds the sections.
const CACHE_FOLDER: &str = "remote-sections";

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

impl Cache {
    /// The cache for `url` in `root`, emptied first if the object changed since its entries
    /// were written.
    pub fn open(
        root: &Path,
        url: &str,
        e_tag: Option<&str>,
        last_modified: impl std::fmt::Display,
        max_bytes: u64,
    ) -> Cache {
        // A folder of its own under the root, so trimming never meets another file.
        let root = root.join(CACHE_FOLDER);
        let dir = root.join(format!("{:016x}", checksum(url.as_bytes())));
        let version = ObjectVersion {
            url: url.to_string(),
            e_tag: e_tag.map(str::to_string),
            last_modified: last_modified.to_string(),
        };
        let record = dir.join("object.json");
        let recorded: Option<ObjectVersion> = std::fs::read(&record)
            .ok()
            .and_then(|b| serde_json::from_slice(&b).ok());
        if recorded.as_ref() != Some(&version) {
            let _ = std::fs::remove_dir_all(&dir);
            if std::fs::create_dir_all(&dir).is_ok() {
                if let Ok(json) = serde_json::to_vec(&version) {
                    let _ = crate::output::write_bytes(&record, &json);
                }
            }
        }
        Cache {
            root,
            dir,
            max_bytes,
        }
    }

    fn entry(&self, index_checksum: u64, want: &Wanted) -> PathBuf {
        self.dir
            .join(format!("{index_checksum:016x}-{}.bin", want.index))
    }

    /// The cached bytes of `want`, if present and still what the table says.
    pub fn get(&self, index_checksum: u64, want: &Wanted) -> Option<Vec<u8>> {
        let path = self.entry(index_checksum, want);
        let bytes = std::fs::read(&path).ok()?;
        if !want.matches(&bytes) {
            let _ = std::fs::remove_file(&path);
            return None;
        }
        // Least recently used goes first: a hit counts as a use.
        if let Ok(file) = std::fs::File::options().append(true).open(&path) {
            let _ = file.set_modified(std::time::SystemTime::now());
        }
        Some(bytes)
    }

    /// Keeps `bytes` (which matched `want`); [`Cache::trim`] after a batch.
    pub fn put(&self, index_checksum: u64, want: &Wanted, bytes: &[u8]) {
        if bytes.len() as u64 > self.max_bytes {
            return;
        }
        let _ = std::fs::create_dir_all(&self.dir);
        let _ = crate::output::write_bytes(&self.entry(index_checksum, want), bytes);
    }

    /// Removes the least recently used entries (of every URL) until the cache holds at most
    /// `max_bytes`. Only files named as entries, in folders that hold an `object.json`, count
    /// or go.
    pub fn trim(&self) {
        let mut entries: Vec<(std::time::SystemTime, u64, PathBuf)> = Vec::new();
        let Ok(objects) = std::fs::read_dir(&self.root) else {
            return;
        };
        for object in objects.flatten() {
            if !object.path().join("object.json").is_file() {
                continue;
            }
            let Ok(files) = std::fs::read_dir(object.path()) else {
                continue;
            };
            for file in files.flatten() {
                let path = file.path();
                if !is_entry_name(&file.file_name().to_string_lossy()) {
                    continue;
                }
                if let Ok(meta) = file.metadata() {
                    let used = meta.modified().unwrap_or(std::time::UNIX_EPOCH);
                    entries.push((used, meta.len(), path));
                }
            }
        }
        let mut total: u64 = entries.iter().map(|e| e.1).sum();
        entries.sort();
        for (_, len, path) in entries {
            if total <= self.max_bytes {
                break;
            }
            if std::fs::remove_file(&path).is_ok() {
                total -= len;
            }
        }
    }
}

#[cfg(test)]
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
        let cache = Cache::open(root.path(), "http://h/m.sfpm", Some("\"a\""), "t", 1 << 20);
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
        Cache::open(root.path(), "s3://b/k", Some("\"1\""), "t", 1 << 20).put(1, &want, b"xyz");
        let same = Cache::open(root.path(), "s3://b/k", Some("\"1\""), "t", 1 << 20);
        assert!(same.get(1, &want).is_some());
        let changed = Cache::open(root.path(), "s3://b/k", Some("\"2\""), "t", 1 << 20);
        assert!(changed.get(1, &want).is_none());
    }

    #[test]
    fn the_cap_evicts_the_least_recently_used() {
        let root = tempfile::tempdir().unwrap();
        let cache = Cache::open(root.path(), "http://h/m", None, "t", 10);
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
}
