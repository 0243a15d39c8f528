//! [`Error`]: every error of the crate in one type, for callers that handle them alike (`?`
//! into `sfpmap::Result`) and match on the few kinds they treat apart. Each module keeps its
//! own error (what its functions return, with the details a caller may inspect); this gathers
//! them.
//!
//! [`ErrorKind`] is the one classification of them: what a caller does about an error (a file
//! to fix, a damaged map, a level that is not there, an option out of range, a query that
//! does not fit the map). The C ABI's status codes and the Python package's exception classes
//! are each one `match` on it, so a new error variant is classified here, once, for all of
//! them.

/// Any error of the crate. Its text is the module error's own (each names the file, map or
/// query it is about), so its [`source`](std::error::Error::source) is that error's source.
#[derive(Debug)]
#[non_exhaustive]
pub enum Error {
    /// A map file: its header, index, sections or checksums ([`crate::format::Error`]).
    Format(crate::format::Error),
    /// A file that cannot be opened as an input ([`crate::input::OpenError`]).
    Open(crate::input::OpenError),
    /// An input file's contents: a query list, a features file, a poses file.
    Input(crate::io::InputError),
    /// An output that may not or could not be written ([`crate::output::OutputError`]).
    Output(crate::output::OutputError),
    /// A COLMAP model or database ([`crate::colmap::Error`]).
    #[cfg(feature = "colmap-model")]
    Colmap(crate::colmap::Error),
    /// Building a map ([`crate::build::ConvertError`]).
    #[cfg(feature = "colmap")]
    Convert(crate::build::ConvertError),
    /// A kapture folder read or written ([`crate::io::kapture::KaptureError`]).
    #[cfg(feature = "colmap")]
    Kapture(crate::io::kapture::KaptureError),
    /// Cameras and pose estimation ([`crate::geometry::GeometryError`]).
    #[cfg(feature = "geometry")]
    Geometry(crate::geometry::GeometryError),
    /// The SFP extractor: its model, the runtime, an image ([`crate::extract::ExtractError`]).
    #[cfg(feature = "onnx")]
    Extract(crate::extract::ExtractError),
    /// The localizer: options, levels, query features ([`crate::localize::LocalizeError`]).
    #[cfg(feature = "localize")]
    Localize(crate::localize::LocalizeError),
    /// A session: its source, the map/model fit ([`crate::session::SessionError`]).
    #[cfg(feature = "localize")]
    Session(crate::session::SessionError),
    /// Writing a features file ([`crate::io::features_h5::H5Error`]).
    #[cfg(feature = "onnx")]
    FeaturesH5(crate::io::features_h5::H5Error),
    /// An MCAP log ([`crate::io::mcap_io::McapIoError`]).
    #[cfg(feature = "mcap")]
    Mcap(crate::io::mcap_io::McapIoError),
    /// Localizing the images of an MCAP log ([`crate::session::mcap_log::LogError`]).
    #[cfg(feature = "mcap")]
    McapLog(crate::session::mcap_log::LogError),
    /// Rendering a plot ([`crate::io::plot::PlotError`]).
    #[cfg(feature = "plot")]
    Plot(crate::io::plot::PlotError),
}

/// `Result` with [`Error`].
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Calls `$m!` with every variant and its type, so the impls below list them once.
macro_rules! each_variant {
    ($m:ident) => {
        $m!(Format, crate::format::Error);
        $m!(Open, crate::input::OpenError);
        $m!(Input, crate::io::InputError);
        $m!(Output, crate::output::OutputError);
        #[cfg(feature = "colmap-model")]
        $m!(Colmap, crate::colmap::Error);
        #[cfg(feature = "colmap")]
        $m!(Convert, crate::build::ConvertError);
        #[cfg(feature = "colmap")]
        $m!(Kapture, crate::io::kapture::KaptureError);
        #[cfg(feature = "geometry")]
        $m!(Geometry, crate::geometry::GeometryError);
        #[cfg(feature = "onnx")]
        $m!(Extract, crate::extract::ExtractError);
        #[cfg(feature = "localize")]
        $m!(Localize, crate::localize::LocalizeError);
        #[cfg(feature = "localize")]
        $m!(Session, crate::session::SessionError);
        #[cfg(feature = "onnx")]
        $m!(FeaturesH5, crate::io::features_h5::H5Error);
        #[cfg(feature = "mcap")]
        $m!(Mcap, crate::io::mcap_io::McapIoError);
        #[cfg(feature = "mcap")]
        $m!(McapLog, crate::session::mcap_log::LogError);
        #[cfg(feature = "plot")]
        $m!(Plot, crate::io::plot::PlotError);
    };
}

