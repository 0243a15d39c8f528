//! Pose evaluation against ground truth: median errors, recall at thresholds, and errors
//! relative to the map's median nearest-camera distance (SfM scale is arbitrary).

use super::Localization;
use crate::format::{Error as FormatError, Map};
use crate::geometry::Pose;
use serde_json::json;
use std::collections::{BTreeMap, HashMap};

/// Evaluation of a set of estimated poses.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    /// The queries with ground truth.
    pub queries: usize,
    /// How many of them were localized.
    pub localized: usize,
    /// Medians over all ground-truth queries, failures counted as infinite error (so a median
    /// is `None` when half or more failed).
    pub median_translation: Option<f64>,
    /// The median rotation error, in degrees.
    pub median_rotation_deg: Option<f64>,
    /// The median translation error over [`Evaluation::scale`].
    pub median_translation_rel: Option<f64>,
    /// (translation threshold, rotation threshold, share of queries within both).
    pub recall: Vec<(f64, f64, f64)>,
    /// Median distance from a map camera to its nearest other map camera, if a map was given.
    pub scale: Option<f64>,
    /// Per query: name, translation error, rotation error (`None` = not localized).
    pub per_query: Vec<(String, Option<(f64, f64)>)>,
}

impl Evaluation {
    /// The summary every evaluation report shares: counts, medians, recall.
    pub fn summary_json(&self) -> serde_json::Map<String, serde_json::Value> {
        let summary = json!({
            "queries": self.queries,
            "localized": self.localized,
            "median_translation": self.median_translation,
            "median_rotation_deg": self.median_rotation_deg,
            "median_translation_rel": self.median_translation_rel,
            "recall": self.recall_json(),
        });
        summary.as_object().cloned().unwrap_or_default()
    }

    /// The recall list as JSON: `[{ "translation", "rotation_deg", "recall" }, ...]`, one
    /// object per threshold.
    pub fn recall_json(&self) -> serde_json::Value {
        self.recall
            .iter()
            .map(|(t, r, v)| json!({ "translation": t, "rotation_deg": r, "recall": v }))
            .collect()
    }
}

/// How localized queries went, counted: the path (retrieval or tracking), why tracking was
/// lost, which stored descriptor ranked the images, and retrieval's fallbacks (queries
/// matched against every point), each reason with its count (what `sfpmap localize --json`
/// reports).
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct PathCounts {
    /// Queries per [`LocalizationPath`](super::LocalizationPath) (`"retrieval"`,
    /// `"tracking"`).
    pub path: BTreeMap<&'static str, usize>,
    /// Queries per reason tracking was lost ([`TrackingLost`](super::TrackingLost)).
    pub tracking_lost: BTreeMap<String, usize>,
    /// Queries per stored descriptor that ranked their images (`"vlad"`, `"global"`).
    pub retrieval: BTreeMap<&'static str, usize>,
    /// Queries per reason retrieval fell back to every point
    /// ([`RetrievalFallback`](super::RetrievalFallback)).
    pub retrieval_fallback: BTreeMap<String, usize>,
}

impl PathCounts {
    /// The counts over `results`.
    pub fn of<'a>(results: impl IntoIterator<Item = &'a Localization>) -> PathCounts {
        let mut counts = PathCounts::default();
        for r in results {
            *counts.path.entry(r.path.name()).or_default() += 1;
            if let Some(why) = r.tracking_lost {
                *counts.tracking_lost.entry(why.to_string()).or_default() += 1;
            }
            if let Some(method) = r.retrieval {
                *counts.retrieval.entry(method.name()).or_default() += 1;
            }
            if let Some(why) = r.retrieval_fallback {
                *counts
                    .retrieval_fallback
                    .entry(why.to_string())
                    .or_default() += 1;
            }
        }
        counts
    }
}

/// Median distance from each camera centre to its nearest other centre.
///
/// With an even count this is the upper of the two middle values, not their mean as in
/// [`median`]: kept so that scales, and so relative errors, match earlier results.
pub fn median_nearest_camera_distance(centres: &[[f64; 3]]) -> Option<f64> {
    if centres.len() < 2 {
        return None;
    }
    let mut nearest: Vec<f64> = centres
        .iter()
        .enumerate()
        .map(|(i, a)| {
            centres
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, b)| {
                    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
                })
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    nearest.sort_by(f64::total_cmp);
    Some(nearest[nearest.len() / 2])
}

