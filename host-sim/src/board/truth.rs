//! A board map against the simulator's ground truth: the truth raster and the statistics of
//! the map's errors (the simulator's side of [`dpsa_board::assemble`]).

use dpsa_board::resample::BoardGrid;
use dpsa_formats::grid::Grid;

/// The ground truth of a board: heights on a raster of `pitch_mm` from `(x0_mm, y0_mm)`
/// (row `i` along the motion), um.
#[derive(Clone, Debug)]
pub struct BoardTruth {
    /// Board `X` (along the motion) of the raster's corner, mm: cell `i` is centred at
    /// `x0_mm + (i + 0.5) pitch_mm`.
    pub x0_mm: f64,
    /// Board `Y` (across) of the raster's corner, mm.
    pub y0_mm: f64,
    /// Raster pitch on both axes, mm.
    pub pitch_mm: f64,
    /// The true heights, um: row `i` along the motion, column `j` across.
    pub heights: Grid,
}

impl BoardTruth {
    /// Bilinear height at board `(x, y)`; NaN outside.
    pub fn at(&self, x: f64, y: f64) -> f32 {
        let (fi, fj) = (
            (x - self.x0_mm) / self.pitch_mm - 0.5,
            (y - self.y0_mm) / self.pitch_mm - 0.5,
        );
        let g = &self.heights;
        if g.rows == 0 || g.width == 0 || g.data.len() < g.rows * g.width {
            return f32::NAN;
        }
        if !(fi >= 0.0 && fj >= 0.0) || fi > (g.rows - 1) as f64 || fj > (g.width - 1) as f64 {
            return f32::NAN;
        }
        let (i, j) = (fi.floor() as usize, fj.floor() as usize);
        let (i1, j1) = ((i + 1).min(g.rows - 1), (j + 1).min(g.width - 1));
        let (a, b) = ((fi - i as f64) as f32, (fj - j as f64) as f32);
        let top = g.at(i, j) * (1.0 - b) + g.at(i, j1) * b;
        let bot = g.at(i1, j) * (1.0 - b) + g.at(i1, j1) * b;
        top * (1.0 - a) + bot * a
    }
}

/// The map against the truth (`truth.*` and `unwrap.*` of `dpsa board --json`).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct MapAccuracy {
    /// Valid pixels inside the truth.
    pub pixels: u64,
    /// Of them, on flat board: the truth's second differences (along, across and both
    /// diagonals, over one step of the coarser of the map and truth grids, at the pixel and
    /// at the corners of the truth cell around it) below [`FLAT_UM`] (no deposit wall nearby;
    /// the bow's curvature is far below it), where the errors are measured.
    pub flat_pixels: u64,
    /// RMS of `h - truth` over the flat pixels, um (the truth carries the warp, so the warp
    /// is removed by it).
    pub rms_um: Option<f64>,
    /// Mean of `h - truth` over the flat pixels, um.
    pub bias_um: Option<f64>,
    /// The Cramer-Rao bound over the same pixels: RMS of each pixel's bound, propagated from
    /// its cameras' pixels through the resampling and blending weights, um (None without a
    /// noise model; pixels without a bound are then left out of `rms_um` too).
    pub crb_rms_um: Option<f64>,
    /// `rms_um / crb_rms_um`.
    pub over_crb: Option<f64>,
    /// Valid pixels whose absolute height is off by half a turn or more.
    pub wrong_turn_pixels: u64,
}

/// The truth's largest second difference over one pixel below which a pixel is flat, um.
pub const FLAT_UM: f32 = 1.0;

