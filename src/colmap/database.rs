//! COLMAP `database.db`: cameras, images, keypoints and descriptors.
//!
//! The tables read here have kept their layout since 2017: `cameras(camera_id, model, width,
//! height, params)`, `images(image_id, name, camera_id, …)`, `keypoints(image_id, rows, cols,
//! data)` and `descriptors(image_id, rows, cols, data)`, plus a `type` column in
//! `descriptors` since COLMAP 3.12 (0 = SIFT). Columns are found with `PRAGMA table_info`, so
//! both schemas (and extra columns such as the old `prior_*`) work. Blobs are little-endian
//! row-major matrices: keypoints `f32`, descriptors `u8` (SIFT) or `f32` (a learned feature's
//! `type`), camera params `f64`.

use std::path::{Path, PathBuf};

use rusqlite::{Connection, OpenFlags, OptionalExtension};

use super::error::{Error, Result};
use super::model::Camera;
use crate::geometry::CameraModel;

/// An image row of the database.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DbImage {
    /// `image_id`.
    pub id: u32,
    /// The image's name, relative to the images folder.
    pub name: String,
    /// The camera it was taken with (the `cameras` table's `camera_id`).
    pub camera_id: u32,
}

/// What the columns of a keypoints blob mean (COLMAP's `FeatureKeypointsFromBlob`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum KeypointLayout {
    /// `x, y`: location only.
    Xy,
    /// `x, y, scale, orientation` (COLMAP until 2018, e.g. the 2017 schema).
    ScaleOrientation,
    /// `x, y, a11, a12, a21, a22`: the affine shape, columns of `A` mapping the unit circle
    /// to the feature's ellipse (COLMAP since 2018).
    Affine,
}

impl KeypointLayout {
    fn from_cols(cols: i64) -> Option<Self> {
        match cols {
            2 => Some(KeypointLayout::Xy),
            4 => Some(KeypointLayout::ScaleOrientation),
            6 => Some(KeypointLayout::Affine),
            _ => None,
        }
    }

    /// Columns per row.
    pub fn cols(self) -> usize {
        match self {
            KeypointLayout::Xy => 2,
            KeypointLayout::ScaleOrientation => 4,
            KeypointLayout::Affine => 6,
        }
    }
}

/// One keypoint in COLMAP's affine form (`FeatureKeypoint`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    /// x of the keypoint, COLMAP pixels (the top-left pixel's centre at 0.5).
    pub x: f32,
    /// y of the keypoint, COLMAP pixels.
    pub y: f32,
    /// Affine shape `A = [[a11, a12], [a21, a22]]`: maps the unit circle to the feature's
    /// ellipse (scale and orientation in one).
    pub a11: f32,
    /// See `a11`.
    pub a12: f32,
    /// See `a11`.
    pub a21: f32,
    /// See `a11`.
    pub a22: f32,
}

impl Keypoint {
    /// The feature's scale in pixels: the mean of the norms of the columns of `A`.
    ///
    /// Why this and not `sqrt(|det A|)`: it is COLMAP's own `FeatureKeypoint::ComputeScale`,
    /// so scales (and the levels derived from them) agree with what COLMAP reports. For SIFT
    /// the shape is a scaled rotation, where both definitions give the same value; they differ
    /// only for anisotropic (affine-adapted) shapes, where the mean of the two axis lengths
    /// is also less sensitive to a near-degenerate axis than the area.
    pub fn scale(&self) -> f32 {
        let sx = (self.a11 * self.a11 + self.a21 * self.a21).sqrt();
        let sy = (self.a12 * self.a12 + self.a22 * self.a22).sqrt();
        (sx + sy) / 2.0
    }

    /// The orientation in radians (COLMAP's `ComputeOrientation`).
    pub fn orientation(&self) -> f32 {
        self.a21.atan2(self.a11)
    }
}

/// The keypoints of one image.
#[derive(Debug, Clone, PartialEq)]
pub struct Keypoints {
    layout: KeypointLayout,
    /// Row-major, `layout.cols()` values per keypoint.
    data: Vec<f32>,
}