macro_rules! from_variant {
    ($variant:ident, $ty:ty) => {
        impl From<$ty> for Error {
            fn from(e: $ty) -> Self {
                Error::$variant(e)
            }
        }
    };
}
each_variant!(from_variant);

/// An option out of range ([`crate::localize::LocalizeOptions::validate`]) is the localizer's
/// error, as [`crate::localize::Localizer::new`] returns it.
#[cfg(feature = "localize")]
impl From<crate::localize::OptionError> for Error {
    fn from(e: crate::localize::OptionError) -> Self {
        Error::Localize(crate::localize::LocalizeError::Option(e))
    }
}

impl Error {
    /// The module error inside, as a trait object (what `Display` and `source` defer to).
    fn inner(&self) -> &(dyn std::error::Error + 'static) {
        match self {
            Error::Format(e) => e,
            Error::Open(e) => e,
            Error::Input(e) => e,
            Error::Output(e) => e,
            #[cfg(feature = "colmap-model")]
            Error::Colmap(e) => e,
            #[cfg(feature = "colmap")]
            Error::Convert(e) => e,
            #[cfg(feature = "colmap")]
            Error::Kapture(e) => e,
            #[cfg(feature = "geometry")]
            Error::Geometry(e) => e,
            #[cfg(feature = "onnx")]
            Error::Extract(e) => e,
            #[cfg(feature = "localize")]
            Error::Localize(e) => e,
            #[cfg(feature = "localize")]
            Error::Session(e) => e,
            #[cfg(feature = "onnx")]
            Error::FeaturesH5(e) => e,
            #[cfg(feature = "mcap")]
            Error::Mcap(e) => e,
            #[cfg(feature = "mcap")]
            Error::McapLog(e) => e,
            #[cfg(feature = "plot")]
            Error::Plot(e) => e,
        }
    }
}

/// What kind of error an [`Error`] is: what a caller does about it, without matching on the
/// module errors. [`Error::kind`] (and [`SessionError::kind`](crate::session::SessionError::kind)
/// for a session's errors) gives it. The C ABI's status codes (`SFPM_ERR_*`) and the Python
/// package's exception classes are each made from it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum ErrorKind {
    /// A file that cannot be read or written: missing, unreadable, not a regular file (a
    /// folder, a FIFO), an output that exists or may not be replaced, a failed write.
    Io,
    /// A map file that is not a valid map (another format, another major version, a damaged
    /// index), or a section that fails its checks when it is read (a checksum, a length, a
    /// contradiction); also a map operation refused for what it was given (a slice of no
    /// levels, a writer's inconsistent input: `format::Error::InvalidInput`).
    Format,
    /// The map has no level by the id asked for.
    NoSuchLevel,
    /// The map lacks a section a call needs (a level's `rest` block, the images, the
    /// visibility).
    Missing,
    /// The map holds no descriptors (a geometry-only map): nothing to localize against.
    NoDescriptors,
    /// An option or argument out of its range (`ratio 1.5: a ratio in (0, 1]`), a camera that
    /// cannot be one, a name that cannot be written.
    InvalidArgument,
    /// An input's contents: a query list, a features file, a query database, an MCAP log's
    /// records or messages, a query asked for by name of a source that reads none.
    Input,
    /// A query source that does not fit the map: features of another model than the map's, a
    /// map whose descriptors the extractor does not make.
    Mismatch,
    /// Query features that cannot be matched against the map (descriptors of another size,
    /// no features for a level, no usable level), or a pose that cannot be estimated. A query
    /// that merely is not localized is no error.
    Localize,
    /// The SFP extractor: ONNX Runtime, the model, an image that does not decode, an inference.
    Extract,
    /// A COLMAP model or database that cannot be made into a map (its contents; its files
    /// are [`ErrorKind::Io`]).
    Convert,
    /// What no other kind names: a plot that cannot be drawn.
    Other,
}

