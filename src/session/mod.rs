//! One query, from its source to its pose: a [`Session`] owns the localizer of a shared map,
//! where the queries' features come from ([`QuerySource`]: extracted from images with the
//! map's model, a features file, a COLMAP database, or handed in), the checks that map and
//! features fit, and a sequence's tracking (the pose prior, and the global descriptor
//! computed late when tracking is lost). The CLI, the Python package and the C ABI all
//! localize through it; [`LocalizeOptions::validate`] is the one home of the options' rules.
//! A list of queries runs on threads with [`Session::localize_all`]; the images of an MCAP
//! log with [`mcap_log`] (feature `mcap`).
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use sfpmap::format::Map;
//! use sfpmap::geometry::Camera;
//! use sfpmap::session::{QuerySource, Session};
//! use std::sync::Arc;
//!
//! let map = Arc::new(Map::open("south-building.sfpm")?);
//! let session = Session::builder(map, "south-building.sfpm")
//!     .source(QuerySource::Database("queries.db".into()))
//!     .build(&sfpmap::progress::Silent)?;
//! let camera = Camera::parse("SIMPLE_RADIAL 3072 2304 2559.81 1536 1152 -0.0204")?;
//! let found = session.localize("P1180141.JPG", &camera)?;
//! println!("{:?}", found.pose());
//! # Ok(())
//! # }
//! ```

pub mod catalog;
#[cfg(feature = "mcap")]
pub mod mcap_log;
mod source;

#[cfg(feature = "onnx")]
pub use source::image_misfits_camera;
pub use source::{check_extractable, QuerySource};
pub(crate) use source::{Inference, QueryReader};

use crate::format::{Error as FormatError, Map};
use crate::geometry::Camera;
use crate::io::queries::Query;
use crate::localize::{
    FeatureModel, Localization, LocalizeError, LocalizeOptions, Localizer, MotionModel,
    QueryFailure, QueryFeatures, SkippedLevel,
};
use crate::progress::Reporter;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

self_cell::self_cell!(
    /// The map and the localizer that borrows it, owned together: a session lives as long
    /// as it likes, and the map as long as any session over it.
    struct Prepared {
        owner: Arc<Map<'static>>,
        #[not_covariant]
        dependent: Localizer,
    }
);

/// A map prepared for queries, with where their features come from. `Send + Sync`: threads
/// share one session (a query source that reads a file or runs the extractor takes turns).
pub struct Session {
    prepared: Prepared,
    /// The map as the user named it (a path or a URL), in front of every error, and what
    /// its queries' features must be.
    fit: Fit,
    reader: Mutex<QueryReader>,
    /// Sequence mode: each query is predicted from the last ones and tracked.
    tracking: Option<Mutex<MotionModel>>,
    /// Whether the motion model predicts the next query, for the extraction of frames that
    /// runs beside the localizing thread ([`Session::extract`]).
    tracked: AtomicBool,
}

/// How a [`Session`] is made: [`Session::builder`], then options, a source, and
/// [`SessionBuilder::build`].
pub struct SessionBuilder {
    map: Arc<Map<'static>>,
    map_name: String,
    options: Option<LocalizeOptions>,
    source: QuerySource,
    #[cfg(feature = "hdf5")]
    global_features: Option<std::path::PathBuf>,
    sequence: bool,
    inference: Inference,
}

impl SessionBuilder {
    /// The localizer's options; default [`LocalizeOptions::for_map`]. Checked by
    /// [`LocalizeOptions::validate`] when the session is built.
    pub fn options(mut self, options: LocalizeOptions) -> Self {
        self.options = Some(options);
        self
    }

    /// Where the queries' features come from; default [`QuerySource::Given`].
    pub fn source(mut self, source: QuerySource) -> Self {
        self.source = source;
        self
    }

    /// Queries are an ordered sequence (a camera moving): each is localized by guided
    /// matching around the pose predicted from the last ones (constant velocity), through
    /// retrieval only when tracking is lost. Queries must then come in order from one thread
    /// (calls from several run one at a time, in whichever order they take the lock).
    pub fn sequence(mut self, sequence: bool) -> Self {
        self.sequence = sequence;
        self
    }