impl Keypoints {
    /// Keypoints from row-major values; `None` if `data` is not whole rows.
    pub fn new(layout: KeypointLayout, data: Vec<f32>) -> Option<Self> {
        (data.len() % layout.cols() == 0).then_some(Keypoints { layout, data })
    }

    /// What the rows' columns mean.
    pub fn layout(&self) -> KeypointLayout {
        self.layout
    }

    /// How many keypoints.
    pub fn len(&self) -> usize {
        self.data.len() / self.layout.cols()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The raw row-major values as stored.
    pub fn raw(&self) -> &[f32] {
        &self.data
    }

    fn row(&self, i: usize) -> Option<&[f32]> {
        let cols = self.layout.cols();
        self.data
            .get(i.checked_mul(cols)?..i.checked_add(1)?.checked_mul(cols)?)
    }

    /// Location of keypoint `i` (COLMAP pixel convention: top-left pixel centre at 0.5, 0.5).
    pub fn xy(&self, i: usize) -> Option<[f32; 2]> {
        self.row(i).map(|r| [r[0], r[1]])
    }

    /// Keypoint `i` in affine form, converted as COLMAP does: a 2-column keypoint gets the
    /// identity shape, a 4-column one `A = scale · R(orientation)`.
    pub fn get(&self, i: usize) -> Option<Keypoint> {
        let r = self.row(i)?;
        let (x, y) = (r[0], r[1]);
        Some(match self.layout {
            KeypointLayout::Xy => Keypoint {
                x,
                y,
                a11: 1.0,
                a12: 0.0,
                a21: 0.0,
                a22: 1.0,
            },
            KeypointLayout::ScaleOrientation => {
                let (scale, (sin, cos)) = (r[2], r[3].sin_cos());
                Keypoint {
                    x,
                    y,
                    a11: scale * cos,
                    a12: -scale * sin,
                    a21: scale * sin,
                    a22: scale * cos,
                }
            }
            KeypointLayout::Affine => Keypoint {
                x,
                y,
                a11: r[2],
                a12: r[3],
                a21: r[4],
                a22: r[5],
            },
        })
    }

    /// Scale of keypoint `i` in pixels; `None` past the end or for a 2-column layout, which
    /// stores no shape. 4 columns: the stored scale; 6 columns: [`Keypoint::scale`].
    pub fn scale(&self, i: usize) -> Option<f32> {
        match self.layout {
            KeypointLayout::Xy => None,
            KeypointLayout::ScaleOrientation => self.row(i).map(|r| r[2]),
            KeypointLayout::Affine => self.get(i).map(|k| k.scale()),
        }
    }

    /// The first keypoint whose x, y or scale ([`scale`](Self::scale)) is NaN or infinite,
    /// as `(index, "x" | "y" | "scale", value)`. Callers refuse such keypoints naming the
    /// image: a NaN position or scale would reach matching and pose estimation unchecked.
    pub fn first_non_finite(&self) -> Option<(usize, &'static str, f32)> {
        (0..self.len()).find_map(|i| {
            let [x, y] = self.xy(i)?;
            let scale = self.scale(i).unwrap_or(1.0);
            [("x", x), ("y", y), ("scale", scale)]
                .into_iter()
                .find(|(_, v)| !v.is_finite())
                .map(|(field, v)| (i, field, v))
        })
    }
}

/// The `type` of SIFT descriptors in COLMAP's `descriptors` table (`FeatureExtractorType`).
const SIFT_DESCRIPTOR_TYPE: i64 = 0;

/// A descriptor `type` of COLMAP's `descriptors` table (`pycolmap.FeatureExtractorType`, COLMAP
/// 4.2): its name there, the name maps record for it, and whether its rows are f32 values.
/// COLMAP keeps every learned feature's descriptors as little-endian f32 bytes (`cols` = 4 ×
/// dimensions); only SIFT's are u8.
struct DescriptorType {
    colmap: &'static str,
    feature: &'static str,
    float: bool,
}

/// The types COLMAP 4.2 defines with a fixed layout; `UNDEFINED` (-1) and any other value are
/// refused (no layout to read them by).
fn descriptor_type(t: i64) -> Option<DescriptorType> {
    let (colmap, feature, float) = match t {
        0 => ("SIFT", "sift", false),
        1 => ("ALIKED_N16ROT", "aliked-n16rot", true),
        2 => ("ALIKED_N32", "aliked-n32", true),
        3 => ("LOMA_B", "loma-b", true),
        4 => ("LOMA_B128", "loma-b128", true),
        _ => return None,
    };
    Some(DescriptorType {
        colmap,
        feature,
        float,
    })
}

/// The name COLMAP 4.2 gives a descriptor `type`, for messages.
fn descriptor_type_name(t: i64) -> &'static str {
    match (t, descriptor_type(t)) {
        (_, Some(d)) => d.colmap,
        (-1, None) => "UNDEFINED",
        _ => "a type COLMAP 4.2 does not define",
    }
}