/// The map's scale: [`median_nearest_camera_distance`] over its image centres; `None` if the
/// map has fewer than two images with a usable pose. Images whose stored pose is unusable (zero
/// quaternion, non-finite values) are skipped.
pub fn map_scale(map: &Map<'_>) -> Result<Option<f64>, FormatError> {
    let Some(images) = map.images()? else {
        return Ok(None);
    };
    let centres: Vec<[f64; 3]> = images
        .poses
        .iter()
        .filter_map(|&q| Pose::from_colmap_array(q).ok())
        .map(|p| p.center().into())
        .collect();
    Ok(median_nearest_camera_distance(&centres))
}

/// The median (the mean of the two middle values for an even count); `None` for no values or
/// a non-finite median (e.g. when half or more of the values are infinite).
pub fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let m = if v.len() % 2 == 1 {
        v[v.len() / 2]
    } else {
        (v[v.len() / 2 - 1] + v[v.len() / 2]) / 2.0
    };
    m.is_finite().then_some(m)
}

/// Compares `estimates` to `ground_truth` (every ground-truth query counts; estimates of
/// names without ground truth are ignored).
pub fn evaluate(
    estimates: &[(String, Pose)],
    ground_truth: &[(String, Pose)],
    thresholds: &[(f64, f64)],
    scale: Option<f64>,
) -> Evaluation {
    let by_name: HashMap<&str, &Pose> = estimates.iter().map(|(n, p)| (n.as_str(), p)).collect();
    let mut per_query = Vec::new();
    for (name, gt) in ground_truth {
        let err = by_name
            .get(name.as_str())
            .map(|p| (p.center_distance(gt), p.rotation_error_deg(gt)));
        per_query.push((name.clone(), err));
    }
    let t: Vec<f64> = per_query
        .iter()
        .map(|(_, e)| e.map_or(f64::INFINITY, |e| e.0))
        .collect();
    let r: Vec<f64> = per_query
        .iter()
        .map(|(_, e)| e.map_or(f64::INFINITY, |e| e.1))
        .collect();
    let n = per_query.len().max(1) as f64;
    let recall = thresholds
        .iter()
        .map(|&(tt, rt)| {
            (
                tt,
                rt,
                per_query
                    .iter()
                    .filter(|(_, e)| e.is_some_and(|e| e.0 <= tt && e.1 <= rt))
                    .count() as f64
                    / n,
            )
        })
        .collect();
    Evaluation {
        queries: per_query.len(),
        localized: per_query.iter().filter(|(_, e)| e.is_some()).count(),
        median_translation: median(t.clone()),
        median_rotation_deg: median(r),
        median_translation_rel: scale.and_then(|s| median(t.iter().map(|x| x / s).collect())),
        recall,
        scale,
        per_query,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_count_failures_as_infinite() {
        let gt: Vec<(String, Pose)> = (0..4)
            .map(|i| {
                (
                    format!("q{i}"),
                    Pose::from_colmap(1.0, 0.0, 0.0, 0.0, i as f64, 0.0, 0.0).unwrap(),
                )
            })
            .collect();
        let est = vec![
            (
                gt[0].0.clone(),
                Pose::from_colmap(1.0, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0).unwrap(),
            ),
            (
                gt[1].0.clone(),
                Pose::from_colmap(1.0, 0.0, 0.0, 0.0, 1.3, 0.0, 0.0).unwrap(),
            ),
            (gt[2].0.clone(), gt[2].1),
        ];
        let e = evaluate(&est, &gt, &[(0.25, 2.0), (0.5, 5.0)], Some(2.0));
        assert_eq!((e.queries, e.localized), (4, 3));
        // Errors 0.1, 0.3, 0, inf → median (0.1 + 0.3) / 2.
        assert!((e.median_translation.unwrap() - 0.2).abs() < 1e-12);
        assert!((e.median_translation_rel.unwrap() - 0.1).abs() < 1e-12);
        assert_eq!(e.recall[0].2, 0.5);
        assert_eq!(e.recall[1].2, 0.75);
        let none = evaluate(&[], &gt, &[], None);
        assert_eq!(none.median_translation, None);
    }

    #[test]
    fn median_of_even_odd_and_empty() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(Vec::new()), None);
        assert_eq!(median(vec![1.0, f64::INFINITY]), None);
    }

    #[test]
    fn nearest_camera_distance() {
        let c = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 0.0, 0.0]];
        assert_eq!(median_nearest_camera_distance(&c), Some(1.0));
    }
}