    /// An hloc `global-feats.h5` with the queries' global descriptors (`global_descriptor`
    /// by image name, NetVLAD's or any other's): they replace what the source gives, for
    /// retrieval against a map that stores the same kind (`convert --global-features`).
    #[cfg(feature = "hdf5")]
    pub fn global_features(mut self, path: Option<std::path::PathBuf>) -> Self {
        self.global_features = path;
        self
    }

    /// Threads of the extractor's inference (default 2).
    pub fn extractor_threads(mut self, threads: usize) -> Self {
        self.inference.threads = threads.max(1);
        self
    }

    /// Keep the extractor's inference threads spinning a while after each image (default
    /// off): frames that come at a camera's rate are inferred on warm threads and cores,
    /// about a third faster here at 10 Hz, for CPU spent waiting. For a live stream whose
    /// latency counts more than its cores (`sfpmap ros2 --spin`).
    pub fn extractor_spinning(mut self, spin: bool) -> Self {
        self.inference.spin = spin;
        self
    }

    /// Checks the options and that the source fits the map (its model, its descriptors),
    /// opens the source, and indexes the map's levels. Warnings (a features file's global
    /// descriptors of another size, another model asked for on purpose) go to `reporter`.
    pub fn build(self, reporter: &dyn Reporter) -> Result<Session, SessionError> {
        let SessionBuilder {
            map,
            map_name,
            options,
            source,
            #[cfg(feature = "hdf5")]
            global_features,
            sequence,
            inference,
        } = self;
        let options = options.unwrap_or_else(|| LocalizeOptions::for_map(&map));
        let fit = Fit::of(&map, map_name);
        // The options first: a value out of range is refused before any file is opened.
        options.validate().map_err(|e| SessionError::Localize {
            map: fit.map_name.clone(),
            source: LocalizeError::Option(e),
        })?;
        #[allow(unused_mut)]
        let mut reader = QueryReader::open_for(
            source,
            fit.clone(),
            Some(&map),
            &options,
            inference,
            reporter,
        )?;
        #[cfg(feature = "hdf5")]
        if let Some(path) = global_features {
            let map_dim = map_global_dim(&map);
            reader.set_global_features(crate::io::features_h5::H5Features::open(&path)?, map_dim);
        }
        let prepared =
            Prepared::try_new(map, |map| Localizer::new(map, options)).map_err(|source| {
                SessionError::Localize {
                    map: fit.map_name.clone(),
                    source,
                }
            })?;
        Ok(Session {
            prepared,
            fit,
            reader: Mutex::new(reader),
            tracking: sequence.then(|| Mutex::new(MotionModel::new())),
            tracked: AtomicBool::new(false),
        })
    }
}

/// A query's features as its source gave them, and, for a frame extracted without its
/// global descriptor (the sequence was tracking), the image to compute it from should
/// tracking be lost.
pub struct Frame {
    /// The query's features.
    pub features: QueryFeatures,
    #[cfg(feature = "onnx")]
    deferred: Option<Box<crate::extract::image::GrayInput>>,
    /// Made by the caller ([`Frame::new`]), not by the session's own source: its features'
    /// model is checked against the map as [`Session::localize_features`] checks it.
    handed_in: bool,
}

/// The image a frame deferred its global descriptor for (nothing without the extractor).
#[cfg(feature = "onnx")]
type Deferred = crate::extract::image::GrayInput;
#[cfg(not(feature = "onnx"))]
type Deferred = std::convert::Infallible;

impl Frame {
    /// Features handed in.
    pub fn new(features: QueryFeatures) -> Frame {
        Frame {
            features,
            #[cfg(feature = "onnx")]
            deferred: None,
            handed_in: true,
        }
    }

    /// Features the session's source read or extracted (a `--model` asked for on purpose
    /// may be another model than the map's: the source warned when it opened).
    pub(crate) fn from_source(features: QueryFeatures) -> Frame {
        Frame {
            handed_in: false,
            ..Frame::new(features)
        }
    }

