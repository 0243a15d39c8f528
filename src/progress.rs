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

/// The most worker threads any thread-count setting gets: 4 per core this machine has, at most
/// 256. More only costs memory and start-up time (10^6 threads took 48 s for 3 queries).
pub fn max_threads() -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    cores.saturating_mul(4).min(256)
}

/// `requested` threads capped at [`max_threads`], with a warning through `reporter` when it is
/// cut; `option` names the setting in it (the CLI's `--threads`, Python's `threads`). Zero
/// counts as one: callers refuse it first (the CLI's parser does).
pub fn cap_threads(option: &str, requested: usize, reporter: &dyn Reporter) -> usize {
    let max = max_threads();
    if requested > max {
        reporter.warn(&format!(
            "{option} {requested}: using {max} (4 per core, at most 256)"
        ));
        return max;
    }
    requested.max(1)
}
