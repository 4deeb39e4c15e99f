//! Registration: where the design lies on the board map.
//!
//! Each fiducial (a raised copper disc of the program's diameter) is searched within
//! `fiducials.search_mm` of its nominal place (the program's placement). In that window the
//! board is levelled by a robust quadratic surface (the warp curves over a few mm;
//! `measure::robust_surface`), pixels above
//! 6 um form candidates (4-connected), and of the candidates shaped like the disc (0.6 to
//! 1.5 times its area, as wide as tall within 25 %, filling 0.6 to 0.9 of their box as a
//! disc fills pi/4 and a rectangular deposit all of it) the one nearest the nominal place is
//! kept. Its centre is refined with partial-pixel
//! weights `clamp(h / plateau, 0, 1)` (the plateau is the median height of its core), which
//! makes the centre sub-pixel. A rigid transform (rotation and shift; the map is in mm, so
//! no scale) is fitted to the found centres by least squares; the residual is the rms of
//! the fit's misses.

use crate::map::BoardMap;
use crate::measure::{robust_surface, surface_at};
use crate::program::Program;
use dpsa_gerber::pads::{Point, Rigid};
use serde::Serialize;

/// Why the design could not be registered on the map.
#[derive(Debug, thiserror::Error)]
pub enum RegisterError {
    /// [`register`] called for a program without fiducials.
    #[error("the program lists no fiducials: the design cannot be registered to the board")]
    NoFiducials,
    /// The paste pattern did not give a transform ([`crate::register_paste`]).
    #[error("registration by the paste pattern (the program has no fiducials): {why}")]
    NoPattern {
        /// What was wrong (too few pads, no clear match, ...).
        why: String,
    },
    /// Fewer than two fiducials found.
    #[error("found {found} of {listed} fiducials (need at least 2): {missing}")]
    TooFew {
        /// Fiducials found.
        found: usize,
        /// Fiducials the program lists.
        listed: usize,
        /// The missing ones, `(x, y): why`, separated by `; `.
        missing: String,
    },
}

/// One fiducial's search.
#[derive(Clone, Debug, Serialize)]
pub struct FiducialHit {
    /// The program's centre, design mm.
    pub design_mm: Point,
    /// Where the nominal placement put it, board mm.
    pub nominal_mm: Point,
    /// Where it was found, board mm (None: not found).
    pub found_mm: Option<Point>,
    /// Disc height above the board (the plateau's median), um; 0 when not found.
    pub height_um: f64,
    /// Distance from the fitted transform's prediction, um; NaN when not found.
    pub residual_um: f64,
    /// Why it was not found.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub why: Option<String>,
}

/// Where the design lies on the board map.
#[derive(Clone, Debug, Serialize)]
pub struct Registration {
    /// `fiducials` or `paste pattern`.
    pub method: &'static str,
    /// Design to board transform.
    pub transform: Rigid,
    /// Its departure from the nominal placement: shift (mm) and rotation (deg).
    pub shift_mm: Point,
    /// The departure's rotation, degrees counter-clockwise.
    pub rotation_deg: f64,
    /// Every fiducial's search, in the program's order (empty for the paste pattern).
    pub fiducials: Vec<FiducialHit>,
    /// Rms of the fit's misses over the found fiducials, um (0 for two: exact), or over the
    /// deposits the paste pattern was fitted to.
    pub residual_um: f64,
    /// The pads whose deposits the paste pattern was fitted to (registration without
    /// fiducials, [`super::register_paste`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pads_used: Option<usize>,
}

/// Lowest fiducial disc height found, um (copper is about 35 um; the candidates are cut at
/// half of this, about 5 noise sigma).
pub(crate) const MIN_DISC_UM: f64 = 12.0;

/// Finds one disc of `diameter` (mm) within `search` (mm) of board point `q0`: its centre
/// (board mm) and height (um), or why not.
pub(crate) fn find_disc(
    map: &BoardMap,
    q0: Point,
    diameter: f64,
    search: f64,
) -> Result<(Point, f64), String> {
    let reach = search + diameter;
    let (ri, rj) = map.window([q0[0] - reach, q0[1] - reach, q0[0] + reach, q0[1] + reach]);
    let win = Window { ri, rj };
    if win.rows() < 3 || win.cols() < 3 {
        return Err("its search window is off the map".into());
    }
    let surface = window_surface(map, &win, q0)?;
    let mut r = vec![f64::NAN; win.rows() * win.cols()];
    level(map, &win, &surface, q0, &mut r);
    let thr = MIN_DISC_UM / 2.0;
    let Some(mut c) = nearest_disc(map, &win, &r, thr, diameter, q0) else {
        return Err(format!(
            "no disc of {diameter} mm within {search} mm of the nominal place (threshold {thr:.1} um)"
        ));
    };
    // The board right around the disc, levelled again on a ring (the window's plane does
    // not follow the warp's curvature over the whole window).
    if let Some(ring) = ring_surface(map, &win, c, diameter) {
        level(map, &win, &ring, c, &mut r);
    }
    let plateau = refine_centre(map, &win, &r, diameter, &mut c);
    Ok((c, plateau))
}

