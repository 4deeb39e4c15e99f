//! Figures of a calibration: the held-out plane measured with it (needs only the known plane
//! height), and, when the recording carries the simulator's truth, the error of every
//! estimated parameter and the Cramer-Rao bound of the held-out plane.

use crate::array::record::{ArrayRecording, ArrayTruth, PassKind};
use crate::array::scene::CameraModel;
use crate::calibration::estimate::measure_plane;
use crate::calibration::file::{CalFile, CameraCal};
use crate::simulation::recording::Recording;
use crate::{At, Result};
use dpsa_formats::calibration::wrap_phase;
use nalgebra::{Matrix3, Vector3};
use serde::Serialize;
use std::f64::consts::TAU;

/// Estimated parameters against the truth (max over cameras unless said otherwise).
#[derive(Serialize, Clone, Debug, Default)]
pub struct CalibrationAccuracy {
    /// `max |T_z^(c) / T_z(c) - 1|` over columns.
    pub t_z_rel_max: f64,
    /// `|f_core / mean_c f_x(c) - 1|`: the core's single fringe frequency.
    pub f_x_rel_max: f64,
    /// `max |f_x^(c) / f_x(c) - 1|` over columns: the field map.
    pub f_x_field_rel_max: f64,
    /// rms over columns of `wrap_phase(phi_0^ - phi_0)`, mrad.
    pub phi0_rms_mrad: f64,
    /// rms distance between the estimated and the true board point of every pixel of rows
    /// 0, H/2, H-1, um.
    pub lateral_rms_um: f64,
    /// `|cpp^ / cpp - 1|` (encoder counts per board row).
    pub encoder_rel_max: f64,
    /// `|counts_per_mm^ / counts_per_mm - 1|` of the file's mean.
    pub counts_per_mm_rel: f64,
    /// `|rotation^ - rotation|`, millidegrees.
    pub rotation_err_mdeg_max: f64,
    /// `max |B^(c) / B(c) - 1|` over columns without a dead pixel: the flat field.
    pub background_rel_max: f64,
    /// `max |C^(c) / C(c) - 1|` over the same columns: the modulation.
    pub modulation_rel_max: f64,
    /// Dead pixels of the truth not flagged, summed over cameras.
    pub dead_pixels_missed: usize,
    /// Flagged pixels that are not dead in the truth, summed over cameras.
    pub dead_pixels_false: usize,
}

/// The held-out plane measured with the calibration.
#[derive(Serialize, Clone, Debug, Default)]
pub struct Holdout {
    /// Known height of the held-out plane (`array.json`), um.
    pub height_um: f64,
    /// `max |mean(h - height)|` over cameras, um.
    pub bias_um_max: f64,
    /// `max rms(h - height)` over cameras, um.
    pub rms_um: f64,
    /// rms of the per-pixel CRB over the same pixels (camera of `rms_um`), um (truth only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub crb_rms_um: Option<f64>,
    /// `max rms / crb_rms` over cameras (truth only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rms_over_crb_max: Option<f64>,
    /// Pixels measured, summed over cameras (pixels fed by a flagged dead pixel excluded).
    pub pixels: u64,
}

/// Per camera.
#[derive(Serialize, Clone, Debug, Default)]
pub struct CameraFigures {
    /// The camera's place in the array.
    pub id: u8,
    /// `mean(h - height)` of this camera's held-out plane, um.
    pub holdout_bias_um: f64,
    /// `rms(h - height)` of this camera's held-out plane, um.
    pub holdout_rms_um: f64,
    /// rms of the truth's per-pixel Cramer-Rao bound over the same pixels, um (truth only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub holdout_crb_rms_um: Option<f64>,
    /// The held-out plane's Cramer-Rao bound from the images and the calibration alone
    /// ([`holdout_bound`]), um, and `holdout_rms_um` over it (at most [`HOLDOUT_CRB_LIMIT`]).
    pub holdout_bound_um: f64,
    /// `holdout_rms_um / holdout_bound_um`; above [`HOLDOUT_CRB_LIMIT`] the calibration is refused.
    pub holdout_rms_over_bound: f64,
    /// Worst height error the field variation of `f_x` causes with the core's single `f_x`, um.
    pub fx_height_error_um: f64,
    /// `true` when `fx_height_error_um` exceeds the budget `fx_budget_um`.
    pub fx_over_budget: bool,
    /// Image pixels the calibration flagged as dead or low-modulation.
    pub dead_pixels: usize,
    /// Lateral-target marks used in the lateral fit.
    pub marks: u32,
    /// `max |T_z^(c) / T_z(c) - 1|` over this camera's columns (truth only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub t_z_rel_max: Option<f64>,
    /// rms distance between the estimated and the true board point of every pixel of rows
    /// 0, H/2, H-1, um (truth only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lateral_rms_um: Option<f64>,
}