impl Error {
    /// The kind of this error (see [`ErrorKind`]).
    ///
    /// ```
    /// let e = sfpmap::format::Map::open("/nonexistent/m.sfpm").map_err(sfpmap::Error::from);
    /// assert_eq!(e.unwrap_err().kind(), sfpmap::ErrorKind::Io);
    /// ```
    pub fn kind(&self) -> ErrorKind {
        match self {
            Error::Format(e) => format_kind(e),
            Error::Open(_) | Error::Output(_) => ErrorKind::Io,
            Error::Input(_) => ErrorKind::Input,
            #[cfg(feature = "colmap-model")]
            Error::Colmap(e) => colmap_kind(e),
            #[cfg(feature = "colmap")]
            Error::Convert(e) => convert_kind(e),
            #[cfg(feature = "colmap")]
            Error::Kapture(e) => kapture_kind(e),
            #[cfg(feature = "geometry")]
            Error::Geometry(e) => geometry_kind(e),
            #[cfg(feature = "onnx")]
            Error::Extract(e) => extract_kind(e),
            #[cfg(feature = "localize")]
            Error::Localize(e) => localize_kind(e),
            #[cfg(feature = "localize")]
            Error::Session(e) => e.kind(),
            #[cfg(feature = "onnx")]
            Error::FeaturesH5(e) => h5_kind(e),
            #[cfg(feature = "mcap")]
            Error::Mcap(e) => mcap_kind(e),
            #[cfg(feature = "mcap")]
            Error::McapLog(e) => log_kind(e),
            #[cfg(feature = "plot")]
            Error::Plot(e) => plot_kind(e),
        }
    }
}

/// Kept beside [`Error::kind`], the one home of the classification, rather than in the
/// session module.
#[cfg(feature = "localize")]
impl crate::session::SessionError {
    /// The kind of this error (see [`ErrorKind`]), as [`Error::kind`] gives it for
    /// `Error::Session`: an option out of range is [`ErrorKind::InvalidArgument`], the map's
    /// own errors keep their kinds, features of another model are [`ErrorKind::Mismatch`].
    pub fn kind(&self) -> ErrorKind {
        use crate::session::SessionError as S;
        match self {
            S::Localize { source, .. } | S::Query { source, .. } => localize_kind(source),
            S::Mismatch(_) => ErrorKind::Mismatch,
            S::NotExtractable { descriptor, .. } if descriptor.is_empty() => {
                ErrorKind::NoDescriptors
            }
            S::NotExtractable { .. } => ErrorKind::Mismatch,
            S::NoSource(_) | S::Input(_) => ErrorKind::Input,
            S::Map { source, .. } => format_kind(source),
            S::Place { source, .. } => source.kind(),
            // A query database is an input whatever failed in it, its file included.
            #[cfg(feature = "colmap")]
            S::Database { .. } => ErrorKind::Input,
            #[cfg(feature = "onnx")]
            S::Extract(e) => extract_kind(e),
        }
    }
}

fn format_kind(e: &crate::format::Error) -> ErrorKind {
    use crate::format::Error as E;
    match e {
        E::Io { .. } | E::NotARegularFile { .. } => ErrorKind::Io,
        E::NoSuchLevel { .. } => ErrorKind::NoSuchLevel,
        E::MissingSection { .. } => ErrorKind::Missing,
        // The file or a section fails its checks; `InvalidInput` (a writer's or a slice's
        // input) is reported with them, as the bindings always have.
        _ => ErrorKind::Format,
    }
}

