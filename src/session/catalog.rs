//! A catalog of place maps (`sfpmap catalog build`, [`Catalog`]) queried as one map: each
//! query's candidate places are ranked by retrieval on the catalog's place summaries (a
//! VLAD of the query on the catalog's codebook against each place's images), optionally only those near a prior position; the best few are opened
//! on first use (files, or URLs read by range: only the sections the localizer reads),
//! checked against what the catalog recorded, and localize the query; the pose with the
//! most inliers wins. Poses are in the chosen place's frame.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use sfpmap::format::Map;
//! use sfpmap::geometry::Camera;
//! use sfpmap::session::catalog::CatalogSession;
//! use sfpmap::session::QuerySource;
//! use std::sync::Arc;
//!
//! let catalog = Arc::new(Map::open("city.sfpc")?);
//! let session = CatalogSession::builder(catalog, "city.sfpc")
//!     .source(QuerySource::Database("queries.db".into()))
//!     .build(&sfpmap::progress::Silent)?;
//! let camera = Camera::parse("SIMPLE_RADIAL 3072 2304 2559.81 1536 1152 -0.0204")?;
//! let found = session.localize("P1180141.JPG", &camera, None)?;
//! if let Some(place) = found.place {
//!     println!("{}: {:?}", session.places()[place].name, found.localization.pose());
//! }
//! # Ok(())
//! # }
//! ```

use super::{QueryReader, QuerySource, Session, SessionError};
use crate::format::{Catalog, Map, Place};
use crate::geometry::Camera;
use crate::input::is_url;
use crate::io::queries::Query;
use crate::localize::catalog::PlaceRanker;
pub use crate::localize::catalog::PlaceScore;
use crate::localize::{
    Localization, LocalizeError, LocalizeOptions, OptionError, QueryFailure, QueryFeatures,
};
use crate::progress::Reporter;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

