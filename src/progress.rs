//! Progress reporting. The library never prints: long operations take a `&dyn Reporter`
//! and the CLI implements it with indicatif bars (hidden under `--quiet` / `--json`).

/// Receives progress and warnings from long-running library operations.
///
/// Every method has an empty default, so an implementation only overrides what it shows.
/// Implementations must be cheap: `advance` may be called once per item.
pub trait Reporter: Send + Sync {
    /// A new stage begins (`"reading points3D"`, `"writing"`), with its item count if known.
    fn start(&self, _stage: &str, _total: Option<u64>) {}
    /// `n` more items of the current stage are done.
    fn advance(&self, _n: u64) {}
    /// The current stage is complete.
    fn finish(&self) {}
    /// Something worth telling the user that does not stop the operation.
    fn warn(&self, _message: &str) {}
}

/// A reporter that discards everything.
#[derive(Debug, Default, Clone, Copy)]
pub struct Silent;

impl Reporter for Silent {}