#[cfg(feature = "localize")]
fn localize_kind(e: &crate::localize::LocalizeError) -> ErrorKind {
    use crate::localize::LocalizeError as E;
    match e {
        E::Format(e) => format_kind(e),
        E::Option(_) => ErrorKind::InvalidArgument,
        E::NonFinite(_) => ErrorKind::Input,
        E::NoDescriptors => ErrorKind::NoDescriptors,
        E::DescriptorMismatch { .. }
        | E::NoFeaturesForLevel { .. }
        | E::FeatureShape { .. }
        | E::BadLevel { .. }
        | E::NoUsableLevel { .. }
        | E::GlobalDescriptor(_) => ErrorKind::Localize,
    }
}

#[cfg(feature = "onnx")]
fn extract_kind(e: &crate::extract::ExtractError) -> ErrorKind {
    use crate::extract::ExtractError as E;
    match e {
        E::Io { .. } => ErrorKind::Io,
        E::RuntimeNotFound { .. }
        | E::Runtime { .. }
        | E::Model { .. }
        | E::Contract { .. }
        | E::Image { .. }
        | E::Inference { .. } => ErrorKind::Extract,
    }
}

#[cfg(feature = "colmap-model")]
fn colmap_kind(e: &crate::colmap::Error) -> ErrorKind {
    use crate::colmap::Error as E;
    match e {
        E::Io { .. } | E::NotAFile { .. } | E::Output(_) => ErrorKind::Io,
        // A model's or a database's contents (a model file missing beside the others
        // included: the model is incomplete).
        _ => ErrorKind::Convert,
    }
}

#[cfg(feature = "colmap")]
fn convert_kind(e: &crate::build::ConvertError) -> ErrorKind {
    use crate::build::ConvertError as E;
    match e {
        E::Colmap(e) => colmap_kind(e),
        E::Format(e) => format_kind(e),
        E::Io { .. } | E::Output(_) => ErrorKind::Io,
        #[cfg(feature = "onnx")]
        E::Extract(e) => extract_kind(e),
        E::NameMismatch { .. }
        | E::KeypointOutOfRange { .. }
        | E::KeypointScaleNotFinite { .. }
        | E::MissingFeatures { .. }
        | E::DescriptorDim { .. }
        | E::MissingImages { .. }
        // A features file's contents, like a database's.
        | E::Input(_)
        | E::KeypointOutsideImage { .. } => ErrorKind::Convert,
        // The budget asked for, not the input, is what must change.
        E::Options(_) | E::MemoryBudget { .. } => ErrorKind::InvalidArgument,
        E::Kapture(e) => kapture_kind(e),
    }
}

#[cfg(feature = "colmap")]
fn kapture_kind(e: &crate::io::kapture::KaptureError) -> ErrorKind {
    use crate::io::kapture::KaptureError as E;
    match e {
        E::Missing { .. } | E::Read { .. } | E::Output(_) => ErrorKind::Io,
        E::Map(e) => format_kind(e),
        E::Model(e) => colmap_kind(e),
        E::Unwritable { .. } => ErrorKind::InvalidArgument,
        // A folder's contents, as a model's or a database's are.
        _ => ErrorKind::Convert,
    }
}

#[cfg(feature = "geometry")]
fn geometry_kind(e: &crate::geometry::GeometryError) -> ErrorKind {
    use crate::geometry::GeometryError as E;
    match e {
        E::UnknownCameraModel { .. }
        | E::UnsupportedCameraModel { .. }
        | E::WrongParamCount { .. }
        | E::ParseCamera { .. }
        | E::InvalidCamera { .. }
        | E::LengthMismatch { .. }
        | E::NonFinite { .. }
        | E::InvalidOptions { .. } => ErrorKind::InvalidArgument,
        E::TooFewCorrespondences { .. }
        | E::Degenerate { .. }
        | E::NoModel { .. }
        | E::TooFewInliers { .. }
        | E::RefinementFailed { .. } => ErrorKind::Localize,
    }
}

