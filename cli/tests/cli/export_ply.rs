//! `sfpmap export` on the `levels` spec vector: the PLY read back by a small parser here,
//! TUM and images.txt poses, `--colmap` equal to `export-colmap`, and refusals.

use crate::run::sfpmap;
use serde_json::Value;
use std::path::{Path, PathBuf};

fn vector() -> (PathBuf, Value) {
    let root = crate::shared_data::repo_root().join("spec/vectors/valid");
    let json = std::fs::read_to_string(root.join("levels.json")).unwrap();
    (
        root.join("levels.sfpm"),
        serde_json::from_str::<Value>(&json).unwrap(),
    )
}

fn origin(map: &Path) -> [f64; 3] {
    sfpmap::format::Map::open(map).unwrap().metadata().origin
}

struct Vertex {
    xyz: [f64; 3],
    rgb: [u8; 3],
    level: i32,
    level_mask: u32,
}

/// Reads the binary little-endian PLY `sfpmap export --ply` writes; checks the header says
/// what the records hold.
fn read_ply(bytes: &[u8]) -> (Vec<String>, Vec<Vertex>) {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("end_header")
        + 11;
    let header = std::str::from_utf8(&bytes[..end]).unwrap();
    let lines: Vec<String> = header.lines().map(str::to_string).collect();
    assert_eq!(lines[0], "ply");
    assert_eq!(lines[1], "format binary_little_endian 1.0");
    let count: usize = lines
        .iter()
        .find_map(|l| l.strip_prefix("element vertex "))
        .unwrap()
        .parse()
        .unwrap();
    let properties: Vec<&str> = lines
        .iter()
        .filter_map(|l| l.strip_prefix("property "))
        .collect();
    assert_eq!(
        properties,
        [
            "double x",
            "double y",
            "double z",
            "uchar red",
            "uchar green",
            "uchar blue",
            "int level",
            "uint level_mask"
        ]
    );
    const RECORD: usize = 3 * 8 + 3 + 4 + 4;
    let body = &bytes[end..];
    assert_eq!(body.len(), count * RECORD, "PLY body length");
    let vertices = body
        .chunks_exact(RECORD)
        .map(|r| {
            let f = |i: usize| f64::from_le_bytes(r[i * 8..i * 8 + 8].try_into().unwrap());
            Vertex {
                xyz: [f(0), f(1), f(2)],
                rgb: [r[24], r[25], r[26]],
                level: i32::from_le_bytes(r[27..31].try_into().unwrap()),
                level_mask: u32::from_le_bytes(r[31..35].try_into().unwrap()),
            }
        })
        .collect();
    (lines, vertices)
}

