//! Maps in object storage, read by range: `http://`, `https://` and `s3://` URLs through
//! the `object_store` crate, with an on-disk cache of checked sections (`cache.rs`).
//!
//! [`open`] reads the first 64 KiB in one GET (the header and, usually, the whole index), then [`Map`] fetches the sections it uses, merging
//! neighbours into one request. Every section GET carries `If-Match` with the ETag of the
//! first response, and every response's ETag (its Last-Modified when it has none) is compared
//! with the first one's, so an object replaced meanwhile is an error, not a mix of two maps,
//! even from a server that ignores `If-Match`. A body is read a frame at a time and never past
//! the bytes asked for, whatever its Content-Length says (a server that ignores ranges: the
//! size its HEAD gave, at most 512 MiB).
//!
//! S3 takes its endpoint, region and credentials from the usual `AWS_*` variables
//! (`AWS_ENDPOINT_URL`, `AWS_REGION`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, or
//! `AWS_SKIP_SIGNATURE=true` for a public bucket).
//!
//! Every request follows the outbound policy (`policy.rs`): redirects only to the same
//! scheme, host and port unless [`RemoteOptions::allow_redirects`]; never a link-local address;
//! loopback and private ones only from a URL the user named; no credential lookup the user's
//! configuration did not ask for.

mod cache;
pub mod objects;
pub(crate) mod policy;

use crate::format::{coalesce, Error, Map, RangeSource, SourceStats, Wanted, HEAD_READ};
use cache::Cache;
use object_store::path::Path as StorePath;
use object_store::{GetOptions, GetRange, ObjectStore, ObjectStoreExt};
use std::ops::Range;
use std::path::PathBuf;
use std::sync::{Mutex, OnceLock};

use crate::input::is_url;
pub(crate) use policy::NamedBy;

/// How remote maps are read. The default keeps no cache. Non-exhaustive: start from
/// [`RemoteOptions::default`] or [`RemoteOptions::from_env`] and set fields.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct RemoteOptions {
    /// The cache folder, `None` for no cache.
    pub cache_dir: Option<PathBuf>,
    /// The most bytes the cache keeps; the least recently used sections go first.
    pub cache_max_bytes: u64,
    /// Follow redirects to another scheme, host or port (never to a link-local address, nor
    /// from https to http; to loopback or private ones only from a URL on one).
    pub allow_redirects: bool,
    /// Let a catalog file on disk name places on loopback and private addresses (a catalog
    /// is an untrusted file: by default its places may name only public hosts).
    pub allow_private_places: bool,
    /// Let S3 without configured credentials take the EC2 instance's role from the instance
    /// metadata service (by default such a URL is refused before any request).
    pub instance_metadata: bool,
}

impl Default for RemoteOptions {
    fn default() -> RemoteOptions {
        RemoteOptions {
            cache_dir: None,
            cache_max_bytes: DEFAULT_CACHE_MAX_BYTES,
            allow_redirects: false,
            allow_private_places: false,
            instance_metadata: false,
        }
    }
}

impl RemoteOptions {
    /// From the environment: `SFPMAP_CACHE_DIR` (default `$XDG_CACHE_HOME/sfpmap` or
    /// `~/.cache/sfpmap`; `off` for none), `SFPMAP_CACHE_MAX_BYTES` (default 2 GiB), and
    /// `1` (or `true`) in `SFPMAP_ALLOW_REDIRECTS`, `SFPMAP_ALLOW_PRIVATE_PLACES`,
    /// `SFPMAP_AWS_INSTANCE_METADATA` for the policy's opt-ins.
    pub fn from_env() -> RemoteOptions {
        let cache_dir = match std::env::var_os("SFPMAP_CACHE_DIR") {
            Some(dir) if dir == "off" => None,
            Some(dir) => Some(PathBuf::from(dir)),
            None => std::env::var_os("XDG_CACHE_HOME")
                .map(PathBuf::from)
                .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")))
                .map(|base| base.join("sfpmap")),
        };
        let cache_max_bytes = std::env::var("SFPMAP_CACHE_MAX_BYTES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(DEFAULT_CACHE_MAX_BYTES);
        let flag = |name: &str| {
            std::env::var(name).is_ok_and(|v| v == "1" || v.eq_ignore_ascii_case("true"))
        };
        RemoteOptions {
            cache_dir,
            cache_max_bytes,
            allow_redirects: flag(policy::ALLOW_REDIRECTS_ENV),
            allow_private_places: flag(policy::ALLOW_PRIVATE_PLACES_ENV),
            instance_metadata: flag(policy::INSTANCE_METADATA_ENV),
        }
    }
}

/// The most bytes one GET asks for: a longer range is read in pieces.
pub(crate) const MAX_REQUEST: u64 = 32 << 20;

/// The largest object read whole from a server that ignores range requests.
pub(crate) const MAX_WHOLE_OBJECT: u64 = 512 << 20;

/// The cache's default cap.
pub(crate) const DEFAULT_CACHE_MAX_BYTES: u64 = 2 << 30;

/// Opens the map at `url` by range.
pub fn open(url: &str, options: &RemoteOptions) -> Result<Map<'static>, Error> {
    open_named(url, options, NamedBy::User)
}