/// A fiducial's search window: pixel rows `ri` and columns `rj` of the map.
struct Window {
    ri: std::ops::Range<usize>,
    rj: std::ops::Range<usize>,
}

impl Window {
    fn rows(&self) -> usize {
        self.ri.len()
    }

    fn cols(&self) -> usize {
        self.rj.len()
    }

    /// Every pixel, row by row: `(index in the window, map row, map column)`.
    fn pixels(&self) -> impl Iterator<Item = (usize, usize, usize)> + '_ {
        let ww = self.cols();
        self.ri.clone().enumerate().flat_map(move |(a, i)| {
            self.rj
                .clone()
                .enumerate()
                .map(move |(b, j)| (a * ww + b, i, j))
        })
    }
}

/// The window's board surface (a robust quadratic about `q0`: the warp curves over a window
/// of a few mm) from about 4,000 of its pixels; an error when most of them are invalid or no
/// surface fits.
fn window_surface(map: &BoardMap, win: &Window, q0: Point) -> Result<Vec<f64>, String> {
    let (hw, ww) = (win.rows(), win.cols());
    let stride = ((hw * ww) as f64 / 4000.0).sqrt().ceil().max(1.0) as usize;
    let mut samples = Vec::with_capacity(hw * ww);
    let mut looked = 0usize;
    for i in win.ri.clone().step_by(stride) {
        for j in win.rj.clone().step_by(stride) {
            looked += 1;
            let h = map.heights.data[i * map.grid.width + j];
            if h.is_finite() {
                let (x, y) = map.grid.centre(i, j);
                samples.push([x - q0[0], y - q0[1], f64::from(h)]);
            }
        }
    }
    if samples.len() < looked / 2 {
        return Err(format!(
            "its search window is mostly invalid ({} of {looked} pixels looked at valid)",
            samples.len()
        ));
    }
    match robust_surface(&samples, true) {
        Some(fit) => Ok(fit.coef),
        None => Err("no board surface in its window".into()),
    }
}

/// Heights above `surface` (about `origin`, board mm) into `r` (row-major over the window),
/// um, at the valid pixels; the others keep their value.
fn level(map: &BoardMap, win: &Window, surface: &[f64], origin: Point, r: &mut [f64]) {
    for (idx, i, j) in win.pixels() {
        let h = map.heights.data[i * map.grid.width + j];
        if h.is_finite() {
            let (x, y) = map.grid.centre(i, j);
            r[idx] = f64::from(h) - surface_at(surface, x - origin[0], y - origin[1]);
        }
    }
}

/// A 4-connected group of pixels above the threshold: its pixel count, the sum of their
/// centres (board mm) and its box in window rows and columns (inclusive).
struct Blob {
    n: usize,
    sum: Point,
    rows: (usize, usize),
    cols: (usize, usize),
}

impl Blob {
    /// Shaped like a disc of `disc_px` pixels: 0.6 to 1.5 times its area, as wide as tall
    /// within 25 %, filling 0.6 to 0.9 of its box (a disc fills pi/4 of it, a rectangle all).
    fn is_disc(&self, disc_px: f64) -> bool {
        let ext_a = (self.rows.1 - self.rows.0 + 1) as f64;
        let ext_b = (self.cols.1 - self.cols.0 + 1) as f64;
        let ratio = self.n as f64 / disc_px;
        let fill = self.n as f64 / (ext_a * ext_b);
        (0.6..=1.5).contains(&ratio)
            && ext_a / ext_b <= 1.25
            && ext_b / ext_a <= 1.25
            && (0.6..=0.9).contains(&fill)
    }
}

