//! A top-down PNG of a map and trajectories (feature `plot`): points coloured by their level,
//! database cameras, localized and ground-truth camera centres joined by error lines.
//!
//! Which view is "top-down": SfM worlds have no gravity axis, so the plot uses the two world
//! axes along which the database camera centres spread most (people carry cameras over the
//! ground, rarely up and down); the axis left out is the one looked along. For COLMAP models
//! whose first camera was held upright that is usually x–z (y points down), and x to the
//! right with z up is then a view from above, not a mirror image (x × z = −y). Both axes use
//! one scale, and the extent is the points' 0.5–99.5 % range (SfM leaves a few far points)
//! grown to hold every camera and pose.
//!
//! Text needs a font: plotters' `ab_glyph` backend draws with registered fonts only, so a
//! Latin-1 subset of DejaVu Sans (`fonts/`, Bitstream Vera licence) is compiled in.

use crate::format::{Error, Map};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::{register_font, FontStyle};
use std::path::Path;
use std::sync::Once;

/// The embedded font (see `fonts/LICENSE-DejaVu.txt`).
const FONT: &[u8] = include_bytes!("fonts/DejaVuSans-subset.ttf");

/// Colours per level id (cycled), from the Tableau 10 palette: distinct and colour-blind safe.
const LEVEL_COLORS: [RGBColor; 8] = [
    RGBColor(78, 121, 167),
    RGBColor(242, 142, 43),
    RGBColor(89, 161, 79),
    RGBColor(176, 122, 161),
    RGBColor(237, 201, 72),
    RGBColor(118, 183, 178),
    RGBColor(156, 117, 95),
    RGBColor(255, 157, 167),
];
const NO_LEVEL: RGBColor = RGBColor(170, 170, 170);
const CAMERA: RGBColor = RGBColor(40, 40, 40);
const ESTIMATED: RGBColor = RGBColor(214, 39, 40);
const GROUND_TRUTH: RGBColor = RGBColor(0, 128, 0);

/// What to draw besides the map.
#[derive(Debug, Clone)]
pub struct PlotOptions {
    /// PNG width in pixels.
    pub width: u32,
    /// PNG height in pixels.
    pub height: u32,
    /// Points beyond this are subsampled (every k-th point) to keep the PNG readable.
    pub max_points: usize,
    /// The caption.
    pub title: String,
    /// Localized camera centres by query name.
    pub estimated: Vec<(String, [f64; 3])>,
    /// Ground-truth camera centres by query name; pairs with `estimated` get a line.
    pub ground_truth: Vec<(String, [f64; 3])>,
}

impl Default for PlotOptions {
    fn default() -> Self {
        PlotOptions {
            width: 1600,
            height: 1200,
            max_points: 200_000,
            title: String::new(),
            estimated: Vec::new(),
            ground_truth: Vec::new(),
        }
    }
}

/// What was drawn.
#[derive(Debug, Clone, PartialEq)]
pub struct PlotSummary {
    /// World axes shown, horizontal then vertical (0 = x, 1 = y, 2 = z).
    pub axes: (usize, usize),
    /// Map points drawn (after subsampling).
    pub points_drawn: usize,
    /// Database cameras drawn.
    pub cameras: usize,
    /// Estimated poses that had a ground-truth pose of the same name.
    pub pairs: usize,
}

/// What can stop a plot.
#[derive(Debug)]
#[non_exhaustive]
pub enum PlotError {
    /// Reading the map.
    Format(Error),
    /// Plotters could not draw or encode the image.
    Draw(String),
    /// Nothing to plot (no points, cameras or poses).
    Empty,
    /// The map's coordinates cannot be plotted (none is finite, or they span more than f64
    /// can scale); says which.
    Unplottable(String),
    /// The PNG cannot be written ([`crate::output`]'s policy or its I/O).
    Output(crate::output::OutputError),
}

