//! Whole objects in a bucket or on a web server, for jobs that turn a bucket of inputs into a
//! bucket of maps (`python -m sfpmap.batch`): list a prefix, read an object into a file, write
//! a file as an object, delete one. The same stores, credentials and outbound policy as maps
//! read by range ([`super::policy::build_store`]), on a one-thread runtime per call.
//!
//! An object written here appears whole or not at all: S3 stores a PUT (or a multipart upload,
//! at its completion) only once the body is complete, and every body carries its SHA-256
//! (`x-amz-checksum-sha256`), which the server checks before storing. A file read here is
//! written through [`AtomicFile`]: complete, or not there.

use super::policy::{build_store, NamedBy, Traffic};
use super::RemoteOptions;
use crate::format::Error;
use crate::output::AtomicFile;
use object_store::path::Path as StorePath;
use object_store::{ObjectMeta, ObjectStore, ObjectStoreExt, PutPayload, WriteMultipart};
use std::io::{Read, Write};
use std::path::Path;

/// An object: its URL, length, ETag (when the server gave one) and modification time.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub struct ObjectInfo {
    /// `s3://bucket/key` or `http(s)://host/path`.
    pub url: String,
    /// Its length in bytes.
    pub size: u64,
    /// Its ETag, as the server gave it.
    pub e_tag: Option<String>,
    /// Its Last-Modified, in milliseconds since the Unix epoch.
    pub last_modified_ms: i64,
}

/// Files up to this size are written in one PUT (held whole, once); larger ones in parts of
/// [`PART_BYTES`], at most [`PARTS_IN_FLIGHT`] in flight besides the one being filled and the
/// read buffer (so about 100 MiB held).
const SINGLE_PUT_BYTES: u64 = 64 << 20;
const PART_BYTES: usize = 16 << 20;
const PARTS_IN_FLIGHT: usize = 4;

/// A store, the object path in it and the URL's scheme and authority, for one call.
struct Target {
    store: Box<dyn ObjectStore>,
    path: StorePath,
    /// `s3://bucket` or `https://host:port`: what a listed path is appended to.
    root: String,
    runtime: tokio::runtime::Runtime,
}

impl Target {
    /// `traffic`: [`Traffic::WholeObjects`] for a body of any size, [`Traffic::Ranges`] for a
    /// listing, HEAD or DELETE (an unreachable server reported in seconds, not minutes).
    fn connect(url: &str, options: &RemoteOptions, traffic: Traffic) -> Result<Target, Error> {
        let parsed = url::Url::parse(url).map_err(|e| fail(url, format!("not a URL: {e}")))?;
        if !matches!(parsed.scheme(), "s3" | "http" | "https") {
            return Err(fail(url, "not an s3://, http:// or https:// URL".into()));
        }
        let (store, path) =
            build_store(&parsed, NamedBy::User, options, traffic).map_err(|m| fail(url, m))?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| fail(url, format!("cannot start the I/O runtime: {e}")))?;
        Ok(Target {
            store,
            path,
            root: parsed[..url::Position::BeforePath].to_string(),
            runtime,
        })
    }

    fn info(&self, meta: ObjectMeta) -> ObjectInfo {
        ObjectInfo {
            url: format!("{}/{}", self.root, meta.location),
            size: meta.size,
            e_tag: meta.e_tag,
            last_modified_ms: meta.last_modified.timestamp_millis(),
        }
    }
}

/// The next item of a stream (object_store's streams are boxed, so `Unpin`).
async fn next<S: futures_core::Stream + Unpin>(stream: &mut S) -> Option<S::Item> {
    std::future::poll_fn(|cx| std::pin::Pin::new(&mut *stream).poll_next(cx)).await
}

fn fail(url: &str, message: String) -> Error {
    Error::Io {
        path: url.into(),
        message,
    }
}