#[cfg(feature = "onnx")]
fn h5_kind(e: &crate::io::features_h5::H5Error) -> ErrorKind {
    use crate::io::features_h5::H5Error as E;
    match e {
        E::Hdf5 { .. } | E::Io { .. } | E::Output(_) => ErrorKind::Io,
        E::BadName { .. } => ErrorKind::InvalidArgument,
    }
}

#[cfg(feature = "mcap")]
fn mcap_kind(e: &crate::io::mcap_io::McapIoError) -> ErrorKind {
    use crate::io::mcap_io::McapIoError as E;
    match e {
        E::Io(_) | E::NotRegularFile(_) | E::Mcap(_) => ErrorKind::Io,
        // The log's records, messages and images.
        _ => ErrorKind::Input,
    }
}

#[cfg(feature = "mcap")]
fn log_kind(e: &crate::session::mcap_log::LogError) -> ErrorKind {
    use crate::session::mcap_log::LogError as E;
    match e {
        E::Open { source, .. } => mcap_kind(source),
        E::Session(e) => e.kind(),
        E::Write { .. } | E::Output(_) => ErrorKind::Io,
        E::NoTopic { .. }
        | E::NoCameraInfo { .. }
        | E::CameraInfo { .. }
        | E::Unreadable { .. }
        | E::NoMessages { .. }
        | E::Undecodable { .. } => ErrorKind::Input,
    }
}

#[cfg(feature = "plot")]
fn plot_kind(e: &crate::io::plot::PlotError) -> ErrorKind {
    use crate::io::plot::PlotError as E;
    match e {
        E::Format(e) => format_kind(e),
        E::Output(_) => ErrorKind::Io,
        E::Empty | E::Unplottable(_) => ErrorKind::Input,
        E::Draw(_) => ErrorKind::Other,
    }
}

impl std::fmt::Display for Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        std::fmt::Display::fmt(self.inner(), f)
    }
}