    fn deferred(&self) -> Option<&Deferred> {
        #[cfg(feature = "onnx")]
        return self.deferred.as_deref();
        #[cfg(not(feature = "onnx"))]
        None
    }
}

/// What the map says its query features must be: the descriptor kind, and the model's hash
/// where the map records it.
#[derive(Clone)]
pub(crate) struct Fit {
    pub(crate) map_name: String,
    pub(crate) descriptor: String,
    /// Whether the descriptor names a feature queries must be (not an unnamed one).
    pub(crate) named: bool,
    /// Whether the map's descriptors came from a features source, not an extractor.
    pub(crate) from_feature_source: bool,
    pub(crate) model_xxh3: Option<String>,
    /// The map's levels with points as (level id, the dimensions a query's descriptor of it
    /// has: its projection's input, else its full dimensions): what a model must make to be
    /// matched against it.
    #[cfg(feature = "onnx")]
    pub(crate) levels: Vec<(u16, u32)>,
}

impl Fit {
    fn of(map: &Map<'_>, map_name: String) -> Fit {
        let first = map.metadata().levels.first();
        let descriptor = first.map(|l| l.descriptor.clone()).unwrap_or_default();
        let model_xxh3 = map
            .metadata()
            .provenance
            .model
            .as_ref()
            .map(|m| m.xxh3.clone())
            .filter(|h| !h.is_empty());
        Fit {
            map_name,
            descriptor,
            named: first.is_some_and(|l| l.names_feature()),
            from_feature_source: first.is_some_and(|l| l.from_feature_source()),
            model_xxh3,
            // Levels without points are skipped by the localizer: nothing to match there.
            #[cfg(feature = "onnx")]
            levels: map
                .metadata()
                .levels
                .iter()
                .filter(|l| {
                    map.find(crate::format::SectionKind::LevelPoints, Some(l.level))
                        .is_some_and(|s| s.rows() > 0)
                })
                .map(|l| {
                    let projection =
                        map.find(crate::format::SectionKind::LevelProjection, Some(l.level));
                    let d_in = projection
                        .map_or(l.dim_full, |p| u32::try_from(p.cols()).unwrap_or(u32::MAX));
                    (l.level, d_in)
                })
                .collect(),
        }
    }

    /// Refuses features of another model than the map's: another feature (`sift` for an
    /// `aliked-n16` map, one SFP model for another), or the same model with another hash where
    /// both record one (a retrained model exported under the same name). `origin` names where
    /// the features came from (made only for an error). Features that do not say what they
    /// are (arrays handed in, a features file of no name) and maps whose feature has no name
    /// (`features-<dim>`, `colmap-<dim>`) are taken as they are: the localizer still refuses
    /// another dimension.
    pub(crate) fn check_model(
        &self,
        model: &FeatureModel,
        origin: impl Fn() -> String,
    ) -> Result<(), SessionError> {
        let descriptor = &self.descriptor;
        if !self.named {
            return Ok(());
        }
        let map = &self.map_name;
        if model.name != *descriptor {
            let origin = origin();
            let fix = if self.from_feature_source {
                format!("give query features of {descriptor:?}")
            } else {
                format!("extract the queries with model {descriptor:?}")
            };
            return Err(SessionError::Mismatch(format!(
                "{origin}: features of model {:?}, but the map {map} holds {descriptor:?} \
                 descriptors: {fix}",
                model.name
            )));
        }
        if let (Some(hash), Some(map_hash)) = (&model.xxh3, &self.model_xxh3) {
            if hash != map_hash {
                let origin = origin();
                return Err(SessionError::Mismatch(format!(
                    "{origin}: features of a {descriptor:?} model of hash {hash:?}, but the map \
                     {map} was made with one of hash {map_hash:?}: extract the queries with that \
                     model"
                )));
            }
        }
        Ok(())
    }
}

