//! Poses in and out: `name qw qx qy qz tx ty tz` lines (COLMAP `cam_from_world`, as
//! `gt_poses.txt` and `sfpmap localize` write them) read by [`read_poses`] and written by
//! [`colmap_pose_line`]; and database image poses out to trajectory tools: TUM (`timestamp tx ty tz qx qy qz qw`,
//! `world_from_cam`, what evo and the TUM scripts read) and COLMAP `images.txt` without
//! observations; and a list of localized queries in one of three layouts
//! ([`write_query_poses`], what `sfpmap localize -o` writes).

use super::InputError;
use crate::escape::escape_control_characters;
use crate::format::{Error, Map};
use crate::geometry::Pose;
use std::fmt::Write as _;
use std::path::Path;

/// One TUM row, `timestamp tx ty tz qx qy qz qw` (`world_from_cam`), without the newline, for a
/// `cam_from_world` pose. `−0` is written as `0`.
pub fn tum_line(timestamp: impl std::fmt::Display, cam_from_world: &Pose) -> String {
    let [qw, qx, qy, qz, x, y, z] = cam_from_world.inverse().to_colmap();
    // `+ 0.0` turns the conjugate's −0 into 0, which reads better.
    format!(
        "{timestamp} {} {} {} {} {} {} {}",
        x + 0.0,
        y + 0.0,
        z + 0.0,
        qx + 0.0,
        qy + 0.0,
        qz + 0.0,
        qw + 0.0
    )
}

/// TUM lines for `(name, cam_from_world)` poses. TUM needs a timestamp: the pose's index in
/// the list, with the names listed in order in the header comment so rows can be traced back.
///
/// Names there have their control characters escaped (`\n`), not refused as `images.txt`
/// refuses them: the rows hold no names, so the comment is only for people, and escaping
/// keeps it one line (a raw newline would end it and inject a row).
pub fn to_tum<'a>(poses: impl IntoIterator<Item = (&'a str, Pose)>) -> String {
    let mut names =
        String::from("# sfpmap: TUM trajectory (world_from_cam); timestamp = index of the image:");
    let mut body = String::new();
    for (i, (name, pose)) in poses.into_iter().enumerate() {
        write!(names, " {i}={}", escape_control_characters(name)).ok();
        body.push_str(&tum_line(i, &pose));
        body.push('\n');
    }
    names.push_str("\n# timestamp tx ty tz qx qy qz qw\n");
    names + &body
}

/// The map's database images as TUM; a pose that is no rotation (a zero or non-finite
/// quaternion) is an error naming the image.
pub fn images_tum(map: &Map<'_>) -> Result<String, Error> {
    let images = map
        .images()?
        .ok_or_else(|| Error::inconsistent("the map has no images"))?;
    let poses = (0..images.len())
        .map(|i| {
            let pose = Pose::from_colmap_array(images.poses[i])
                .map_err(|e| Error::inconsistent(format!("image {i}: pose: {e}")))?;
            // A finite pose far out (a translation near f64::MAX) can overflow on inversion.
            if !pose.inverse().is_finite() {
                return Err(Error::inconsistent(format!(
                    "image {i}: pose: its inverse is not finite"
                )));
            }
            Ok((images.name(i)?, pose))
        })
        .collect::<Result<Vec<_>, Error>>()?;
    Ok(to_tum(poses))
}

/// The map's database images as a COLMAP `images.txt` with empty POINTS2D lines (a valid
/// model file once next to a `cameras.txt`; `export --colmap` writes one with observations).
/// A name that line cannot hold (a control character, a space) is an error naming the image.
pub fn images_txt(map: &Map<'_>) -> Result<String, Error> {
    super::colmap_export::images_txt_without_points(map)
}

/// One line of a poses file, `name qw qx qy qz tx ty tz` (COLMAP `cam_from_world`, as in
/// `gt_poses.txt`), without the newline; [`read_poses`] reads it back bit for bit.
pub fn colmap_pose_line(name: &str, cam_from_world: &Pose) -> String {
    let [qw, qx, qy, qz, tx, ty, tz] = cam_from_world.to_colmap();
    format!("{name} {qw} {qx} {qy} {qz} {tx} {ty} {tz}")
}

/// How [`write_query_poses`] lays out a list of localized queries.
#[cfg(feature = "localize")]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum QueryPoseFormat {
    /// `name qw qx qy qz tx ty tz` (COLMAP `cam_from_world`, [`colmap_pose_line`]), like
    /// `gt_poses.txt`; a failed query as `# failed NAME: reason`.
    Colmap,
    /// `index tx ty tz qx qy qz qw` (TUM: the camera's pose in the world, [`tum_line`]); a
    /// failed query as `# failed INDEX NAME: reason`.
    Tum,
    /// One JSON object per query (its pose, failure, inliers, retrieved images, path and
    /// time), in a list.
    Json,
}