/// Compares `map` on `grid` with `truth`; `period` gives each pixel's height per turn (um).
pub fn against_truth(
    map: &Grid,
    variance: Option<&Grid>,
    period: impl Fn(usize, usize) -> f32,
    grid: &BoardGrid,
    truth: &BoardTruth,
    rows_done: &indicatif::ProgressBar,
) -> MapAccuracy {
    let mut st = MapAccuracy::default();
    let (mut sum, mut sq, mut vsum) = (0.0f64, 0.0f64, 0.0f64);
    for i in 0..grid.rows {
        rows_done.inc(1);
        for j in 0..grid.width {
            let h = map.at(i, j);
            if !h.is_finite() {
                continue;
            }
            let (x, y) = grid.centre(i, j);
            let t = truth.at(x, y);
            if !t.is_finite() {
                continue;
            }
            st.pixels += 1;
            let d = f64::from(h - t);
            if d.abs() >= 0.5 * f64::from(period(i, j)) {
                st.wrong_turn_pixels += 1;
            }
            // The truth's curvature at the pixel and at the four corners of the truth cell
            // around it, over one step of the coarser of the two grids: a truth raster coarser
            // than the map cannot show a deposit wall between its nodes to a finer test, and
            // the bilinear truth there is not the board.
            let p = grid.pitch_mm.max(truth.pitch_mm);
            let h = 0.5 * truth.pitch_mm;
            let curvature = [(0.0, 0.0), (h, h), (h, -h), (-h, h), (-h, -h)]
                .iter()
                .flat_map(|&(ox, oy)| {
                    let (cx, cy) = (x + ox, y + oy);
                    let tc = truth.at(cx, cy);
                    [(p, 0.0), (0.0, p), (p, p), (p, -p)].map(|(dx, dy)| {
                        (truth.at(cx + dx, cy + dy) + truth.at(cx - dx, cy - dy) - 2.0 * tc).abs()
                    })
                })
                .fold(
                    0.0f32,
                    |m, v| if v.is_nan() { f32::INFINITY } else { m.max(v) },
                );
            let var = variance.map(|v| f64::from(v.at(i, j)));
            if curvature < FLAT_UM && var.is_none_or(f64::is_finite) {
                vsum += var.unwrap_or(0.0);
                st.flat_pixels += 1;
                sum += d;
                sq += d * d;
            }
        }
    }
    if st.flat_pixels > 0 {
        let n = st.flat_pixels as f64;
        st.rms_um = Some((sq / n).sqrt());
        st.bias_um = Some(sum / n);
        if variance.is_some() {
            st.crb_rms_um = Some((vsum / n).sqrt());
            st.over_crb = st.rms_um.zip(st.crb_rms_um).map(|(r, c)| r / c);
        }
    }
    st
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_board::assemble::{assemble, CameraRows};
    use dpsa_board::resample::CameraPlacement;

    /// Two cameras over a bowed board with paste, each wrapped and with noise: the assembled
    /// map matches the truth with no wrong turn, within the noise on flat board.
    #[test]
    fn two_wrapped_cameras_assemble_into_the_truth() {
        let (len, wid) = (14.0, 9.0);
        let bow = |x: f64, y: f64| {
            let (xi, eta) = (2.0 * x / len - 1.0, 2.0 * y / wid - 1.0);
            800.0 * (1.0 - xi * xi) * (1.0 - eta * eta)
        };
        let paste = |x: f64, y: f64| {
            let (u, v) = (x.rem_euclid(1.2), y.rem_euclid(1.0));
            let inside = (u - 0.2).min(0.7 - u).min(v - 0.2).min(0.6 - v);
            120.0 * (inside / 0.05 + 0.5).clamp(0.0, 1.0)
        };
        let truth_fn = |x: f64, y: f64| bow(x, y) + paste(x, y);
        let tp = 0.01;
        let mut raster = Grid::invalid((wid / tp) as usize, (len / tp) as usize);
        for i in 0..raster.rows {
            for j in 0..raster.width {
                *raster.at_mut(i, j) =
                    truth_fn((i as f64 + 0.5) * tp, (j as f64 + 0.5) * tp) as f32;
            }
        }
        let truth = BoardTruth {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: tp,
            heights: raster,
        };
        let t_um = 400.0f32;
        let mut seed = 7u64;
        let mut noise = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
            ((seed >> 33) as f32 / (1u64 << 31) as f32 - 0.5) * 3.0
        };
        let mut cams = Vec::new();
        for (k, y0) in [0.0, 4.3].into_iter().enumerate() {
            let place = CameraPlacement {
                x0_mm: 0.0,
                y0_mm: y0,
                row_mm: 0.03,
                pitch_mm: 0.0301,
                rotation_rad: [0.002, -0.003][k],
            };
            let (w, rows) = (160usize, 466usize);
            let period: Vec<f32> = (0..w)
                .map(|c| t_um * (1.0 + 0.02 * (c as f32 / w as f32 - 0.5)))
                .collect();
            let mut g = Grid::invalid(w, rows);
            for b in 0..rows {
                for (c, &t) in period.iter().enumerate() {
                    let (x, y) = place.to_board(b as f64, c as f64);
                    let h = truth_fn(x, y) as f32 + noise();
                    *g.at_mut(b, c) = h - t * (h / t + 0.5).floor();
                }
            }
            cams.push(CameraRows {
                heights: g,
                // The uniform noise's variance, (3 um)^2 / 12.
                variance: Some(Grid {
                    width: w,
                    rows,
                    data: vec![0.75; w * rows],
                }),
                dead_masked: 0,
                places: None,
                first_row: 0,
                lost: Vec::new(),
                period_um: period,
                reference_rad: Vec::new(),
                placement: place,
            });
        }
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 466,
            width: 300,
        };
        let a = assemble(cams, &grid, Default::default());
        let st = against_truth(
            &a.blended.heights,
            a.blended.variance.as_ref(),
            |_, _| t_um,
            &grid,
            &truth,
            &indicatif::ProgressBar::hidden(),
        );
        assert_eq!(st.wrong_turn_pixels, 0, "{st:?}");
        assert!(st.flat_pixels > 50_000, "{st:?}");
        // Uniform noise of +-1.5 um: rms 0.87 um, halved where cameras blend.
        assert!(st.rms_um.unwrap() < 1.0, "{st:?}");
        assert!(st.bias_um.unwrap().abs() < 0.1, "{st:?}");
        assert!(a.blended.seams[0].height_step_um.unwrap().abs() < 0.3);
        // The propagated variance predicts the measured error: white noise through bilinear
        // resampling and feathered blending (each pixel its own weights).
        let ratio = st.over_crb.unwrap();
        assert!((0.95..1.05).contains(&ratio), "{st:?}");
        assert!(st.crb_rms_um.unwrap() < 0.87, "{st:?}");
    }
}
