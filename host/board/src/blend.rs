//! The cameras' layers into one board map.
//!
//! 1. **Turns between cameras.** Each camera was unwrapped on its own (`super::unwrap`), so
//!    two neighbours may sit whole turns apart. Layers are taken in order across the board;
//!    each is moved by the whole number of turns that brings the median of its difference to
//!    the previous layer, over their shared valid pixels, nearest to zero.
//! 2. **The board's turn.** The board is clamped at its edges on the conveyor rails, which the
//!    calibration planes define as height 0: the whole map is moved by the whole number of
//!    turns that brings the median height of the valid pixels within `edge_px` of the board
//!    outline nearest to zero.
//! 3. **Blend.** Each pixel is the weighted mean of the valid layers (weights fall to zero at a
//!    camera's side edges, so overlaps are feathered); the camera with the largest weight is
//!    recorded as the pixel's source.
//! 4. **Seams.** For each pair of neighbouring layers, over their shared valid pixels on flat
//!    board (the 3 x 3 range of the blended map below [`FLAT_RANGE_UM`]): the mean height
//!    difference, and the lateral misregistration: the shift (along and across, sub-pixel, a
//!    gradient estimate without interpolation, see `best_shift`) that best aligns one layer to
//!    the other over all shared pixels. The shift needs texture: at least [`MIN_WALL_PIXELS`]
//!    deposit-wall pixels (a step above [`WALL_UM`] between neighbours along the shift) in the
//!    overlap; otherwise it is not reported (null).

use crate::resample::{BoardGrid, Layer};
use crate::Grid;

/// A pixel counts as flat board when the 3 x 3 range of the blended map is below this, um.
pub const FLAT_RANGE_UM: f32 = 25.0;

/// A height step between neighbouring pixels above this is a deposit wall, um.
pub const WALL_UM: f32 = 20.0;
/// Wall pixels a seam's shared area needs for its misregistration to be measured.
pub const MIN_WALL_PIXELS: usize = 50;

/// No camera (invalid pixel) in [`Blended::camera`].
pub const NO_CAMERA: u8 = u8::MAX;

/// Two neighbouring cameras over their shared pixels.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Seam {
    /// Layer indices (the earlier, the later).
    pub cameras: (usize, usize),
    /// Shared valid pixels.
    pub pixels: u64,
    /// Of them, on flat board.
    pub flat_pixels: u64,
    /// Mean height of the later minus the earlier over the flat shared pixels, um.
    pub height_step_um: Option<f64>,
    /// Misregistration along the motion (later against earlier), um.
    pub shift_x_um: Option<f64>,
    /// Misregistration across the motion, um.
    pub shift_y_um: Option<f64>,
}

impl Seam {
    /// Length of the misregistration vector, um.
    pub fn lateral_um(&self) -> Option<f64> {
        Some(self.shift_x_um?.hypot(self.shift_y_um?))
    }
}

/// The blended board map.
#[derive(Clone, Debug)]
pub struct Blended {
    /// Absolute heights, um (NaN invalid).
    pub heights: Grid,
    /// Variance of each height, um^2, through the blending weights (NaN: unknown); `None`
    /// when no camera came with one.
    pub variance: Option<Grid>,
    /// Source camera of each pixel ([`NO_CAMERA`] where invalid).
    pub camera: Vec<u8>,
    /// Whole turns each layer was moved by (steps 1 and 2).
    pub turns: Vec<i32>,
    /// Median height of the board edge before step 2, um (None: no valid edge pixel).
    pub edge_median_um: Option<f64>,
    /// Neighbouring layers.
    pub seams: Vec<Seam>,
}

fn median(mut v: Vec<f32>) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f32::total_cmp);
    Some(v[v.len() / 2])
}