/// The queries `names` and their `results` in `format`; `image_names` names the map's images
/// the JSON lists as retrieved (empty: none named). A name a COLMAP row cannot hold
/// ([`text_name_problem`](crate::colmap::text::text_name_problem)) is an `InvalidInput`
/// error: refuse it before any work, as `sfpmap localize` does.
#[cfg(feature = "localize")]
pub fn write_query_poses(
    out: &mut impl std::io::Write,
    format: QueryPoseFormat,
    names: &[&str],
    results: &[crate::localize::Localization],
    image_names: &[&str],
) -> std::io::Result<()> {
    use crate::colmap::text::text_name_problem;
    use crate::escape::quoted_name;
    match format {
        QueryPoseFormat::Colmap => {
            writeln!(out, "# name qw qx qy qz tx ty tz (COLMAP cam_from_world)")?;
            for (i, (name, r)) in names.iter().zip(results).enumerate() {
                if let Some(problem) = text_name_problem(name) {
                    return Err(std::io::Error::new(
                        std::io::ErrorKind::InvalidInput,
                        format!("query {} {} {problem}", i + 1, quoted_name(name)),
                    ));
                }
                match r.pose() {
                    Some(p) => writeln!(out, "{}", colmap_pose_line(name, p))?,
                    None => writeln!(out, "# failed {name}: {}", r.failure_line())?,
                }
            }
        }
        QueryPoseFormat::Tum => {
            writeln!(out, "# index tx ty tz qx qy qz qw (TUM: world_from_cam); query names in order of the list")?;
            for (i, (name, r)) in names.iter().zip(results).enumerate() {
                match r.pose() {
                    Some(p) => writeln!(out, "{}", tum_line(i, p))?,
                    None => writeln!(
                        out,
                        "# failed {i} {}: {}",
                        escape_control_characters(name),
                        r.failure_line()
                    )?,
                }
            }
        }
        QueryPoseFormat::Json => {
            let list: Vec<_> = names
                .iter()
                .zip(results)
                .map(|(name, r)| query_json(name, r, image_names))
                .collect();
            serde_json::to_writer_pretty(&mut *out, &list)?;
            writeln!(out)?;
        }
    }
    Ok(())
}

/// A query's object in [`QueryPoseFormat::Json`].
#[cfg(feature = "localize")]
fn query_json(
    name: &str,
    r: &crate::localize::Localization,
    image_names: &[&str],
) -> serde_json::Value {
    let retrieved: Vec<_> = r
        .retrieved
        .iter()
        .filter_map(|&i| image_names.get(i))
        .collect();
    serde_json::json!({
        "name": name,
        "cam_from_world": r.pose().map(|p| p.to_colmap()),
        "failure": r.failure().map(|f| f.to_string()),
        "inliers": r.inliers,
        "inliers_per_level": r.inliers_per_level,
        "matches": r.matches,
        "retrieved_images": r.retrieved_images,
        "retrieved": retrieved,
        "path": r.path.name(),
        "tracking_lost": r.tracking_lost.map(|w| w.to_string()),
        "retrieval": r.retrieval.map(|m| m.name()),
        "retrieval_fallback": r.retrieval_fallback.map(|w| w.to_string()),
        "ms": r.times.total_ms,
    })
}