#[test]
fn ply_holds_every_point_in_world_coordinates_with_colour_and_level() {
    let (map, json) = vector();
    let tmp = tempfile::tempdir().unwrap();
    let ply = tmp.path().join("points.ply");
    let out = sfpmap(&[
        "export",
        map.to_str().unwrap(),
        "--ply",
        ply.to_str().unwrap(),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    let (header, vertices) = read_ply(&std::fs::read(&ply).unwrap());
    let content = &json["content"];
    let positions = content["positions"].as_array().unwrap();
    assert_eq!(vertices.len(), positions.len());
    assert_eq!(report["ply"]["points"], positions.len());
    let o = origin(&map);
    assert!(header.iter().any(|l| l.starts_with("comment origin ")));

    // Each point's deepest level and mask, from the JSON's level point lists.
    let mut deepest = vec![-1i32; positions.len()];
    let mut mask = vec![0u32; positions.len()];
    for level in content["levels"].as_array().unwrap() {
        let id = level["level"].as_i64().unwrap() as i32;
        for p in level["points"].as_array().unwrap() {
            let p = p.as_u64().unwrap() as usize;
            deepest[p] = deepest[p].max(id);
            mask[p] |= 1 << id;
        }
    }
    assert!(
        deepest.contains(&-1),
        "the vector should have a point in no level"
    );
    for (p, v) in vertices.iter().enumerate() {
        for k in 0..3 {
            // Stored f32 offset + f64 origin, computed in f64 by both sides.
            let expected = o[k] + positions[p][k].as_f64().unwrap();
            assert_eq!(v.xyz[k], expected, "point {p} axis {k}");
        }
        let rgb: Vec<u8> = content["colors"][p]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c.as_u64().unwrap() as u8)
            .collect();
        assert_eq!(v.rgb.to_vec(), rgb, "point {p} colour");
        assert_eq!(v.level, deepest[p], "point {p} level");
        assert_eq!(v.level_mask, mask[p], "point {p} level mask");
    }
    assert_eq!(
        report["ply"]["points_in_levels"],
        deepest.iter().filter(|&&l| l >= 0).count()
    );
}

#[test]
fn poses_as_tum_and_images_txt() {
    let (map, json) = vector();
    let tmp = tempfile::tempdir().unwrap();
    let tum = tmp.path().join("poses.tum");
    let images = tmp.path().join("images.txt");
    let out = sfpmap(&[
        "export",
        map.to_str().unwrap(),
        "--tum",
        tum.to_str().unwrap(),
        "--images-txt",
        images.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let expected = json["content"]["images"].as_array().unwrap();

    let tum = std::fs::read_to_string(&tum).unwrap();
    let rows: Vec<Vec<f64>> = tum
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split_whitespace().map(|t| t.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), expected.len());
    for (i, (row, image)) in rows.iter().zip(expected).enumerate() {
        assert!(tum.contains(&format!("{i}={}", image["name"].as_str().unwrap())));
        let q: Vec<f64> = (0..7)
            .map(|k| image["cam_from_world"][k].as_f64().unwrap())
            .collect();
        // The vector's rotations are the identity: centre = −t, orientation unchanged.
        assert_eq!(q[..4], [1.0, 0.0, 0.0, 0.0]);
        assert_eq!(row[0], i as f64);
        for k in 0..3 {
            assert!((row[1 + k] + q[4 + k]).abs() < 1e-12, "image {i} axis {k}");
        }
        assert_eq!(row[4..], [0.0, 0.0, 0.0, 1.0]);
    }

    let text = std::fs::read_to_string(&images).unwrap();
    let lines: Vec<&str> = text.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(lines.len(), 2 * expected.len(), "two lines per image");
    for (pair, image) in lines.chunks(2).zip(expected) {
        let t: Vec<&str> = pair[0].split_whitespace().collect();
        assert_eq!(t[0], image["id"].to_string());
        assert_eq!(t[9], image["name"].as_str().unwrap());
        for k in 0..7 {
            let v: f64 = t[1 + k].parse().unwrap();
            assert_eq!(v, image["cam_from_world"][k].as_f64().unwrap());
        }
        assert_eq!(pair[1], "", "no observations");
    }
}

#[test]
fn colmap_output_matches_export_colmap() {
    let (map, _) = vector();
    let tmp = tempfile::tempdir().unwrap();
    let a = tmp.path().join("export");
    let b = tmp.path().join("export-colmap");
    let poses = tmp.path().join("images.txt");
    let m = map.to_str().unwrap();
    let out = sfpmap(&[
        "export",
        m,
        "--colmap",
        a.to_str().unwrap(),
        "--images-txt",
        poses.to_str().unwrap(),
        "--json",
    ]);
    assert!(out.status.success());
    let nested: Value = serde_json::from_slice(&out.stdout).unwrap();
    let out = sfpmap(&["export-colmap", m, "-o", b.to_str().unwrap(), "--json"]);
    assert!(out.status.success());
    // export-colmap keeps its own flat JSON keys.
    let flat: Value = serde_json::from_slice(&out.stdout).unwrap();
    let mut keys: Vec<&str> = flat
        .as_object()
        .unwrap()
        .keys()
        .map(|k| k.as_str())
        .collect();
    keys.sort_unstable();
    assert_eq!(
        keys,
        ["cameras", "images", "observations", "output", "points"]
    );
    assert_eq!(flat["output"], b.to_str().unwrap());
    for k in ["cameras", "images", "points", "observations"] {
        assert_eq!(flat[k], nested["colmap"][k], "{k}");
    }
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        assert_eq!(
            std::fs::read(a.join(f)).unwrap(),
            std::fs::read(b.join(f)).unwrap(),
            "{f}"
        );
    }
    // --images-txt writes the same header and image lines, with empty POINTS2D lines.
    let full = std::fs::read_to_string(a.join("images.txt")).unwrap();
    let bare = std::fs::read_to_string(&poses).unwrap();
    let (full, bare): (Vec<&str>, Vec<&str>) = (full.lines().collect(), bare.lines().collect());
    assert_eq!(full.len(), bare.len());
    // Both come from the one COLMAP text writer.
    assert_eq!(full[..4], bare[..4], "header");
    assert!(bare[3].starts_with("# Number of images: "), "{}", bare[3]);
    for i in (4..full.len()).step_by(2) {
        assert_eq!(full[i], bare[i], "image line {i}");
        assert_eq!(bare[i + 1], "");
    }

    // The same refusal as export --colmap: an existing model needs --force.
    let out = sfpmap(&["export-colmap", m, "-o", b.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--force"));
    let out = sfpmap(&["export-colmap", m, "-o", b.to_str().unwrap(), "--force"]);
    assert!(out.status.success());
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        format!(
            "{}: {} cameras, {} images, {} points, {} observations",
            b.display(),
            flat["cameras"],
            flat["images"],
            flat["points"],
            flat["observations"]
        )
    );
}

#[test]
fn refuses_no_output_existing_files_and_maps_without_images() {
    let (map, _) = vector();
    let m = map.to_str().unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let out = sfpmap(&["export", m]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("nothing to export"));

    let ply = tmp.path().join("p.ply");
    std::fs::write(&ply, b"keep me").unwrap();
    let out = sfpmap(&["export", m, "--ply", ply.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--force"));
    assert_eq!(std::fs::read(&ply).unwrap(), b"keep me");
    let out = sfpmap(&["export", m, "--ply", ply.to_str().unwrap(), "--force"]);
    assert!(out.status.success());

    // minimal has no images: the TUM export says so and leaves nothing behind.
    let minimal = crate::shared_data::repo_root().join("spec/vectors/valid/minimal.sfpm");
    let sfpm = sfpmap::format::Map::open(&minimal).unwrap();
    assert!(sfpm.images().unwrap().is_none());
    let tum = tmp.path().join("t.txt");
    let out = sfpmap(&[
        "export",
        minimal.to_str().unwrap(),
        "--tum",
        tum.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no images"));
    assert!(!tum.exists());
}
