//! The values of numeric flags, checked once as clap parses them: every number finite and in
//! the range its `--help` states, so `--radius NaN` or `--threshold=-1,-5` is refused with
//! the flag named (exit status 2) instead of running and finding nothing. Whole numbers use
//! clap's own ranged parsers (`clap::value_parser!(u32).range(..)`); the ones here take
//! decimals, which Rust's `parse` reads as NaN or infinity too, and hold them to the library's
//! rule for that kind of value (`sfpmap::ranges`), so the CLI, Python and C refuse alike. The
//! localizer's options (`--ratio`, `--top-k`) are checked by `LocalizeOptions::validate`, in
//! the words Python and C get too, before `localize` opens any map or catalog place, and
//! refused the same way (exit status 2, the flag named); their help states the same ranges.
// The commands that take these flags are features' (localize, colmap, onnx): a build without
// them leaves some parsers unused.
#![cfg_attr(
    not(all(feature = "localize", feature = "colmap", feature = "onnx")),
    allow(dead_code)
)]

use sfpmap::ranges::{self, Range};

/// `text` as a number in `range`, else what the range expects.
fn number(text: &str, range: Range) -> Result<f64, String> {
    let expected = || format!("expected {}", range.expected);
    let v = text.trim().parse::<f64>().map_err(|_| expected())?;
    range.check(v).map_err(|_| expected())
}

/// A distance in map units (`localize --radius`): [`ranges::DISTANCE`].
pub fn distance(text: &str) -> Result<f64, String> {
    number(text, ranges::DISTANCE)
}

/// A keypoint score threshold (`extract --threshold`, `convert --score-threshold`):
/// [`ranges::SCORE`].
pub fn score(text: &str) -> Result<f32, String> {
    #[allow(clippy::cast_possible_truncation)] // in [0, 1]
    number(text, ranges::SCORE).map(|v| v as f32)
}

/// A world point `x,y,z` (`localize --prior`): three [`ranges::COORDINATE`]s.
pub fn point(text: &str) -> Result<[f64; 3], String> {
    // Three of `ranges::COORDINATE`.
    let expected = || "expected x,y,z: three finite coordinates".to_owned();
    let coordinate = |c: &str| number(c, ranges::COORDINATE).map_err(|_| expected());
    match text.split(',').collect::<Vec<_>>()[..] {
        [x, y, z] => Ok([coordinate(x)?, coordinate(y)?, coordinate(z)?]),
        _ => Err(expected()),
    }
}

/// A recall threshold `METERS,DEGREES` (`eval --threshold`): [`ranges::RECALL_DISTANCE`]
/// and [`ranges::RECALL_DEGREES`].
pub fn recall_threshold(text: &str) -> Result<(f64, f64), String> {
    let expected = || {
        format!(
            "expected METERS,DEGREES: {} and {}",
            ranges::RECALL_DISTANCE.expected,
            ranges::RECALL_DEGREES.expected
        )
    };
    let (t, r) = text.split_once(',').ok_or_else(expected)?;
    let t = number(t, ranges::RECALL_DISTANCE).map_err(|_| expected())?;
    let r = number(r, ranges::RECALL_DEGREES).map_err(|_| expected())?;
    Ok((t, r))
}

/// A byte count as people write it: `2MB` (decimal), `1.5MiB` (binary), `500000`
/// (`slice --budget`, `ros2 --max-message-bytes`).
pub fn byte_size(s: &str) -> Result<u64, String> {
    s.trim()
        .parse::<bytesize::ByteSize>()
        .map(|b| b.as_u64())
        .map_err(|e| format!("{s:?} is not a size such as 2MB, 500kB or 1.5MiB ({e})"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_finite_and_out_of_range_values_are_refused() {
        for bad in ["NaN", "nan", "inf", "-inf", "1e400", "-1", "x", ""] {
            assert!(distance(bad).is_err(), "{bad}");
            assert!(score(bad).is_err(), "{bad}");
        }
        assert_eq!(score("1.5").unwrap_err(), "expected a score in [0, 1]");
        for bad in [
            "nan,nan", "-1,-5", "0,5", "1,0", "1,181", "inf,2", "1", "1,2,3",
        ] {
            assert!(recall_threshold(bad).is_err(), "{bad}");
        }
        for bad in ["1,2", "1,2,NaN", "1,inf,2", "1,2,3,4"] {
            assert!(point(bad).is_err(), "{bad}");
        }
        assert_eq!(distance("0").unwrap(), 0.0);
        assert_eq!(recall_threshold("0.25, 2").unwrap(), (0.25, 2.0));
        assert_eq!(point("1, -2,3.5").unwrap(), [1.0, -2.0, 3.5]);
    }
}