fn open_named(url: &str, options: &RemoteOptions, named: NamedBy) -> Result<Map<'static>, Error> {
    let source = RemoteSource::connect(url, options, named)?;
    Map::open_source(Box::new(source))
}

/// Opens the map at `location`: an `http(s)://` / `s3://` URL ([`is_url`]) by range, any
/// other name as a local file ([`Map::open`]).
pub fn open_location(
    location: &std::path::Path,
    options: &RemoteOptions,
) -> Result<Map<'static>, Error> {
    match location.to_str().filter(|l| is_url(l)) {
        Some(url) => open(url, options),
        None => Map::open(location),
    }
}

/// Opens a catalog's place at `location` (resolved by `session::catalog`), as
/// [`open_location`] does, with the outbound policy's rule for URLs that `named` names.
#[cfg(feature = "localize")]
pub(crate) fn open_place(
    location: &std::path::Path,
    options: &RemoteOptions,
    named: NamedBy,
) -> Result<Map<'static>, Error> {
    match location.to_str().filter(|l| is_url(l)) {
        Some(url) => open_named(url, options, named),
        None => Map::open(location),
    }
}

/// An object in an HTTP server or S3 bucket, read by range.
pub(crate) struct RemoteSource {
    url: String,
    store: Box<dyn ObjectStore>,
    path: StorePath,
    runtime: tokio::runtime::Runtime,
    len: u64,
    /// The ETag of the first response; every later GET must match it.
    e_tag: Option<String>,
    /// The object's version in the first response ([`version_of`]); every later response
    /// must carry the same.
    version: Option<String>,
    /// The first bytes, read at connect.
    head: Vec<u8>,
    /// The whole object, when the server ignored the first range request.
    whole: OnceLock<Vec<u8>>,
    cache: Option<Cache>,
    stats: Mutex<SourceStats>,
}

impl std::fmt::Debug for RemoteSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RemoteSource")
            .field("url", &self.url)
            .field("len", &self.len)
            .finish()
    }
}

