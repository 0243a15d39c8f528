//! [`Error`]: every error of the crate in one type, for callers that handle them alike (`?`
//! into `sfpmap::Result`) and match on the few kinds they treat apart. Each module keeps its
//! own error (what its functions return, with the details a caller may inspect); this gathers
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
}