/// Blends `layers` (in order across the board) on `grid`; see the module docs.
pub fn blend(layers: &mut [Layer], grid: &BoardGrid, edge_px: usize) -> Blended {
    let n = grid.rows * grid.width;
    let mut turns = vec![0i32; layers.len()];

    // 1. Turns between neighbours.
    for k in 1..layers.len() {
        let (done, rest) = layers.split_at_mut(k);
        let (prev, cur) = (&done[k - 1], &mut rest[0]);
        let mut d = Vec::new();
        let mut t = Vec::new();
        // Over the shared window, in board order (outside it one of the two is NaN).
        let (rows, cols) = prev.overlap(cur);
        for r in rows {
            for c in cols.clone() {
                let (Some(ia), Some(ib)) = (prev.index(r, c), cur.index(r, c)) else {
                    continue;
                };
                let (a, b) = (prev.heights.data[ia], cur.heights.data[ib]);
                if a.is_finite() && b.is_finite() {
                    d.push(b - a);
                    t.push(cur.period_um.data[ib]);
                }
            }
        }
        if let (Some(d), Some(t)) = (median(d), median(t)) {
            let k_turns = (-d / t).round() as i32;
            shift(cur, k_turns);
            turns[k] = k_turns;
        }
    }

    // 3. Blend (the board's turn is applied after, to the layers and the map alike).
    let mut heights = Grid::invalid(grid.width, grid.rows);
    let mut variance = layers
        .iter()
        .any(|l| l.variance.is_some())
        .then(|| Grid::invalid(grid.width, grid.rows));
    // The blended height per turn is not kept (a board-sized grid): step 2 recomputes it
    // where it needs it ([`mixed_period`]).
    let mut camera = vec![NO_CAMERA; n];
    // In parallel over row bands: every pixel is its own weighted mean.
    let threads = std::thread::available_parallelism().map_or(1, |t| t.get());
    let band = n.div_ceil(threads.max(1)).max(1);
    let layers_ref: &[Layer] = layers;
    std::thread::scope(|sc| {
        let parts = heights
            .data
            .chunks_mut(band)
            .zip(
                variance
                    .as_mut()
                    .map_or(&mut [][..], |v| &mut v.data[..])
                    .chunks_mut(band)
                    .map(Some)
                    .chain(std::iter::repeat_with(|| None)),
            )
            .zip(camera.chunks_mut(band))
            .enumerate();
        for (part, ((hs, mut vs_out), cs)) in parts {
            sc.spawn(move || {
                // Board row and column of the band's first pixel, then stepped.
                let first = part * band;
                let (mut r, mut c) = (first / grid.width, first % grid.width);
                for j in 0..hs.len() {
                    let (mut s, mut ws, mut vs) = (0.0f64, 0.0f64, 0.0f64);
                    let mut best = (0.0f32, NO_CAMERA);
                    for (k, l) in layers_ref.iter().enumerate() {
                        let Some(i) = l.index(r, c) else {
                            continue;
                        };
                        let h = l.heights.data[i];
                        let w = l.weight.data[i];
                        if h.is_finite() && w > 0.0 {
                            let wf = f64::from(w);
                            s += wf * f64::from(h);
                            ws += wf;
                            // A camera without a variance leaves the pixel's unknown (NaN).
                            vs += wf
                                * wf
                                * l.variance
                                    .as_ref()
                                    .map_or(f64::NAN, |v| f64::from(v.data[i]));
                            if w > best.0 {
                                best = (w, k.min(254) as u8);
                            }
                        }
                    }
                    c += 1;
                    if c == grid.width {
                        (r, c) = (r + 1, 0);
                    }
                    if ws > 0.0 {
                        hs[j] = (s / ws) as f32;
                        if let Some(v) = vs_out.as_deref_mut() {
                            v[j] = (vs / (ws * ws)) as f32;
                        }
                        cs[j] = best.1;
                    }
                }
            });
        }
    });

    // 2. The board's turn from its clamped edges.
    let mut edge = Vec::new();
    let mut edge_t = Vec::new();
    for r in 0..grid.rows {
        for c in 0..grid.width {
            let on_edge =
                r < edge_px || c < edge_px || r + edge_px >= grid.rows || c + edge_px >= grid.width;
            let h = heights.at(r, c);
            if on_edge && h.is_finite() {
                edge.push(h);
                edge_t.push(mixed_period(layers, r, c));
            }
        }
    }
    let edge_median_um = median(edge).map(f64::from);
    if let (Some(m), Some(t)) = (edge_median_um, median(edge_t)) {
        let k = (-m / f64::from(t)).round() as i32;
        if k != 0 {
            for (l, tk) in layers.iter_mut().zip(turns.iter_mut()) {
                shift(l, k);
                *tk += k;
            }
            // Each valid pixel by `k` turns of its blended height per turn, recomputed from
            // the layers (the shift above moved their heights, not their validity or weights).
            let layers_ref: &[Layer] = layers;
            let width = grid.width;
            std::thread::scope(|sc| {
                for (part, hs) in heights.data.chunks_mut(band).enumerate() {
                    sc.spawn(move || {
                        let first = part * band;
                        let (mut r, mut c) = (first / width, first % width);
                        for h in hs.iter_mut() {
                            if h.is_finite() {
                                *h += k as f32 * mixed_period(layers_ref, r, c);
                            }
                            c += 1;
                            if c == width {
                                (r, c) = (r + 1, 0);
                            }
                        }
                    });
                }
            });
        }
    }

    // 4. Seams.
    let seams = (1..layers.len())
        .map(|k| seam(&layers[k - 1], &layers[k], &heights, grid, (k - 1, k)))
        .collect();
    Blended {
        heights,
        variance,
        camera,
        turns,
        edge_median_um,
        seams,
    }
}