/// What `dpsa calibrate --json` prints.
#[derive(Serialize, Clone, Debug, Default)]
pub struct CalibrationReport {
    /// Cameras in the calibration file.
    pub cameras: usize,
    /// Encoder scale, the mean of the cameras' estimates, counts/mm.
    pub counts_per_mm: f64,
    /// Budget of each camera's `fx_height_error_um`, um.
    pub fx_budget_um: f64,
    /// Ids of the cameras whose `fx_height_error_um` exceeds the budget.
    pub fx_over_budget: Vec<u8>,
    /// The held-out plane measured with the calibration (absent without a held-out pass).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub holdout: Option<Holdout>,
    /// Estimated parameters against the truth (only when the recording carries it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub truth_error: Option<CalibrationAccuracy>,
    /// Figures per camera, camera `i` at index `i`.
    pub per_camera: Vec<CameraFigures>,
}

/// Cramer-Rao bound of the height variance of one pixel (um^2): samples at image rows
/// `rows` of column `c` of a plane at `h`, true model `m`, plane background / modulation.
fn crb_var(
    m: &CameraModel,
    bg: f64,
    md: f64,
    noise: (f64, f64),
    c: usize,
    h: f64,
    rows: &[i64],
) -> Option<f64> {
    let (gain, read) = noise;
    let f = m.fringe_frequency[c];
    let t = m.height_per_turn_um[c];
    let mut fisher = Matrix3::<f64>::zeros();
    for &r in rows {
        let ph = TAU * f * r as f64 + m.reference_phase_rad[c] + TAU * h / t;
        let (s, co) = ph.sin_cos();
        let i = (bg + md * co).max(0.0);
        let var = read * read + i / gain + 1.0 / 12.0;
        let j = Vector3::new(1.0, co, -md * s);
        fisher += j * j.transpose() / var;
    }
    fisher
        .try_inverse()
        .map(|inv| inv[(2, 2)] * (t / TAU).powi(2))
}

/// How far the held-out plane measured with a calibration may be from its known height:
/// `rms(h - H)` at most this multiple of its own Cramer-Rao bound ([`holdout_bound`]). Good
/// calibrations of the shipped scenes measure 1.02 to 1.03 (`docs/calibration.md`); a plane
/// height 50 um off in `array.json` gives 6.2. 1.5 leaves room for a real recording's
/// calibration residuals while refusing errors of a few um.
pub const HOLDOUT_CRB_LIMIT: f64 = 1.5;