/// Descriptor values as a database (or another feature store) keeps them, row-major.
#[derive(Debug, Clone, PartialEq)]
pub enum DescriptorValues {
    /// SIFT's bytes.
    U8(Vec<u8>),
    /// A learned feature's floats (ALIKED, DISK, LoMa, …).
    F32(Vec<f32>),
}

impl DescriptorValues {
    /// Row `i` of `dim` values widened to f32 into `out` (cleared first); `false` if there is
    /// no such row.
    pub fn row_into(&self, dim: usize, i: usize, out: &mut Vec<f32>) -> bool {
        out.clear();
        let Some(range) = i
            .checked_mul(dim)
            .and_then(|s| Some(s..s.checked_add(dim)?))
        else {
            return false;
        };
        match self {
            DescriptorValues::U8(v) => v
                .get(range)
                .map(|r| out.extend(r.iter().map(|&b| f32::from(b)))),
            DescriptorValues::F32(v) => v.get(range).map(|r| out.extend_from_slice(r)),
        }
        .is_some()
    }
}

/// The descriptors of one image: `len() × dim` values, row `i` for keypoint `i`.
#[derive(Debug, Clone, PartialEq)]
pub struct Descriptors {
    /// Values per descriptor (128 for SIFT; a float type's `cols` is 4 × this).
    pub dim: usize,
    /// The `type` column where the schema has one (COLMAP ≥ 3.12; 0 = SIFT), else `None`
    /// (older databases only held SIFT).
    pub type_id: Option<i64>,
    /// Row-major values.
    pub values: DescriptorValues,
}

impl Descriptors {
    /// How many descriptors (rows).
    pub fn len(&self) -> usize {
        let n = match &self.values {
            DescriptorValues::U8(v) => v.len(),
            DescriptorValues::F32(v) => v.len(),
        };
        n.checked_div(self.dim).unwrap_or(0)
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The feature maps record for these descriptors: `sift`, `aliked-n16rot`, `aliked-n32`,
    /// `loma-b`, `loma-b128`; SIFT-like bytes of another length than 128 (an old tool's)
    /// `colmap-<dim>`.
    pub fn feature(&self) -> String {
        match self.type_id.and_then(descriptor_type) {
            Some(t) if t.float => t.feature.to_owned(),
            _ if self.dim == 128 => "sift".to_owned(),
            _ => format!("colmap-{}", self.dim),
        }
    }

    /// Descriptor `i` widened to f32 into `out` (cleared first); `false` if there is none.
    pub fn row_into(&self, i: usize, out: &mut Vec<f32>) -> bool {
        self.values.row_into(self.dim, i, out)
    }
}

/// One image with its features; either may be absent from the database.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageFeatures {
    /// The image row.
    pub image: DbImage,
    /// Its keypoints, if the database has any.
    pub keypoints: Option<Keypoints>,
    /// Its descriptors, if the database has any.
    pub descriptors: Option<Descriptors>,
}

/// A `(rows, cols, data)` matrix row, its blob size checked.
struct RawMatrix {
    rows: usize,
    cols: usize,
    type_id: Option<i64>,
    data: Vec<u8>,
}

/// A COLMAP database, open read-only.
#[derive(Debug)]
pub struct Database {
    conn: Connection,
    path: PathBuf,
    descriptors_have_type: bool,
}