/// The blended height per turn at board pixel `(r, c)`, um: the covering layers' weighted as
/// step 3 weighs their heights (the same sums in the same order); 0 where no layer is valid.
fn mixed_period(layers: &[Layer], r: usize, c: usize) -> f32 {
    let (mut ts, mut ws) = (0.0f64, 0.0f64);
    for l in layers {
        let Some(i) = l.index(r, c) else {
            continue;
        };
        let (h, w) = (l.heights.data[i], l.weight.data[i]);
        if h.is_finite() && w > 0.0 {
            let wf = f64::from(w);
            ts += wf * f64::from(l.period_um.data[i]);
            ws += wf;
        }
    }
    if ws > 0.0 {
        (ts / ws) as f32
    } else {
        0.0
    }
}

fn shift(l: &mut Layer, turns: i32) {
    if turns == 0 {
        return;
    }
    for (h, t) in l.heights.data.iter_mut().zip(&l.period_um.data) {
        *h += turns as f32 * t;
    }
}

/// Pixels whose 3 x 3 neighbourhood is valid with a range below [`FLAT_RANGE_UM`].
/// True when pixel `(r, c)` of `g` is flat board: its 3 x 3 neighbourhood valid with a range
/// below [`FLAT_RANGE_UM`] (the outermost rows and columns never are).
fn is_flat(g: &Grid, r: usize, c: usize) -> bool {
    if r == 0 || c == 0 || r + 1 >= g.rows || c + 1 >= g.width {
        return false;
    }
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for rr in r - 1..=r + 1 {
        for cc in c - 1..=c + 1 {
            let h = g.at(rr, cc);
            lo = lo.min(h);
            hi = hi.max(h);
        }
    }
    lo.is_finite() && hi.is_finite() && hi - lo < FLAT_RANGE_UM
}

fn seam(a: &Layer, b: &Layer, map: &Grid, grid: &BoardGrid, ids: (usize, usize)) -> Seam {
    let (mut pixels, mut flat_n, mut sum) = (0u64, 0u64, 0.0f64);
    // Over the shared window in board order: outside it one of the two is NaN.
    let (rows, cols) = a.overlap(b);
    for r in rows {
        for c in cols.clone() {
            let (ha, hb) = (a.height(r, c), b.height(r, c));
            if ha.is_finite() && hb.is_finite() {
                pixels += 1;
                if is_flat(map, r, c) {
                    flat_n += 1;
                    sum += f64::from(hb - ha);
                }
            }
        }
    }
    let to_um = grid.pitch_mm * 1000.0;
    let shift_x = best_shift(a, b, 1, 0).map(|s| s * to_um);
    let shift_y = best_shift(a, b, 0, 1).map(|s| s * to_um);
    Seam {
        cameras: ids,
        pixels,
        flat_pixels: flat_n,
        height_step_um: (flat_n > 0).then(|| sum / flat_n as f64),
        shift_x_um: shift_x,
        shift_y_um: shift_y,
    }
}