impl std::error::Error for Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        self.inner().source()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_text_is_the_module_errors_and_question_mark_converts() {
        fn open() -> Result<crate::format::Map<'static>> {
            Ok(crate::format::Map::open("/nonexistent/m.sfpm")?)
        }
        let e = open().unwrap_err();
        assert!(matches!(e, Error::Format(_)), "{e:?}");
        assert!(e.to_string().contains("/nonexistent/m.sfpm"), "{e}");
    }

    /// A conformance vector's file (`valid` or `invalid`).
    fn vector(set: &str, name: &str) -> String {
        format!(
            "{}/spec/vectors/{set}/{name}.sfpm",
            env!("CARGO_MANIFEST_DIR")
        )
    }

    fn open(path: &str) -> Result<crate::format::Map<'static>> {
        Ok(crate::format::Map::open(path)?)
    }

    /// The kind of `result`'s error; a success is a test failure.
    fn kind_of<T>(result: std::result::Result<T, impl Into<Error>>) -> ErrorKind {
        match result {
            Ok(_) => panic!("expected an error"),
            Err(e) => e.into().kind(),
        }
    }

    /// Opening and reading maps: a file that is not there or not a file is `Io` (C's
    /// `SFPM_ERR_IO`, Python's `FileError`), a damaged or foreign file `Format`, a section the
    /// map's own sections call for `Missing`, a level the map lacks `NoSuchLevel`.
    #[test]
    fn the_kinds_of_map_errors() {
        assert_eq!(kind_of(open("/nonexistent/m.sfpm")), ErrorKind::Io);
        let folder = tempfile::tempdir().unwrap();
        assert_eq!(
            kind_of(open(folder.path().to_str().unwrap())),
            ErrorKind::Io
        );
        for damaged in [
            "bad_magic",
            "unknown_major",
            "truncated",
            "overlapping_sections",
        ] {
            assert_eq!(
                kind_of(open(&vector("invalid", damaged))),
                ErrorKind::Format,
                "{damaged}"
            );
        }
        assert_eq!(
            kind_of(open(&vector("invalid", "vlad_without_image_vlad"))),
            ErrorKind::Missing
        );
        let map = open(&vector("valid", "levels")).unwrap();
        assert_eq!(kind_of(map.level(7)), ErrorKind::NoSuchLevel);
        // An output that exists, not to be replaced.
        let existing = tempfile::NamedTempFile::new().unwrap();
        assert_eq!(
            kind_of(crate::output::check_output(existing.path(), &[], false)),
            ErrorKind::Io
        );
    }

    /// The localizer and sessions: options out of range are `InvalidArgument` however they
    /// are met, a geometry-only map `NoDescriptors`, a level the map lacks keeps its kind
    /// through the session's error, features of another size are `Localize`; an input file's
    /// contents are `Input`. [`SessionError::kind`] agrees with [`Error::kind`].
    #[cfg(feature = "localize")]
    #[test]
    fn the_kinds_of_localizer_and_session_errors() {
        use crate::localize::{FeatureSet, LocalizeOptions, Localizer, QueryFeatures};
        use crate::session::{Session, SessionError};
        use std::sync::Arc;

        let mut options = LocalizeOptions::default();
        options.matching.ratio = 1.5;
        assert_eq!(kind_of(options.validate()), ErrorKind::InvalidArgument);

        let geometry = open(&vector("valid", "geometry_only")).unwrap();
        let options = LocalizeOptions::for_map(&geometry);
        assert_eq!(
            kind_of(Localizer::new(&geometry, options)),
            ErrorKind::NoDescriptors
        );

        let map = Arc::new(open(&vector("valid", "levels")).unwrap());
        let session = |options: LocalizeOptions| {
            Session::builder(map.clone(), "levels.sfpm")
                .options(options)
                .build(&crate::progress::Silent)
        };
        let refused = |options| -> SessionError {
            match session(options) {
                Ok(_) => panic!("expected an error"),
                Err(e) => e,
            }
        };
        let defaults = LocalizeOptions::for_map(&map);
        let mut bad_ratio = defaults.clone();
        bad_ratio.matching.ratio = 1.5;
        let e = refused(bad_ratio);
        assert_eq!(e.kind(), ErrorKind::InvalidArgument, "{e}");
        assert_eq!(Error::from(e).kind(), ErrorKind::InvalidArgument);
        let no_level = LocalizeOptions {
            levels: vec![7],
            ..defaults.clone()
        };
        let e = refused(no_level);
        assert_eq!(e.kind(), ErrorKind::NoSuchLevel, "{e}");
        assert_eq!(Error::from(e).kind(), ErrorKind::NoSuchLevel);

        let session = session(defaults).unwrap();
        let camera = crate::geometry::Camera::from_model_name(
            "PINHOLE",
            640,
            480,
            &[500.0, 500.0, 320.0, 240.0],
        )
        .unwrap();
        let dim = 5;
        let features = QueryFeatures {
            sets: vec![FeatureSet {
                level: None,
                keypoints: vec![[10.0, 20.0]; 4],
                descriptors: vec![0.5; 4 * dim],
                dim,
            }],
            global: None,
            model: None,
        };
        let e = match session.localize_features(&features, &camera, "q") {
            Ok(_) => panic!("5 dimensions against levels of 16 and 8"),
            Err(e) => e,
        };
        assert_eq!(e.kind(), ErrorKind::Localize, "{e}");

        let poses = tempfile::NamedTempFile::new().unwrap();
        std::fs::write(poses.path(), "q 1 0 0\n").unwrap();
        assert_eq!(
            kind_of(crate::io::poses::read_poses(poses.path())),
            ErrorKind::Input
        );
    }
}
