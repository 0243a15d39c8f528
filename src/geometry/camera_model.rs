//! COLMAP camera models: ids, names, parameter counts and names.
//!
//! Ids and counts follow COLMAP 4 (`src/colmap/sensor/models/base.h`, the `CameraModelId`
//! enum, and the per-model `*_CAMERA_MODEL_DEFINITIONS` in `sensor/models/*.h`). The id is what
//! `cameras.bin` and `database.db` store; the name is what `cameras.txt` stores.

/// A COLMAP camera model. The discriminant is COLMAP's model id.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[non_exhaustive]
pub enum CameraModel {
    /// `f, cx, cy`
    SimplePinhole = 0,
    /// `fx, fy, cx, cy`
    Pinhole = 1,
    /// `f, cx, cy, k`
    SimpleRadial = 2,
    /// `f, cx, cy, k1, k2`
    Radial = 3,
    /// `fx, fy, cx, cy, k1, k2, p1, p2`
    OpenCv = 4,
    /// `fx, fy, cx, cy, k1, k2, k3, k4`
    OpenCvFisheye = 5,
    /// `fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6`
    FullOpenCv = 6,
    /// `fx, fy, cx, cy, omega`
    Fov = 7,
    /// `f, cx, cy, k`
    SimpleRadialFisheye = 8,
    /// `f, cx, cy, k1, k2`
    RadialFisheye = 9,
    /// `fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1`
    ThinPrismFisheye = 10,
    /// `fx, fy, cx, cy, k0..k5, p0, p1, s0..s3`
    RadTanThinPrismFisheye = 11,
    /// `f, cx, cy, k`
    SimpleDivision = 12,
    /// `fx, fy, cx, cy, k`
    Division = 13,
    /// `f, cx, cy`
    SimpleFisheye = 14,
    /// `fx, fy, cx, cy`
    Fisheye = 15,
    /// `fx, fy, cx, cy, alpha, beta`
    Eucm = 16,
    /// `w, h` (an omnidirectional panorama: the params are image dimensions, not a focal length)
    Equirectangular = 17,
}

/// Every model in id order, with its name, parameter count and parameter names; the one table
/// the methods read.
const MODELS: [(CameraModel, &str, usize, &str); 18] = [
    (CameraModel::SimplePinhole, "SIMPLE_PINHOLE", 3, "f, cx, cy"),
    (CameraModel::Pinhole, "PINHOLE", 4, "fx, fy, cx, cy"),
    (
        CameraModel::SimpleRadial,
        "SIMPLE_RADIAL",
        4,
        "f, cx, cy, k",
    ),
    (CameraModel::Radial, "RADIAL", 5, "f, cx, cy, k1, k2"),
    (
        CameraModel::OpenCv,
        "OPENCV",
        8,
        "fx, fy, cx, cy, k1, k2, p1, p2",
    ),
    (
        CameraModel::OpenCvFisheye,
        "OPENCV_FISHEYE",
        8,
        "fx, fy, cx, cy, k1, k2, k3, k4",
    ),
    (
        CameraModel::FullOpenCv,
        "FULL_OPENCV",
        12,
        "fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6",
    ),
    (CameraModel::Fov, "FOV", 5, "fx, fy, cx, cy, omega"),
    (
        CameraModel::SimpleRadialFisheye,
        "SIMPLE_RADIAL_FISHEYE",
        4,
        "f, cx, cy, k",
    ),
    (
        CameraModel::RadialFisheye,
        "RADIAL_FISHEYE",
        5,
        "f, cx, cy, k1, k2",
    ),
    (
        CameraModel::ThinPrismFisheye,
        "THIN_PRISM_FISHEYE",
        12,
        "fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, sx1, sy1",
    ),
    (
        CameraModel::RadTanThinPrismFisheye,
        "RAD_TAN_THIN_PRISM_FISHEYE",
        16,
        "fx, fy, cx, cy, k0, k1, k2, k3, k4, k5, p0, p1, s0, s1, s2, s3",
    ),
    (
        CameraModel::SimpleDivision,
        "SIMPLE_DIVISION",
        4,
        "f, cx, cy, k",
    ),
    (CameraModel::Division, "DIVISION", 5, "fx, fy, cx, cy, k"),
    (CameraModel::SimpleFisheye, "SIMPLE_FISHEYE", 3, "f, cx, cy"),
    (CameraModel::Fisheye, "FISHEYE", 4, "fx, fy, cx, cy"),
    (CameraModel::Eucm, "EUCM", 6, "fx, fy, cx, cy, alpha, beta"),
    (CameraModel::Equirectangular, "EQUIRECTANGULAR", 2, "w, h"),
];

impl CameraModel {
    /// All models in id order.
    pub const ALL: [CameraModel; 18] = {
        let mut all = [CameraModel::SimplePinhole; 18];
        let mut i = 0;
        while i < MODELS.len() {
            all[i] = MODELS[i].0;
            i += 1;
        }
        all
    };

    /// COLMAP's model id, as stored in `cameras.bin` and `database.db`.
    pub const fn id(self) -> i32 {
        self as i32
    }