impl RemoteSource {
    /// Parses `url`, builds its store under the outbound policy for a URL `named` names
    /// (refused there, before any request, when the policy says no) and reads the object's
    /// first bytes (one GET), which give its length and ETag.
    pub fn connect(
        url: &str,
        options: &RemoteOptions,
        named: NamedBy,
    ) -> Result<RemoteSource, Error> {
        let fail = |message: String| Error::Io {
            path: url.into(),
            message,
        };
        let parsed = url::Url::parse(url).map_err(|e| fail(format!("not a URL: {e}")))?;
        let (store, path) =
            policy::build_store(&parsed, named, options, policy::Traffic::Ranges).map_err(fail)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| fail(format!("cannot start the I/O runtime: {e}")))?;
        let mut source = RemoteSource {
            url: url.to_string(),
            store,
            path,
            runtime,
            len: 0,
            e_tag: None,
            version: None,
            head: Vec::new(),
            whole: OnceLock::new(),
            cache: None,
            stats: Mutex::new(SourceStats::default()),
        };
        let first = source.get(Ask::Range(0..HEAD_READ), false);
        let (bytes, meta) = match first {
            Ok(got) => got,
            Err(GetError::NotPartial) => {
                // The server answered the range with the whole object: read it once, keep
                // it, if it is not too large to hold.
                source.stats_mut().requests += 1;
                let head = source.runtime.block_on(source.store.head(&source.path));
                let size = head.map_err(|e| source.error(GetError::from(e)))?.size;
                source.stats_mut().requests += 1;
                if size > MAX_WHOLE_OBJECT {
                    return Err(fail(format!(
                        "the server ignores range requests and the object is {size} bytes (more than {MAX_WHOLE_OBJECT} to hold whole); download it and open the file"
                    )));
                }
                let (bytes, meta) = source
                    .get(Ask::Whole { size }, false)
                    .map_err(|e| source.error(e))?;
                source.stats_mut().whole_object = true;
                (bytes, meta)
            }
            Err(e) => return Err(source.error(e)),
        };
        source.len = meta.size;
        source.version = Some(version_of(&meta));
        // If-Match compares strongly: a weak ETag (a proxy's) would fail every later read.
        // Without one, the per-section checksums still catch a replaced object.
        source.e_tag = meta.e_tag.filter(|t| !t.starts_with("W/"));
        if source.stats_mut().whole_object {
            if bytes.len() as u64 != meta.size {
                return Err(fail(format!(
                    "truncated response: {} bytes of {}",
                    bytes.len(),
                    meta.size
                )));
            }
            source.head = bytes[..bytes.len().min(HEAD_READ as usize)].to_vec();
            let _ = source.whole.set(bytes);
        } else {
            source.head = bytes;
        }
        if let Some(dir) = &options.cache_dir {
            match Cache::open(
                dir,
                url,
                source.e_tag.as_deref(),
                meta.last_modified,
                options.cache_max_bytes,
            ) {
                Ok(cache) => source.cache = Some(cache),
                Err(cache::Unusable::Unsafe) => source.stats_mut().cache_links_skipped = 1,
                Err(cache::Unusable::Unavailable) => {}
            }
        }
        Ok(source)
    }

    fn stats_mut(&self) -> std::sync::MutexGuard<'_, SourceStats> {
        self.stats.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn error(&self, e: GetError) -> Error {
        Error::Io {
            path: self.url.clone().into(),
            message: match e {
                GetError::NotPartial => "the server answered a range request with the whole object".into(),
                GetError::Changed => "the object changed since its index was read (ETag no longer matches); open it again".into(),
                GetError::Replaced { first, now } => format!("the object changed while reading: the first response had {first}, a later one {now}; open it again"),
                GetError::Short { got, wanted } => format!("truncated response: {got} bytes of {wanted}"),
                GetError::TooLong { asked } => format!("the server sent more than the {asked} bytes asked for"),
                GetError::WholeSize { head, got } => format!("the server ignores range requests and its whole-object answer is {got} bytes, not the {head} its HEAD gave"),
                GetError::Store(message) => message,
            },
        }
    }

    /// One GET of a range or of the whole object, `If-Match` the first ETag once known. The
    /// body is read a frame at a time into a buffer of the bytes asked for, never of a size the
    /// server claims ([`read_body`]).
    fn get(
        &self,
        ask: Ask,
        conditional: bool,
    ) -> Result<(Vec<u8>, object_store::ObjectMeta), GetError> {
        let options = GetOptions {
            range: match &ask {
                Ask::Range(range) => Some(GetRange::Bounded(range.clone())),
                Ask::Whole { .. } => None,
            },
            if_match: if conditional {
                self.e_tag.clone()
            } else {
                None
            },
            ..GetOptions::default()
        };
        let (bytes, meta) = self.runtime.block_on(async {
            let got = self.store.get_opts(&self.path, options).await?;
            // The most body bytes the answer may carry, decided before reading any.
            let limit = match ask {
                // object_store checked the Content-Range against the range asked for (the
                // object's end may shorten it), never the Content-Length.
                Ask::Range(asked) => (got.range.end - got.range.start).min(asked.end - asked.start),
                // The whole object's size is its Content-Length: it must be the one HEAD gave,
                // which was checked against what can be held.
                Ask::Whole { size } => {
                    if got.meta.size != size || size > MAX_WHOLE_OBJECT {
                        return Err(GetError::WholeSize {
                            head: size,
                            got: got.meta.size,
                        });
                    }
                    size
                }
            };
            let meta = got.meta.clone();
            let bytes = read_body(got, limit).await?;
            Ok::<_, GetError>((bytes, meta))
        })?;
        let mut stats = self.stats_mut();
        stats.requests += 1;
        stats.bytes += bytes.len() as u64;
        drop(stats);
        // `If-Match` is only a request: a server may ignore it and answer from another
        // object. The response says which object it came from.
        if let Some(first) = &self.version {
            let now = version_of(&meta);
            if &now != first {
                return Err(GetError::Replaced {
                    first: first.clone(),
                    now,
                });
            }
        }
        Ok((bytes, meta))
    }

    /// Bytes `range`, from the first read, the whole object, or conditional GETs of at most
    /// [`MAX_REQUEST`] bytes each: memory grows with the bytes that arrive, never with what a
    /// server's index claims.
    fn read(&self, range: Range<u64>) -> Result<Vec<u8>, Error> {
        if let Some(whole) = self.whole.get() {
            return Ok(whole[range.start as usize..range.end as usize].to_vec());
        }
        if range.end <= self.head.len() as u64 {
            return Ok(self.head[range.start as usize..range.end as usize].to_vec());
        }
        let mut out = Vec::new();
        let mut at = range.start;
        while at < range.end {
            let end = range.end.min(at.saturating_add(MAX_REQUEST));
            // `get` read no more than the range asked for, and all of the part of it that the
            // server confirmed (object_store checked that part against the range asked for).
            let (bytes, _) = self
                .get(Ask::Range(at..end), true)
                .map_err(|e| self.error(e))?;
            out.extend_from_slice(&bytes);
            at = end;
        }
        Ok(out)
    }
}