const TABLES: [(&str, &[&str]); 4] = [
    (
        "cameras",
        &["camera_id", "model", "width", "height", "params"],
    ),
    ("images", &["image_id", "name", "camera_id"]),
    ("keypoints", &["image_id", "rows", "cols", "data"]),
    ("descriptors", &["image_id", "rows", "cols", "data"]),
];

/// `file:` URI path: percent-encode everything but unreserved characters and `/`, so `?`,
/// `#` and `%` in a file name cannot end the path or start an escape.
fn uri_path(path: &Path) -> String {
    let mut out = String::new();
    for &b in path.as_os_str().as_encoded_bytes() {
        if b.is_ascii_alphanumeric() || b"-._~/".contains(&b) {
            out.push(b as char);
        } else {
            out.push_str(&format!("%{b:02X}"));
        }
    }
    out
}

impl Database {
    /// Opens `path` read-only and immutable; it must be a regular file
    /// ([`Error::NotAFile`] otherwise).
    ///
    /// `immutable=1` tells SQLite the file cannot change: it takes no locks and never
    /// creates `-wal`/`-shm`/journal files, so the user's database is left byte-identical
    /// (a plain read-only open of a WAL database would create them). Consequence: SQLite
    /// ignores a `-wal` file then, so a non-empty one is an error ([`Error::PendingWal`])
    /// rather than a silently stale read.
    pub fn open(path: &Path) -> Result<Database> {
        let io = |source| Error::Io {
            path: path.to_path_buf(),
            source,
        };
        // SQLite would open a FIFO and wait for a writer, and a folder gives a vague error.
        super::check_regular_path(path)?;
        let mut wal = path.as_os_str().to_owned();
        wal.push("-wal");
        let wal = PathBuf::from(wal);
        if std::fs::metadata(&wal).is_ok_and(|m| m.len() > 0) {
            return Err(Error::PendingWal {
                path: path.to_path_buf(),
                wal,
            });
        }
        let absolute = std::path::absolute(path).map_err(io)?;
        let uri = format!("file:{}?mode=ro&immutable=1", uri_path(&absolute));
        let flags = OpenFlags::SQLITE_OPEN_READ_ONLY
            | OpenFlags::SQLITE_OPEN_URI
            | OpenFlags::SQLITE_OPEN_NO_MUTEX;
        let conn = Connection::open_with_flags(&uri, flags).map_err(|e| sqlite(path, e))?;
        let mut db = Database {
            conn,
            path: path.to_path_buf(),
            descriptors_have_type: false,
        };
        for (table, columns) in TABLES {
            let present = db.columns(table)?;
            if present.is_empty() {
                return Err(Error::MissingTable {
                    path: db.path.clone(),
                    table,
                });
            }
            if let Some(column) = columns.iter().find(|c| !present.iter().any(|p| p == *c)) {
                return Err(Error::MissingColumn {
                    path: db.path.clone(),
                    table,
                    column,
                });
            }
            if table == "descriptors" {
                db.descriptors_have_type = present.iter().any(|p| p == "type");
            }
        }
        Ok(db)
    }

    /// The path given to [`open`](Self::open).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether `descriptors` has the `type` column (COLMAP ≥ 3.12 schema).
    pub fn descriptors_have_type(&self) -> bool {
        self.descriptors_have_type
    }

    /// Column names of `table`; empty if there is no such table. The first query on the file,
    /// so this is where a non-database file shows.
    fn columns(&self, table: &str) -> Result<Vec<String>> {
        let mut stmt = self
            .conn
            .prepare("SELECT name FROM pragma_table_info(?1)")
            .map_err(|e| self.err(e))?;
        let rows = stmt
            .query_map([table], |row| row.get::<_, String>(0))
            .map_err(|e| self.err(e))?;
        rows.collect::<rusqlite::Result<Vec<_>>>()
            .map_err(|e| self.err(e))
    }

    fn err(&self, e: rusqlite::Error) -> Error {
        sqlite(&self.path, e)
    }

    fn bad_row(&self, table: &'static str, id: i64, what: String) -> Error {
        Error::BadRow {
            path: self.path.clone(),
            table,
            id,
            what,
        }
    }

