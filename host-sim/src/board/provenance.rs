//! Where a camera's board rows came from: for every board row the core emitted, the frames of
//! its window and the image row each frame saw it at (the registration of `docs/model.md`,
//! replayed from the manifest's latches by [`crate::reference::dpsa::plan`], which the core
//! matches row for row).
//!
//! Two things need it:
//! - **Dead pixels.** A dead or weak image pixel `(r, c)` of the calibration feeds board row
//!   `b` at column `c` exactly when one of `b`'s window frames `k` saw `b` at image row
//!   `b - o_k = r`. Those board pixels are masked ([`mask_dead_pixels`]): with a steady
//!   step of `s` rows per frame that is one board row in about `s`, a streak the least
//!   squares would otherwise turn into a wrong height (tens of um) that looks valid.
//! - **The Cramer-Rao bound per pixel** ([`crb_variance`]): from the window's actual shifts,
//!   the camera truth's background, contrast and height, the noise model, and the column's
//!   calibrated height per turn `T_z(c)`. The board stage carries it through resampling and
//!   blending with the same weights as the heights, so `truth.crb_rms_um` bounds the map the
//!   tool writes, not a raw camera pixel.

use super::Grid;
use crate::reference::crb::phase_variance;
use crate::reference::dpsa::{offsets, plan};
use crate::reference::truth::TruthReader;
use crate::simulation::recording::Recording;
use anyhow::{Context, Result};
use std::collections::HashMap;
use std::f64::consts::TAU;

/// The window of every board row with a complete one: `b -> (o_w, ..., o_{w+n-1})` and the
/// sub-row travel of each of those frames, `latch_k / cpp - o_k` in `[-1/2, 1/2)` rows (the core
/// registers whole rows, `o_k = round(latch_k / cpp)`).
fn windows(rec: &Recording) -> HashMap<i64, (Vec<i64>, Vec<f64>)> {
    let m = &rec.manifest;
    let n = usize::from(m.processing.n);
    let cpp = m.calibration.counts_per_pixel;
    let Some(o) = offsets(m) else {
        return HashMap::new();
    };
    plan(m)
        .into_iter()
        .filter_map(|p| {
            let w = p.first_frame?;
            (p.flags == 0 && w + n <= o.len()).then(|| {
                let frac = (w..w + n)
                    .map(|k| m.frames[k].latch as f64 / cpp - o[k] as f64)
                    .collect();
                (p.row, (o[w..w + n].to_vec(), frac))
            })
        })
        .collect()
}

/// Where each row of a camera's grid (row `i` is board row `first_row + i`) was seen, as
/// [`RowPlaces`]: along the motion `i + mean_k(latch_k / cpp - o_k)` over its window frames,
/// across it the mean image row `mean_k(b - o_k)` against the placement's `r_w`.
///
/// The core registers whole rows, so the board points behind one board row lie up to half a row
/// off its nominal place in each window frame, by that frame's sub-row travel; and the row is
/// seen at a different image row in each window frame, which with a rotation `a` of the image
/// rows moves it across by `p sin a` per image row. The row's height is the least-squares blend
/// of those points, centred on their mean. Rows without a window keep the nominal place.
pub fn row_places(
    rec: &Recording,
    first_row: i64,
    rows: usize,
    r_w: f64,
    rotation_rad: f64,
) -> RowPlaces {
    let win = windows(rec);
    let mean = |v: &mut dyn Iterator<Item = f64>| {
        let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
        s / n.max(1) as f64
    };
    let mut along = Vec::with_capacity(rows);
    let mut across = Vec::with_capacity(rows);
    for i in 0..rows {
        let b = first_row + i as i64;
        match win.get(&b) {
            Some((o, f)) => {
                along.push(i as f64 + mean(&mut f.iter().copied()));
                let r_mean = mean(&mut o.iter().map(|&ok| (b - ok) as f64));
                across.push((r_mean - r_w) * rotation_rad.tan());
            }
            None => {
                along.push(i as f64);
                across.push(0.0);
            }
        }
    }
    RowPlaces { along, across }
}