impl std::fmt::Display for PlotError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlotError::Format(e) => e.fmt(f),
            PlotError::Draw(e) => write!(f, "drawing the plot failed: {e}"),
            PlotError::Empty => f.write_str("nothing to plot: the map has no points or cameras"),
            PlotError::Unplottable(what) => write!(f, "cannot plot: {what}"),
            PlotError::Output(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for PlotError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            // Shown by Display already: the rest of the chain only.
            PlotError::Output(e) => e.source(),
            _ => None,
        }
    }
}

impl From<crate::output::OutputError> for PlotError {
    fn from(e: crate::output::OutputError) -> Self {
        PlotError::Output(e)
    }
}

impl From<Error> for PlotError {
    fn from(e: Error) -> Self {
        PlotError::Format(e)
    }
}

fn draw_err(e: impl std::fmt::Display) -> PlotError {
    // One line whatever the cause says (plotters' bitmap errors print their Debug form).
    let what: Vec<String> = e.to_string().split_whitespace().map(String::from).collect();
    PlotError::Draw(what.join(" "))
}

fn register_embedded_font() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The bytes are a valid TrueType font (checked by the plot test); ignore the
        // impossible error rather than panic in a library.
        let _ = register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

const AXIS_NAMES: [&str; 3] = ["x", "y", "z"];

/// The two axes with the largest spread (variance) of `centres`, in ascending axis order.
fn view_axes(centres: &[[f64; 3]]) -> (usize, usize) {
    let n = centres.len() as f64;
    let mut var = [0.0f64; 3];
    for (k, v) in var.iter_mut().enumerate() {
        let mean = centres.iter().map(|c| c[k]).sum::<f64>() / n;
        *v = centres.iter().map(|c| (c[k] - mean).powi(2)).sum::<f64>() / n;
    }
    let dropped = (0..3)
        .min_by(|&a, &b| var[a].total_cmp(&var[b]))
        .unwrap_or(1);
    match dropped {
        0 => (1, 2),
        1 => (0, 2),
        _ => (0, 1),
    }
}

/// The corner of the plot where a legend box (38 % wide, `height` of the plot high) covers
/// the fewest of `xy`; upper right on a tie.
fn legend_corner(
    xy: impl Iterator<Item = (f64, f64)>,
    (lo, hi): ([f64; 2], [f64; 2]),
    height: f64,
) -> SeriesLabelPosition {
    let height = height.clamp(0.1, 0.6);
    let mut counts = [0usize; 4];
    for (x, y) in xy {
        let u = (x - lo[0]) / (hi[0] - lo[0]);
        let v = (y - lo[1]) / (hi[1] - lo[1]);
        let (right, left) = (u > 0.62, u < 0.38);
        let (upper, lower) = (v > 1.0 - height, v < height);
        for (k, inside) in [right && upper, left && upper, right && lower, left && lower]
            .into_iter()
            .enumerate()
        {
            counts[k] += usize::from(inside);
        }
    }
    let best = (0..4).min_by_key(|&k| (counts[k], k)).unwrap_or(0);
    [
        SeriesLabelPosition::UpperRight,
        SeriesLabelPosition::UpperLeft,
        SeriesLabelPosition::LowerRight,
        SeriesLabelPosition::LowerLeft,
    ][best]
        .clone()
}

/// Whether plotters cannot resolve the range `lo..hi` as it is. Its tick loop steps from
/// the range's start by about a hundredth of the range: a step below the start's rounding
/// (f64 holds 16 digits) goes nowhere and the loop never ends, which is how a map whose
/// origin is 1.7e308 hung `plot`. And padding and the one-scale widening must not overflow.
/// Such a range is drawn relative to its middle instead.
fn needs_offset(lo: f64, hi: f64) -> bool {
    let magnitude = lo.abs().max(hi.abs());
    !(hi - lo > magnitude * 1e-9 && magnitude < 1e300)
}

/// Everything drawn, in plot coordinates: world coordinates less an offset.
struct PlotCoordinates {
    world: Vec<([f64; 3], Option<u16>)>,
    cameras: Vec<([f64; 3], [f64; 3])>,
    estimated: Vec<(String, [f64; 3])>,
    ground_truth: Vec<(String, [f64; 3])>,
}