    /// `value`, a u32 id column of row `row_id`, checked.
    fn id_u32(&self, table: &'static str, row_id: i64, value: i64, what: &str) -> Result<u32> {
        u32::try_from(value)
            .map_err(|_| self.bad_row(table, row_id, format!("{what} {value} out of range")))
    }

    /// All cameras, sorted by id, parameter counts checked against the model and every
    /// parameter finite.
    pub fn cameras(&self) -> Result<Vec<Camera>> {
        let mut stmt = self
            .conn
            .prepare(
                "SELECT camera_id, model, width, height, params FROM cameras ORDER BY camera_id",
            )
            .map_err(|e| self.err(e))?;
        let mut rows = stmt.query([]).map_err(|e| self.err(e))?;
        let mut cameras = Vec::new();
        while let Some(row) = rows.next().map_err(|e| self.err(e))? {
            let id: i64 = row.get(0).map_err(|e| self.err(e))?;
            let model_id: i64 = row.get(1).map_err(|e| self.err(e))?;
            let width: i64 = row.get(2).map_err(|e| self.err(e))?;
            let height: i64 = row.get(3).map_err(|e| self.err(e))?;
            let params: Option<Vec<u8>> = row.get(4).map_err(|e| self.err(e))?;
            let camera_id = self.id_u32("cameras", id, id, "camera_id")?;
            let model = i32::try_from(model_id)
                .ok()
                .and_then(CameraModel::from_id)
                .ok_or_else(|| Error::UnknownCameraModelId {
                    path: self.path.clone(),
                    camera_id,
                    model_id,
                })?;
            let (Ok(width), Ok(height)) = (u64::try_from(width), u64::try_from(height)) else {
                return Err(self.bad_row("cameras", id, "negative width or height".into()));
            };
            let params = params.unwrap_or_default();
            if params.len() % 8 != 0 {
                return Err(self.bad_row(
                    "cameras",
                    id,
                    format!("params blob of {} bytes is not whole f64s", params.len()),
                ));
            }
            let params: Vec<f64> = params
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
                .collect();
            if params.len() != model.num_params() {
                return Err(Error::ParamCount {
                    path: self.path.clone(),
                    camera_id,
                    model: model.name(),
                    expected: model.num_params(),
                    found: params.len(),
                });
            }
            if let Some(field) = super::model::non_finite_param(&params) {
                return Err(Error::NotFinite {
                    path: self.path.clone(),
                    line: None,
                    kind: "camera",
                    id: camera_id.into(),
                    field,
                });
            }
            cameras.push(Camera {
                id: camera_id,
                model,
                width,
                height,
                params,
            });
        }
        Ok(cameras)
    }

    /// All images (id, name, camera), sorted by id.
    pub fn images(&self) -> Result<Vec<DbImage>> {
        let mut stmt = self
            .conn
            .prepare("SELECT image_id, name, camera_id FROM images ORDER BY image_id")
            .map_err(|e| self.err(e))?;
        let mut rows = stmt.query([]).map_err(|e| self.err(e))?;
        let mut images = Vec::new();
        while let Some(row) = rows.next().map_err(|e| self.err(e))? {
            let id: i64 = row.get(0).map_err(|e| self.err(e))?;
            let name: String = row.get(1).map_err(|e| self.err(e))?;
            let camera_id: i64 = row.get(2).map_err(|e| self.err(e))?;
            let image_id = self.id_u32("images", id, id, "image_id")?;
            // The model readers' rule: such a name would inject lines into every text export.
            if super::model::has_control_character(&name) {
                return Err(Error::BadImageName {
                    path: self.path.clone(),
                    line: None,
                    image_id,
                    name: super::error::shown_name(&name),
                });
            }
            images.push(DbImage {
                id: image_id,
                name,
                camera_id: self.id_u32("images", id, camera_id, "camera_id")?,
            });
        }
        Ok(images)
    }