/// The store's error, cut to [`MAX_ERROR_CHARS`]: a server's error body is in it, and a
/// hostile one may be large.
fn store_error(url: &str, e: object_store::Error) -> Error {
    let mut message = super::describe(&e);
    if let Some((cut, _)) = message.char_indices().nth(MAX_ERROR_CHARS) {
        message.truncate(cut);
        message.push_str("...");
    }
    fail(url, message)
}

/// The longest error text kept from a store.
const MAX_ERROR_CHARS: usize = 1000;

/// The objects under the prefix `url` (`s3://bucket/places/a` lists `places/a/…`; a whole
/// path segment, never `places/ab`), sorted by URL. At most `max_objects`: more is an error,
/// so a listing cannot grow a job's memory without bound.
pub fn list(
    url: &str,
    max_objects: usize,
    options: &RemoteOptions,
) -> Result<Vec<ObjectInfo>, Error> {
    let target = Target::connect(url, options, Traffic::Ranges)?;
    let prefix = (!target.path.as_ref().is_empty()).then_some(&target.path);
    let mut found = Vec::new();
    target.runtime.block_on(async {
        let mut stream = target.store.list(prefix);
        while let Some(meta) = next(&mut stream).await {
            let meta = meta.map_err(|e| store_error(url, e))?;
            if found.len() == max_objects {
                return Err(fail(
                    url,
                    format!("more than {max_objects} objects under this prefix"),
                ));
            }
            found.push(target.info(meta));
        }
        Ok(())
    })?;
    found.sort_by(|a, b| a.url.cmp(&b.url));
    Ok(found)
}

/// The folders right under the prefix `url` (`s3://bucket/city` gives `s3://bucket/city/a/`,
/// …: one listing request per thousand, whatever each folder holds), sorted; more than
/// `max_folders` is an error.
pub fn list_folders(
    url: &str,
    max_folders: usize,
    options: &RemoteOptions,
) -> Result<Vec<String>, Error> {
    let target = Target::connect(url, options, Traffic::Ranges)?;
    let prefix = (!target.path.as_ref().is_empty()).then_some(&target.path);
    let listed = target
        .runtime
        .block_on(target.store.list_with_delimiter(prefix))
        .map_err(|e| store_error(url, e))?;
    if listed.common_prefixes.len() > max_folders {
        return Err(fail(
            url,
            format!("more than {max_folders} folders under this prefix"),
        ));
    }
    let mut folders: Vec<String> = listed
        .common_prefixes
        .iter()
        .map(|p| format!("{}/{p}/", target.root))
        .collect();
    folders.sort();
    Ok(folders)
}

/// The object at `url`, or `None` when there is none.
pub fn head(url: &str, options: &RemoteOptions) -> Result<Option<ObjectInfo>, Error> {
    let target = Target::connect(url, options, Traffic::Ranges)?;
    match target.runtime.block_on(target.store.head(&target.path)) {
        Ok(meta) => Ok(Some(target.info(meta))),
        Err(object_store::Error::NotFound { .. }) => Ok(None),
        Err(e) => Err(store_error(url, e)),
    }
}

