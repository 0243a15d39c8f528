//! The values of numeric flags, checked once as clap parses them: every number finite and in
//! the range its `--help` states, so `--radius NaN` or `--threshold=-1,-5` is refused with
//! the flag named (exit status 2) instead of running and finding nothing. Whole numbers use
//! clap's own ranged parsers (`clap::value_parser!(u32).range(..)`); the ones here take
//! decimals, which Rust's `parse` reads as NaN or infinity too. The localizer's options
//! (`--ratio`, `--top-k`) are checked by the library's rules (`LocalizeOptions::validate`), in
//! the words Python and C get too, before `localize` opens any map or catalog place, and
//! refused the same way (exit status 2, the flag named); their help states the same ranges.
// The commands that take these flags are features' (localize, colmap, onnx): a build without
// them leaves some parsers unused.
#![cfg_attr(
    not(all(feature = "localize", feature = "colmap", feature = "onnx")),
    allow(dead_code)
)]

/// `text` as a finite number in `[min, max]` (`max` may be infinite), else what is
/// expected.
fn number(text: &str, min: f64, max: f64, expected: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v >= min && v <= max => Ok(v),
        _ => Err(format!("expected {expected}")),
    }
}

/// A distance in map units (`localize --radius`): finite, 0 or more.
pub fn distance(text: &str) -> Result<f64, String> {
    number(text, 0.0, f64::INFINITY, "a finite distance of 0 or more")
}

/// A keypoint score threshold (`extract --threshold`, `convert --score-threshold`): finite,
/// 0 or more.
pub fn score(text: &str) -> Result<f32, String> {
    let v = number(
        text,
        0.0,
        f64::from(f32::MAX),
        "a finite score of 0 or more",
    )?;
    #[allow(clippy::cast_possible_truncation)] // within f32's range
    Ok(v as f32)
}

/// A world point `x,y,z` (`localize --prior`): three finite numbers.
pub fn point(text: &str) -> Result<[f64; 3], String> {
    let coordinate = |c: &str| number(c, f64::MIN, f64::MAX, "three finite numbers x,y,z");
    match text.split(',').collect::<Vec<_>>()[..] {
        [x, y, z] => Ok([coordinate(x)?, coordinate(y)?, coordinate(z)?]),
        _ => Err("expected three finite numbers x,y,z".to_owned()),
    }
}

/// A recall threshold `METERS,DEGREES` (`eval --threshold`): a finite distance over 0 and an
/// angle over 0 and at most 180 degrees.
pub fn recall_threshold(text: &str) -> Result<(f64, f64), String> {
    const EXPECTED: &str = "METERS,DEGREES: a finite distance over 0 and an angle in (0, 180]";
    let (t, r) = text.split_once(',').ok_or(EXPECTED)?;
    let t = number(t, 0.0, f64::INFINITY, EXPECTED)?;
    let r = number(r, 0.0, 180.0, EXPECTED)?;
    if t > 0.0 && r > 0.0 {
        Ok((t, r))
    } else {
        Err(EXPECTED.to_owned())
    }
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