/// The group of `start` (unlabelled, above `thr`): labels it `id` in `label`.
fn flood(
    map: &BoardMap,
    win: &Window,
    r: &[f64],
    thr: f64,
    label: &mut [u32],
    id: u32,
    start: usize,
) -> Blob {
    let (hw, ww) = (win.rows(), win.cols());
    let mut stack = vec![start];
    label[start] = id;
    let (mut n, mut sx, mut sy) = (0usize, 0.0, 0.0);
    let (mut amin, mut amax, mut bmin, mut bmax) = (usize::MAX, 0, usize::MAX, 0);
    while let Some(idx) = stack.pop() {
        let (a, b) = (idx / ww, idx % ww);
        n += 1;
        let (x, y) = map.grid.centre(win.ri.start + a, win.rj.start + b);
        sx += x;
        sy += y;
        amin = amin.min(a);
        amax = amax.max(a);
        bmin = bmin.min(b);
        bmax = bmax.max(b);
        let mut visit = |m: usize| {
            if label[m] == 0 && r[m] > thr {
                label[m] = id;
                stack.push(m);
            }
        };
        if a > 0 {
            visit(idx - ww);
        }
        if a + 1 < hw {
            visit(idx + ww);
        }
        if b > 0 {
            visit(idx - 1);
        }
        if b + 1 < ww {
            visit(idx + 1);
        }
    }
    Blob {
        n,
        sum: [sx, sy],
        rows: (amin, amax),
        cols: (bmin, bmax),
    }
}

/// Of the groups of pixels above `thr` (um over the levelled heights `r`) shaped like a disc
/// of `diameter` (mm), the centre (board mm) of the one nearest `q0`.
fn nearest_disc(
    map: &BoardMap,
    win: &Window,
    r: &[f64],
    thr: f64,
    diameter: f64,
    q0: Point,
) -> Option<Point> {
    let p = map.grid.pitch_mm;
    let disc_px = std::f64::consts::PI * diameter * diameter / 4.0 / (p * p);
    let mut label = vec![0u32; r.len()];
    let mut best: Option<(f64, Point)> = None;
    let mut next = 0u32;
    for start in 0..r.len() {
        if label[start] != 0 || r[start].is_nan() || r[start] <= thr {
            continue;
        }
        next += 1;
        let blob = flood(map, win, r, thr, &mut label, next, start);
        if !blob.is_disc(disc_px) {
            continue;
        }
        let c = [blob.sum[0] / blob.n as f64, blob.sum[1] / blob.n as f64];
        let d = (c[0] - q0[0]).hypot(c[1] - q0[1]);
        if best.is_none_or(|(bd, _)| d < bd) {
            best = Some((d, c));
        }
    }
    best.map(|(_, c)| c)
}

/// The board on a ring around a disc of `diameter` (mm) at `c` (0.15 to 0.6 mm beyond its
/// edge): a robust quadratic about `c`, or None.
fn ring_surface(map: &BoardMap, win: &Window, c: Point, diameter: f64) -> Option<Vec<f64>> {
    let ring: Vec<[f64; 3]> =
        win.pixels()
            .filter_map(|(_, i, j)| {
                let h = map.heights.data[i * map.grid.width + j];
                let (x, y) = map.grid.centre(i, j);
                let d = (x - c[0]).hypot(y - c[1]);
                (h.is_finite() && d > 0.5 * diameter + 0.15 && d < 0.5 * diameter + 0.6)
                    .then_some([x - c[0], y - c[1], f64::from(h)])
            })
            .collect();
    robust_surface(&ring, true).map(|fit| fit.coef)
}

/// The disc's centre `c` made sub-pixel (three rounds of partial-pixel weights
/// `clamp(h / plateau, 0, 1)` within 0.75 diameters); returns the plateau, the median height
/// within 0.3 diameters (um; 0 when no pixel lies there).
fn refine_centre(map: &BoardMap, win: &Window, r: &[f64], diameter: f64, c: &mut Point) -> f64 {
    let mut plateau = 0.0;
    for _ in 0..3 {
        let mut core: Vec<f64> = Vec::new();
        for (idx, i, j) in win.pixels() {
            let (x, y) = map.grid.centre(i, j);
            if (x - c[0]).hypot(y - c[1]) < 0.3 * diameter && r[idx].is_finite() {
                core.push(r[idx]);
            }
        }
        if core.is_empty() {
            break;
        }
        let mid = core.len() / 2;
        let (_, med, _) = core.select_nth_unstable_by(mid, f64::total_cmp);
        plateau = *med;
        if plateau <= 0.0 {
            break;
        }
        let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for (idx, i, j) in win.pixels() {
            let (x, y) = map.grid.centre(i, j);
            let v = r[idx];
            if (x - c[0]).hypot(y - c[1]) < 0.75 * diameter && v.is_finite() {
                let w = (v / plateau).clamp(0.0, 1.0);
                sw += w;
                sx += w * x;
                sy += w * y;
            }
        }
        if sw > 0.0 {
            *c = [sx / sw, sy / sw];
        }
    }
    plateau
}