/// The localizer options of a place: its map's, from [`LocalizeOptions::for_map`] unless the
/// caller changes them.
type PlaceOptions = Box<dyn Fn(&Map<'_>) -> LocalizeOptions + Send + Sync>;

/// A catalog prepared for queries: its places ranked per query, each place's [`Session`]
/// made on first use. `Send + Sync`; queries read from the source take turns.
pub struct CatalogSession {
    /// The catalog as the user named it (a path or a URL), in front of every error.
    name: String,
    catalog: Arc<Map<'static>>,
    places: Vec<Place>,
    /// Where each place's map is ([`CatalogSession::locations`]).
    locations: Vec<PathBuf>,
    ranker: PlaceRanker,
    reader: Mutex<QueryReader>,
    place_options: PlaceOptions,
    places_per_query: usize,
    max_open_places: usize,
    /// The places open now, and those that failed to open.
    open: Mutex<OpenPlaces>,
    /// One lock a place, held while it is opened: threads that rank the same place first
    /// wait for one opening rather than each reading the map.
    opening: Vec<Mutex<()>>,
    #[cfg(feature = "remote")]
    remote: crate::remote::RemoteOptions,
}

/// The places a catalog session holds open (at most `max_open_places`, the least recently
/// used closed first) and those that could not be opened (each fails again without another
/// attempt).
#[derive(Default)]
struct OpenPlaces {
    sessions: HashMap<usize, (Arc<Session>, u64)>,
    failed: HashMap<usize, Arc<SessionError>>,
    /// Ticks of use, for the least recently used.
    clock: u64,
}

/// How a [`CatalogSession`] is made: [`CatalogSession::builder`], then its settings, then
/// [`CatalogSessionBuilder::build`].
pub struct CatalogSessionBuilder {
    catalog: Arc<Map<'static>>,
    name: String,
    source: QuerySource,
    place_options: PlaceOptions,
    places_per_query: usize,
    max_open_places: usize,
    #[cfg(feature = "remote")]
    remote: crate::remote::RemoteOptions,
}

/// How many places a catalog session holds open by default: a place is a map and its
/// localizer (a 1 M-point map read by range holds about its file size in memory).
pub const DEFAULT_MAX_OPEN_PLACES: usize = 16;

/// How many of a query's ranked places [`CatalogLocalization::ranked`] keeps.
pub const RANKED_KEPT: usize = 16;

impl CatalogSessionBuilder {
    /// Where the queries' features come from; default [`QuerySource::Given`]. A features
    /// file must be of the catalog's descriptor; images cannot be extracted for a catalog.
    pub fn source(mut self, source: QuerySource) -> Self {
        self.source = source;
        self
    }

    /// Each place's localizer options, made from its map (default
    /// [`LocalizeOptions::for_map`]); checked when the place is first opened.
    pub fn place_options(
        mut self,
        options: impl Fn(&Map<'_>) -> LocalizeOptions + Send + Sync + 'static,
    ) -> Self {
        self.place_options = Box::new(options);
        self
    }

    /// How many of the best-ranked places each query is localized in (default 2; at least 1).
    pub fn places_per_query(mut self, n: usize) -> Self {
        self.places_per_query = n;
        self
    }

    /// How many places are held open at once (default [`DEFAULT_MAX_OPEN_PLACES`]; at least
    /// 1): opening one more closes the least recently used.
    pub fn max_open_places(mut self, n: usize) -> Self {
        self.max_open_places = n.max(1);
        self
    }

    /// How place maps named by URL are read (default
    /// [`RemoteOptions::default`](crate::remote::RemoteOptions): no cache; the CLI passes
    /// [`RemoteOptions::from_env`](crate::remote::RemoteOptions::from_env)).
    #[cfg(feature = "remote")]
    pub fn remote(mut self, options: crate::remote::RemoteOptions) -> Self {
        self.remote = options;
        self
    }

    /// Reads the catalog's places and ranking data, resolves where each place's map is, and
    /// opens the query source. No place map is opened yet.
    pub fn build(self, reporter: &dyn Reporter) -> Result<CatalogSession, SessionError> {
        let name = self.name;
        if self.places_per_query == 0 {
            return Err(option_error(
                &name,
                "places_per_query",
                "0",
                "at least 1 place",
            ));
        }
        let map_error = |source| SessionError::Map {
            map: name.clone(),
            source,
        };
        let catalog = Catalog::of(&self.catalog)
            .map_err(map_error)?
            .ok_or_else(|| {
                SessionError::Mismatch(format!(
                    "{name}: not a catalog (its metadata lists no places)"
                ))
            })?;
        let places = catalog.places().to_vec();
        let locations = places
            .iter()
            .map(|p| {
                resolve(
                    &name,
                    p,
                    #[cfg(feature = "remote")]
                    &self.remote,
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        let ranker = PlaceRanker::new(&catalog).map_err(map_error)?;
        let reader =
            QueryReader::for_catalog(self.source, &name, &catalog.listing.descriptor, reporter)?;
        Ok(CatalogSession {
            opening: places.iter().map(|_| Mutex::new(())).collect(),
            open: Mutex::new(OpenPlaces::default()),
            max_open_places: self.max_open_places,
            name,
            catalog: self.catalog,
            places,
            locations,
            ranker,
            reader: Mutex::new(reader),
            place_options: self.place_options,
            places_per_query: self.places_per_query,
            #[cfg(feature = "remote")]
            remote: self.remote,
        })
    }
}

/// An option of the catalog session out of its range, as the localizer's options are
/// refused ([`OptionError`]).
fn option_error(
    catalog: &str,
    option: &'static str,
    value: &str,
    expected: &'static str,
) -> SessionError {
    SessionError::Localize {
        map: catalog.to_string(),
        source: LocalizeError::Option(OptionError {
            option,
            value: value.to_string(),
            expected,
        }),
    }
}

/// Where place `place`'s map is, under the outbound policy (`remote::policy`): a URL as is,
/// if the policy admits a catalog file's URL (public hosts only, unless the user allows
/// private ones; never link-local; only http, https and s3); a path from the catalog's folder
/// (absolute ones as they are). A catalog read from a URL names only locations on its own
/// server: its places' locations are resolved against its URL and must keep its scheme, host
/// and port (an S3 catalog: its bucket), so a downloaded catalog can make the reader open
/// neither a local file, nor another host (an internal address, another bucket signed with the
/// user's credentials), nor plain HTTP for an HTTPS catalog. Refused here, before any request.
fn resolve(
    catalog: &str,
    place: &Place,
    #[cfg(feature = "remote")] options: &crate::remote::RemoteOptions,
) -> Result<PathBuf, SessionError> {
    let location = place.map.as_str();
    let refused = |rule: String| {
        SessionError::Mismatch(format!(
            "{}: place {}: map {}: {rule}",
            crate::escape::escape_control_characters(catalog),
            crate::escape::quoted_name(&place.name),
            crate::escape::escape_control_characters(location),
        ))
    };
    #[cfg(feature = "remote")]
    {
        use crate::remote::policy;
        if is_url(catalog) {
            return policy::place_of_remote_catalog(catalog, location)
                .map(PathBuf::from)
                .map_err(|rule| refused(policy::refused(rule)));
        }
        if is_url(location) {
            let url = url::Url::parse(location).map_err(|e| refused(format!("not a URL: {e}")))?;
            policy::admit(&url, policy::NamedBy::LocalCatalog, options)
                .map_err(|rule| refused(policy::refused(rule)))?;
            return Ok(PathBuf::from(location));
        }
        if let Some(rule) = policy::foreign_scheme(location) {
            return Err(refused(policy::refused(rule)));
        }
    }
    #[cfg(not(feature = "remote"))]
    if is_url(catalog) {
        return Err(refused(
            "a catalog read from a URL, and this build reads no URLs (feature `remote`)".into(),
        ));
    }
    if is_url(location) {
        return Ok(PathBuf::from(location));
    }
    let folder = Path::new(catalog).parent().unwrap_or(Path::new("."));
    Ok(folder.join(location))
}

/// Only places whose bounding box lies within `radius` of `position` (world coordinates of
/// the catalog) are ranked. Every value finite, the radius at least 0
/// ([`crate::ranges::COORDINATE`], [`crate::ranges::DISTANCE`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Near {
    /// The prior position.
    pub position: [f64; 3],
    /// How far from a place's bounding box it may be.
    pub radius: f64,
}

/// A query localized against a catalog.
#[derive(Debug, Clone)]
pub struct CatalogLocalization {
    /// The best place's localization (the most inliers of those with a pose), or the
    /// failure of the best-ranked place when none found a pose; a
    /// [`QueryFailure::NoFeatures`] when the query's features could not be read or no place
    /// could rank it.
    pub localization: Localization,
    /// The place the pose is in (an index into [`CatalogSession::places`]); `None` without
    /// a pose.
    pub place: Option<usize>,
    /// The places the query could go to, best ranked first (at most [`RANKED_KEPT`]).
    pub ranked: Vec<PlaceScore>,
    /// Whether the query's features were read (false: the source has none for it).
    pub features_read: bool,
}

impl CatalogSession {
    /// A catalog session over `catalog` (a map whose metadata lists places), named
    /// `catalog_name` in errors; relative place locations are resolved from its folder (or
    /// against its URL).
    pub fn builder(
        catalog: Arc<Map<'static>>,
        catalog_name: impl Into<String>,
    ) -> CatalogSessionBuilder {
        CatalogSessionBuilder {
            catalog,
            name: catalog_name.into(),
            source: QuerySource::Given,
            place_options: Box::new(LocalizeOptions::for_map),
            places_per_query: 2,
            max_open_places: DEFAULT_MAX_OPEN_PLACES,
            #[cfg(feature = "remote")]
            remote: crate::remote::RemoteOptions::default(),
        }
    }

    /// The catalog map.
    pub fn catalog(&self) -> &Arc<Map<'static>> {
        &self.catalog
    }

    /// The catalog's places, in its order.
    pub fn places(&self) -> &[Place] {
        &self.places
    }

    /// Where each place's map is, resolved (a path, or a URL): inputs no output may replace.
    pub fn locations(&self) -> &[PathBuf] {
        &self.locations
    }

    /// Place `i`'s map (an index into [`CatalogSession::places`]), opened as the session
    /// opens it to localize: under the outbound policy, and refused when it is not the map
    /// the catalog was built from. For a caller that localizes in one place on its own (a
    /// camera stream tracked in the building it is in).
    pub fn open_place_map(&self, i: usize) -> Result<Map<'static>, SessionError> {
        if i >= self.places.len() {
            return Err(SessionError::Mismatch(format!(
                "{}: no place {i} (it lists {})",
                self.name,
                self.places.len()
            )));
        }
        self.open_place(i).map_err(|e| self.place_error(i, e))
    }

    /// The places open now and their sessions, in the catalog's order.
    pub fn opened(&self) -> Vec<(usize, Arc<Session>)> {
        let open = self.lock_open();
        let mut opened: Vec<_> = (open.sessions.iter())
            .map(|(&i, (session, _))| (i, session.clone()))
            .collect();
        opened.sort_by_key(|(i, _)| *i);
        opened
    }

    /// The query `name` from the session's source, localized in its best-ranked places
    /// (those `near` allows). A query whose features cannot be read, or do not fit the
    /// places, is a [`QueryFailure::NoFeatures`] with `read` false, not an error.
    pub fn localize(
        &self,
        name: &str,
        camera: &Camera,
        near: Option<Near>,
    ) -> Result<CatalogLocalization, SessionError> {
        let read = self
            .reader
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .read(name)?;
        // Features read by name that do not fit the places fail this query alone, as
        // features that cannot be read do.
        let reason = match read {
            Ok(features) => match self.localize_features(&features, camera, name, near) {
                Err(e) => e.unusable_query().ok_or(e)?,
                found => return found,
            },
            Err(reason) => reason,
        };
        Ok(CatalogLocalization {
            localization: Localization::failed(QueryFailure::NoFeatures(reason)),
            place: None,
            ranked: Vec::new(),
            features_read: false,
        })
    }

    /// Each of `queries` localized as [`CatalogSession::localize`] does, on `threads`
    /// workers; the results in the order of `queries`, progress to `reporter`, one item per
    /// query. The first error stops the run.
    pub fn localize_all(
        &self,
        queries: &[Query],
        near: Option<Near>,
        threads: usize,
        reporter: &dyn Reporter,
    ) -> Result<Vec<CatalogLocalization>, SessionError> {
        super::run_all(queries.len(), threads, reporter, |i| {
            self.localize(&queries[i].name, &queries[i].camera, near)
        })
    }

    /// `features` handed in, localized in the best-ranked places `near` allows; `name`
    /// names the query in errors.
    pub fn localize_features(
        &self,
        features: &QueryFeatures,
        camera: &Camera,
        name: &str,
        near: Option<Near>,
    ) -> Result<CatalogLocalization, SessionError> {
        if let Some(n) = near {
            use crate::ranges::{COORDINATE, DISTANCE};
            if n.position.iter().any(|&v| !COORDINATE.contains(v)) {
                let value = format!("{:?}", n.position);
                return Err(option_error(
                    &self.name,
                    "near",
                    &value,
                    COORDINATE.expected,
                ));
            }
            if let Err(expected) = DISTANCE.check(n.radius) {
                let value = n.radius.to_string();
                return Err(option_error(&self.name, "radius", &value, expected));
            }
        }
        // Before ranking: the ranker skips rows that are not finite, and a query of nothing
        // but NaN would rank no place instead of being refused.
        Session::check_finite(features, &self.name, name)?;
        let allowed = |i: usize| near.is_none_or(|n| self.places[i].near(n.position, n.radius));
        let mut ranked = self.ranker.rank(features, allowed);
        ranked.truncate(RANKED_KEPT.max(self.places_per_query));
        let mut best: Option<(Localization, usize)> = None;
        for candidate in ranked.iter().take(self.places_per_query) {
            let l = self
                .place_session(candidate.place)?
                .localize_features(features, camera, name)
                .map_err(|e| self.place_error(candidate.place, e))?;
            let better = match &best {
                None => true,
                Some((b, _)) => l.pose().is_some() && (b.pose().is_none() || l.inliers > b.inliers),
            };
            if better {
                best = Some((l, candidate.place));
            }
        }
        let (localization, place) = match best {
            Some((l, place)) => {
                let place = l.pose().is_some().then_some(place);
                (l, place)
            }
            None => (
                Localization::failed(QueryFailure::NoFeatures(
                    "no place of the catalog could rank the query (none near the prior, or no \
                     retrieval data for its features)"
                        .into(),
                )),
                None,
            ),
        };
        Ok(CatalogLocalization {
            localization,
            place,
            ranked,
            features_read: true,
        })
    }

    /// Place `i`'s session, made on first use: its map opened and checked against what the
    /// catalog recorded, once (other threads wait for it); a place that fails to open fails
    /// the same way again. Opening one more than `max_open_places` closes the least recently
    /// used (queries running in it keep it until they end).
    fn place_session(&self, i: usize) -> Result<Arc<Session>, SessionError> {
        if let Some(found) = self.cached(i) {
            return found;
        }
        let _opening = self.opening[i].lock().unwrap_or_else(|p| p.into_inner());
        if let Some(found) = self.cached(i) {
            return found;
        }
        let made = self.open_place(i).and_then(|map| {
            let options = (self.place_options)(&map);
            let location = crate::escape::path(&self.locations[i]).to_string();
            Session::builder(Arc::new(map), location)
                .options(options)
                .build(&crate::progress::Silent)
        });
        let mut open = self.lock_open();
        match made {
            Ok(session) => {
                let session = Arc::new(session);
                if open.sessions.len() >= self.max_open_places {
                    let oldest = (open.sessions.iter())
                        .min_by_key(|(_, (_, used))| *used)
                        .map(|(&p, _)| p);
                    if let Some(p) = oldest {
                        open.sessions.remove(&p);
                    }
                }
                open.clock += 1;
                let tick = open.clock;
                open.sessions.insert(i, (session.clone(), tick));
                Ok(session)
            }
            Err(e) => {
                let e = Arc::new(e);
                open.failed.insert(i, e.clone());
                Err(self.place_error_shared(i, e))
            }
        }
    }

    /// Place `i`'s open session (its use recorded), or its failure; `None`: not opened yet.
    fn cached(&self, i: usize) -> Option<Result<Arc<Session>, SessionError>> {
        let mut open = self.lock_open();
        if let Some(e) = open.failed.get(&i) {
            return Some(Err(self.place_error_shared(i, e.clone())));
        }
        open.clock += 1;
        let tick = open.clock;
        let (session, used) = open.sessions.get_mut(&i)?;
        *used = tick;
        Some(Ok(session.clone()))
    }

    fn lock_open(&self) -> MutexGuard<'_, OpenPlaces> {
        self.open.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn open_place(&self, i: usize) -> Result<Map<'static>, SessionError> {
        let location = &self.locations[i];
        let map_error = |source| SessionError::Map {
            map: crate::escape::path(location).to_string(),
            source,
        };
        #[cfg(feature = "remote")]
        let map = {
            use crate::remote::NamedBy;
            let named = match is_url(&self.name) {
                true => NamedBy::RemoteCatalog,
                false => NamedBy::LocalCatalog,
            };
            crate::remote::open_place(location, &self.remote, named).map_err(map_error)?
        };
        #[cfg(not(feature = "remote"))]
        let map = match location.to_str().filter(|l| is_url(l)) {
            Some(url) => {
                return Err(SessionError::NoSource(format!(
                    "{url}: a URL, and this build reads no URLs (feature `remote`)"
                )))
            }
            None => Map::open(location).map_err(map_error)?,
        };
        let found = format!("{:016x}", map.index_checksum());
        let recorded = &self.places[i].index_checksum;
        if found != *recorded {
            return Err(SessionError::Mismatch(format!(
                "{}: not the map the catalog was built from (index checksum {found}, catalog \
                 says {recorded}); rebuild the catalog",
                crate::escape::path(location)
            )));
        }
        Ok(map)
    }

    fn place_error(&self, i: usize, source: SessionError) -> SessionError {
        self.place_error_shared(i, Arc::new(source))
    }

    fn place_error_shared(&self, i: usize, source: Arc<SessionError>) -> SessionError {
        SessionError::Place {
            catalog: self.name.clone(),
            place: self.places[i].name.clone(),
            source,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn place(map: &str) -> Place {
        Place {
            name: "p".into(),
            map: map.into(),
            origin: [0.0; 3],
            bbox_min: [0.0; 3],
            bbox_max: [0.0; 3],
            points: 0,
            images: 0,
            file_bytes: 0,
            index_checksum: String::new(),
        }
    }

    /// Where the catalog `catalog` finds a place whose map is `map`, by default options.
    fn resolved(catalog: &str, map: &str) -> Result<PathBuf, SessionError> {
        resolve(
            catalog,
            &place(map),
            #[cfg(feature = "remote")]
            &crate::remote::RemoteOptions::default(),
        )
    }

    #[test]
    fn a_local_catalog_s_places_are_found_from_its_folder() {
        let r = |c, m| resolved(c, m).unwrap();
        assert_eq!(r("city/city.sfpc", "a/m.sfpm"), Path::new("city/a/m.sfpm"));
        assert_eq!(r("city.sfpc", "m.sfpm"), Path::new("m.sfpm"));
        assert_eq!(r("city/city.sfpc", "/abs/m.sfpm"), Path::new("/abs/m.sfpm"));
        assert_eq!(
            r("city/city.sfpc", "https://h/m.sfpm"),
            Path::new("https://h/m.sfpm")
        );
    }

    #[cfg(feature = "remote")]
    #[test]
    fn a_downloaded_catalog_names_only_its_own_server() {
        let r = |m| resolved("https://h/maps/city.sfpc", m);
        assert_eq!(r("a/m.sfpm").unwrap(), Path::new("https://h/maps/a/m.sfpm"));
        assert_eq!(r("../m.sfpm").unwrap(), Path::new("https://h/m.sfpm"));
        // An absolute path stays on the catalog's server, and so may a full URL.
        assert_eq!(r("/etc/passwd").unwrap(), Path::new("https://h/etc/passwd"));
        assert_eq!(
            r("https://h/x.sfpm").unwrap(),
            Path::new("https://h/x.sfpm")
        );
        assert_eq!(
            r("https://H:443/x.sfpm").unwrap(),
            Path::new("https://h/x.sfpm")
        );
        // Another scheme, host, port or bucket is not a location on the server.
        for bad in [
            "file:///etc/passwd",
            "data:,x",
            "//evil.com/m.sfpm",
            "\\\\evil.com\\m.sfpm",
            "/\\evil.com/x",
            "http://h/x.sfpm",
            "https://h:8443/x.sfpm",
            "http://169.254.169.254/latest/meta-data/",
            "s3://victim-bucket/k",
        ] {
            let e = r(bad).unwrap_err().to_string();
            assert!(
                e.contains("refused by the outbound policy") && e.contains("its own server"),
                "{bad}: {e}"
            );
        }
        let s3 = |m| resolved("s3://maps/city/city.sfpc", m);
        assert_eq!(s3("a.sfpm").unwrap(), Path::new("s3://maps/city/a.sfpm"));
        assert!(s3("s3://other/a.sfpm").is_err());
    }
}