impl RangeSource for RemoteSource {
    fn name(&self) -> &str {
        &self.url
    }

    fn len(&self) -> u64 {
        self.len
    }

    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, Error> {
        self.read(range)
    }

    fn read_sections(
        &self,
        index_checksum: u64,
        wanted: &[Wanted],
        fresh: bool,
    ) -> Result<Vec<Vec<u8>>, Error> {
        let mut out: Vec<Option<Vec<u8>>> = vec![None; wanted.len()];
        if fresh {
            self.stats_mut().refetched += wanted.len() as u64;
        } else if let Some(cache) = &self.cache {
            for (slot, want) in out.iter_mut().zip(wanted) {
                if let Some(bytes) = cache.get(index_checksum, want) {
                    let mut stats = self.stats_mut();
                    stats.cache_hits += 1;
                    stats.cache_bytes += bytes.len() as u64;
                    *slot = Some(bytes);
                }
            }
        }
        let missing: Vec<usize> = (0..wanted.len()).filter(|&i| out[i].is_none()).collect();
        let refs: Vec<&Wanted> = missing.iter().map(|&i| &wanted[i]).collect();
        // Neighbouring sections are read in one run (damaged ones read again are few).
        let mut cached = false;
        for (run, members) in coalesce(&refs) {
            let mut bytes = self.read(run.clone())?;
            let whole_run = members.len() == 1;
            for m in members {
                let want = refs[m];
                let from = (want.range.start - run.start) as usize;
                let to = (want.range.end - run.start) as usize;
                // A section that is its run alone (a large one, read by itself) is moved out,
                // not copied: a 1 GiB section is held once.
                let part = if whole_run && from == 0 && to == bytes.len() {
                    std::mem::take(&mut bytes)
                } else {
                    bytes[from..to].to_vec()
                };
                if let Some(cache) = &self.cache {
                    if want.matches(&part) {
                        cache.put(index_checksum, want, &part);
                        cached = true;
                    }
                }
                out[missing[m]] = Some(part);
            }
        }
        // Trimming lists the whole cache: only after this batch added to it, so a catalog
        // opening its places from a warm cache of 100,000 entries does not list it per place.
        if let (Some(cache), true) = (&self.cache, cached) {
            let trimmed = cache.trim();
            let mut stats = self.stats_mut();
            stats.cache_links_skipped = stats.cache_links_skipped.max(trimmed.links_skipped);
        }
        Ok(out.into_iter().map(|b| b.unwrap_or_default()).collect())
    }

    fn stats(&self) -> SourceStats {
        *self.stats_mut()
    }
}

/// What one GET asks for.
enum Ask {
    /// These bytes.
    Range(Range<u64>),
    /// The whole object, of `size` bytes by its HEAD (at most [`MAX_WHOLE_OBJECT`]).
    Whole { size: u64 },
}