/// The held-out plane measured with camera `cal` against its known height, and the bound it
/// should meet, from the images alone (no truth): the per-pixel noise variance is the variance
/// across the plane's frames (a flat plane shows the same fringes in every frame, so the
/// frame-to-frame scatter is the noise: read, shot and rounding as they are), the fringe
/// model is the calibration's (`f_x(c)`, `phi_0(c)`, `T_z(c)`, the column modulation), and the
/// bound is the Cramer-Rao bound of each pixel's window samples. Returns `(rms, crb_rms,
/// bias, pixels)`, um.
pub fn holdout_bound(
    hr: &Recording,
    cal: &CameraCal,
    known_um: f64,
) -> Result<(f64, f64, f64, usize)> {
    let (h, w) = (hr.rows(), hr.width());
    let mut sum = vec![0f64; h * w];
    let mut sq = vec![0f64; h * w];
    for k in 0..hr.len() {
        let f = hr.frame(k)?;
        for ((s, q), &v) in sum.iter_mut().zip(sq.iter_mut()).zip(&f.data) {
            let v = f64::from(v);
            *s += v;
            *q += v * v;
        }
    }
    let n = hr.len().max(2) as f64;
    let var: Vec<f64> = sum
        .iter()
        .zip(&sq)
        .map(|(&s, &q)| ((q - s * s / n) / (n - 1.0)).max(1.0 / 12.0))
        .collect();
    let (mut e2, mut bias, mut crb2, mut used) = (0.0, 0.0, 0.0, 0usize);
    measure_plane(hr, cal, known_um, |c, v, rows| {
        let f = cal.fringe_frequency(c as f64);
        let t = cal.height_per_turn_um[c];
        let md = cal.modulation_dn[c];
        let mut fisher = Matrix3::<f64>::zeros();
        for &r in rows {
            let Some(&vr) = usize::try_from(r).ok().and_then(|r| var.get(r * w + c)) else {
                continue;
            };
            let ph = TAU * f * r as f64 + cal.reference_phase_rad[c] + TAU * known_um / t;
            let (sn, co) = ph.sin_cos();
            let j = Vector3::new(1.0, co, -md * sn);
            fisher += j * j.transpose() / vr;
        }
        if let Some(inv) = fisher.try_inverse() {
            crb2 += inv[(2, 2)] * (t / TAU).powi(2);
            e2 += (v - known_um).powi(2);
            bias += v - known_um;
            used += 1;
        }
    })?;
    let m = used.max(1) as f64;
    Ok(((e2 / m).sqrt(), (crb2 / m).sqrt(), bias / m, used))
}

fn truth_errors(cal: &CalFile, truth: &ArrayTruth) -> (CalibrationAccuracy, Vec<(f64, f64)>) {
    let mut e = CalibrationAccuracy::default();
    let mut per = Vec::new();
    e.counts_per_mm_rel = (cal.counts_per_mm / truth.counts_per_mm - 1.0).abs();
    for (k, (c, m)) in cal.camera.iter().zip(&truth.cameras).enumerate() {
        let w = c.width as usize;
        let tz = (0..w)
            .map(|i| (c.height_per_turn_um[i] / m.height_per_turn_um[i] - 1.0).abs())
            .fold(0.0, f64::max);
        e.t_z_rel_max = e.t_z_rel_max.max(tz);
        let f_true_mean = m.fringe_frequency.iter().sum::<f64>() / w as f64;
        e.f_x_rel_max = e
            .f_x_rel_max
            .max((1.0 / c.fringe_period_px / f_true_mean - 1.0).abs());
        let field = (0..w)
            .map(|i| (c.fringe_frequency(i as f64) / m.fringe_frequency[i] - 1.0).abs())
            .fold(0.0, f64::max);
        e.f_x_field_rel_max = e.f_x_field_rel_max.max(field);
        let phi = ((0..w)
            .map(|i| wrap_phase(c.reference_phase_rad[i] - m.reference_phase_rad[i]).powi(2))
            .sum::<f64>()
            / w as f64)
            .sqrt();
        e.phi0_rms_mrad = e.phi0_rms_mrad.max(phi * 1e3);
        let mut sq = 0.0;
        let mut n = 0.0;
        for r in [0.0, f64::from(c.rows) / 2.0, f64::from(c.rows) - 1.0] {
            for i in 0..w {
                let (xe, ye) = c.board_point(0.0, r, i as f64);
                let (xt, yt) = m.board_point(0.0, r, i as f64);
                sq += (xe - xt).powi(2) + (ye - yt).powi(2);
                n += 1.0;
            }
        }
        let lat = (sq / n).sqrt() * 1e3;
        e.lateral_rms_um = e.lateral_rms_um.max(lat);
        e.encoder_rel_max = e
            .encoder_rel_max
            .max((c.counts_per_pixel / m.counts_per_pixel - 1.0).abs());
        e.rotation_err_mdeg_max = e
            .rotation_err_mdeg_max
            .max((c.lateral.rotation_rad - m.rotation_rad).abs().to_degrees() * 1e3);
        let bg = &truth.plane_background_dn[k];
        let md = &truth.plane_modulation_dn[k];
        let dead_cols: Vec<usize> = m.dead_pixels.iter().map(|p| p[1] as usize).collect();
        for i in (0..w).filter(|i| !dead_cols.contains(i)) {
            e.background_rel_max = e
                .background_rel_max
                .max((c.background_dn[i] / bg[i] - 1.0).abs());
            e.modulation_rel_max = e
                .modulation_rel_max
                .max((c.modulation_dn[i] / md[i] - 1.0).abs());
        }
        e.dead_pixels_missed += m
            .dead_pixels
            .iter()
            .filter(|p| !c.dead_pixels.contains(p))
            .count();
        e.dead_pixels_false += c
            .dead_pixels
            .iter()
            .filter(|p| !m.dead_pixels.contains(p))
            .count();
        per.push((tz, lat));
    }
    (e, per)
}