impl PlotCoordinates {
    /// Points from their `stored` (origin-relative) positions, cameras and poses from world
    /// coordinates; poses that are not finite are left out (they cannot be drawn).
    fn new(
        origin: [f64; 3],
        offset: [f64; 3],
        stored: &[([f32; 3], Option<u16>)],
        cameras: &[([f64; 3], [f64; 3])],
        options: &PlotOptions,
    ) -> PlotCoordinates {
        let base = [0, 1, 2].map(|k| origin[k] - offset[k]);
        let shift = |c: &[f64; 3]| [0, 1, 2].map(|k| c[k] - offset[k]);
        let poses = |poses: &[(String, [f64; 3])]| {
            poses
                .iter()
                .filter(|(_, c)| c.iter().all(|v| v.is_finite()))
                .map(|(n, c)| (n.clone(), shift(c)))
                .collect()
        };
        PlotCoordinates {
            world: stored
                .iter()
                .map(|(p, l)| ([0, 1, 2].map(|k| base[k] + f64::from(p[k])), *l))
                .collect(),
            cameras: cameras.iter().map(|(c, d)| (shift(c), *d)).collect(),
            estimated: poses(&options.estimated),
            ground_truth: poses(&options.ground_truth),
        }
    }

    /// The robust range of the points (0.5–99.5 %, SfM leaves a few far points) along axes
    /// `a` and `b`, grown to every camera and pose; infinite where nothing is finite.
    fn extent(&self, (a, b): (usize, usize)) -> ([f64; 2], [f64; 2]) {
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for (k, axis) in [a, b].into_iter().enumerate() {
            let mut v: Vec<f64> = self
                .world
                .iter()
                .map(|(p, _)| p[axis])
                .filter(|x| x.is_finite())
                .collect();
            if !v.is_empty() {
                v.sort_by(f64::total_cmp);
                lo[k] = percentile(&v, 0.005);
                hi[k] = percentile(&v, 0.995);
            }
            let extra = self
                .cameras
                .iter()
                .map(|(c, _)| c)
                .chain(self.estimated.iter().map(|(_, c)| c))
                .chain(self.ground_truth.iter().map(|(_, c)| c));
            for c in extra {
                if c[axis].is_finite() {
                    lo[k] = lo[k].min(c[axis]);
                    hi[k] = hi[k].max(c[axis]);
                }
            }
        }
        (lo, hi)
    }
}

/// A tick label in scientific notation with at most 4 digits (`2.5e307`), for views whose
/// numbers plotters would print in full (hundreds of digits).
fn scientific(v: &f64) -> String {
    if *v == 0.0 {
        return "0".into();
    }
    let text = format!("{v:.3e}");
    match text.split_once('e') {
        Some((mantissa, exponent)) if mantissa.contains('.') => {
            let mantissa = mantissa.trim_end_matches('0').trim_end_matches('.');
            format!("{mantissa}e{exponent}")
        }
        _ => text,
    }
}

