//! Where a session's query features come from, opened and checked against the map.

use super::{Fit, Frame, SessionError};
use crate::format::Map;
use crate::geometry::Camera;
#[cfg(feature = "onnx")]
use crate::localize::{FeatureModel, RetrievalMethod};
use crate::localize::{LocalizeOptions, QueryFeatures};
use crate::progress::Reporter;
#[cfg(any(feature = "colmap", feature = "onnx"))]
use std::path::PathBuf;

/// How a session's extractor infers: its threads, and whether they spin between images
/// ([`super::SessionBuilder::extractor_spinning`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Inference {
    pub threads: usize,
    pub spin: bool,
}

/// Where a session's query features come from.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub enum QuerySource {
    /// Handed to each call ([`Session::localize_features`], [`Session::localize_frame`]):
    /// the caller's own extractor, or features of any origin.
    ///
    /// [`Session::localize_features`]: super::Session::localize_features
    /// [`Session::localize_frame`]: super::Session::localize_frame
    Given,
    /// A COLMAP database holding the queries' keypoints and descriptors (SIFT, or the
    /// feature its `type` records), by image name; rows of another feature than the map's
    /// fail their query.
    #[cfg(feature = "colmap")]
    Database(PathBuf),
    /// An hloc-style features.h5 (`sfpmap extract`'s, or hloc's), by image name; one that
    /// records its model (`sfp.model_name`, `sfp.model_xxh3`) must be the map's.
    #[cfg(feature = "hdf5")]
    FeaturesFile(PathBuf),
    /// Extracted with the map's model (SFP or ALIKED) from the images of `folder`, by name (a name that is an
    /// absolute path or has a `..` component fails its query: [`crate::input::join_inside`];
    /// `None`: images are handed to [`Session::extract`], as decoded from an MCAP log).
    /// `model`: an ONNX file or a built-in model's name; `None`: the built-in model the map
    /// was made with.
    ///
    /// [`Session::extract`]: super::Session::extract
    #[cfg(feature = "onnx")]
    Images {
        /// The images' folder.
        folder: Option<PathBuf>,
        /// The model.
        model: Option<PathBuf>,
    },
}

/// A source, opened. One per session (or catalog): the size of its largest variant does not
/// matter, and which variant is largest depends on the features.
#[allow(clippy::large_enum_variant)]
pub(super) enum Source {
    Given,
    #[cfg(feature = "colmap")]
    Database {
        db: crate::io::queries::DatabaseFeatures,
        path: PathBuf,
    },
    #[cfg(feature = "hdf5")]
    FeaturesFile(crate::io::features_h5::H5Features),
    #[cfg(feature = "onnx")]
    Images {
        extractor: crate::extract::Extractor,
        folder: Option<PathBuf>,
        /// The size of the map's global descriptors ([`GlobalSize::of_map`]), or `Skip` where
        /// retrieval will not rank by them.
        ///
        /// [`GlobalSize::of_map`]: crate::extract::GlobalSize::of_map
        global: crate::extract::GlobalSize,
    },
}

/// A [`QuerySource`], opened and checked against a map: the queries' features by name. A
/// [`Session`](super::Session) keeps one; a catalog's places share one (their features are
/// read once and localized in several places).
pub(crate) struct QueryReader {
    source: Source,
    /// The queries' global descriptors from their own file (hloc's `global-feats.h5`), and
    /// the map's global descriptors' dimension they must have.
    #[cfg(feature = "hdf5")]
    global: Option<(crate::io::features_h5::H5Features, Option<usize>)>,
    fit: Fit,
    /// Queries extracted without their global descriptor (tracked frames).
    global_deferred: usize,
}

impl QueryReader {
    /// `source` for the queries of a catalog's places, whose descriptors are `descriptor`
    /// (features files are checked against it; images cannot be extracted for several maps).
    pub(crate) fn for_catalog(
        source: QuerySource,
        catalog_name: &str,
        descriptor: &str,
        reporter: &dyn Reporter,
    ) -> Result<QueryReader, SessionError> {
        let fit = Fit {
            map_name: catalog_name.to_string(),
            descriptor: descriptor.to_string(),
            named: crate::format::descriptor_names_feature(descriptor),
            // Catalog queries come from files, never an extractor: only the hint's wording.
            from_feature_source: !crate::localize::is_sfp_descriptor(descriptor),
            model_xxh3: None,
            #[cfg(feature = "onnx")]
            levels: Vec::new(),
        };
        let options = LocalizeOptions::default();
        let inference = Inference {
            threads: 1,
            spin: false,
        };
        Self::open_for(source, fit, None, &options, inference, reporter)
    }