/// The dimensions of `map`'s global descriptors, from its section table (nothing is read);
/// `None` when it stores none.
pub(crate) fn map_global_dim(map: &Map<'_>) -> Option<usize> {
    map.find(crate::format::SectionKind::ImageGlobal, None)
        .map(|section| section.cols as usize)
}

/// Why a query's global descriptor of `len` values cannot rank the images of the map named
/// `map_name`, whose global descriptors have `map_dim` dimensions (`None`: it stores none):
/// retrieval would fall back in silence. The one rule for features files, descriptors handed
/// in (Python) and the C ABI. `None` when it fits.
pub(crate) fn global_mismatch(
    len: usize,
    map_dim: Option<usize>,
    map_name: &str,
) -> Option<String> {
    match map_dim {
        Some(d) if d == len => None,
        Some(d) => Some(format!(
            "{len} values, but the map {map_name} stores global descriptors of {d}"
        )),
        None => Some(format!(
            "{len} values, but the map {map_name} stores no global descriptors"
        )),
    }
}

impl Session {
    /// A session over `map`, which errors call `map_name` (the path or URL it was opened
    /// from).
    pub fn builder(map: Arc<Map<'static>>, map_name: impl Into<String>) -> SessionBuilder {
        SessionBuilder {
            map,
            map_name: map_name.into(),
            options: None,
            source: QuerySource::Given,
            #[cfg(feature = "hdf5")]
            global_features: None,
            sequence: false,
            inference: Inference {
                threads: 2,
                spin: false,
            },
        }
    }