/// The axis title: its name, less the plot offset if there is one, and the units.
fn axis_title(axis: usize, offset: f64, units: &str) -> String {
    let name = AXIS_NAMES[axis];
    if offset == 0.0 {
        format!("{name} ({units})")
    } else if offset.abs() >= 1e7 || offset.abs() < 1e-3 {
        format!("{name} - {} ({units})", scientific(&offset))
    } else {
        format!("{name} - {offset} ({units})")
    }
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// Renders the plot to a PNG at `path`.
pub fn plot_map(
    map: &Map<'_>,
    options: &PlotOptions,
    path: &Path,
) -> Result<PlotSummary, PlotError> {
    register_embedded_font();
    let positions = map.point_positions()?;
    let (levels, _) = super::ply::point_levels(map)?;
    let origin = map.metadata().origin;
    // Centre and viewing direction (the optical axis in the world: Rᵀ·(0, 0, 1), the third
    // row of R) of each database camera. A camera whose pose is no rotation (a zero or
    // non-finite quaternion) or whose centre is not finite cannot be drawn.
    let cameras: Vec<([f64; 3], [f64; 3])> = match map.images()? {
        Some(images) => images
            .poses
            .iter()
            .filter_map(|&p| {
                let pose = crate::geometry::Pose::from_colmap_array(p).ok()?;
                // The viewing direction, +z of the camera, in the world.
                let axis = pose.rotation.inverse() * nalgebra::Vector3::z();
                Some((pose.center().into(), axis.into()))
            })
            .filter(|(c, _): &([f64; 3], [f64; 3])| c.iter().all(|v| v.is_finite()))
            .collect(),
        None => Vec::new(),
    };
    let step = positions.len().div_ceil(options.max_points.max(1)).max(1);
    let stored: Vec<([f32; 3], Option<u16>)> = positions
        .iter()
        .zip(&levels)
        .step_by(step)
        .map(|(&p, &l)| (p, l))
        .collect();

    // The view axes from the spread of the camera centres (else the poses, else the points),
    // taken relative to the origin: the same spread, without the rounding of far-out world
    // coordinates.
    let from_origin = |c: &[f64; 3]| [c[0] - origin[0], c[1] - origin[1], c[2] - origin[2]];
    let mut centres: Vec<[f64; 3]> = cameras.iter().map(|(c, _)| from_origin(c)).collect();
    if centres.len() < 2 {
        centres.extend(options.ground_truth.iter().map(|(_, c)| from_origin(c)));
        centres.extend(options.estimated.iter().map(|(_, c)| from_origin(c)));
    }
    if centres.len() < 2 {
        centres.extend(stored.iter().map(|(p, _)| p.map(f64::from)));
    }
    if centres.is_empty() {
        return Err(PlotError::Empty);
    }
    let (a, b) = view_axes(&centres);

    // Plot coordinates are world coordinates less an offset, zero unless plotters could not
    // resolve the view in world coordinates (see `needs_offset`); points are computed as
    // (origin − offset) + stored position, so an offset near the origin loses nothing.
    let mut offset = [0.0f64; 3];
    let mut view = PlotCoordinates::new(origin, offset, &stored, &cameras, options);
    let (mut lo, mut hi) = view.extent((a, b));
    if !(lo[0].is_finite() && lo[1].is_finite()) {
        return Err(PlotError::Unplottable(
            "no point, camera or pose has finite coordinates".into(),
        ));
    }
    let mut shifted = false;
    for (k, axis) in [a, b].into_iter().enumerate() {
        if needs_offset(lo[k], hi[k]) {
            offset[axis] = lo[k] / 2.0 + hi[k] / 2.0;
            shifted = true;
        }
    }
    if shifted {
        view = PlotCoordinates::new(origin, offset, &stored, &cameras, options);
        (lo, hi) = view.extent((a, b));
    }
    let PlotCoordinates {
        world,
        cameras,
        estimated,
        ground_truth,
    } = view;
    // What is drawn is in plot coordinates, poses included.
    let options = &PlotOptions {
        estimated,
        ground_truth,
        ..options.clone()
    };
    let offset = [offset[a], offset[b]];

    // Drawn in memory, then encoded through the atomic writer: plotters' own file output
    // writes in place, so a kill mid-write lost the old PNG.
    let (width, height) = (options.width, options.height);
    let mut pixels = vec![0u8; width as usize * height as usize * 3];
    let summary = {
        let root = BitMapBackend::with_buffer(&mut pixels, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let summary = draw(
            &root,
            map,
            options,
            (a, b),
            offset,
            (lo, hi),
            &world,
            &cameras,
        )?;
        root.present().map_err(draw_err)?;
        summary
    };
    write_png(path, width, height, &pixels)?;
    Ok(summary)
}

/// `rgb` (8-bit RGB rows) as a PNG at `path`, through [`crate::output::write_atomic`].
fn write_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<(), PlotError> {
    crate::output::write_atomic(path, |out| {
        let mut encoder = png::Encoder::new(out, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let encoded = encoder.write_header().and_then(|mut writer| {
            writer.write_image_data(rgb)?;
            writer.finish()
        });
        encoded.map_err(|e| match e {
            png::EncodingError::IoError(source) => {
                PlotError::Output(crate::output::OutputError::cannot_write(path, source))
            }
            e => draw_err(e),
        })
    })
}

#[allow(clippy::too_many_arguments)]
fn draw(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    map: &Map<'_>,
    options: &PlotOptions,
    (a, b): (usize, usize),
    offset: [f64; 2],
    (mut lo, mut hi): ([f64; 2], [f64; 2]),
    world: &[([f64; 3], Option<u16>)],
    cameras: &[([f64; 3], [f64; 3])],
) -> Result<PlotSummary, PlotError> {
    let units = &map.metadata().units;
    let extent = (lo, hi);
    let caption_size = (options.height / 32).clamp(14, 40);
    let label_size = (options.height / 55).clamp(10, 24);
    let (left, bottom) = (label_size * 5, label_size * 3);
    // One scale on both axes: widen the range that is too narrow for the plotting area.
    let plot_w = f64::from(options.width.saturating_sub(left + 30).max(1));
    let plot_h = f64::from(
        options
            .height
            .saturating_sub(bottom + caption_size * 2 + 20)
            .max(1),
    );
    for k in 0..2 {
        let pad = ((hi[k] - lo[k]) * 0.03).max(1e-9);
        lo[k] -= pad;
        hi[k] += pad;
    }
    let scale = ((hi[0] - lo[0]) / plot_w).max((hi[1] - lo[1]) / plot_h);
    for (k, size) in [(0, plot_w), (1, plot_h)] {
        let mid = (lo[k] + hi[k]) / 2.0;
        lo[k] = mid - scale * size / 2.0;
        hi[k] = mid + scale * size / 2.0;
    }
    // Plot coordinates keep the view resolvable; what is left is a span past f64's reach.
    for (k, axis) in [a, b].into_iter().enumerate() {
        if needs_offset(lo[k], hi[k]) {
            return Err(PlotError::Unplottable(format!(
                "{} runs from {} to {} ({units}), more than a plot can scale",
                AXIS_NAMES[axis],
                scientific(&(extent.0[k] + offset[k])),
                scientific(&(extent.1[k] + offset[k])),
            )));
        }
    }

    let mut chart = ChartBuilder::on(root)
        .caption(&options.title, ("sans-serif", caption_size))
        .margin(15)
        .x_label_area_size(bottom)
        .y_label_area_size(left)
        .build_cartesian_2d(lo[0]..hi[0], lo[1]..hi[1])
        .map_err(draw_err)?;
    let mut mesh = chart.configure_mesh();
    mesh.x_desc(axis_title(a, offset[0], units))
        .y_desc(axis_title(b, offset[1], units))
        .label_style(("sans-serif", label_size))
        .light_line_style(RGBColor(235, 235, 235))
        .bold_line_style(RGBColor(215, 215, 215));
    // Plotters prints a tick label in full, which for 1e300 is 301 digits.
    if lo[0].abs().max(hi[0].abs()) >= 1e7 {
        mesh.x_label_formatter(&scientific);
    }
    if lo[1].abs().max(hi[1].abs()) >= 1e7 {
        mesh.y_label_formatter(&scientific);
    }
    mesh.draw().map_err(draw_err)?;

    let in_view = |x: f64, y: f64| x >= lo[0] && x <= hi[0] && y >= lo[1] && y <= hi[1];
    // Bigger dots for sparse maps, so a few thousand points still read as structure.
    let dot = (options.width / 1000).max(1) + u32::from(world.len() < 20_000);
    // Points in no level first, then levels ascending: the deepest (sparsest) on top.
    let mut groups: Vec<Option<u16>> = vec![None];
    groups.extend(map.level_ids().into_iter().map(Some));
    let mut points_drawn = 0;
    for group in groups {
        let pts: Vec<(f64, f64)> = world
            .iter()
            .filter(|(_, l)| *l == group)
            .map(|(p, _)| (p[a], p[b]))
            .filter(|&(x, y)| in_view(x, y))
            .collect();
        if pts.is_empty() {
            continue;
        }
        points_drawn += pts.len();
        let color = match group {
            Some(l) => LEVEL_COLORS[usize::from(l) % LEVEL_COLORS.len()],
            None => NO_LEVEL,
        };
        let label = match group {
            Some(l) => format!("level {l} ({} points)", pts.len()),
            None => format!("no level ({} points)", pts.len()),
        };
        chart
            .draw_series(
                pts.into_iter()
                    .map(|c| Circle::new(c, dot, color.mix(0.75).filled())),
            )
            .map_err(draw_err)?
            .label(label)
            .legend(move |(x, y)| Circle::new((x, y), 5, color.filled()));
    }

    if !cameras.is_empty() {
        // A tick along each camera's viewing direction, 2.5 % of the view wide.
        let tick = 0.025 * (hi[0] - lo[0]);
        chart
            .draw_series(cameras.iter().map(|(c, d)| {
                let len = (d[a] * d[a] + d[b] * d[b]).sqrt().max(1e-12);
                let end = (c[a] + tick * d[a] / len, c[b] + tick * d[b] / len);
                PathElement::new(vec![(c[a], c[b]), end], CAMERA.stroke_width(1))
            }))
            .map_err(draw_err)?;
        chart
            .draw_series(
                cameras
                    .iter()
                    .map(|(c, _)| TriangleMarker::new((c[a], c[b]), 4, CAMERA.filled())),
            )
            .map_err(draw_err)?
            .label(format!(
                "database cameras ({}), tick = viewing direction",
                cameras.len()
            ))
            .legend(|(x, y)| TriangleMarker::new((x, y), 5, CAMERA.filled()));
    }

    // Error lines first so the markers sit on top of them.
    let gt: std::collections::HashMap<&str, [f64; 3]> = options
        .ground_truth
        .iter()
        .map(|(n, c)| (n.as_str(), *c))
        .collect();
    let pairs: Vec<([f64; 3], [f64; 3])> = options
        .estimated
        .iter()
        .filter_map(|(n, e)| gt.get(n.as_str()).map(|g| (*e, *g)))
        .collect();
    if !pairs.is_empty() {
        chart
            .draw_series(pairs.iter().map(|(e, g)| {
                PathElement::new(
                    vec![(e[a], e[b]), (g[a], g[b])],
                    ESTIMATED.mix(0.8).stroke_width(2),
                )
            }))
            .map_err(draw_err)?
            .label(format!("localization error ({} pairs)", pairs.len()))
            .legend(|(x, y)| PathElement::new(vec![(x - 8, y), (x + 8, y)], ESTIMATED));
    }
    if !options.ground_truth.is_empty() {
        chart
            .draw_series(
                options
                    .ground_truth
                    .iter()
                    .map(|(_, c)| Circle::new((c[a], c[b]), 5, GROUND_TRUTH.stroke_width(2))),
            )
            .map_err(draw_err)?
            .label(format!("ground truth ({})", options.ground_truth.len()))
            .legend(|(x, y)| Circle::new((x, y), 5, GROUND_TRUTH.stroke_width(2)));
    }
    if !options.estimated.is_empty() {
        chart
            .draw_series(
                options
                    .estimated
                    .iter()
                    .map(|(_, c)| Cross::new((c[a], c[b]), 5, ESTIMATED.stroke_width(2))),
            )
            .map_err(draw_err)?
            .label(format!("localized ({})", options.estimated.len()))
            .legend(|(x, y)| Cross::new((x, y), 5, ESTIMATED.stroke_width(2)));
    }

    let entries = map.level_ids().len() + 5;
    let position = legend_corner(
        world
            .iter()
            .map(|(p, _)| (p[a], p[b]))
            .chain(cameras.iter().map(|(c, _)| (c[a], c[b])))
            .chain(options.estimated.iter().map(|(_, c)| (c[a], c[b])))
            .chain(options.ground_truth.iter().map(|(_, c)| (c[a], c[b]))),
        (lo, hi),
        f64::from(label_size) * 1.6 * entries as f64 / plot_h,
    );
    chart
        .configure_series_labels()
        .position(position)
        .label_font(("sans-serif", label_size))
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(120, 120, 120))
        .draw()
        .map_err(draw_err)?;

    Ok(PlotSummary {
        axes: (a, b),
        points_drawn,
        cameras: cameras.len(),
        pairs: pairs.len(),
    })
}