    pub(super) fn open_for(
        source: QuerySource,
        fit: Fit,
        map: Option<&Map<'_>>,
        options: &LocalizeOptions,
        inference: Inference,
        reporter: &dyn Reporter,
    ) -> Result<QueryReader, SessionError> {
        let source = Source::open(source, &fit, map, options, inference, reporter)?;
        Ok(QueryReader {
            source,
            #[cfg(feature = "hdf5")]
            global: None,
            fit,
            global_deferred: 0,
        })
    }

    /// Every query's global descriptor comes from `h5` (by name), of `map_dim` dimensions
    /// (the map's; `None`: the map stores none).
    #[cfg(feature = "hdf5")]
    pub(crate) fn set_global_features(
        &mut self,
        h5: crate::io::features_h5::H5Features,
        map_dim: Option<usize>,
    ) {
        self.global = Some((h5, map_dim));
    }

    /// The query `name`'s features, or why it has none (missing, an image that does not
    /// decode): a failed query, not an error.
    pub(crate) fn read(
        &mut self,
        name: &str,
    ) -> Result<Result<QueryFeatures, String>, SessionError> {
        Ok(self.frame(name, false, None)?.map(|f| f.features))
    }

    /// Queries extracted without their global descriptor (tracked frames).
    pub(crate) fn global_deferred(&self) -> usize {
        self.global_deferred
    }
}

impl Source {
    fn open(
        source: QuerySource,
        fit: &Fit,
        map: Option<&Map<'_>>,
        options: &LocalizeOptions,
        inference: Inference,
        reporter: &dyn Reporter,
    ) -> Result<Source, SessionError> {
        #[cfg(not(feature = "onnx"))]
        let _ = (fit, map, options, inference, reporter);
        Ok(match source {
            QuerySource::Given => Source::Given,
            #[cfg(feature = "colmap")]
            QuerySource::Database(path) => {
                let db = crate::io::queries::DatabaseFeatures::open(&path).map_err(|source| {
                    SessionError::Database {
                        path: path.clone(),
                        source,
                    }
                })?;
                Source::Database { db, path }
            }
            #[cfg(feature = "hdf5")]
            QuerySource::FeaturesFile(path) => {
                let h5 = crate::io::features_h5::H5Features::open(&path)?;
                // A file that names its feature (`sfp.model_name`, hloc's `feats-<conf>.h5`)
                // must hold the map's; one that does not is taken as it is.
                if let Some(name) = h5.feature_name()? {
                    let model = FeatureModel {
                        name,
                        xxh3: h5.root_string("sfp.model_xxh3")?,
                    };
                    fit.check_model(&model, || crate::escape::path(&path).to_string())?;
                }
                #[cfg(feature = "onnx")]
                if let Some(map) = map {
                    warn_global_size(&h5, &path, map, reporter);
                }
                Source::FeaturesFile(h5)
            }
            #[cfg(feature = "onnx")]
            QuerySource::Images { folder, model } => {
                let Some(map) = map else {
                    return Err(SessionError::NoSource(format!(
                        "{}: query features for a catalog's places come from a database or a \
                         features file, not from images",
                        fit.map_name
                    )));
                };
                let extractor = extractor(fit, model, &options.levels, inference, reporter)?;
                Source::Images {
                    extractor,
                    folder,
                    global: global_size(options, map),
                }
            }
        })
    }
}

