//! The synthetic localization scene shared by the localizer and C API tests: random points in
//! front of the origin camera, random unit descriptors, and a known query pose.
#![allow(dead_code)]

use sfpmap::format::LevelInfo;
use sfpmap::geometry::Pose;

/// A 64-bit LCG: deterministic and dependency-free.
pub struct Rng(pub u64);

impl Rng {
    /// Uniform in `[0, 1)`.
    pub fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Standard normal (Box–Muller).
    pub fn normal(&mut self) -> f64 {
        let (u, v) = (self.next().max(1e-12), self.next());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

pub fn unit(v: &mut [f32]) {
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    v.iter_mut().for_each(|x| *x /= n);
}

/// `n` points in a 20 × 10 × 20 m box 10 m ahead, and `n` unit descriptors of `dim`.
pub fn points_and_descriptors(n: usize, dim: usize) -> (Vec<[f64; 3]>, Vec<f32>) {
    let mut rng = Rng(42);
    let points = (0..n)
        .map(|_| {
            [
                rng.next() * 20.0 - 10.0,
                rng.next() * 10.0 - 5.0,
                10.0 + rng.next() * 20.0,
            ]
        })
        .collect();
    let mut descriptors = Vec::with_capacity(n * dim);
    for _ in 0..n {
        let mut d: Vec<f32> = (0..dim).map(|_| rng.normal() as f32).collect();
        unit(&mut d);
        descriptors.extend(d);
    }
    (points, descriptors)
}

/// Level `level` of the scene's maps: stride 4·2^level, `dim` full and 16 short dimensions.
pub fn level_info(level: u16, dim: usize) -> LevelInfo {
    LevelInfo {
        level,
        stride: 4.0 * (1 << level) as f64,
        descriptor: "test".into(),
        dim_full: dim as u32,
        dim_short: 16,
        normalization: "l2".into(),
        extra: Default::default(),
    }
}

/// The query's `cam_from_world`.
pub fn truth() -> Pose {
    Pose::from_colmap(0.995, 0.05, -0.07, 0.03, 0.4, -0.2, 1.5).unwrap()
}