/// Reads the object at `url` into the file `dest` (a temp file in its folder, renamed over it
/// once complete), a piece at a time. An object over `max_bytes` is refused before a byte is
/// written, and a body that runs past its announced length is an error.
pub fn download(
    url: &str,
    dest: &Path,
    max_bytes: u64,
    options: &RemoteOptions,
) -> Result<ObjectInfo, Error> {
    let target = Target::connect(url, options, Traffic::WholeObjects)?;
    let io = |e: std::io::Error| Error::Io {
        path: dest.to_path_buf(),
        message: e.to_string(),
    };
    target.runtime.block_on(async {
        let got = target
            .store
            .get(&target.path)
            .await
            .map_err(|e| store_error(url, e))?;
        let meta = got.meta.clone();
        if meta.size > max_bytes {
            return Err(fail(
                url,
                format!("{} bytes, more than the {max_bytes} allowed", meta.size),
            ));
        }
        let mut file = AtomicFile::create(dest).map_err(|e| Error::Io {
            path: dest.to_path_buf(),
            message: e.to_string(),
        })?;
        let mut written = 0u64;
        let mut body = got.into_stream();
        while let Some(piece) = next(&mut body).await {
            let piece = piece.map_err(|e| store_error(url, e))?;
            written += piece.len() as u64;
            if written > meta.size {
                return Err(fail(
                    url,
                    format!("the body runs past its {} bytes", meta.size),
                ));
            }
            file.write_all(&piece).map_err(io)?;
        }
        if written != meta.size {
            return Err(fail(
                url,
                format!("truncated: {written} of {} bytes", meta.size),
            ));
        }
        file.commit().map_err(|e| Error::Io {
            path: dest.to_path_buf(),
            message: e.to_string(),
        })?;
        Ok(target.info(meta))
    })
}

/// Writes the file `src` as the object at `url`, replacing one there. The object appears
/// only complete (see the module's note); what is returned is the stored object's HEAD, whose
/// size must be the file's.
pub fn upload(src: &Path, url: &str, options: &RemoteOptions) -> Result<ObjectInfo, Error> {
    let target = Target::connect(url, options, Traffic::WholeObjects)?;
    let io = |e: std::io::Error| Error::Io {
        path: src.to_path_buf(),
        message: e.to_string(),
    };
    let mut file = crate::input::open_regular(src).map_err(|e| Error::Io {
        path: src.to_path_buf(),
        message: e.to_string(),
    })?;
    let size = file.metadata().map_err(io)?.len();
    target.runtime.block_on(async {
        if size <= SINGLE_PUT_BYTES {
            let mut bytes = Vec::with_capacity(size as usize);
            // At most one byte past the size it had: a file growing meanwhile is refused, not
            // read on.
            (&mut file)
                .take(size + 1)
                .read_to_end(&mut bytes)
                .map_err(io)?;
            if bytes.len() as u64 != size {
                return Err(io(std::io::Error::other("the file changed while read")));
            }
            target
                .store
                .put(&target.path, PutPayload::from(bytes))
                .await
                .map_err(|e| store_error(url, e))?;
        } else {
            let upload = target
                .store
                .put_multipart(&target.path)
                .await
                .map_err(|e| store_error(url, e))?;
            let mut parts = WriteMultipart::new_with_chunk_size(upload, PART_BYTES);
            let mut buf = vec![0u8; PART_BYTES];
            let mut sent = 0u64;
            loop {
                let n = match file.read(&mut buf) {
                    Ok(0) => break,
                    Ok(n) => n,
                    Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                    Err(e) => {
                        let _ = parts.abort().await;
                        return Err(io(e));
                    }
                };
                sent += n as u64;
                if let Err(e) = parts.wait_for_capacity(PARTS_IN_FLIGHT).await {
                    let _ = parts.abort().await;
                    return Err(store_error(url, e));
                }
                parts.write(&buf[..n]);
            }
            if sent != size {
                let _ = parts.abort().await;
                return Err(io(std::io::Error::other("the file changed while read")));
            }
            parts.finish().await.map_err(|e| store_error(url, e))?;
        }
        let meta = target
            .store
            .head(&target.path)
            .await
            .map_err(|e| store_error(url, e))?;
        if meta.size != size {
            return Err(fail(url, format!("stored {} bytes of {size}", meta.size)));
        }
        Ok(target.info(meta))
    })
}

/// Deletes the object at `url`; one that is not there is no error.
pub fn delete(url: &str, options: &RemoteOptions) -> Result<(), Error> {
    let target = Target::connect(url, options, Traffic::Ranges)?;
    match target.runtime.block_on(target.store.delete(&target.path)) {
        Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
        Err(e) => Err(store_error(url, e)),
    }
}