    /// The map.
    pub fn map(&self) -> &Arc<Map<'static>> {
        self.prepared.borrow_owner()
    }

    /// The map's name as errors give it.
    pub fn map_name(&self) -> &str {
        &self.fit.map_name
    }

    /// The options, as validated.
    pub fn options(&self) -> LocalizeOptions {
        self.prepared.with_dependent(|_, l| l.options().clone())
    }

    /// Level ids in matching order (deepest first).
    pub fn level_order(&self) -> Vec<u16> {
        self.prepared.with_dependent(|_, l| l.level_order())
    }

    /// Selected levels that are not matched, and why.
    pub fn skipped_levels(&self) -> Vec<SkippedLevel> {
        self.prepared
            .with_dependent(|_, l| l.skipped_levels().to_vec())
    }

    /// Whether queries are a sequence ([`SessionBuilder::sequence`]).
    pub fn is_sequence(&self) -> bool {
        self.tracking.is_some()
    }

    /// Whether the sequence predicts the next query's pose (it has localized the last one).
    pub fn is_tracking(&self) -> bool {
        self.tracked.load(Ordering::Relaxed)
    }

    /// Queries extracted without their global descriptor because the sequence was tracking.
    pub fn global_deferred(&self) -> usize {
        self.lock_reader().global_deferred()
    }

    /// The query `name` from the session's source (an image of its folder, an entry of its
    /// features file or database), localized. A query whose features cannot be had (missing,
    /// an image that does not decode) is a [`QueryFailure::NoFeatures`], not an error.
    pub fn localize(&self, name: &str, camera: &Camera) -> Result<Localization, SessionError> {
        let mut tracking = self.tracking_lock();
        let tracked = tracking.as_ref().is_some_and(|m| m.predict().is_some());
        let frame = self.lock_reader().frame(name, tracked, Some(camera))?;
        match frame {
            Ok(frame) => {
                let (features, deferred) = (&frame.features, frame.deferred());
                let found = self.localize_tracked(
                    tracking.as_deref_mut(),
                    features,
                    deferred,
                    camera,
                    name,
                );
                // Read from the source, not handed in: features that do not fit the map fail
                // this query alone, as features that cannot be read do.
                match found {
                    Err(e) => match e.unusable_query() {
                        Some(reason) => Ok(Localization::failed(QueryFailure::NoFeatures(reason))),
                        None => Err(e),
                    },
                    found => found,
                }
            }
            Err(reason) => {
                if let Some(motion) = tracking.as_deref_mut() {
                    self.update(motion, None);
                }
                Ok(Localization::failed(QueryFailure::NoFeatures(reason)))
            }
        }
    }

    /// Each of `queries` from the session's source, localized as [`Session::localize`] does,
    /// on `threads` workers (one for a sequence, whose queries run in order); the results in
    /// the order of `queries`. Progress goes to `reporter`, one item per query. The first
    /// error of any query stops the run.
    pub fn localize_all(
        &self,
        queries: &[Query],
        threads: usize,
        reporter: &dyn Reporter,
    ) -> Result<Vec<Localization>, SessionError> {
        self.run_all(queries.len(), threads, reporter, |i| {
            self.localize(&queries[i].name, &queries[i].camera)
        })
    }

    /// Each of `queries`, features handed in with their camera and name, localized as
    /// [`Session::localize_features`] does, on threads as [`Session::localize_all`] runs
    /// them; the results in the order of `queries`. The first error stops the run.
    pub fn localize_features_all(
        &self,
        queries: &[(&QueryFeatures, &Camera, &str)],
        threads: usize,
        reporter: &dyn Reporter,
    ) -> Result<Vec<Localization>, SessionError> {
        self.run_all(queries.len(), threads, reporter, |i| {
            let (features, camera, name) = queries[i];
            self.localize_features(features, camera, name)
        })
    }

    /// `run(i)` for each of `n` queries on `threads` workers (one for a sequence).
    fn run_all(
        &self,
        n: usize,
        threads: usize,
        reporter: &dyn Reporter,
        run: impl Fn(usize) -> Result<Localization, SessionError> + Sync,
    ) -> Result<Vec<Localization>, SessionError> {
        let threads = if self.is_sequence() { 1 } else { threads };
        run_all(n, threads, reporter, run)
    }

    /// `features` handed in (the caller's own extractor, or a query of any source),
    /// localized; `name` names the query in errors. Features that record their model are
    /// refused for a map of another model.
    pub fn localize_features(
        &self,
        features: &QueryFeatures,
        camera: &Camera,
        name: &str,
    ) -> Result<Localization, SessionError> {
        self.check_handed_in(features, name)?;
        let mut tracking = self.tracking_lock();
        self.localize_tracked(tracking.as_deref_mut(), features, None, camera, name)
    }

    /// `input` (an image decoded by the caller: an MCAP message, a camera) extracted with
    /// the session's model. While the sequence tracks, the global descriptor is deferred
    /// where it costs another inference: [`Session::localize_frame`] computes it only if
    /// tracking is lost. Extraction takes turns on the one model; callers may decode and
    /// call this from several threads while another localizes.
    #[cfg(feature = "onnx")]
    pub fn extract(&self, input: crate::extract::image::GrayInput) -> Result<Frame, SessionError> {
        let tracked = self.is_sequence() && self.is_tracking();
        self.lock_reader().extract(input, tracked)
    }

    /// The RGB-to-grey weights of the session's model, to prepare an image for
    /// [`Session::extract`]; `None` when the session does not extract.
    #[cfg(feature = "onnx")]
    pub fn gray_weights(&self) -> Option<[f32; 3]> {
        self.lock_reader().gray_weights()
    }

    /// A frame from [`Session::extract`] (or [`Frame::new`]), localized; in a sequence, in
    /// order. `name` names it in errors.
    pub fn localize_frame(
        &self,
        frame: Frame,
        camera: &Camera,
        name: &str,
    ) -> Result<Localization, SessionError> {
        if frame.handed_in {
            self.check_handed_in(&frame.features, name)?;
        }
        let mut tracking = self.tracking_lock();
        let (features, deferred) = (&frame.features, frame.deferred());
        self.localize_tracked(tracking.as_deref_mut(), features, deferred, camera, name)
    }

    /// Features from outside the session's source: where they record their model, the
    /// map's (every value finite is the localizer's own check, [`QueryFeatures::check_finite`],
    /// whoever made them).
    fn check_handed_in(&self, features: &QueryFeatures, name: &str) -> Result<(), SessionError> {
        self.check_fit(features, name)
    }

    /// Every value of `features` finite, else the error naming `map` and the query.
    pub(crate) fn check_finite(
        features: &QueryFeatures,
        map: &str,
        name: &str,
    ) -> Result<(), SessionError> {
        features.check_finite().map_err(|e| SessionError::Query {
            map: map.to_string(),
            query: name.to_string(),
            source: LocalizeError::NonFinite(e),
        })
    }

    /// Features that record their model are the map's, and a global descriptor has the
    /// map's global descriptors' size ([`global_mismatch`]).
    fn check_fit(&self, features: &QueryFeatures, name: &str) -> Result<(), SessionError> {
        let origin = || format!("{}: query {name:?}", self.fit.map_name);
        if let Some(model) = &features.model {
            self.fit.check_model(model, origin)?;
        }
        if let Some(global) = &features.global {
            // A value that is not finite is named first, as the localizer names it.
            crate::localize::check_global_finite(Some(global)).map_err(|e| {
                SessionError::Query {
                    map: self.fit.map_name.clone(),
                    query: name.to_string(),
                    source: LocalizeError::NonFinite(e),
                }
            })?;
            // Only where retrieval would rank by it (`--retrieval vlad` or `off` never does).
            let ranks = self.prepared.with_dependent(|_, l| {
                matches!(
                    l.options().retrieval,
                    crate::localize::RetrievalMethod::Auto
                        | crate::localize::RetrievalMethod::Global
                )
            });
            let map_dim = map_global_dim(self.map());
            if let Some(why) =
                global_mismatch(global.len(), map_dim, &self.fit.map_name).filter(|_| ranks)
            {
                return Err(SessionError::Query {
                    map: self.fit.map_name.clone(),
                    query: name.to_string(),
                    source: LocalizeError::GlobalDescriptor(why),
                });
            }
        }
        Ok(())
    }

    /// The dimensions of the map's global descriptors; `None` when it stores none (it
    /// ranks its images by VLAD).
    pub fn global_dim(&self) -> Option<usize> {
        map_global_dim(self.map())
    }

    /// A query of the sequence that has no features (it could not be read or decoded):
    /// tracking restarts, and the next query goes through retrieval.
    pub fn reset_tracking(&self) {
        if let Some(motion) = self.tracking_lock().as_deref_mut() {
            self.update(motion, None);
        }
    }

    /// `features` localized (with the sequence's prior, which it then updates); `deferred`:
    /// the image to compute the global descriptor from, if it was deferred and tracking is
    /// lost.
    fn localize_tracked(
        &self,
        motion: Option<&mut MotionModel>,
        features: &QueryFeatures,
        deferred: Option<&Deferred>,
        camera: &Camera,
        name: &str,
    ) -> Result<Localization, SessionError> {
        let prior = motion.as_ref().and_then(|m| m.predict());
        #[cfg(feature = "onnx")]
        // The reader is locked only for a frame that deferred its descriptor: others must not
        // wait behind an extraction for a `None`.
        let mut global = || {
            let deferred = deferred?;
            self.lock_reader().global_of(deferred)
        };
        #[cfg(not(feature = "onnx"))]
        let mut global = || deferred.and(None);
        let found = self.prepared.with_dependent(|_, localizer| {
            localizer.localize_with_prior_then_global(features, camera, prior.as_ref(), &mut global)
        });
        if let Some(motion) = motion {
            self.update(motion, found.as_ref().ok().and_then(Localization::pose));
        }
        found.map_err(|source| SessionError::Query {
            map: self.fit.map_name.clone(),
            query: name.to_string(),
            source,
        })
    }

    fn update(&self, motion: &mut MotionModel, pose: Option<&crate::geometry::Pose>) {
        motion.update(pose);
        self.tracked
            .store(motion.predict().is_some(), Ordering::Relaxed);
    }

    /// The motion model of a sequence, held for one query so queries run in order (`None`
    /// outside sequences: queries run in parallel).
    fn tracking_lock(&self) -> Option<MutexGuard<'_, MotionModel>> {
        self.tracking
            .as_ref()
            .map(|m| m.lock().unwrap_or_else(|p| p.into_inner()))
    }

    fn lock_reader(&self) -> MutexGuard<'_, QueryReader> {
        self.reader.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// `run(i)` for each of `n` queries on `threads` workers (capped: no more than the queries,