impl QueryReader {
    /// The query `name`'s features, or why it has none (a failed query, not an error).
    /// `tracked`: a sequence's frame with a pose prior, which does not retrieve, so the
    /// extractor defers the global descriptor where it costs another inference.
    #[cfg_attr(
        not(any(feature = "colmap", feature = "onnx")),
        allow(unreachable_code, unused_variables)
    )]
    pub(super) fn frame(
        &mut self,
        name: &str,
        tracked: bool,
        camera: Option<&Camera>,
    ) -> Result<Result<Frame, String>, SessionError> {
        #[cfg(not(feature = "onnx"))]
        let _ = (tracked, camera);
        let missing = |what: &str| Err(format!("no features for {name:?} ({what})"));
        let map_name = &self.fit.map_name;
        let features: Option<QueryFeatures> = match &mut self.source {
            Source::Given => {
                return Err(SessionError::NoSource(format!(
                    "{}: query {name:?}: this session's features are handed in, not read by name",
                    map_name
                )))
            }
            // A query the file holds but that cannot be used (a NaN keypoint, descriptors
            // that do not fit its keypoints) fails alone, as a missing one does; the error
            // names the file, the query and what is wrong.
            #[cfg(feature = "colmap")]
            Source::Database { db, path } => match db.features(name) {
                // Each image's row says its feature (COLMAP 4's `type`): one of another
                // feature than the map's fails alone, named with the database and the query.
                Ok(Some(features)) => {
                    if let Some(model) = &features.model {
                        let origin = || {
                            format!(
                                "{}: query {}",
                                crate::escape::path(path),
                                crate::escape::quoted_name(name)
                            )
                        };
                        if let Err(e) = self.fit.check_model(model, origin) {
                            return Ok(Err(e.to_string()));
                        }
                    }
                    Some(features)
                }
                Ok(None) => None,
                Err(source) => {
                    let path = path.clone();
                    return Ok(Err(SessionError::Database { path, source }.to_string()));
                }
            },
            #[cfg(feature = "hdf5")]
            Source::FeaturesFile(h5) => match h5.features(name) {
                Ok(features) => features,
                Err(e) => return Ok(Err(e.to_string())),
            },
            #[cfg(feature = "onnx")]
            Source::Images {
                folder, extractor, ..
            } => {
                use crate::extract::ExtractError;
                let Some(folder) = folder else {
                    return Err(SessionError::NoSource(format!(
                        "{}: query {name:?}: this session's images are handed in, not read by name",
                        map_name
                    )));
                };
                // A name the list gave stays inside the folder the user named.
                let path = match crate::input::join_inside(folder, name) {
                    Ok(path) => path,
                    Err(why) => return Ok(Err(why.to_owned())),
                };
                // A FIFO or folder goes on to `load`, whose regular-file rule names it.
                if !path.exists() {
                    return Ok(missing("no such image"));
                }
                let weights = extractor.contract().gray_weights;
                let input = match crate::extract::image::load(&path, weights, None) {
                    Ok(input) => input,
                    Err(ExtractError::Image { source, .. }) => {
                        return Ok(Err(format!("the image does not decode: {source}")))
                    }
                    Err(ExtractError::Io { source, .. }) => {
                        return Ok(Err(format!("the image cannot be read: {source}")))
                    }
                    Err(e) => return Err(e.into()),
                };
                // One oversized query, or one whose camera is of another size, is a failed
                // query, not an aborted run.
                if let Some(reason) =
                    crate::extract::too_large_for_the_network(input.width, input.height).or_else(
                        || {
                            // The size as decoded, before any shrinking to the network's
                            // budget (keypoints are scaled back to it).
                            let [w, h] = input
                                .original_size
                                .map(|n| usize::try_from(n).unwrap_or(usize::MAX));
                            image_misfits_camera(w, h, camera?)
                        },
                    )
                {
                    return Ok(Err(reason));
                }
                return self.extract(input, tracked).map(Ok).map_err(|e| match e {
                    SessionError::Extract(e) => SessionError::Extract(e.on_image(&path)),
                    e => e,
                });
            }
        };
        #[cfg(feature = "hdf5")]
        let features = match (features, &self.global) {
            // As convert refuses a map image without one: a query retrieving by a global
            // descriptor it does not have would rank by nothing.
            (Some(mut f), Some((global, map_dim))) => match global.global(name) {
                // A query's unusable descriptor (NaN) fails that query alone.
                Err(e) => return Ok(Err(e.to_string())),
                // Another network's (or none in the map): retrieval would fall back in silence.
                // Said for the query, which fails alone as one of another dimension does.
                Ok(Some(g)) => {
                    if let Some(why) = super::global_mismatch(g.len(), *map_dim, &self.fit.map_name)
                    {
                        let what = format!("{name}/global_descriptor: {why}");
                        return Ok(Err(global.err(what).to_string()));
                    }
                    f.global = Some(g);
                    Some(f)
                }
                Ok(None) => {
                    return Ok(Err(format!(
                        "no global_descriptor for it in {}",
                        crate::escape::path(global.path())
                    )))
                }
            },
            (f, _) => f,
        };
        Ok(match features {
            Some(features) => Ok(Frame::from_source(features)),
            #[cfg(feature = "colmap")]
            None if matches!(self.source, Source::Database { .. }) => {
                missing("not in the database")
            }
            None => missing("not in the features file"),
        })
    }

    /// The RGB-to-grey weights of the extractor's model.
    #[cfg(feature = "onnx")]
    pub(super) fn gray_weights(&self) -> Option<[f32; 3]> {
        match &self.source {
            Source::Images { extractor, .. } => Some(extractor.contract().gray_weights),
            _ => None,
        }
    }

    /// `input` extracted (see [`Session::extract`](super::Session::extract)).
    #[cfg(feature = "onnx")]
    pub(super) fn extract(
        &mut self,
        input: crate::extract::image::GrayInput,
        tracked: bool,
    ) -> Result<Frame, SessionError> {
        let map_name = &self.fit.map_name;
        let Source::Images {
            extractor, global, ..
        } = &mut self.source
        else {
            return Err(SessionError::NoSource(format!(
                "{}: this session's features are not extracted from images",
                map_name
            )));
        };
        let size = global.for_frame(tracked, input.width, input.height);
        let defer = size != *global;
        let options = crate::extract::DetectOptions {
            global: size,
            ..Default::default()
        };
        let f = extractor.extract(&input, &options)?;
        self.global_deferred += usize::from(defer);
        Ok(Frame {
            deferred: defer.then(|| Box::new(input)),
            ..Frame::from_source(crate::io::queries::sfp_query(&f, extractor))
        })
    }

    /// The global descriptor of `input`, a frame that deferred it and lost tracking; `None`
    /// when the inference fails (the query then retrieves without it, which it reports).
    #[cfg(feature = "onnx")]
    pub(super) fn global_of(
        &mut self,
        input: &crate::extract::image::GrayInput,
    ) -> Option<Vec<f32>> {
        match &mut self.source {
            Source::Images {
                extractor, global, ..
            } => extractor.global_of(input, *global).ok(),
            _ => None,
        }
    }
}

