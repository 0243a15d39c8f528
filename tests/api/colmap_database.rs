//! COLMAP `database.db` reading on both schemas, and the database never being modified.
#![cfg(feature = "colmap")]

use crate::common;
use crate::shared_data;

use std::path::{Path, PathBuf};

use sfpmap::colmap::{self, Database, Error, KeypointLayout, Keypoints};

fn data_root() -> Option<PathBuf> {
    shared_data::shared_data("colmap").map(|c| c.join(".."))
}

fn dir_listing(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// Checks one database against its model: same images, keypoints = points2D, descriptors.
fn check_database(db_path: &Path, model_dir: &Path, layout: KeypointLayout, has_type: bool) {
    let model = colmap::read_model(model_dir).unwrap();
    let db = Database::open(db_path).unwrap_or_else(|e| panic!("{}: {e}", db_path.display()));
    assert_eq!(db.descriptors_have_type(), has_type);
    let cameras = db.cameras().unwrap();
    assert!(!cameras.is_empty());
    let images = db.images().unwrap();
    for image in model.images() {
        let db_image = images.iter().find(|i| i.id == image.id).unwrap();
        assert_eq!(db_image.name, image.name);
        assert!(cameras.iter().any(|c| c.id == db_image.camera_id));
        let n = image.points2d.len();
        assert_eq!(db.num_keypoints(image.id).unwrap(), Some(n as u64));
        let features = db.features(image.id).unwrap();
        let keypoints = features.keypoints.unwrap();
        assert_eq!(keypoints.len(), n, "image {}", image.id);
        assert_eq!(keypoints.layout(), layout);
        let descriptors = features.descriptors.unwrap();
        assert_eq!((descriptors.len(), descriptors.dim), (n, 128));
        assert_eq!(descriptors.type_id, has_type.then_some(0));
        // Keypoints are the model's points2D (kapture's text model rounds to ~5e-3 px).
        for (i, p) in image.points2d.iter().enumerate().step_by(37) {
            let [x, y] = keypoints.xy(i).unwrap();
            assert!(
                (f64::from(x) - p.xy[0]).abs() < 1e-2,
                "image {} kp {i}",
                image.id
            );
            assert!(
                (f64::from(y) - p.xy[1]).abs() < 1e-2,
                "image {} kp {i}",
                image.id
            );
            let scale = keypoints.scale(i).unwrap();
            assert!(scale.is_finite() && scale > 0.0, "scale {scale}");
            let mut row = Vec::new();
            assert!(descriptors.row_into(i, &mut row));
            assert!(row.iter().any(|&v| v != 0.0));
        }
        assert!(keypoints.xy(n).is_none() && !descriptors.row_into(n, &mut Vec::new()));
    }
    // Streaming visits every image once, in id order.
    let streamed: Vec<u32> = db
        .iter_features()
        .unwrap()
        .map(|f| f.unwrap().image.id)
        .collect();
    assert_eq!(streamed, images.iter().map(|i| i.id).collect::<Vec<_>>());
    let err = db.features(999_999).unwrap_err();
    assert!(
        matches!(
            err,
            Error::ImageNotInDatabase {
                image_id: 999_999,
                ..
            }
        ),
        "{err}"
    );
}

/// Copies `db` into a fresh temp dir, checks it there, and checks that neither the copy nor
/// the original changed or grew companion files.
fn check_copy(db: &Path, model_dir: &Path, layout: KeypointLayout, has_type: bool) {
    let original = std::fs::read(db).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    // Characters that end or escape a URI path must still name the file.
    let dir = tmp.path().join("we?ird #dir %41");
    std::fs::create_dir(&dir).unwrap();
    let copy = dir.join("database.db");
    std::fs::copy(db, &copy).unwrap();
    check_database(&copy, model_dir, layout, has_type);
    assert_eq!(dir_listing(&dir), ["database.db"]);
    assert!(std::fs::read(&copy).unwrap() == original, "copy modified");
    // In place too: immutable means no -wal/-shm/-journal next to the user's file.
    let before = dir_listing(db.parent().unwrap());
    check_database(db, model_dir, layout, has_type);
    assert_eq!(dir_listing(db.parent().unwrap()), before);
    assert!(std::fs::read(db).unwrap() == original, "original modified");
}

#[test]
fn old_2017_schema_loads() {
    let Some(root) = data_root() else { return };
    let base = root.join("colmap/bartoszek_test_colmap");
    check_copy(
        &base.join("database.db"),
        &base.join("sparse/0"),
        KeypointLayout::ScaleOrientation,
        false,
    );
    let db = Database::open(&base.join("database.db")).unwrap();
    let total: usize = db
        .iter_features()
        .unwrap()
        .map(|f| f.unwrap().keypoints.unwrap().len())
        .sum();
    assert_eq!(total, 16646);
}

#[test]
fn colmap_3_6_schema_with_affine_keypoints_loads() {
    let Some(root) = data_root() else { return };
    let base = root.join("colmap/kapture_maupertuis");
    check_copy(
        &base.join("colmap.db"),
        &base.join("reconstruction"),
        KeypointLayout::Affine,
        false,
    );
}

#[test]
fn current_schema_with_descriptor_type_loads() {
    let Some(root) = data_root() else { return };
    let base = root.join("scenes/sacre-coeur");
    check_copy(
        &base.join("database.db"),
        &base.join("sparse-map"),
        KeypointLayout::Affine,
        true,
    );
}

#[test]
fn wrong_files_give_clear_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("missing.db");
    let err = Database::open(&missing).unwrap_err();
    assert!(matches!(err, Error::Io { .. }), "{err}");
    assert!(!missing.exists(), "opening must not create the file");

    let text = tmp.path().join("notes.db");
    std::fs::write(
        &text,
        "this is not a database, just some text that is long enough ".repeat(20),
    )
    .unwrap();
    let err = Database::open(&text).unwrap_err();
    assert!(matches!(err, Error::NotADatabase { .. }), "{err:?}");
    assert_eq!(
        err.to_string(),
        format!("{}: not an SQLite database", text.display())
    );

    let other = tmp.path().join("other.db");
    {
        let conn = rusqlite::Connection::open(&other).unwrap();
        conn.execute_batch(
            "CREATE TABLE cameras (camera_id INTEGER, model INTEGER, width INTEGER, \
             height INTEGER, params BLOB); CREATE TABLE images (image_id INTEGER, name TEXT);",
        )
        .unwrap();
    }
    let err = Database::open(&other).unwrap_err();
    assert!(
        matches!(
            err,
            Error::MissingColumn {
                table: "images",
                column: "camera_id",
                ..
            }
        ),
        "{err}"
    );
    {
        let conn = rusqlite::Connection::open(&other).unwrap();
        conn.execute_batch("DROP TABLE images;").unwrap();
    }
    let err = Database::open(&other).unwrap_err();
    assert!(
        matches!(
            err,
            Error::MissingTable {
                table: "images",
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("not a COLMAP database"), "{err}");
}

/// The model readers' rule for image names, in a database too: a newline would inject rows into
/// `images.txt` and TUM files written from it.
#[test]
fn an_image_name_with_a_control_character_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("db.db");
    {
        let conn = rusqlite::Connection::open(&path).unwrap();
        common::colmap_schema(&conn);
        conn.execute_batch(
            "INSERT INTO images VALUES (1, 'a.jpg', 1), (2, 'b.jpg' || char(10) || '2 0 0 0', 1);",
        )
        .unwrap();
    }
    let db = Database::open(&path).unwrap();
    let err = db.images().unwrap_err();
    assert!(
        matches!(err, Error::BadImageName { image_id: 2, .. }),
        "{err}"
    );
    let message = err.to_string();
    assert!(
        message.starts_with(&path.display().to_string()),
        "{message}"
    );
    assert!(message.contains("\\n"), "{message}");
    assert!(!message.contains('\n'), "{message}");
}

#[test]
fn bad_rows_are_errors_not_panics() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("db.db");
    {
        let conn = rusqlite::Connection::open(&path).unwrap();
        common::colmap_schema(&conn);
        let params: Vec<u8> = [1.0f64, 2.0, 3.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        conn.execute(
            "INSERT INTO cameras VALUES (1, 2, 10, 10, ?1, 0), (2, 42, 10, 10, ?1, 0)",
            [&params],
        )
        .unwrap();
        conn.execute_batch(
            "INSERT INTO images VALUES (1, 'a.jpg', 1), (2, 'b.jpg', 1), (3, 'c.jpg', 1), \
               (4, 'd.jpg', 1);
             INSERT INTO keypoints VALUES (1, 2, 3, zeroblob(24)), (2, 2, 2, zeroblob(15)), \
               (3, 1, 2, zeroblob(8)), (4, -1, 2, NULL);
             INSERT INTO descriptors VALUES (3, 2, 128, zeroblob(256));",
        )
        .unwrap();
    }
    let db = Database::open(&path).unwrap();
    let err = db.cameras().unwrap_err();
    // Camera 1 is SIMPLE_RADIAL with 3 params.
    assert!(
        matches!(
            err,
            Error::ParamCount {
                camera_id: 1,
                expected: 4,
                found: 3,
                ..
            }
        ),
        "{err}"
    );
    let err = db.keypoints(1).unwrap_err();
    assert!(
        err.to_string()
            .contains("3 columns; COLMAP keypoints have 2, 4 or 6"),
        "{err}"
    );
    let err = db.keypoints(2).unwrap_err();
    assert!(err.to_string().contains("blob of 15 bytes"), "{err}");
    let err = db.keypoints(4).unwrap_err();
    assert!(err.to_string().contains("bad shape -1 x 2"), "{err}");
    let err = db.features(3).unwrap_err();
    assert!(
        err.to_string().contains("2 descriptors for 1 keypoints"),
        "{err}"
    );
    assert_eq!(db.keypoints(9).unwrap(), None);
    assert_eq!(db.descriptors(1).unwrap(), None);
    // The stream stops for good after its first error.
    let items: Vec<_> = db.iter_features().unwrap().collect();
    assert_eq!(items.len(), 1);
    assert!(items[0].is_err());
}

#[test]
fn a_pending_write_ahead_log_is_an_error() {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("wal.db");
    let conn = rusqlite::Connection::open(&path).unwrap();
    conn.pragma_update(None, "journal_mode", "wal").unwrap();
    conn.pragma_update(None, "wal_autocheckpoint", 0).unwrap();
    common::colmap_schema(&conn);
    // While `conn` is open its changes sit in wal.db-wal, invisible to an immutable open.
    let err = Database::open(&path).unwrap_err();
    assert!(matches!(err, Error::PendingWal { .. }), "{err}");
    drop(conn);
    // Closing checkpoints and removes the log; now it opens.
    Database::open(&path).unwrap();
}

#[test]
fn keypoint_scale_follows_colmap() {
    // 4 columns: x, y, scale, orientation; the affine form is scale * R(orientation).
    let k = Keypoints::new(KeypointLayout::ScaleOrientation, vec![1.0, 2.0, 3.0, 0.5]).unwrap();
    assert_eq!(k.scale(0), Some(3.0));
    let a = k.get(0).unwrap();
    assert!((a.scale() - 3.0).abs() < 1e-6);
    assert!((a.orientation() - 0.5).abs() < 1e-6);
    assert!((a.a11 - 3.0 * 0.5f32.cos()).abs() < 1e-6 && (a.a21 - 3.0 * 0.5f32.sin()).abs() < 1e-6);
    // 6 columns: the mean of the column norms (COLMAP's ComputeScale), here (2 + 8) / 2.
    let k = Keypoints::new(KeypointLayout::Affine, vec![0.0, 0.0, 2.0, 0.0, 0.0, 8.0]).unwrap();
    assert_eq!(k.scale(0), Some(5.0));
    // 2 columns carry no shape.
    let k = Keypoints::new(KeypointLayout::Xy, vec![0.0, 0.0]).unwrap();
    assert_eq!(k.scale(0), None);
    assert_eq!(k.get(0).unwrap().scale(), 1.0);
    assert!(Keypoints::new(KeypointLayout::Affine, vec![0.0; 5]).is_none());
}

/// COLMAP 4's typed descriptors, as pycolmap 4.2.1 writes each type: SIFT's u8 rows and the
/// learned features' f32 rows read back exactly, each named as maps record it; a type with no
/// layout (`UNDEFINED`, or one COLMAP does not define) is a one-line error naming the
/// database, the image and the type, never bytes misread.
#[test]
fn typed_descriptors_are_read_by_their_type_or_an_error_naming_the_type_and_image() {
    let t = tempfile::tempdir().unwrap();
    let db_path = t.path().join("typed.db");
    let script = r#"
import sys, sqlite3, numpy as np, pycolmap
db = pycolmap.Database.open(sys.argv[1])
cid = db.write_camera(pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480, params=[500, 320, 240]))
T = pycolmap.FeatureExtractorType
for k, t in enumerate([T.SIFT, T.ALIKED_N16ROT, T.ALIKED_N32, T.LOMA_B, T.LOMA_B128, T.SIFT, T.SIFT]):
    iid = db.write_image(pycolmap.Image(name=f"image{k + 1}.jpg", camera_id=cid))
    if t == T.SIFT:
        d = pycolmap.FeatureDescriptors(t, (np.arange(3 * 128).reshape(3, 128) % 251).astype(np.uint8))
    else:
        d = pycolmap.FeatureDescriptorsFloat(t, (np.arange(3 * 96).reshape(3, 96) / 7.0).astype(np.float32)).to_bytes()
    db.write_descriptors(iid, d)
    db.write_keypoints(iid, (np.arange(6).reshape(3, 2) * 10.0).astype(np.float32))
db.close()
# Types with no layout: UNDEFINED and one COLMAP 4.2 does not define.
c = sqlite3.connect(sys.argv[1])
c.execute("UPDATE descriptors SET type = -1 WHERE image_id = 6")
c.execute("UPDATE descriptors SET type = 9 WHERE image_id = 7")
c.commit()
"#;
    let out = std::process::Command::new(crate::python::python_with("numpy, pycolmap"))
        .args(["-c", script])
        .arg(&db_path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let db = Database::open(&db_path).unwrap();
    assert!(db.descriptors_have_type());
    let sift = db.features(1).unwrap().descriptors.unwrap();
    assert_eq!(
        (sift.len(), sift.dim, sift.type_id, sift.feature()),
        (3, 128, Some(0), "sift".to_string())
    );
    let mut row = Vec::new();
    assert!(sift.row_into(2, &mut row));
    assert_eq!(row[..2], [(256 % 251) as f32, (257 % 251) as f32]);
    for (id, feature) in [
        (2, "aliked-n16rot"),
        (3, "aliked-n32"),
        (4, "loma-b"),
        (5, "loma-b128"),
    ] {
        let d = db.features(id).unwrap().descriptors.unwrap();
        assert_eq!(
            (d.len(), d.dim, d.type_id, d.feature()),
            (3, 96, Some(id as i64 - 1), feature.to_string())
        );
        assert!(d.row_into(1, &mut row));
        assert_eq!(row[0], 96.0f32 / 7.0, "{feature}: f32 values, not bytes");
        assert_eq!(row[95], 191.0f32 / 7.0);
    }
    for (id, t, name) in [
        (6, -1, "UNDEFINED"),
        (7, 9, "a type COLMAP 4.2 does not define"),
    ] {
        let e = db.features(id).unwrap_err().to_string();
        assert_eq!(
            e,
            format!(
                "{}: table descriptors, id {id}: type {t} ({name}): no descriptor layout is \
                 known for it (SIFT is type 0)",
                db_path.display()
            )
        );
    }
}
