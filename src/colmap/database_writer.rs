//! Writing a COLMAP `database.db`: cameras, images, keypoints and descriptors, in COLMAP's
//! current schema (plus its empty `matches` and `two_view_geometries` tables), readable by
//! COLMAP, pycolmap and [`super::Database`].
//!
//! The database is built in memory and written at [`DatabaseWriter::write`] through the
//! crate's one atomic writer (temp file, fsync, rename): SQLite writing in place would leave
//! a half-written file (and journals) behind on a failure. The cost: the database is in
//! memory once (SQLite's memdb, serialized without a copy; 1.6 GB for the 1 M-point street).

use std::path::{Path, PathBuf};

use rusqlite::{params, Connection, OpenFlags, MAIN_DB};

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

/// The most a database may grow to in memory. memdb's default, 1 GiB, is less than the
/// 1 M-point street's 1.6 GB; the buffer only grows as rows are added.
const MEMDB_MAX_BYTES: i64 = 1 << 40;

/// Sets the memdb VFS's size limit of `conn`'s main database to `bytes` (a negative value
/// changes nothing) and returns the limit now in force.
///
/// Why unsafe: SQLite sets this limit only through `sqlite3_file_control`, which rusqlite
/// does not wrap. The alternative, a compile-time `SQLITE_MEMDB_DEFAULT_MAXSIZE`, would not
/// reach users who build the crate without this repository's build settings.
#[allow(unsafe_code)]
fn memdb_limit(conn: &Connection, bytes: i64) -> rusqlite::Result<i64> {
    use rusqlite::ffi;
    let mut limit: ffi::sqlite3_int64 = bytes;
    // SAFETY: `handle` is `conn`'s open database, used on this thread only for the call;
    // "main" is a NUL-terminated name; SQLITE_FCNTL_SIZE_LIMIT reads and writes one
    // sqlite3_int64 through the pointer, which points at `limit`, alive for the call.
    let rc = unsafe {
        ffi::sqlite3_file_control(
            conn.handle(),
            c"main".as_ptr(),
            ffi::SQLITE_FCNTL_SIZE_LIMIT,
            (&mut limit as *mut ffi::sqlite3_int64).cast(),
        )
    };
    if rc != ffi::SQLITE_OK {
        return Err(rusqlite::Error::SqliteFailure(ffi::Error::new(rc), None));
    }
    Ok(limit)
}

/// A `database.db` being built. Keypoints are written in COLMAP's current 6-column affine
/// layout from `(x, y, scale, orientation)`.
pub struct DatabaseWriter {
    conn: Connection,
    /// Named in errors: the file this database is for.
    path: PathBuf,
}

impl DatabaseWriter {
    /// An empty database in memory, for `path`.
    pub fn new(path: &Path) -> Result<DatabaseWriter> {
        let err = |e| sqlite(path, e);
        // SQLite's memdb VFS keeps the database in one buffer that `serialize` can hand out
        // without a copy (a plain in-memory database is copied: twice the memory).
        let flags = OpenFlags::SQLITE_OPEN_READ_WRITE
            | OpenFlags::SQLITE_OPEN_CREATE
            | OpenFlags::SQLITE_OPEN_URI
            | OpenFlags::SQLITE_OPEN_NO_MUTEX;
        let conn =
            Connection::open_with_flags("file:sfpmap-database?vfs=memdb", flags).map_err(err)?;
        memdb_limit(&conn, MEMDB_MAX_BYTES).map_err(err)?;
        conn.execute_batch(SCHEMA).map_err(err)?;
        conn.execute_batch("BEGIN").map_err(err)?;
        Ok(DatabaseWriter {
            conn,
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
        self.conn
            .execute(
                "INSERT INTO images VALUES (?1, ?2, ?3)",
                params![id, name, camera_id],
            )
            .map_err(err)?;
        self.conn
            .execute(
                "INSERT INTO keypoints VALUES (?1, ?2, 6, ?3)",
                params![id, rows, affine],
            )
            .map_err(err)?;
        self.conn
            .execute(
                "INSERT INTO descriptors VALUES (?1, ?2, ?3, ?4)",
                params![id, rows, dim as i64, descriptors],
            )
            .map_err(err)?;
        Ok(())
    }

    /// Writes the database to its path through [`crate::output::write_atomic`].
    pub fn write(self) -> Result<()> {
        let err = |e| sqlite(&self.path, e);
        self.conn.execute_batch("COMMIT").map_err(err)?;
        let bytes = self.conn.serialize(MAIN_DB).map_err(err)?;
        Ok(crate::output::write_bytes(&self.path, &bytes)?)
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

    #[test]
    fn a_database_may_grow_past_memdbs_default_gigabyte() {
        let dir = tempfile::tempdir().unwrap();
        let db = DatabaseWriter::new(&dir.path().join("database.db")).unwrap();
        assert_eq!(memdb_limit(&db.conn, -1).unwrap(), MEMDB_MAX_BYTES);
        const { assert!(MEMDB_MAX_BYTES > 2 << 30) };
    }

    #[test]
    fn a_written_database_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("database.db");
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
        assert_eq!(d.row(1), Some(&descriptors[4..]));
    }
}