/// A response's body, read a frame at a time: it must be `limit` bytes, and a byte more is an
/// error as soon as it arrives. `limit` is the range asked for, or a whole object's size that
/// its HEAD gave (checked against [`MAX_WHOLE_OBJECT`]); the buffer reserves at most
/// [`MAX_REQUEST`] up front and grows with the bytes that came. The server's Content-Length is
/// never reserved, nor read past.
async fn read_body(got: object_store::GetResult, limit: u64) -> Result<Vec<u8>, GetError> {
    let mut body = got.into_stream();
    let mut out = Vec::with_capacity(limit.min(MAX_REQUEST) as usize);
    while let Some(frame) =
        std::future::poll_fn(|cx| futures_core::Stream::poll_next(body.as_mut(), cx)).await
    {
        let frame = frame?;
        if (out.len() + frame.len()) as u64 > limit {
            return Err(GetError::TooLong { asked: limit });
        }
        out.extend_from_slice(&frame);
    }
    if out.len() as u64 != limit {
        return Err(GetError::Short {
            got: out.len() as u64,
            wanted: limit,
        });
    }
    Ok(out)
}

enum GetError {
    /// A range request answered `200` with the whole body.
    NotPartial,
    /// `If-Match` failed: the object is not the one whose index was read.
    Changed,
    /// A response came from another version of the object than the first (ETag, or
    /// Last-Modified without one): a server that ignores `If-Match`.
    Replaced {
        first: String,
        now: String,
    },
    /// Fewer body bytes than the response announced.
    Short {
        got: u64,
        wanted: u64,
    },
    /// More body bytes than the range asked for (whatever the Content-Length said).
    TooLong {
        asked: u64,
    },
    /// A whole-object answer whose size is not the one HEAD gave (or more than can be held).
    WholeSize {
        head: u64,
        got: u64,
    },
    Store(String),
}

impl From<object_store::Error> for GetError {
    fn from(e: object_store::Error) -> GetError {
        let text = describe(&e);
        match &e {
            object_store::Error::Precondition { .. } => GetError::Changed,
            object_store::Error::NotFound { .. } => GetError::Store("not found (HTTP 404)".into()),
            // The HTTP store says "Range request not supported", the S3 one "non-partial
            // response": both mean a 200 with the whole body.
            _ if ["non-partial response", "Range request not supported"]
                .iter()
                .any(|m| text.contains(m)) =>
            {
                GetError::NotPartial
            }
            // A redirect or a resolved address the outbound policy refused: its words say all
            // (the URL is in front of the message already), not the layers it came through.
            _ if text.contains(policy::REFUSED) => {
                let at = text.find(policy::REFUSED).unwrap_or(0);
                GetError::Store(text[at..].to_string())
            }
            // hyper's words for a body that ends before its Content-Length.
            _ if text.contains("before message length reached") => {
                GetError::Store(format!("truncated response: {text}"))
            }
            _ => GetError::Store(text),
        }
    }
}

/// What identifies the version of the object a response came from: its ETag (weak ones
/// too: they still change with the object), or its Last-Modified when it has none. ETags
/// compare weakly (RFC 9110, 8.8.3.2): `W/"x"` and `"x"` are one version, as a server that
/// marks some responses weak (a compressing proxy) still sends the same object.
fn version_of(meta: &object_store::ObjectMeta) -> String {
    match &meta.e_tag {
        Some(tag) => format!("ETag {}", tag.strip_prefix("W/").unwrap_or(tag)),
        None => format!("Last-Modified {}", meta.last_modified),
    }
}

/// An error and its causes on one line (object_store's own messages say what failed, its
/// causes say why: a refused connection, a status code).
fn describe(e: &(dyn std::error::Error + 'static)) -> String {
    let mut message = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let text = c.to_string();
        if !message.contains(&text) {
            message.push_str(": ");
            message.push_str(&text);
        }
        cause = c.source();
    }
    message.replace('\n', " ")
}

#[cfg(test)]
mod tests {
    use super::version_of;

    fn meta(e_tag: Option<&str>) -> object_store::ObjectMeta {
        object_store::ObjectMeta {
            location: "m.sfpm".into(),
            last_modified: Default::default(),
            size: 1,
            e_tag: e_tag.map(String::from),
            version: None,
        }
    }

    #[test]
    fn etags_compare_weakly_and_last_modified_stands_in() {
        assert_eq!(
            version_of(&meta(Some("W/\"abc\""))),
            version_of(&meta(Some("\"abc\"")))
        );
        assert_ne!(
            version_of(&meta(Some("\"abc\""))),
            version_of(&meta(Some("\"abd\"")))
        );
        assert!(version_of(&meta(None)).starts_with("Last-Modified "));
    }
}