/// Reads `name qw qx qy qz tx ty tz` lines (COLMAP `cam_from_world`); `#` lines are comments
/// (the localizer lists failed queries as `# failed NAME: reason`). The last seven fields are
/// the numbers and the name is everything before them, spaces included (as
/// [`colmap_pose_line`] writes a name with spaces): a line with an extra column reads its
/// first number into the name.
pub fn read_poses(path: &Path) -> Result<Vec<(String, Pose)>, InputError> {
    super::parse_lines(path, |line| {
        // The last seven fields are the numbers; the name is the rest, spaces and all, as
        // `colmap_pose_line` writes it (COLMAP image names may hold spaces).
        let tokens: Vec<&str> = line.split_whitespace().collect();
        if tokens.len() < 8 {
            return Err(format!(
                "expected `name qw qx qy qz tx ty tz`, found {} fields",
                tokens.len()
            ));
        }
        let numbers = &tokens[tokens.len() - 7..];
        let mut v = [0.0; 7];
        for (v, t) in v.iter_mut().zip(numbers) {
            *v = t.parse().map_err(|_| format!("not a number: {t:?}"))?;
        }
        let pose = Pose::from_colmap_array(v).map_err(|e| e.to_string())?;
        // Where the first number starts in `line`: the name ends before it.
        let first = numbers[0].as_ptr() as usize - line.as_ptr() as usize;
        Ok((line[..first].trim_end().to_string(), pose))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(v: [f64; 7]) -> Pose {
        Pose::from_colmap_array(v).unwrap()
    }

    #[test]
    fn tum_rows_of_a_rotated_camera_are_its_centre_and_inverse_rotation() {
        // 90° about z (R maps x to y) and t = (1, 0, 0): the centre is −Rᵀt = (0, 1, 0).
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let row = tum_line(0, &pose([h, 0.0, 0.0, h, 1.0, 0.0, 0.0]));
        let v: Vec<f64> = row.split(' ').skip(1).map(|t| t.parse().unwrap()).collect();
        let expected = [0.0, 1.0, 0.0, 0.0, 0.0, -h, h];
        assert!(
            v.iter().zip(expected).all(|(a, b)| (a - b).abs() < 1e-12),
            "{row}"
        );
    }

    #[test]
    fn a_name_with_spaces_reads_back_whole() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("poses.txt");
        let p = pose([1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0]);
        let text = colmap_pose_line("day 1/img  7.jpg", &p);
        std::fs::write(&path, format!("# a comment\n{text}\nshort 1 0 0 0 1 2\n")).unwrap();
        let e = read_poses(&path).unwrap_err().to_string();
        assert!(e.contains(":3") && e.contains("found 7 fields"), "{e}");
        std::fs::write(&path, format!("{text}\n")).unwrap();
        let read = read_poses(&path).unwrap();
        assert_eq!(read.len(), 1);
        assert_eq!(read[0].0, "day 1/img  7.jpg");
        assert_eq!(read[0].1.to_colmap(), p.to_colmap());
    }

    #[test]
    fn poses_files_read_back_bit_for_bit() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("poses.txt");
        let poses = [
            ("a.jpg", pose([0.5, -0.5, 0.5, 0.5, 1e-300, -2.5, 3.0])),
            (
                "b.jpg",
                pose([
                    0.9238795325112867,
                    0.0,
                    0.3826834323650898,
                    0.0,
                    0.1,
                    0.2,
                    0.3,
                ]),
            ),
        ];
        let mut text = String::from("# name qw qx qy qz tx ty tz\n# failed c.jpg: why\n");
        for (name, p) in &poses {
            text += &colmap_pose_line(name, p);
            text.push('\n');
        }
        std::fs::write(&path, text).unwrap();
        let read = read_poses(&path).unwrap();
        assert_eq!(read.len(), 2);
        for ((name, p), (read_name, read_pose)) in poses.iter().zip(&read) {
            assert_eq!(name, read_name);
            assert_eq!(p.to_colmap(), read_pose.to_colmap());
        }
        std::fs::write(&path, "a.jpg 1 0 0 0 0 0\n").unwrap();
        let e = read_poses(&path).unwrap_err().to_string();
        assert!(
            e.ends_with("poses.txt:1: expected `name qw qx qy qz tx ty tz`, found 7 fields"),
            "{e}"
        );
    }

    #[test]
    fn tum_rows_are_world_from_cam_without_negative_zero() {
        assert_eq!(
            tum_line(3, &pose([1.0, 0.0, 0.0, 0.0, 1.0, -0.5, 2.0])),
            "3 -1 0.5 -2 0 0 0 1"
        );
        assert_eq!(
            tum_line("12.000000005", &pose([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])),
            "12.000000005 0 0 0 0 0 0 1"
        );
        let text = to_tum([("a.jpg", pose([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]))]);
        assert_eq!(
            text,
            "# sfpmap: TUM trajectory (world_from_cam); timestamp = index of the image: 0=a.jpg\n\
             # timestamp tx ty tz qx qy qz qw\n\
             0 -1 0 0 0 0 0 1\n"
        );
    }

    #[test]
    fn tum_names_stay_in_their_comment_line() {
        let p = pose([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        let text = to_tum([("a\n1 2 3 4 5 6 7 8\r", p), ("b\u{1b}.jpg", p)]);
        assert_eq!(
            text.lines().next(),
            Some(
                "# sfpmap: TUM trajectory (world_from_cam); timestamp = index of the image: \
                 0=a\\n1 2 3 4 5 6 7 8\\r 1=b\\x1b.jpg"
            )
        );
        assert_eq!(text.lines().filter(|l| !l.starts_with('#')).count(), 2);
    }
}