/// Why an image of `width × height` cannot be the query of `camera`: its intrinsics are in
/// the pixels of an image of the camera's size, so keypoints of another size would give a
/// wrong pose, not a failed one. `None` when the sizes agree.
#[cfg(feature = "onnx")]
pub fn image_misfits_camera(width: usize, height: usize, camera: &Camera) -> Option<String> {
    let fits = u32::try_from(width).ok() == Some(camera.width())
        && u32::try_from(height).ok() == Some(camera.height());
    (!fits).then(|| {
        format!(
            "the image is {width}x{height} but the camera is {}x{}",
            camera.width(),
            camera.height()
        )
    })
}

/// The size the queries' global descriptors are extracted at: the map's (`global_max_side`),
/// or none where retrieval will not rank by them (the map stores none, or retrieval is VLAD
/// or off).
#[cfg(feature = "onnx")]
fn global_size(options: &LocalizeOptions, map: &Map<'_>) -> crate::extract::GlobalSize {
    let ranks_by_global = matches!(
        options.retrieval,
        RetrievalMethod::Auto | RetrievalMethod::Global
    ) && matches!(map.image_global(), Ok(Some(_)));
    if ranks_by_global {
        crate::extract::GlobalSize::of_map(map.metadata())
    } else {
        crate::extract::GlobalSize::Skip
    }
}

/// Refuses `map` (named `map_name` in the error) when the SFP extractor cannot make its
/// queries' features: a map without descriptors, or of SIFT or other COLMAP ones. What
/// [`QuerySource::Images`] checks first; a caller may ask before anything costly (building
/// a session loads the model and indexes the map).
pub fn check_extractable(map: &Map<'_>, map_name: &str) -> Result<(), SessionError> {
    Fit::of(map, map_name.to_string()).check_extractable()
}

impl Fit {
    fn check_extractable(&self) -> Result<(), SessionError> {
        // What the localizer matches as SFP descriptors is what the extractor makes: not SIFT,
        // nor a features file's or a database's learned features, nor none.
        if self.from_feature_source || !crate::localize::is_sfp_descriptor(&self.descriptor) {
            return Err(SessionError::NotExtractable {
                map: self.map_name.clone(),
                descriptor: self.descriptor.clone(),
            });
        }
        Ok(())
    }
}

