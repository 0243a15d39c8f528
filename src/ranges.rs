//! The ranges that decimal options take, one rule each, with the words that state it.
//!
//! Every check of a decimal option goes through a [`Range`] here: the localizer's options
//! ([`LocalizeOptions::validate`](crate::localize::LocalizeOptions::validate)), a catalog
//! query's prior ([`Near`](crate::session::Near)), a map's score threshold, and the CLI's flag
//! parsers, which read the text and then ask the same [`Range`]. So `--radius NaN`, Python's
//! `radius=float("nan")` and C's `radius = NAN` are refused by one rule, in the same words, and
//! a range changed here changes everywhere (the `--help` texts quote [`Range::expected`]).
//! Rust's `parse::<f64>` reads `NaN` and `inf`: every range here is finite.

/// A closed or half-open interval of finite numbers, and how errors state it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Range {
    min: f64,
    /// Whether `min` itself is outside (`(0, 1]`).
    min_open: bool,
    max: f64,
    /// What a value must be, for errors: `a ratio in (0, 1]`.
    pub expected: &'static str,
}

impl Range {
    /// Whether `v` is finite and in the range.
    pub fn contains(&self, v: f64) -> bool {
        let above = if self.min_open {
            v > self.min
        } else {
            v >= self.min
        };
        v.is_finite() && above && v <= self.max
    }

    /// `v`, or the range's [`Range::expected`] words when it is outside.
    pub fn check(&self, v: f64) -> Result<f64, &'static str> {
        if self.contains(v) {
            Ok(v)
        } else {
            Err(self.expected)
        }
    }
}

/// A ratio test's or gate's ratio: `(0, 1]`.
pub const RATIO: Range = Range {
    min: 0.0,
    min_open: true,
    max: 1.0,
    expected: "a ratio in (0, 1]",
};

/// A cosine similarity: `[-1, 1]`.
pub const COSINE: Range = Range {
    min: -1.0,
    min_open: false,
    max: 1.0,
    expected: "a cosine similarity in [-1, 1]",
};

/// An error or gate in pixels: finite, over 0.
pub const PIXELS: Range = Range {
    min: 0.0,
    min_open: true,
    max: f64::MAX,
    expected: "a finite number of pixels > 0",
};

/// A distance in map units (a catalog query's `radius`): finite, 0 or more.
pub const DISTANCE: Range = Range {
    min: 0.0,
    min_open: false,
    max: f64::MAX,
    expected: "a finite distance of 0 or more",
};

/// A world coordinate (a catalog query's prior position): any finite number.
pub const COORDINATE: Range = Range {
    min: f64::MIN,
    min_open: false,
    max: f64::MAX,
    expected: "a finite coordinate",
};

/// A keypoint score threshold: scores are probabilities, `[0, 1]`.
pub const SCORE: Range = Range {
    min: 0.0,
    min_open: false,
    max: 1.0,
    expected: "a score in [0, 1]",
};

/// A recall threshold's distance (`eval --threshold METERS,DEGREES`): finite, over 0.
pub const RECALL_DISTANCE: Range = Range {
    min: 0.0,
    min_open: true,
    max: f64::MAX,
    expected: "a finite distance over 0",
};

/// A recall threshold's angle, in degrees: `(0, 180]`.
pub const RECALL_DEGREES: Range = Range {
    min: 0.0,
    min_open: true,
    max: 180.0,
    expected: "an angle in (0, 180] degrees",
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ends_are_open_or_closed_as_stated_and_non_finite_values_are_outside() {
        assert!(!RATIO.contains(0.0) && RATIO.contains(1.0) && RATIO.contains(1e-9));
        assert!(SCORE.contains(0.0) && SCORE.contains(1.0) && !SCORE.contains(1.0 + 1e-9));
        assert!(DISTANCE.contains(0.0) && !DISTANCE.contains(-1e-300));
        assert!(COSINE.contains(-1.0) && !COSINE.contains(-1.5));
        assert!(RECALL_DEGREES.contains(180.0) && !RECALL_DEGREES.contains(0.0));
        for range in [
            RATIO,
            COSINE,
            PIXELS,
            DISTANCE,
            COORDINATE,
            SCORE,
            RECALL_DISTANCE,
            RECALL_DEGREES,
        ] {
            for v in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                assert_eq!(range.check(v), Err(range.expected), "{v}");
            }
        }
    }
}