/// nor than any thread setting gets, `max_threads`), results in order; progress to
/// `reporter`, one item a query. The first error stops the workers taking further queries
/// (an error every query meets must not cost the whole list first).
pub(crate) fn run_all<T: Send>(
    n: usize,
    threads: usize,
    reporter: &dyn Reporter,
    run: impl Fn(usize) -> Result<T, SessionError> + Sync,
) -> Result<Vec<T>, SessionError> {
    reporter.start("localizing", Some(n as u64));
    let results: Vec<Mutex<Option<T>>> = (0..n).map(|_| Mutex::new(None)).collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let workers = threads
        .clamp(1, crate::progress::max_threads())
        .min(n.max(1));
    let first_error: Mutex<Option<SessionError>> = Mutex::new(None);
    let stop = AtomicBool::new(false);
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| loop {
                if stop.load(Ordering::Relaxed) {
                    break;
                }
                let i = next.fetch_add(1, Ordering::Relaxed);
                if i >= n {
                    break;
                }
                match run(i) {
                    Ok(r) => *results[i].lock().unwrap_or_else(|p| p.into_inner()) = Some(r),
                    Err(e) => {
                        stop.store(true, Ordering::Relaxed);
                        let mut first = first_error.lock().unwrap_or_else(|p| p.into_inner());
                        first.get_or_insert(e);
                    }
                }
                reporter.advance(1);
            });
        }
    });
    reporter.finish();
    if let Some(e) = first_error.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(e);
    }
    Ok(results
        .into_iter()
        .map(|m| {
            let result = m.into_inner().unwrap_or_else(|p| p.into_inner());
            result.expect("every query ran")
        })
        .collect())
}