    /// The image with id `image_id`, if any.
    pub fn image(&self, image_id: u32) -> Result<Option<DbImage>> {
        let mut stmt = self
            .conn
            .prepare_cached("SELECT name, camera_id FROM images WHERE image_id = ?1")
            .map_err(|e| self.err(e))?;
        let row = stmt
            .query_row([image_id], |row| {
                Ok((row.get::<_, String>(0)?, row.get::<_, i64>(1)?))
            })
            .optional()
            .map_err(|e| self.err(e))?;
        match row {
            None => Ok(None),
            Some((name, camera_id)) => Ok(Some(DbImage {
                id: image_id,
                name,
                camera_id: self.id_u32("images", i64::from(image_id), camera_id, "camera_id")?,
            })),
        }
    }

    /// Number of keypoints of image `image_id` without reading the blob; `None` if the image
    /// has no keypoints row.
    pub fn num_keypoints(&self, image_id: u32) -> Result<Option<u64>> {
        let mut stmt = self
            .conn
            .prepare_cached("SELECT rows FROM keypoints WHERE image_id = ?1")
            .map_err(|e| self.err(e))?;
        let rows: Option<i64> = stmt
            .query_row([image_id], |row| row.get(0))
            .optional()
            .map_err(|e| self.err(e))?;
        rows.map(|r| {
            u64::try_from(r)
                .map_err(|_| self.bad_row("keypoints", i64::from(image_id), "negative rows".into()))
        })
        .transpose()
    }

    /// Reads a `(rows, cols, data)` matrix row of `table`, checking the blob size.
    fn matrix(
        &self,
        table: &'static str,
        sql: &str,
        image_id: u32,
        elem: usize,
    ) -> Result<Option<RawMatrix>> {
        let mut stmt = self.conn.prepare_cached(sql).map_err(|e| self.err(e))?;
        let row = stmt
            .query_row([image_id], |row| {
                let kind = if row.as_ref().column_count() > 3 {
                    row.get::<_, Option<i64>>(3)?
                } else {
                    None
                };
                Ok((
                    row.get::<_, i64>(0)?,
                    row.get::<_, i64>(1)?,
                    row.get::<_, Option<Vec<u8>>>(2)?,
                    kind,
                ))
            })
            .optional()
            .map_err(|e| self.err(e))?;
        let Some((rows, cols, data, kind)) = row else {
            return Ok(None);
        };
        let id = i64::from(image_id);
        let (Ok(rows_u), Ok(cols_u)) = (usize::try_from(rows), usize::try_from(cols)) else {
            return Err(self.bad_row(table, id, format!("bad shape {rows} x {cols}")));
        };
        let data = data.unwrap_or_default();
        let expected = rows_u.checked_mul(cols_u).and_then(|n| n.checked_mul(elem));
        if expected != Some(data.len()) {
            return Err(self.bad_row(
                table,
                id,
                format!(
                    "blob of {} bytes does not hold {rows} x {cols} values of {elem} bytes",
                    data.len()
                ),
            ));
        }
        Ok(Some(RawMatrix {
            rows: rows_u,
            cols: cols_u,
            type_id: kind,
            data,
        }))
    }