/// Least-squares rotation and shift taking `design` onto `board` (at least two points).
pub(crate) fn fit_rigid(design: &[Point], board: &[Point]) -> Rigid {
    let n = design.len() as f64;
    let md = design
        .iter()
        .fold([0.0, 0.0], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n]);
    let mb = board
        .iter()
        .fold([0.0, 0.0], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n]);
    let (mut sxx, mut sxy) = (0.0, 0.0);
    for (p, q) in design.iter().zip(board) {
        let (px, py) = (p[0] - md[0], p[1] - md[1]);
        let (qx, qy) = (q[0] - mb[0], q[1] - mb[1]);
        sxx += px * qx + py * qy;
        sxy += px * qy - py * qx;
    }
    let a = sxy.atan2(sxx);
    let rot = Rigid {
        rotation_rad: a,
        tx: 0.0,
        ty: 0.0,
    };
    let r = rot.apply(md);
    Rigid {
        rotation_rad: a,
        tx: mb[0] - r[0],
        ty: mb[1] - r[1],
    }
}

/// Registers the program's design on the map by its fiducials.
pub fn register(map: &BoardMap, program: &Program) -> Result<Registration, RegisterError> {
    let f = &program.fiducials;
    if f.points_mm.is_empty() {
        return Err(RegisterError::NoFiducials);
    }
    let nominal = program.placement.nominal();
    let mut hits: Vec<FiducialHit> = Vec::new();
    for &d in &f.points_mm {
        let q0 = nominal.apply(d);
        let (found, height, why) = match find_disc(map, q0, f.diameter_mm, f.search_mm) {
            Ok((c, h)) => (Some(c), h, None),
            Err(e) => (None, 0.0, Some(e)),
        };
        hits.push(FiducialHit {
            design_mm: d,
            nominal_mm: q0,
            found_mm: found,
            height_um: height,
            residual_um: f64::NAN,
            why,
        });
    }
    let pairs: Vec<(Point, Point)> = hits
        .iter()
        .filter_map(|h| h.found_mm.map(|b| (h.design_mm, b)))
        .collect();
    if pairs.len() < 2 {
        let missing = hits
            .iter()
            .filter(|h| h.found_mm.is_none())
            .map(|h| {
                format!(
                    "({:.3}, {:.3}): {}",
                    h.design_mm[0],
                    h.design_mm[1],
                    h.why.as_deref().unwrap_or("")
                )
            })
            .collect::<Vec<_>>()
            .join("; ");
        return Err(RegisterError::TooFew {
            found: pairs.len(),
            listed: hits.len(),
            missing,
        });
    }
    let (ds, bs): (Vec<Point>, Vec<Point>) = pairs.into_iter().unzip();
    let t = fit_rigid(&ds, &bs);
    let mut ss = 0.0;
    for h in &mut hits {
        if let Some(b) = h.found_mm {
            let p = t.apply(h.design_mm);
            h.residual_um = (p[0] - b[0]).hypot(p[1] - b[1]) * 1000.0;
            ss += h.residual_um * h.residual_um;
        }
    }
    let residual = (ss / ds.len() as f64).sqrt();
    let delta = t.after(&nominal.inverse());
    Ok(Registration {
        method: "fiducials",
        transform: t,
        shift_mm: [delta.tx, delta.ty],
        rotation_deg: delta.rotation_rad.to_degrees(),
        fiducials: hits,
        residual_um: residual,
        pads_used: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rigid_fit_recovers_a_transform() {
        let t = Rigid {
            rotation_rad: 0.004,
            tx: 0.31,
            ty: -0.17,
        };
        let d = [[3.0, 3.0], [217.0, 3.0], [3.0, 165.0], [100.0, 80.0]];
        let b: Vec<Point> = d.iter().map(|&p| t.apply(p)).collect();
        let f = fit_rigid(&d, &b);
        assert!((f.rotation_rad - t.rotation_rad).abs() < 1e-12);
        assert!((f.tx - t.tx).abs() < 1e-9 && (f.ty - t.ty).abs() < 1e-9);
    }
}