/// What stops a session from being made or a query from being run (a query that is merely
/// not localized is a [`Localization`] with its [`QueryFailure`]). Each names the map, the
/// file or the query it is about.
#[derive(Debug)]
#[non_exhaustive]
pub enum SessionError {
    /// The localizer cannot be built: an option out of range, a level the map lacks, a map
    /// without descriptors.
    Localize {
        /// The map's name.
        map: String,
        /// Why.
        source: LocalizeError,
    },
    /// A query's features do not fit the map (dimensions, levels).
    Query {
        /// The map's name.
        map: String,
        /// The query's name.
        query: String,
        /// Why.
        source: LocalizeError,
    },
    /// The source does not fit the map: features of another model, a map whose model no
    /// built-in one matches.
    Mismatch(String),
    /// A SIFT map (or one without descriptors) asked to extract its queries with the SFP
    /// model: its queries' features come from a database or a features file.
    NotExtractable {
        /// The map's name.
        map: String,
        /// The map's descriptor kind (empty: none).
        descriptor: String,
    },
    /// The source is not one this call reads from (a name asked of handed-in features).
    NoSource(String),
    /// A place of a catalog ([`catalog::CatalogSession`]): its map cannot be opened, is not
    /// the one the catalog recorded, or its session cannot be made.
    Place {
        /// The catalog's name.
        catalog: String,
        /// The place's name.
        place: String,
        /// Why (shared: a place that failed to open fails each query that ranks it the
        /// same way, without opening it again).
        source: Arc<SessionError>,
    },
    /// The map itself (it cannot be opened, or a damaged section while reading it).
    Map {
        /// The map's name.
        map: String,
        /// Why.
        source: FormatError,
    },
    /// A features file or a query list.
    Input(crate::io::InputError),
    /// A COLMAP database.
    #[cfg(feature = "colmap")]
    Database {
        /// The database.
        path: std::path::PathBuf,
        /// Why.
        source: crate::colmap::Error,
    },
    /// The extractor (its model, the runtime, an inference).
    #[cfg(feature = "onnx")]
    Extract(crate::extract::ExtractError),
}