pub use dpsa_board::places::RowPlaces;

/// Masks (sets to NaN) every pixel of `g` (row `i` is board row `first_row + i`) that a dead
/// image pixel `[r, c]` of `dead` fed; returns how many valid pixels it masked.
pub fn mask_dead_pixels(rec: &Recording, dead: &[[u32; 2]], first_row: i64, g: &mut Grid) -> u64 {
    if dead.is_empty() {
        return 0;
    }
    let mut by_row: HashMap<i64, Vec<usize>> = HashMap::new();
    for &[r, c] in dead {
        by_row.entry(i64::from(r)).or_default().push(c as usize);
    }
    let mut masked = 0;
    for (b, (offs, _)) in windows(rec) {
        let Some(i) = b
            .checked_sub(first_row)
            .filter(|&i| i >= 0 && (i as usize) < g.rows)
        else {
            continue;
        };
        for &ok in &offs {
            if let Some(cols) = by_row.get(&(b - ok)) {
                for &c in cols {
                    if c < g.width {
                        let v = g.at_mut(i as usize, c);
                        masked += u64::from(v.is_finite());
                        *v = f32::NAN;
                    }
                }
            }
        }
    }
    masked
}

/// Cramer-Rao bound of the height variance, um^2, for every valid pixel of `g` (same layout),
/// from the camera truth of `rec` (its manifest calibrated: `f_x`, `phi_0(c)`) with `T_z(c)` =
/// `height_per_turn_um[c]`. NaN where the pixel is invalid or the truth does not cover it.
/// `Ok(None)` when the recording has no truth or no noise model.
///
/// Model (as [`crate::reference::crb`](fn@crate::reference::crb)): samples `I_j = B + C cos(Phi + theta_j)` with
/// independent Gaussian noise `sigma_j^2 = read^2 + I_j / gain + 1/12` DN^2; Fisher matrix of
/// `(B, C, Phi)` from Jacobian rows `[1, cos, -C sin]`; `var_h = (F^-1)_Phi (T_z / 2 pi)^2`.
pub fn crb_variance(
    rec: &Recording,
    height_per_turn_um: &[f64],
    first_row: i64,
    g: &Grid,
) -> Result<Option<Grid>> {
    let m = &rec.manifest;
    let Some(noise) = &m.noise else {
        return Ok(None);
    };
    let Some(mut truth) = TruthReader::open(rec).context("reading the camera truth")? else {
        return Ok(None);
    };
    let f_x = 1.0 / m.calibration.fringe_period_px;
    let win = windows(rec);
    let mut var = Grid::invalid(g.width, g.rows);
    for i in 0..g.rows {
        let b = first_row + i as i64;
        let Some((offs, _)) = win.get(&b) else {
            continue;
        };
        let Some(t) = truth.row(b).context("reading the camera truth")? else {
            continue;
        };
        let theta: Vec<f64> = offs
            .iter()
            .map(|&ok| -TAU * f_x * (ok - offs[0]) as f64)
            .collect();
        let phi_r = TAU * f_x * (b - offs[0]) as f64;
        for c in 0..g.width {
            if !g.at(i, c).is_finite() {
                continue;
            }
            let Some((h, bg, ct)) = t.at(c) else { continue };
            let phi0 = m.calibration.reference_phase_rad.get(c).copied();
            let t_z = height_per_turn_um.get(c).copied();
            let (Some(phi0), Some(t_z)) = (phi0, t_z) else {
                continue;
            };
            let phi = phi_r + phi0 + TAU * h / t_z;
            if let Some(v) = phase_variance(noise, phi, &theta, bg, ct) {
                *var.at_mut(i, c) = (v * (t_z / TAU).powi(2)) as f32;
            }
        }
    }
    Ok(Some(var))
}
