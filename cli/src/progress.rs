//! The CLI's `Reporter`: indicatif bars on stderr, hidden under `--quiet`/`--json` or when
//! stderr is not a terminal.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use sfpmap::progress::Reporter;
use std::sync::Mutex;

pub struct Bars {
    visible: bool,
    quiet: bool,
    bar: Mutex<Option<ProgressBar>>,
}

impl Bars {
    /// `quiet` hides bars and warnings; `hide_bars` (for `--json`) hides only the bars.
    pub fn new(quiet: bool, hide_bars: bool) -> Bars {
        Bars {
            visible: !quiet && !hide_bars,
            quiet,
            bar: Mutex::new(None),
        }
    }
}

impl Reporter for Bars {
    fn start(&self, stage: &str, total: Option<u64>) {
        let mut slot = self.bar.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(old) = slot.take() {
            old.finish_and_clear();
        }
        if !self.visible {
            return;
        }
        let bar = match total {
            Some(n) => ProgressBar::with_draw_target(Some(n), ProgressDrawTarget::stderr()),
            None => ProgressBar::new_spinner(),
        };
        let template = if total.is_some() {
            "{msg:>20} [{bar:30}] {pos}/{len} ({elapsed})"
        } else {
            "{msg:>20} {spinner} {pos} ({elapsed})"
        };
        if let Ok(style) = ProgressStyle::with_template(template) {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_message(stage.to_string());
        *slot = Some(bar);
    }

    fn advance(&self, n: u64) {
        if let Some(bar) = self.bar.lock().unwrap_or_else(|p| p.into_inner()).as_ref() {
            bar.inc(n);
        }
    }

    fn finish(&self) {
        if let Some(bar) = self.bar.lock().unwrap_or_else(|p| p.into_inner()).take() {
            bar.finish_and_clear();
        }
    }

    fn warn(&self, message: &str) {
        if !self.quiet {
            // One line, whatever the library quotes (paths and names are escaped there too).
            let message = sfpmap::escape::escape_control_characters(message);
            let bar = self.bar.lock().unwrap_or_else(|p| p.into_inner());
            match bar.as_ref() {
                Some(b) => b.suspend(|| eprintln!("warning: {message}")),
                None => eprintln!("warning: {message}"),
            }
        }
    }
}