/// The SFP extractor (`model`, else the built-in one the map was made with), checked against
/// the map's descriptors at `levels` (the levels localization uses; empty: all the map's).
#[cfg(feature = "onnx")]
fn extractor(
    fit: &Fit,
    model: Option<PathBuf>,
    levels: &[u16],
    inference: Inference,
    reporter: &dyn Reporter,
) -> Result<crate::extract::Extractor, SessionError> {
    let Inference { threads, spin } = inference;
    use crate::extract::{builtin_model_names, Extractor, ExtractorOptions};
    fit.check_extractable()?;
    let (map, descriptor) = (&fit.map_name, &fit.descriptor);
    let extractor = match model {
        Some(model) => Extractor::new_spinning(
            &ExtractorOptions {
                model: Some(model),
                threads,
            },
            spin,
            reporter,
        )?,
        // The built-in model the map was made with (never a file).
        None => match Extractor::builtin_spinning(descriptor, threads, spin, reporter) {
            Some(extractor) => extractor?,
            None => {
                return Err(SessionError::Mismatch(format!(
                    "{map}: the map's descriptors are {descriptor:?}, which no built-in model \
                     makes (built in: {}): pass its model file",
                    builtin_model_names()
                )))
            }
        },
    };
    // A built-in model (by default, or asked for by name) of the map's name but other weights
    // than the map's (a retrained model exported under the same name): the map's descriptors
    // would not match the queries'. An explicit file is the user's choice.
    let builtin = extractor.is_builtin();
    if let (true, Some(made)) = (builtin, &fit.model_xxh3) {
        if *made != extractor.model().xxh3 && extractor.contract().model_name == *descriptor {
            return Err(SessionError::Mismatch(format!(
                "{map}: the map was made with a {descriptor:?} model of hash {made:?}, not the \
                 built-in one ({}): pass that model's file",
                extractor.model().xxh3
            )));
        }
    }
    // Only an explicit model can be another one (without it, the map's own runs): that is
    // asked for on purpose (e.g. a faster student of the map's model), so it runs, said once,
    // when it makes the levels used at the map's dimensions; otherwise no query could match.
    // A file under the map's model name is held to the same (it may be another export).
    let contract = extractor.contract();
    let makes = |&(level, dim): &(u16, u32)| {
        contract
            .level_index(level)
            .is_some_and(|i| contract.full_dims[i] == dim as usize)
    };
    let used = |(level, _): &&(u16, u32)| levels.is_empty() || levels.contains(level);
    if let Some((level, dim)) = fit.levels.iter().filter(used).find(|l| !makes(l)) {
        return Err(SessionError::Mismatch(format!(
            "{map}: the map's descriptors are {descriptor:?} (level {level}: {dim} \
             dimensions), which model {:?} does not make: localize with the map's model",
            contract.model_name
        )));
    }
    if contract.model_name != *descriptor {
        reporter.warn(&format!(
            "{map}: the map's descriptors are {descriptor:?} but the model is {:?}: localizing \
             with another model's descriptors, as asked",
            extractor.contract().model_name
        ));
    }
    Ok(extractor)
}

/// Warns when the file's global descriptors were computed at another image size than the
/// map's (`sfp.global_max_side` against metadata `global_max_side`): retrieval by them then
/// compares unlike descriptors. An `sfpmap extract` file without the attribute (written before
/// it) computed them at the image's own size; an hloc file (no `sfp.model_name`) is taken as
/// it is, and so is any file for a map without global descriptors.
#[cfg(feature = "onnx")]
fn warn_global_size(
    h5: &crate::io::features_h5::H5Features,
    path: &std::path::Path,
    map: &Map<'_>,
    reporter: &dyn Reporter,
) {
    use crate::extract::GlobalSize;
    if !matches!(map.image_global(), Ok(Some(_))) {
        return;
    }
    let map_size = GlobalSize::of_map(map.metadata());
    // Only a warning hangs on it: an attribute that is not one string is named, not fatal.
    let stated = match h5.root_string("sfp.global_max_side") {
        Ok(Some(side)) => side,
        Ok(None) if matches!(h5.root_string("sfp.model_name"), Ok(Some(_))) => "0".to_string(),
        Ok(None) => return,
        Err(_) => "(not one string)".to_string(),
    };
    let file_size = stated
        .trim()
        .parse::<u32>()
        .ok()
        .map(|side| GlobalSize::from_max_side(Some(side)));
    if file_size != Some(map_size) {
        let mut shown: String = stated.chars().take(24).collect();
        if shown.len() < stated.len() {
            shown.push('…');
        }
        let map_side = map_size.side();
        reporter.warn(&format!(
            "{}: global descriptors computed at max side {shown:?}, the map's at \"{map_side}\" \
             (0: the image's own size): retrieval by them will be poorer; extract with \
             --global-max-side {map_side}",
            crate::escape::path(path)
        ));
    }
}
