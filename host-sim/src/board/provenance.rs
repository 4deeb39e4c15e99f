//! Where a camera's board rows came from: for every board row the core emitted, the frames of
//! its window and the image row each frame saw it at (the registration of `docs/model.md`,
//! replayed on the frames' triggers by [`crate::reference::dpsa::plan_triggers`], which the
//! core matches row for row): the triggers of a recording's manifest, or the trigger log a
//! camera's packet stream carries (`docs/stream.md`), so that `board --streams` needs no
//! frames. Each row packet's latch confirms its window ([`Provenance::confirms`]).
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
use crate::reference::dpsa::{plan_triggers, trigger_offsets, Registration};
use crate::reference::truth::TruthReader;
use crate::simulation::recording::Recording;
use anyhow::{Context, Result};
use dpsa_core::Trigger;
use std::collections::HashMap;
use std::f64::consts::TAU;

/// One board row's window in the registration replay.
#[derive(Clone, Debug, PartialEq)]
struct RowWindow {
    /// Latch of the window's first frame (what the row's packet carries).
    first_latch: i64,
    /// Row offsets `o_w .. o_{w+n-1}` of the window's frames.
    offsets: Vec<i64>,
    /// Each window frame's sub-row travel `latch_k / cpp - o_k`, in `[-1/2, 1/2)` rows.
    frac: Vec<f64>,
}

/// The registration of a camera's frames replayed on their triggers: for every board row with
/// a complete, unflagged window, the window (the core registers whole rows, `o_k =
/// round(latch_k / cpp)`). From a recording's manifest ([`Provenance::of_recording`]) or a
/// stream's trigger log ([`Provenance::replay`]): the same triggers give the same windows.
#[derive(Clone, Debug, Default)]
pub struct Provenance {
    windows: HashMap<i64, RowWindow>,
}

impl Provenance {
    /// Replays the registration on `triggers` (frame order) with `reg`.
    pub fn replay(triggers: &[Trigger], reg: &Registration) -> Provenance {
        let n = usize::from(reg.n);
        let cpp = reg.counts_per_pixel;
        let Some(o) = trigger_offsets(triggers, cpp) else {
            return Provenance::default();
        };
        let windows = plan_triggers(triggers, reg)
            .into_iter()
            .filter_map(|p| {
                let w = p.first_frame?;
                (p.flags == 0 && w + n <= o.len()).then(|| {
                    let frac = (w..w + n)
                        .map(|k| triggers[k].latch as f64 / cpp - o[k] as f64)
                        .collect();
                    let win = RowWindow {
                        first_latch: triggers[w].latch,
                        offsets: o[w..w + n].to_vec(),
                        frac,
                    };
                    (p.row, win)
                })
            })
            .collect();
        Provenance { windows }
    }

    /// The registration of a recording's frames (its manifest's triggers, processing and
    /// counts per pixel: calibrate the recording first).
    pub fn of_recording(rec: &Recording) -> Provenance {
        let m = &rec.manifest;
        let triggers: Vec<Trigger> = m.frames.iter().map(|f| f.trigger()).collect();
        Provenance::replay(
            &triggers,
            &Registration {
                rows: m.camera.rows,
                n: m.processing.n,
                max_step_rows: m.processing.max_step_rows,
                counts_per_pixel: m.calibration.counts_per_pixel,
            },
        )
    }

    /// Whether board row `row`, emitted with its window's first latch `latch`, has that window
    /// in the replay: only then are its dead-pixel mask and its place known.
    pub fn confirms(&self, row: i64, latch: i64) -> bool {
        self.windows
            .get(&row)
            .is_some_and(|w| w.first_latch == latch)
    }
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
    prov: &Provenance,
    first_row: i64,
    rows: usize,
    r_w: f64,
    rotation_rad: f64,
) -> RowPlaces {
    let mean = |v: &mut dyn Iterator<Item = f64>| {
        let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
        s / n.max(1) as f64
    };
    let mut along = Vec::with_capacity(rows);
    let mut across = Vec::with_capacity(rows);
    for i in 0..rows {
        let b = first_row + i as i64;
        match prov.windows.get(&b) {
            Some(w) => {
                along.push(i as f64 + mean(&mut w.frac.iter().copied()));
                let r_mean = mean(&mut w.offsets.iter().map(|&ok| (b - ok) as f64));
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
pub fn mask_dead_pixels(prov: &Provenance, dead: &[[u32; 2]], first_row: i64, g: &mut Grid) -> u64 {
    if dead.is_empty() {
        return 0;
    }
    let mut by_row: HashMap<i64, Vec<usize>> = HashMap::new();
    for &[r, c] in dead {
        by_row.entry(i64::from(r)).or_default().push(c as usize);
    }
    let mut masked = 0;
    for (&b, w) in &prov.windows {
        let offs = &w.offsets;
        let Some(i) = b
            .checked_sub(first_row)
            .filter(|&i| i >= 0 && (i as usize) < g.rows)
        else {
            continue;
        };
        for &ok in offs {
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
    prov: &Provenance,
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
    let mut var = Grid::invalid(g.width, g.rows);
    for i in 0..g.rows {
        let b = first_row + i as i64;
        let Some(RowWindow { offsets: offs, .. }) = prov.windows.get(&b) else {
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
