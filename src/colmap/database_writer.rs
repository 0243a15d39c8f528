//! Writing a COLMAP `database.db`: cameras, images, keypoints and descriptors, in COLMAP's
//! current schema (plus its empty `matches` and `two_view_geometries` tables), readable by
//! COLMAP, pycolmap and [`super::Database`].
//!
//! SQLite writes the database into a named temp file next to the target
//! ([`crate::output::AtomicPath`]), renamed over the target at [`DatabaseWriter::write`] after
//! an fsync: readers see the old file or the complete new one, and a failure or a writer
//! dropped without `write` leaves the target as it was and no temp file behind. SQLite
//! writing the target in place would leave a half-written file (and journals) instead. The
//! file is a throwaway until the rename, so its journal stays in memory, it is not synced
//! until the commit, and SQLite's page cache is small: the writer's memory does not grow with
//! the database (the 2.4 M-point street's 12 GB is the generator's scene, not SQLite's). A
//! process killed mid-write leaves the named temp file (`.database.db.sfpmap-tmp.*`), removed
//! by the next sfpmap write into that folder: SQLite cannot write an unnamed file.
//!
//! Why not build it in memory (SQLite's memdb) and write it out at the end, as before: that
//! holds the whole database in memory, and memdb keeps it in one buffer, which SQLite cannot
//! grow past its ~2 GiB limit on one allocation (a 2.3 M-point street failed so).

use std::path::{Path, PathBuf};

use rusqlite::{params, Connection, OpenFlags};

use crate::output::AtomicPath;

use super::error::{Error, Result};
use super::model::Camera;

/// COLMAP's `CreateTables` for the tables written here.
const SCHEMA: &str = "
CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, model INTEGER NOT NULL,
  width INTEGER NOT NULL, height INTEGER NOT NULL, params BLOB, prior_focal_length INTEGER NOT NULL);
CREATE TABLE images (image_id INTEGER PRIMARY KEY AUTOINCREMENT NOT NULL, name TEXT NOT NULL UNIQUE,
  camera_id INTEGER NOT NULL, CONSTRAINT image_id_check CHECK(image_id >= 0 and image_id < 2147483647),
  FOREIGN KEY(camera_id) REFERENCES cameras(camera_id));