    /// COLMAP's model name, as stored in `cameras.txt` (`"SIMPLE_RADIAL"`).
    pub const fn name(self) -> &'static str {
        MODELS[self as usize].1
    }

    /// The number of parameters COLMAP stores for this model.
    pub const fn num_params(self) -> usize {
        MODELS[self as usize].2
    }

    /// The model with COLMAP id `id`, or `None` for an id this crate does not know.
    pub fn from_id(id: i32) -> Option<Self> {
        let index = usize::try_from(id).ok()?;
        MODELS.get(index).map(|m| m.0)
    }

    /// The parameter names in COLMAP's order (`"f, cx, cy, k"`), for messages and help.
    pub const fn param_names(self) -> &'static str {
        MODELS[self as usize].3
    }

    /// `(fx, fy, cx, cy)` of any model's parameters, read by the names in COLMAP's order
    /// (`f` is both focal lengths), for drawing a camera as a pinhole; `None` for a model
    /// without them (EQUIRECTANGULAR) or parameters of another count.
    pub fn pinhole_part(self, params: &[f64]) -> Option<[f64; 4]> {
        if params.len() != self.num_params() {
            return None;
        }
        let named = |want: &str| {
            self.param_names()
                .split(", ")
                .position(|n| n == want)
                .map(|i| params[i])
        };
        let focal = named("f");
        Some([
            named("fx").or(focal)?,
            named("fy").or(focal)?,
            named("cx")?,
            named("cy")?,
        ])
    }

    /// The model with COLMAP name `name` (exact, upper case as COLMAP writes it).
    pub fn from_name(name: &str) -> Option<Self> {
        MODELS.iter().find(|m| m.1 == name).map(|m| m.0)
    }

    /// [`CameraModel::from_name`] ignoring ASCII case: hand-written query lists and `--camera`
    /// flags vary; COLMAP's own files are read exactly.
    pub fn from_name_ignore_case(name: &str) -> Option<Self> {
        MODELS
            .iter()
            .find(|m| m.1.eq_ignore_ascii_case(name))
            .map(|m| m.0)
    }
}

impl std::fmt::Display for CameraModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_model_but_equirectangular_has_a_pinhole_part() {
        // Against the localizer's own reading of the models it supports.
        #[cfg(feature = "geometry")]
        for model in crate::geometry::SUPPORTED {
            let params: Vec<f64> = (0..model.num_params()).map(|i| 100.0 + i as f64).collect();
            let camera = crate::geometry::Camera::new(model, 640, 480, params.clone()).unwrap();
            let (fx, fy) = camera.focal_lengths();
            let c = camera.principal_point();
            assert_eq!(
                model.pinhole_part(&params),
                Some([fx, fy, c.x, c.y]),
                "{model}"
            );
        }
        for model in CameraModel::ALL {
            let params = vec![1.0; model.num_params()];
            let has = model.pinhole_part(&params).is_some();
            assert_eq!(has, model != CameraModel::Equirectangular, "{model}");
        }
        // The positions, spelled out for models the localizer does not read.
        assert_eq!(
            CameraModel::Fov.pinhole_part(&[500.0, 510.0, 320.0, 240.0, 0.9]),
            Some([500.0, 510.0, 320.0, 240.0])
        );
        assert_eq!(
            CameraModel::SimpleFisheye.pinhole_part(&[300.0, 322.0, 242.0]),
            Some([300.0, 300.0, 322.0, 242.0])
        );
        let mut thin_prism = vec![0.0; 12];
        thin_prism[..4].copy_from_slice(&[501.0, 502.0, 321.0, 241.0]);
        assert_eq!(
            CameraModel::ThinPrismFisheye.pinhole_part(&thin_prism),
            Some([501.0, 502.0, 321.0, 241.0])
        );
        assert_eq!(
            CameraModel::SimpleDivision.pinhole_part(&[500.0, 321.0, 241.0, -0.1]),
            Some([500.0, 500.0, 321.0, 241.0])
        );
        assert_eq!(
            CameraModel::OpenCv.pinhole_part(&[510.0, 520.0, 323.0, 243.0, 0.1, 0.0, 0.0, 0.0]),
            Some([510.0, 520.0, 323.0, 243.0])
        );
        assert_eq!(CameraModel::OpenCv.pinhole_part(&[1.0]), None);
    }

    #[test]
    fn table_is_in_id_order_and_round_trips() {
        for (i, (model, name, count, params)) in MODELS.iter().enumerate() {
            assert_eq!(params.split(", ").count(), *count, "{name}");
            assert_eq!(
                CameraModel::from_name_ignore_case(&name.to_lowercase()),
                Some(*model)
            );
            assert_eq!(model.id() as usize, i);
            assert_eq!(CameraModel::ALL[i], *model);
            assert_eq!(CameraModel::from_id(model.id()), Some(*model));
            assert_eq!(CameraModel::from_name(name), Some(*model));
        }
        assert_eq!(CameraModel::from_id(-1), None);
        assert_eq!(CameraModel::from_id(18), None);
        assert_eq!(CameraModel::from_name("simple_radial"), None);
    }
}
