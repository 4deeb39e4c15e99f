//! The provenance of a camera's board rows (`dpsa_board::provenance`: the registration replayed
//! on the frames' triggers, the dead-pixel masks, the row places), and with a simulated
//! recording's truth the Cramer-Rao bound per pixel ([`crb_variance`]): from the window's
//! actual shifts, the camera truth's background, contrast and height, the noise model, and the
//! column's calibrated height per turn `T_z(c)`. The board stage carries it through resampling
//! and blending with the same weights as the heights, so `truth.crb_rms_um` bounds the map the
//! tool writes, not a raw camera pixel.

use super::Grid;
use crate::reference::crb::phase_variance;
use crate::reference::truth::CameraTruthReader;
use crate::simulation::recording::Recording;
use crate::{At, Result};
use dpsa_core::Trigger;
use std::f64::consts::TAU;

pub use dpsa_board::places::RowPlaces;
pub use dpsa_board::provenance::{
    mask_dead_pixels, plan_triggers, row_places, Provenance, Registration, RowPlan,
};

/// The registration of a recording's frames (its manifest's triggers, processing and counts
/// per pixel: calibrate the recording first).
pub fn of_recording(rec: &Recording) -> Provenance {
    let m = &rec.manifest;
    let triggers: Vec<Trigger> = m.frames.iter().map(|f| f.trigger()).collect();
    Provenance::replay(&triggers, &registration(rec))
}

/// What replaying a recording's frames needs besides their triggers, from its manifest.
pub fn registration(rec: &Recording) -> Registration {
    let m = &rec.manifest;
    Registration {
        rows: m.camera.rows,
        n: m.processing.n,
        max_step_rows: m.processing.max_step_rows,
        counts_per_pixel: m.calibration.counts_per_pixel,
    }
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
    let Some(mut truth) = CameraTruthReader::open(rec).at(|| "reading the camera truth")? else {
        return Ok(None);
    };
    let f_x = 1.0 / m.calibration.fringe_period_px;
    let mut var = Grid::invalid(g.width, g.rows);
    for i in 0..g.rows {
        let b = first_row + i as i64;
        let Some(offs) = prov.window_offsets(b) else {
            continue;
        };
        let Some(t) = truth.row(b).at(|| "reading the camera truth")? else {
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