CREATE TABLE keypoints (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
  cols INTEGER NOT NULL, data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE descriptors (image_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
  cols INTEGER NOT NULL, data BLOB, FOREIGN KEY(image_id) REFERENCES images(image_id) ON DELETE CASCADE);
CREATE TABLE matches (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
  cols INTEGER NOT NULL, data BLOB);
CREATE TABLE two_view_geometries (pair_id INTEGER PRIMARY KEY NOT NULL, rows INTEGER NOT NULL,
  cols INTEGER NOT NULL, data BLOB, config INTEGER NOT NULL, F BLOB, E BLOB, H BLOB, qvec BLOB,
  tvec BLOB);
";

/// Settings for a file that is thrown away on any failure: the rollback journal in memory (a
/// failed statement is still undone, and no second file sits next to the temp file), no syncs
/// (the commit fsyncs once), a 64 MiB cache, and 64 KiB pages (a street image's 180 KB of
/// descriptors is then 3 overflow pages, not 44; set before the first table).
const PRAGMAS: &str = "PRAGMA page_size = 65536; PRAGMA journal_mode = MEMORY;
PRAGMA synchronous = OFF; PRAGMA cache_size = -65536;";

/// A `database.db` being built. Keypoints are written in COLMAP's current 6-column affine
/// layout from `(x, y, scale, orientation)`.
pub struct DatabaseWriter {
    /// Declared before `out`, so dropped first: SQLite closes the temp file before it goes.
    conn: Connection,
    out: AtomicPath,
    /// Named in errors: the file this database is for.
    path: PathBuf,
}

impl DatabaseWriter {
    /// An empty database for `path`, in a temp file next to it. Refuses a `path` that
    /// exists and is not a regular file.
    pub fn new(path: &Path) -> Result<DatabaseWriter> {
        let err = |e| sqlite(path, e);
        let out = AtomicPath::create(path)?;
        // Not SQLITE_OPEN_URI: the temp path is a plain file name, whatever it contains.
        // Nor through a symlink someone put at the temp name.
        let flags = OpenFlags::SQLITE_OPEN_READ_WRITE
            | OpenFlags::SQLITE_OPEN_NO_MUTEX
            | OpenFlags::SQLITE_OPEN_NOFOLLOW;
        let conn = Connection::open_with_flags(out.temp_path(), flags).map_err(err)?;
        conn.execute_batch(PRAGMAS).map_err(err)?;
        conn.execute_batch(SCHEMA).map_err(err)?;
        conn.execute_batch("BEGIN").map_err(err)?;
        Ok(DatabaseWriter {
            conn,
            out,
            path: path.to_path_buf(),
        })
    }

    /// Adds `camera` under its own id.
    pub fn add_camera(&mut self, camera: &Camera) -> Result<()> {
        let params: Vec<u8> = camera.params.iter().flat_map(|p| p.to_le_bytes()).collect();
        self.conn
            .execute(
                "INSERT INTO cameras VALUES (?1, ?2, ?3, ?4, ?5, 0)",
                params![
                    camera.id,
                    camera.model.id(),
                    camera.width as i64,
                    camera.height as i64,
                    params
                ],
            )
            .map_err(|e| sqlite(&self.path, e))?;
        Ok(())
    }

    /// Adds image `id` with its keypoints (`(x, y, scale, orientation)`, COLMAP pixels) and
    /// `dim`-byte descriptors, one row per keypoint.
    pub fn add_image(
        &mut self,
        id: u32,
        name: &str,
        camera_id: u32,
        keypoints: &[[f32; 4]],
        descriptors: &[u8],
        dim: usize,
    ) -> Result<()> {
        if Some(descriptors.len()) != keypoints.len().checked_mul(dim) {
            return Err(Error::BadRow {
                path: self.path.clone(),
                table: "descriptors",
                id: i64::from(id),
                what: format!(
                    "{} descriptor bytes for {} keypoints of {dim}",
                    descriptors.len(),
                    keypoints.len()
                ),
            });
        }
        let affine: Vec<u8> = keypoints
            .iter()
            .flat_map(|&[x, y, scale, angle]| {
                let (s, c) = angle.sin_cos();
                [x, y, scale * c, -scale * s, scale * s, scale * c]
            })
            .flat_map(f32::to_le_bytes)
            .collect();
        let rows = keypoints.len() as i64;
        let err = |e| sqlite(&self.path, e);
        // Prepared once per writer, not per image (19,200 images on the 2.4 M-point street).
        let insert = |sql: &str, values: &[&dyn rusqlite::ToSql]| {
            self.conn
                .prepare_cached(sql)
                .and_then(|mut statement| statement.execute(values))
                .map_err(err)
        };
        insert(
            "INSERT INTO images VALUES (?1, ?2, ?3)",
            params![id, name, camera_id],
        )?;
        insert(
            "INSERT INTO keypoints VALUES (?1, ?2, 6, ?3)",
            params![id, rows, affine],
        )?;
        insert(
            "INSERT INTO descriptors VALUES (?1, ?2, ?3, ?4)",
            params![id, rows, dim as i64, descriptors],
        )?;
        Ok(())
    }

    /// Finishes the database and puts it at its path: commits, closes the temp file, fsyncs it
    /// and renames it over the path ([`AtomicPath::commit`]).
    pub fn write(self) -> Result<()> {
        // Bound so that `conn` drops (closes the file) before `out` (removes it) on an error.
        let DatabaseWriter { path, out, conn } = self;
        let err = |e| sqlite(&path, e);
        conn.execute_batch("COMMIT").map_err(err)?;
        conn.close().map_err(|(_, e)| err(e))?;
        Ok(out.commit()?)
    }
}

fn sqlite(path: &Path, e: rusqlite::Error) -> Error {
    Error::Sqlite {
        path: path.to_path_buf(),
        source: e,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colmap::{Database, KeypointLayout};
    use crate::geometry::CameraModel;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    #[test]
    fn a_written_database_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("database.db");
        std::fs::write(&path, b"an old file, replaced").unwrap();
        let mut db = DatabaseWriter::new(&path).unwrap();
        let camera = Camera {
            id: 3,
            model: CameraModel::Pinhole,
            width: 640,
            height: 480,
            params: vec![500.0, 501.0, 320.0, 240.0],
        };
        db.add_camera(&camera).unwrap();
        let keypoints = [[10.5, 20.25, 2.0, 0.5], [1.0, 2.0, 4.0, -1.0]];
        let descriptors: Vec<u8> = (0..8).collect();
        db.add_image(7, "a.jpg", 3, &keypoints, &descriptors, 4)
            .unwrap();
        assert!(db
            .add_image(8, "b.jpg", 3, &keypoints, &descriptors, 3)
            .is_err());
        db.write().unwrap();
        // Renamed into place: no temp file, no journal left.
        assert_eq!(names(dir.path()), ["database.db"]);

        let read = Database::open(&path).unwrap();
        assert_eq!(read.cameras().unwrap(), vec![camera]);
        let images = read.images().unwrap();
        assert_eq!((images[0].id, images[0].name.as_str()), (7, "a.jpg"));
        let f = read.features(7).unwrap();
        let (k, d) = (f.keypoints.unwrap(), f.descriptors.unwrap());
        assert_eq!(k.layout(), KeypointLayout::Affine);
        assert_eq!(k.xy(1), Some([1.0, 2.0]));
        assert!((k.scale(0).unwrap() - 2.0).abs() < 1e-6);
        assert!((k.get(1).unwrap().orientation() + 1.0).abs() < 1e-6);
        let mut row = Vec::new();
        assert!(d.row_into(1, &mut row));
        assert_eq!(row, [4.0, 5.0, 6.0, 7.0]);
        assert_eq!((d.dim, d.feature()), (4, "colmap-4".to_string()));
    }

    #[test]
    fn a_writer_dropped_without_write_leaves_neither_target_nor_temp() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("database.db");
        let mut db = DatabaseWriter::new(&path).unwrap();
        let camera = Camera {
            id: 1,
            model: CameraModel::SimplePinhole,
            width: 4,
            height: 4,
            params: vec![4.0, 2.0, 2.0],
        };
        db.add_camera(&camera).unwrap();
        db.add_image(1, "a.jpg", 1, &[[1.0, 2.0, 3.0, 0.0]], &[9; 4], 4)
            .unwrap();
        // SQLite writes a temp file next to the target, not the target.
        let [temp] = &names(dir.path())[..] else {
            panic!("{:?}", names(dir.path()));
        };
        assert!(temp.starts_with(".database.db."), "{temp}");
        drop(db);
        assert!(names(dir.path()).is_empty(), "{:?}", names(dir.path()));
        // Nor does it touch an existing target, and it refuses one that is not a file.
        std::fs::write(&path, b"old").unwrap();
        drop(DatabaseWriter::new(&path).unwrap());
        assert_eq!(std::fs::read(&path).unwrap(), b"old");
        assert_eq!(names(dir.path()), ["database.db"]);
        assert!(DatabaseWriter::new(dir.path()).is_err());
    }
}
