//! `sfpmap plot`: the PNG decodes at the asked size, is not blank (title text, several
//! colours), and shows what was passed in.
#![cfg(feature = "localize")]

use crate::run::sfpmap;
use std::collections::HashSet;
use std::path::{Path, PathBuf};

fn vector(name: &str) -> PathBuf {
    crate::shared_data::repo_root().join(format!("spec/vectors/valid/{name}.sfpm"))
}

/// Width, height and RGB pixels of a PNG.
fn decode(path: &Path) -> (u32, u32, Vec<[u8; 3]>) {
    let file = std::io::BufReader::new(std::fs::File::open(path).unwrap());
    let mut reader = png::Decoder::new(file).read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    assert!(
        channels >= 3,
        "colour PNG expected, got {:?}",
        info.color_type
    );
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    let pixels = buf[..info.buffer_size()]
        .chunks_exact(channels)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    (info.width, info.height, pixels)
}

#[test]
fn plot_of_a_map_with_poses_decodes_and_is_not_blank() {
    let tmp = tempfile::tempdir().unwrap();
    let estimated = tmp.path().join("poses.txt");
    let gt = tmp.path().join("gt.txt");
    std::fs::write(
        &estimated,
        "# name qw qx qy qz tx ty tz\nq1 1 0 0 0 0.5 -0.2 2.1\nq2 1 0 0 0 1.5 -0.7 1.8\n# failed q3: too few inliers\n",
    )
    .unwrap();
    std::fs::write(
        &gt,
        "q1 1 0 0 0 0.3 -0.2 2\nq2 1 0 0 0 1.2 -0.7 2\nq3 1 0 0 0 2.5 -1 2\n",
    )
    .unwrap();
    let png = tmp.path().join("plot.png");
    let out = sfpmap(&[
        "plot",
        vector("levels").to_str().unwrap(),
        "--poses",
        estimated.to_str().unwrap(),
        "--gt",
        gt.to_str().unwrap(),
        "-o",
        png.to_str().unwrap(),
        "--width",
        "800",
        "--height",
        "600",
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["cameras"], 3);
    assert_eq!(report["pairs"], 2);
    assert_eq!(report["points_drawn"], 24);

    let (w, h, pixels) = decode(&png);
    assert_eq!((w, h), (800, 600));
    let colours: HashSet<[u8; 3]> = pixels.iter().copied().collect();
    assert!(colours.len() >= 8, "only {} colours", colours.len());
    let white = pixels.iter().filter(|p| **p == [255, 255, 255]).count();
    assert!(
        white > pixels.len() / 3 && white < pixels.len(),
        "{white} white pixels of {}",
        pixels.len()
    );
    // The title (text drawn with the embedded font) darkens the top band.
    let top_dark = pixels[..(w * h / 20) as usize]
        .iter()
        .filter(|p| p.iter().all(|&c| c < 100))
        .count();
    assert!(
        top_dark > 50,
        "no title text: {top_dark} dark pixels on top"
    );
    // Ground truth green and localized red are drawn unblended.
    assert!(pixels.contains(&[0, 128, 0]), "no ground-truth marker");
    assert!(pixels.contains(&[214, 39, 40]), "no localized marker");
}

#[test]
fn plot_of_a_map_without_images_and_bad_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let png = tmp.path().join("minimal.png");
    let out = sfpmap(&[
        "plot",
        vector("minimal").to_str().unwrap(),
        "-o",
        png.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (w, h, _) = decode(&png);
    assert_eq!((w, h), (1600, 1200));

    let missing = tmp.path().join("nope.txt");
    let out = sfpmap(&[
        "plot",
        vector("levels").to_str().unwrap(),
        "--gt",
        missing.to_str().unwrap(),
        "-o",
        tmp.path().join("x.png").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("nope.txt"));

    let bad = tmp.path().join("bad.txt");
    std::fs::write(&bad, "q1 1 0 0\n").unwrap();
    let out = sfpmap(&[
        "plot",
        vector("levels").to_str().unwrap(),
        "--poses",
        bad.to_str().unwrap(),
        "-o",
        tmp.path().join("y.png").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("bad.txt:1"));
}