/// The shift `s` (px, along `(dr, dc)`) that best aligns `b` to `a`, `b(p) = a(p + s) + k`
/// over the pixels valid in both: a gradient (Lucas-Kanade) estimate, `d = b - a = k + s g`
/// solved by least squares for `(k, s)`, with `g` the central difference along the shift of
/// the two layers' mean. No layer is interpolated: a search over interpolated shifts lowers
/// the noise of the interpolated samples away from whole pixels (`(1-f)^2 + f^2` of it) and
/// so finds a false minimum a fraction of a pixel off either way. `None` without texture (fewer
/// than [`MIN_WALL_PIXELS`] deposit-wall pixels in the shared area) or with a shift beyond
/// the first-order range (2 px).
fn best_shift(a: &Layer, b: &Layer, dr: i64, dc: i64) -> Option<f64> {
    // Board pixel `(r, c)` of a layer; NaN outside the board and the layer's window.
    let at = |l: &Layer, r: i64, c: i64| -> f64 {
        if r < 0 || c < 0 {
            f64::NAN
        } else {
            f64::from(l.height(r as usize, c as usize))
        }
    };
    // The shared area's bounding box: nothing outside it pairs.
    let (rows, cols) = a.overlap(b);
    let (mut r_lo, mut r_hi, mut c_lo, mut c_hi) = (i64::MAX, -1i64, i64::MAX, -1i64);
    for r in rows {
        for c in cols.clone() {
            if a.height(r, c).is_finite() && b.height(r, c).is_finite() {
                let (r, c) = (r as i64, c as i64);
                (r_lo, r_hi, c_lo, c_hi) = (r_lo.min(r), r_hi.max(r), c_lo.min(c), c_hi.max(c));
            }
        }
    }
    if r_hi < 0 {
        return None;
    }
    let (mut n, mut sg, mut sgg, mut sd, mut sdg) = (0u64, 0.0, 0.0, 0.0, 0.0);
    let mut walls = 0usize;
    for r in r_lo..=r_hi {
        for c in c_lo..=c_hi {
            let (a0, b0) = (at(a, r, c), at(b, r, c));
            let (ap, bp) = (at(a, r + dr, c + dc), at(b, r + dr, c + dc));
            let (am, bm) = (at(a, r - dr, c - dc), at(b, r - dr, c - dc));
            if ![a0, b0, ap, bp, am, bm].iter().all(|v| v.is_finite()) {
                continue;
            }
            if (bp - b0).abs() > f64::from(WALL_UM) {
                walls += 1;
            }
            let g = 0.25 * ((ap + bp) - (am + bm));
            let d = b0 - a0;
            n += 1;
            sg += g;
            sgg += g * g;
            sd += d;
            sdg += d * g;
        }
    }
    if walls < MIN_WALL_PIXELS || n < 100 {
        return None;
    }
    let nf = n as f64;
    let det = nf * sgg - sg * sg;
    if det.is_nan() || det <= 0.0 {
        return None;
    }
    let s = (nf * sdg - sg * sd) / det;
    (s.is_finite() && s.abs() <= 2.0).then_some(s)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::resample::{resample, CameraPlacement, Source};

    /// Truth on the board: a bow (0 at the edges) and paste boxes whose walls slope over
    /// 0.1 mm (as a camera's pixel integration and blur make them; a point-sampled step
    /// would hide where its edge lies within a pixel).
    fn truth(x: f64, y: f64, len: f64, wid: f64) -> f64 {
        let (xi, eta) = (2.0 * x / len - 1.0, 2.0 * y / wid - 1.0);
        let bow = 900.0 * (1.0 - xi * xi) * (1.0 - eta * eta);
        // Distance inside the box [0.1, 0.5) x [0.1, 0.6) of each 1 mm cell, mm.
        let (u, v) = (x.rem_euclid(1.0), y.rem_euclid(1.0));
        let inside = (u - 0.1).min(0.5 - u).min(v - 0.1).min(0.6 - v);
        bow + 120.0 * (inside / 0.1 + 0.5).clamp(0.0, 1.0)
    }

    /// A camera of `cols x rows` pixels on a 0.03 mm grid at `y0` across, placed (by its
    /// calibration) `dy` mm off where its pixels really sit, seeing `height` (um at board
    /// `(x, y)`), resampled onto `grid` with a height per turn of `t`.
    fn layer(
        y0: f64,
        dy: f64,
        (cols, rows): (usize, usize),
        t: f32,
        height: impl Fn(f64, f64) -> f64,
        grid: &BoardGrid,
    ) -> Layer {
        let place = CameraPlacement {
            x0_mm: 0.0,
            y0_mm: y0,
            row_mm: 0.03,
            pitch_mm: 0.03,
            rotation_rad: 0.0,
        };
        let real = CameraPlacement {
            y0_mm: y0 - dy,
            ..place
        };
        let mut cam = Grid::invalid(cols, rows);
        for b in 0..rows {
            for c in 0..cols {
                let (x, y) = real.to_board(b as f64, c as f64);
                *cam.at_mut(b, c) = height(x, y) as f32;
            }
        }
        let src = Source {
            heights: &cam,
            variance: None,
            period_um: &vec![t; cols],
            first_row: 0,
            places: None,
            lost_rows: &[],
        };
        resample(&src, &place, grid, 15.0)
    }

    #[test]
    fn three_cameras_turn_aligned_anchored_and_seams_measured() {
        let (len, wid) = (12.0, 9.0);
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 400,
            width: 300,
        };
        let t = 400.0f32;
        // Three cameras of 120 columns, 0.5 mm overlaps; the middle one misplaced by 6 um
        // across (its placement says y0 + 0.006 mm, the pixels sit at y0); each unwrapped
        // to another turn: 0, +1, -2.
        let mut layers: Vec<Layer> = [0.0, 3.1, 6.2]
            .into_iter()
            .enumerate()
            .map(|(k, y0)| {
                let off = f64::from([0.0, 1.0, -2.0][k] * t);
                let dy = if k == 1 { 0.006 } else { 0.0 };
                layer(
                    y0,
                    dy,
                    (120, 400),
                    t,
                    |x, y| truth(x, y, len, wid) + off,
                    &grid,
                )
            })
            .collect();
        let out = blend(&mut layers, &grid, 3);
        assert_eq!(out.turns, vec![0, -1, 2]);
        // Absolute heights against the truth (bilinear on paste walls aside).
        let mut errs = Vec::new();
        for i in 0..grid.rows {
            for j in 0..grid.width {
                let (x, y) = grid.centre(i, j);
                let h = out.heights.at(i, j);
                if h.is_finite() {
                    errs.push((f64::from(h) - truth(x, y, len, wid)).abs());
                }
            }
        }
        errs.sort_by(f64::total_cmp);
        assert!(
            errs[errs.len() / 2] < 1.0,
            "median error {}",
            errs[errs.len() / 2]
        );
        assert!(errs.len() > grid.rows * grid.width * 9 / 10);
        // Seams: flat steps near 0; the 6 um misplacement of camera 1 seen across.
        for s in &out.seams {
            assert!(s.height_step_um.unwrap().abs() < 1.0, "{s:?}");
        }
        let y01 = out.seams[0].shift_y_um.unwrap();
        let y12 = out.seams[1].shift_y_um.unwrap();
        assert!((y01.abs() - 6.0).abs() < 2.0, "{y01}");
        assert!((y12.abs() - 6.0).abs() < 2.0, "{y12}");
        assert!(y01 * y12 < 0.0);
        assert!(out.seams[0].shift_x_um.unwrap().abs() < 2.0);
        assert!(out.camera.contains(&2));
    }

    #[test]
    fn the_boards_turn_moves_every_camera_and_the_map() {
        // Every camera a whole turn off, the edges included: step 2 must bring the map back.
        let (len, wid) = (6.0, 6.0);
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 200,
            width: 200,
        };
        let t = 400.0f32;
        let mut layers: Vec<Layer> = [(0.0, 1.0), (3.0, 2.0)]
            .into_iter()
            .map(|(y0, turns)| {
                let off = f64::from(turns * t);
                layer(
                    y0,
                    0.0,
                    (110, 200),
                    t,
                    |x, y| truth(x, y, len, wid) * 0.1 + off,
                    &grid,
                )
            })
            .collect();
        let out = blend(&mut layers, &grid, 3);
        assert_eq!(out.turns, vec![-1, -2]);
        assert!(out.variance.is_none());
        let mut n = 0;
        for i in 0..grid.rows {
            for j in 0..grid.width {
                let h = out.heights.at(i, j);
                if h.is_finite() {
                    let (x, y) = grid.centre(i, j);
                    assert!(
                        (f64::from(h) - truth(x, y, len, wid) * 0.1).abs() < 15.0,
                        "({i}, {j}) {h}"
                    );
                    n += 1;
                }
            }
        }
        assert!(n > grid.rows * grid.width * 9 / 10, "{n}");
    }
}
