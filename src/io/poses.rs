//! Database image poses out to trajectory tools: TUM (`timestamp tx ty tz qx qy qz qw`,
//! `world_from_cam`, what evo and the TUM scripts read) and COLMAP `images.txt` without
//! observations.

use super::colmap_export::{escape_control_characters, images_txt_header, write_image_line};
use crate::format::{Error, Map};
use std::fmt::Write as _;

/// `cam_from_world` (qw qx qy qz tx ty tz) → `world_from_cam` as (centre, qw qx qy qz).
/// The inverse rotation is the conjugate; the centre is −Rᵀt.
pub fn world_from_cam(cam_from_world: [f64; 7]) -> ([f64; 3], [f64; 4]) {
    let [qw, qx, qy, qz, tx, ty, tz] = cam_from_world;
    let n = (qw * qw + qx * qx + qy * qy + qz * qz).sqrt();
    let (w, x, y, z) = (qw / n, -qx / n, -qy / n, -qz / n);
    let t = [-tx, -ty, -tz];
    // Rotate −t by the conjugate quaternion: v' = v + 2w(u×v) + 2u×(u×v), u = (x, y, z).
    let u = [x, y, z];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let uv = cross(u, t);
    let uuv = cross(u, uv);
    let c = [
        t[0] + 2.0 * (w * uv[0] + uuv[0]),
        t[1] + 2.0 * (w * uv[1] + uuv[1]),
        t[2] + 2.0 * (w * uv[2] + uuv[2]),
    ];
    (c, [w, x, y, z])
}

/// The camera centre of a `cam_from_world` pose.
pub fn camera_center(cam_from_world: [f64; 7]) -> [f64; 3] {
    world_from_cam(cam_from_world).0
}

/// One TUM row, `timestamp tx ty tz qx qy qz qw` (`world_from_cam`), without the newline, for a
/// `cam_from_world` pose (qw qx qy qz tx ty tz). `−0` is written as `0`.
pub fn tum_line(timestamp: impl std::fmt::Display, cam_from_world: [f64; 7]) -> String {
    let (c, q) = world_from_cam(cam_from_world);
    // `+ 0.0` turns the conjugate's −0 into 0, which reads better.
    format!(
        "{timestamp} {} {} {} {} {} {} {}",
        c[0] + 0.0,
        c[1] + 0.0,
        c[2] + 0.0,
        q[1] + 0.0,
        q[2] + 0.0,
        q[3] + 0.0,
        q[0] + 0.0
    )
}

/// TUM lines for `(name, cam_from_world)` poses. TUM needs a timestamp: the pose's index in
/// the list, with the names listed in order in the header comment so rows can be traced back.
///
/// Names there have their control characters escaped (`\n`), not refused as `images.txt`
/// refuses them: the rows hold no names, so the comment is only for people, and escaping
/// keeps it one line (a raw newline would end it and inject a row).
pub fn to_tum<'a>(poses: impl IntoIterator<Item = (&'a str, [f64; 7])>) -> String {
    let mut names =
        String::from("# sfpmap: TUM trajectory (world_from_cam); timestamp = index of the image:");
    let mut body = String::new();
    for (i, (name, pose)) in poses.into_iter().enumerate() {
        write!(names, " {i}={}", escape_control_characters(name)).ok();
        body.push_str(&tum_line(i, pose));
        body.push('\n');
    }
    names.push_str("\n# timestamp tx ty tz qx qy qz qw\n");
    names + &body
}

/// The map's database images as TUM.
pub fn images_tum(map: &Map<'_>) -> Result<String, Error> {
    let images = map
        .images()?
        .ok_or_else(|| Error::inconsistent("the map has no images"))?;
    let names = (0..images.len())
        .map(|i| images.name(i))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(to_tum(
        names.iter().zip(images.poses.iter()).map(|(n, p)| (*n, *p)),
    ))
}

/// The map's database images as a COLMAP `images.txt` with empty POINTS2D lines (a valid
/// model file once next to a `cameras.txt`; `export --colmap` writes one with observations).
/// A name that line cannot hold (a control character, a space) is an error naming the image.
pub fn images_txt(map: &Map<'_>) -> Result<String, Error> {
    let images = map
        .images()?
        .ok_or_else(|| Error::inconsistent("the map has no images"))?;
    let cameras = &map.metadata().cameras;
    let mut text = images_txt_header(images.len(), 0);
    for i in 0..images.len() {
        write_image_line(&mut text, cameras, &images, i)?;
        text.push('\n');
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_of_a_translated_and_rotated_camera() {
        // 90° about z (R maps x to y) and t = (1, 0, 0).
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let c = camera_center([h, 0.0, 0.0, h, 1.0, 0.0, 0.0]);
        // Rᵀ(1,0,0) = (0,−1,0), so −Rᵀt = (0, 1, 0).
        assert!((c[0]).abs() < 1e-12 && (c[1] - 1.0).abs() < 1e-12 && c[2].abs() < 1e-12);
        let c = camera_center([1.0, 0.0, 0.0, 0.0, 1.0, -0.5, 2.0]);
        assert_eq!(c, [-1.0, 0.5, -2.0]);
    }

    #[test]
    fn tum_rows_are_world_from_cam_without_negative_zero() {
        assert_eq!(
            tum_line(3, [1.0, 0.0, 0.0, 0.0, 1.0, -0.5, 2.0]),
            "3 -1 0.5 -2 0 0 0 1"
        );
        assert_eq!(
            tum_line("12.000000005", [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]),
            "12.000000005 0 0 0 0 0 0 1"
        );
        let text = to_tum([("a.jpg", [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0])]);
        assert_eq!(
            text,
            "# sfpmap: TUM trajectory (world_from_cam); timestamp = index of the image: 0=a.jpg\n\
             # timestamp tx ty tz qx qy qz qw\n\
             0 -1 0 0 0 0 0 1\n"
        );
    }

    #[test]
    fn tum_names_stay_in_their_comment_line() {
        let pose = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let text = to_tum([("a\n1 2 3 4 5 6 7 8\r", pose), ("b\u{1b}.jpg", pose)]);
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
