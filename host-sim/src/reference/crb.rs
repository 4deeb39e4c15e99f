//! The Cramer-Rao bound of the height variance, per pixel, from the truth and the noise model.

use super::truth::{truth_at, truth_row_index};
use super::{RefOutput, RefRow};
use crate::simulation::recording::{CameraTruth, Manifest, Noise};
use nalgebra::{Matrix3, Vector3};
use std::f64::consts::TAU;

/// Cramer-Rao bound on the height variance, um^2, of each pixel of `out` (which must come
/// from [`reconstruct`](super::reconstruct): the actual window shifts are used). Indexed `[i][c]` for
/// `out.rows[i]`, column `c`.
///
/// Defined (Some) for pixels of valid rows with a window whose truth exists; parameters
/// `(B, C, Phi)` with the true `B`, `C` (`truth.background` / `truth.contrast`) and the true
/// `Phi = 2 pi f_x (b - o_w) + phi_0(c) + 2 pi h_true / T_z`. Samples
/// `I_j = B + C cos(Phi + theta_j)` are modelled as independent Gaussians with variance
/// `sigma_j^2 = read_noise^2 + I_j / gain + 1/12` DN^2: read noise, shot noise (Poisson with
/// variance `I_j / gain` DN^2, approximated as Gaussian, which is accurate at the electron
/// counts of interest) and rounding to whole DN (uniform, 1/12 DN^2). Saturation clipping and
/// the lateral sub-pixel registration error are not modelled. With Jacobian rows
/// `J_j = [1, cos(Phi + theta_j), -C sin(Phi + theta_j)]`, `F = sum_j J_j J_j^T / sigma_j^2`,
/// `var_Phi = (F^-1)[2][2]` and `var_h = var_Phi (T_z / 2 pi)^2`.
///
/// Every entry is `None` when the manifest has no noise model.
pub fn crb(manifest: &Manifest, truth: &CameraTruth, out: &RefOutput) -> Vec<Vec<Option<f64>>> {
    out.rows
        .iter()
        .map(|row| match truth_row_index(truth, row.row) {
            Some(ti) => crb_row(manifest, row, |c| truth_at(truth, ti, c)),
            None => vec![None; out.width],
        })
        .collect()
}

/// [`crb`] of one reference row, with the truth of its board row given per column as
/// `(height um, background DN, contrast DN)`.
pub fn crb_row(
    manifest: &Manifest,
    row: &RefRow,
    truth: impl Fn(usize) -> Option<(f64, f64, f64)>,
) -> Vec<Option<f64>> {
    let width = row.valid.len();
    let mut v = vec![None; width];
    let Some(noise) = &manifest.noise else {
        return v;
    };
    let Some(window) = row.window.as_ref().filter(|_| row.is_valid()) else {
        return v;
    };
    let cal = &manifest.calibration;
    let f_x = 1.0 / cal.fringe_period_px;
    let phi_r_row = TAU * f_x * (row.row - window.offsets.first().copied().unwrap_or(0)) as f64;
    for (c, slot) in v.iter_mut().enumerate() {
        let Some((h_true, bg, ct)) = truth(c) else {
            continue;
        };
        let phi0 = cal.reference_phase_rad.get(c).copied().unwrap_or(f64::NAN);
        let t_z = cal.height_per_turn_at(c);
        let phi = phi_r_row + phi0 + TAU * h_true / t_z;
        *slot =
            phase_variance(noise, phi, &window.shifts_rad, bg, ct).map(|v| v * (t_z / TAU).powi(2));
    }
    v
}

/// The Cramer-Rao bound of the phase variance, rad^2, of one pixel with true phase `phi`,
/// background `bg` and contrast `ct` (DN) seen at the shifts `theta` (rad), under the noise
/// model of [`crb`]; `None` when the Fisher matrix is singular.
pub fn phase_variance(noise: &Noise, phi: f64, theta: &[f64], bg: f64, ct: f64) -> Option<f64> {
    let read_var = noise.read_noise_dn * noise.read_noise_dn;
    let mut fisher = Matrix3::<f64>::zeros();
    for &t in theta {
        let (s, co) = (phi + t).sin_cos();
        let i = (bg + ct * co).max(0.0);
        let var = read_var + i / noise.gain_e_per_dn + 1.0 / 12.0;
        let jac = Vector3::new(1.0, co, -ct * s);
        fisher += jac * jac.transpose() / var;
    }
    fisher
        .try_inverse()
        .map(|inv| inv[(2, 2)])
        .filter(|x| x.is_finite() && *x >= 0.0)
}