    /// The keypoints of image `image_id`; `None` if it has no keypoints row.
    pub fn keypoints(&self, image_id: u32) -> Result<Option<Keypoints>> {
        let sql = "SELECT rows, cols, data FROM keypoints WHERE image_id = ?1";
        let Some(RawMatrix {
            rows, cols, data, ..
        }) = self.matrix("keypoints", sql, image_id, 4)?
        else {
            return Ok(None);
        };
        // An image without keypoints may be stored as 0 x 0; any layout describes it.
        let layout = KeypointLayout::from_cols(cols as i64);
        let layout = layout
            .or((rows == 0).then_some(KeypointLayout::Affine))
            .ok_or_else(|| {
                self.bad_row(
                    "keypoints",
                    i64::from(image_id),
                    format!("{cols} columns; COLMAP keypoints have 2, 4 or 6"),
                )
            })?;
        let data = data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap_or([0; 4])))
            .collect();
        Ok(Some(Keypoints { layout, data }))
    }

    /// The descriptors of image `image_id`; `None` if it has no descriptors row. A typed
    /// database's rows are read by their `type` (SIFT's u8, a learned feature's f32); a type
    /// without a layout is an error naming it and the image, never bytes misread.
    pub fn descriptors(&self, image_id: u32) -> Result<Option<Descriptors>> {
        let sql = if self.descriptors_have_type {
            "SELECT rows, cols, data, type FROM descriptors WHERE image_id = ?1"
        } else {
            "SELECT rows, cols, data FROM descriptors WHERE image_id = ?1"
        };
        let Some(RawMatrix {
            cols,
            type_id,
            data,
            ..
        }) = self.matrix("descriptors", sql, image_id, 1)?
        else {
            return Ok(None);
        };
        let id = i64::from(image_id);
        let t = type_id.unwrap_or(SIFT_DESCRIPTOR_TYPE);
        let Some(kind) = descriptor_type(t) else {
            return Err(self.bad_row(
                "descriptors",
                id,
                format!(
                    "type {t} ({}): no descriptor layout is known for it (SIFT is type 0)",
                    descriptor_type_name(t)
                ),
            ));
        };
        let (dim, values) = if kind.float {
            if cols % 4 != 0 {
                return Err(self.bad_row(
                    "descriptors",
                    id,
                    format!(
                        "type {t} ({}): {cols} columns are not whole f32 values",
                        kind.colmap
                    ),
                ));
            }
            let values = data
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            (cols / 4, DescriptorValues::F32(values))
        } else {
            (cols, DescriptorValues::U8(data))
        };
        Ok(Some(Descriptors {
            dim,
            type_id,
            values,
        }))
    }

    /// Image `image_id` with its keypoints and descriptors; an error if the image is not in
    /// the database or its keypoint and descriptor counts differ.
    pub fn features(&self, image_id: u32) -> Result<ImageFeatures> {
        let image = self
            .image(image_id)?
            .ok_or_else(|| Error::ImageNotInDatabase {
                path: self.path.clone(),
                image_id,
            })?;
        self.features_of(image)
    }

    fn features_of(&self, image: DbImage) -> Result<ImageFeatures> {
        let keypoints = self.keypoints(image.id)?;
        let mut descriptors = self.descriptors(image.id)?;
        // An empty descriptors row next to keypoints is how some tools leave an image whose
        // descriptors were never computed: report it as missing, not as a mismatch.
        if descriptors.as_ref().is_some_and(|d| d.is_empty())
            && keypoints.as_ref().is_some_and(|k| !k.is_empty())
        {
            descriptors = None;
        }
        if let (Some(k), Some(d)) = (&keypoints, &descriptors) {
            if k.len() != d.len() {
                return Err(self.bad_row(
                    "descriptors",
                    i64::from(image.id),
                    format!("{} descriptors for {} keypoints", d.len(), k.len()),
                ));
            }
        }
        Ok(ImageFeatures {
            image,
            keypoints,
            descriptors,
        })
    }

    /// Streams every image (by id) with its features, one image in memory at a time.
    /// The iterator ends for good after the first error.
    pub fn iter_features(&self) -> Result<ImageFeaturesIter<'_>> {
        Ok(ImageFeaturesIter {
            db: self,
            images: self.images()?.into_iter(),
            failed: false,
        })
    }
}

/// Iterator of [`Database::iter_features`].
#[derive(Debug)]
pub struct ImageFeaturesIter<'db> {
    db: &'db Database,
    images: std::vec::IntoIter<DbImage>,
    failed: bool,
}

impl ImageFeaturesIter<'_> {
    /// Images not yet yielded.
    pub fn remaining(&self) -> usize {
        self.images.len()
    }
}

impl Iterator for ImageFeaturesIter<'_> {
    type Item = Result<ImageFeatures>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        let image = self.images.next()?;
        let item = self.db.features_of(image);
        self.failed = item.is_err();
        Some(item)
    }
}

fn sqlite(path: &Path, e: rusqlite::Error) -> Error {
    if e.sqlite_error_code() == Some(rusqlite::ErrorCode::NotADatabase) {
        Error::NotADatabase {
            path: path.to_path_buf(),
        }
    } else {
        Error::Sqlite {
            path: path.to_path_buf(),
            source: e,
        }
    }
}