/// Measures the held-out plane with `cal` and, with the truth, compares everything.
pub fn evaluate(rec: &ArrayRecording, cal: &CalFile) -> Result<CalibrationReport> {
    let truth = rec.truth()?;
    let holdout = rec
        .manifest
        .passes
        .iter()
        .find(|p| p.kind == PassKind::Holdout);
    let mut report = CalibrationReport {
        cameras: cal.camera.len(),
        counts_per_mm: cal.counts_per_mm,
        fx_budget_um: cal.fx_budget_um,
        fx_over_budget: cal
            .camera
            .iter()
            .filter(|c| c.fx_over_budget)
            .map(|c| c.id)
            .collect(),
        ..CalibrationReport::default()
    };
    let mut per_truth = Vec::new();
    if let Some(t) = &truth {
        let (e, per) = truth_errors(cal, t);
        report.truth_error = Some(e);
        per_truth = per;
    }
    let mut ho = holdout.map(|p| Holdout {
        height_um: p.height_um,
        ..Holdout::default()
    });
    for (i, c) in cal.camera.iter().enumerate() {
        let mut fig = CameraFigures {
            id: c.id,
            fx_height_error_um: c.fx_height_error_um,
            fx_over_budget: c.fx_over_budget,
            dead_pixels: c.dead_pixels.len(),
            marks: c.lateral.marks,
            t_z_rel_max: per_truth.get(i).map(|p| p.0),
            lateral_rms_um: per_truth.get(i).map(|p| p.1),
            ..CameraFigures::default()
        };
        if let (Some(p), Some(h)) = (holdout, ho.as_mut()) {
            let hr = Recording::open(rec.camera_dir(i, Some(&p.name)))
                .at(|| format!("camera {i}, held-out plane"))?;
            let noise_truth = truth
                .as_ref()
                .zip(hr.manifest.noise.as_ref())
                .map(|(t, noise)| (&t.cameras[i], t, noise));
            // Streamed: sums of the error, its square and the CRB variance, no pixel list.
            let (mut count, mut sum, mut sum2, mut var_sum) = (0u64, 0.0f64, 0.0f64, 0.0f64);
            measure_plane(&hr, c, p.height_um, |col, v, rows| {
                count += 1;
                sum += v - p.height_um;
                sum2 += (v - p.height_um).powi(2);
                if let Some((m, t, noise)) = noise_truth {
                    var_sum += crb_var(
                        m,
                        t.plane_background_dn[i][col],
                        t.plane_modulation_dn[i][col],
                        (noise.gain_e_per_dn, noise.read_noise_dn),
                        col,
                        p.height_um,
                        rows,
                    )
                    .unwrap_or(0.0);
                }
            })?;
            let n = count.max(1) as f64;
            let bias = sum / n;
            let rms = (sum2 / n).sqrt();
            let (brms, bound, _, _) = holdout_bound(&hr, c, p.height_um)?;
            fig.holdout_bound_um = bound;
            fig.holdout_rms_over_bound = brms / bound;
            fig.holdout_bias_um = bias;
            fig.holdout_rms_um = rms;
            h.pixels += count;
            h.bias_um_max = h.bias_um_max.max(bias.abs());
            if rms >= h.rms_um {
                h.rms_um = rms;
            }
            if noise_truth.is_some() {
                let var = var_sum / n;
                let crb = var.sqrt();
                fig.holdout_crb_rms_um = Some(crb);
                let ratio = rms / crb;
                if h.rms_over_crb_max.is_none_or(|r| ratio > r) {
                    h.rms_over_crb_max = Some(ratio);
                }
                if rms >= h.rms_um {
                    h.crb_rms_um = Some(crb);
                }
            }
        }
        report.per_camera.push(fig);
    }
    report.holdout = ho;
    Ok(report)
}

/// [`CameraCal`] re-export for callers that only evaluate.
pub type Camera = CameraCal;