impl std::fmt::Display for SessionError {
    /// Map and catalog names are the caller's (a path, a URL) and messages quote paths and
    /// files: control characters escaped ([`crate::escape`]); query and place names are
    /// quoted with Rust's escapes.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SessionError::Localize { map, source } => write!(f, "{}: {source}", text(map)),
            SessionError::Query { map, query, source } => {
                write!(f, "{}: query {query:?}: {source}", text(map))
            }
            SessionError::Mismatch(m) | SessionError::NoSource(m) => f.write_str(&text(m)),
            SessionError::NotExtractable { map, descriptor } if descriptor.is_empty() => {
                let map = text(map);
                write!(f, "{map}: the map has no descriptors (geometry only)")
            }
            SessionError::NotExtractable { map, descriptor } => write!(
                f,
                "{}: a map of {descriptor:?} descriptors, which the SFP extractor does not \
                 make: its queries' features come from a COLMAP database or a features file",
                text(map)
            ),
            // An I/O error names its file already.
            SessionError::Map {
                source: source @ FormatError::Io { .. },
                ..
            } => source.fmt(f),
            SessionError::Map { map, source } => write!(f, "{}: {source}", text(map)),
            SessionError::Place {
                catalog,
                place,
                source,
            } => write!(f, "{}: place {place:?}: {source}", text(catalog)),
            SessionError::Input(e) => e.fmt(f),
            #[cfg(feature = "colmap")]
            SessionError::Database { path, source } => {
                write!(f, "{}: {source}", crate::escape::path(path))
            }
            #[cfg(feature = "onnx")]
            SessionError::Extract(e) => e.fmt(f),
        }
    }
}

/// A name or message for [`SessionError`]'s text, control characters escaped.
fn text(s: &str) -> std::borrow::Cow<'_, str> {
    crate::escape::escape_control_characters(s)
}

impl SessionError {
    /// Why a query's own features cannot be localized (they do not fit the map's levels,
    /// or hold a value that is not finite), `None` for any other error. An error for features
    /// a caller hands in; a failed query ([`QueryFailure::NoFeatures`]) for a query a session
    /// reads by name from its source (a features file, a database), so one bad entry does not
    /// end a run.
    pub(crate) fn unusable_query(&self) -> Option<String> {
        match self {
            SessionError::Query { source, .. } => matches!(
                source,
                LocalizeError::DescriptorMismatch { .. }
                    | LocalizeError::NoFeaturesForLevel { .. }
                    | LocalizeError::FeatureShape { .. }
                    | LocalizeError::GlobalDescriptor(_)
                    | LocalizeError::NonFinite(_)
            )
            .then(|| source.to_string()),
            SessionError::Place { place, source, .. } => {
                let reason = source.unusable_query()?;
                Some(format!("place {place:?}: {reason}"))
            }
            _ => None,
        }
    }
}

/// Each variant prints its cause's text as its own (after the map or file it names), so its
/// `source()` is the cause's own source: a chain printed whole says each thing once.
impl std::error::Error for SessionError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            SessionError::Localize { source, .. } | SessionError::Query { source, .. } => {
                source.source()
            }
            SessionError::Map { source, .. } => source.source(),
            SessionError::Place { source, .. } => source.source(),
            SessionError::Input(e) => e.source(),
            #[cfg(feature = "colmap")]
            SessionError::Database { source, .. } => source.source(),
            #[cfg(feature = "onnx")]
            SessionError::Extract(e) => e.source(),
            _ => None,
        }
    }
}

#[cfg(feature = "onnx")]
impl From<crate::extract::ExtractError> for SessionError {
    fn from(e: crate::extract::ExtractError) -> Self {
        SessionError::Extract(e)
    }
}

impl From<crate::io::InputError> for SessionError {
    fn from(e: crate::io::InputError) -> Self {
        SessionError::Input(e)
    }
}
