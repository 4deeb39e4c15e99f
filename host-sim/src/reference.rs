//! The f64 reference implementation of D-PSA, written from the measurement model in
//! `docs/model.md` (registration steps 1-8 and the validity rules).
//!
//! It is deliberately independent of the fixed-point core (`dpsa-core`): everything is f64,
//! the least squares uses the full `n x 3` design matrix `M` with rows
//! `[1, cos theta_j, -sin theta_j]` and `P = (M^T M)^-1 M^T` computed by nalgebra (not the
//! centred 2x2 shortcut, which is only used for the noise gain, as the model defines it), the
//! phase is an f64 `atan2` and the output is f64-rounded.
//!
//! Besides [`reconstruct`] this module provides the conventional baseline [`psp`] (nominal
//! uniform shifts), the Cramer-Rao bound [`crb`] of the height variance and the truth mask
//! [`flat_mask`] used by [`crate::compare`].

use crate::heightmap::{flags, HeightMap, HeightRow};
use crate::recording::{Frame, Manifest, Truth};
use nalgebra::{Dyn, Matrix2, Matrix3, OMatrix, SymmetricEigen, Vector3, U3};
use std::collections::HashMap;
use std::f64::consts::{PI, TAU};

/// Largest number of board rows [`plan`] will enumerate. Offsets spanning more rows than this
/// (absurd latches or calibration) are treated as unusable data and give an empty plan rather
/// than an enormous allocation.
pub const MAX_PLAN_ROWS: i64 = 1 << 24;

/// Largest absolute offset accepted, px; keeps `o_k + H` far from `i64` overflow.
const MAX_ABS_OFFSET: f64 = (1u64 << 60) as f64;

/// Registration step 1: `o = floor(e / cpp + 1/2)` (round half up), px.
///
/// Computed in f64. `cpp` is a multiple of 2^-16, so the exact quotient `e / cpp` is at least
/// `1 / (2 * 65536 * cpp)` away from a half-integer unless it is one; the f64 quotient is
/// correctly rounded, so the result is exact while `|e| < 2^36` counts (and `e` itself is exact
/// in f64 up to 2^53). Returns `None` for a non-finite result or `|o| >= 2^60`
/// (non-positive or non-finite `cpp`).
pub fn offset(latch: i64, counts_per_pixel: f64) -> Option<i64> {
    if !(counts_per_pixel > 0.0 && counts_per_pixel.is_finite()) {
        return None;
    }
    let o = (latch as f64 / counts_per_pixel + 0.5).floor();
    (o.is_finite() && o.abs() < MAX_ABS_OFFSET).then_some(o as i64)
}

/// Offsets `o_k` of all manifest frames, px; `None` when any is unusable (see [`offset`]).
pub fn offsets(manifest: &Manifest) -> Option<Vec<i64>> {
    let cpp = manifest.calibration.counts_per_pixel;
    manifest
        .frames
        .iter()
        .map(|f| offset(f.latch, cpp))
        .collect()
}

/// The registration decision for one board row.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RowPlan {
    /// Board row `b`.
    pub row: i64,
    /// Index into `manifest.frames` of the frame `w` at which the row entered; `None` for
    /// rows that never entered (`SKIPPED`).
    pub first_frame: Option<usize>,
    /// Row-level flags decidable from the manifest alone: `SKIPPED`, `INCOMPLETE`,
    /// `FRAME_GAP` (sequence gaps), `ENCODER_REVERSAL`. Zero when the window is usable.
    pub flags: u16,
}

/// Registration steps 1-4 of `docs/model.md`.
///
/// Returns every board row from the first frame's top row (`o_0`) to `E_last - 1` exactly
/// once, in increasing order (rows below `o_0`, visible only after a reversal, never enter):
/// - rows that entered at frame `w` (`[max(E_{w-1}, o_w + H - max_step), o_w + H)`) carry
///   `first_frame = Some(w)` and the window flags: `INCOMPLETE` when the row is not visible
///   in one of the frames `w..w+n-1` or the window runs past the last frame, `FRAME_GAP` when
///   consecutive window frames do not have consecutive `seq` (wrapping `u32` counter),
///   `ENCODER_REVERSAL` when the latch decreases between consecutive window frames (a
///   decrease never re-admits rows because `E_k` is a running maximum). The flags of a window
///   truncated by the end of the recording are evaluated over the frames that exist;
/// - all other rows (below the `max_step` bound of the frame that first showed them) are
///   `SKIPPED` with no frame.
///
/// Frame-content checks (a frame that did not deliver the row's line) are added by
/// [`reconstruct`]. An empty manifest, `H = 0`, an unusable `counts_per_pixel` or a row span
/// above [`MAX_PLAN_ROWS`] gives an empty plan.
pub fn plan(manifest: &Manifest) -> Vec<RowPlan> {
    let h = i64::from(manifest.camera.rows);
    let n = usize::from(manifest.processing.n);
    let max_step = i64::from(manifest.processing.max_step_rows);
    let frames = &manifest.frames;
    let Some(o) = offsets(manifest) else {
        return Vec::new();
    };
    let (Some(&lo), Some(&hi)) = (o.first(), o.iter().max()) else {
        return Vec::new();
    };
    let end = hi + h; // E_last
    if h == 0 || end - lo > MAX_PLAN_ROWS {
        return Vec::new();
    }

    let mut rows: Vec<RowPlan> = (lo..end)
        .map(|row| RowPlan {
            row,
            first_frame: None,
            flags: flags::SKIPPED,
        })
        .collect();

    let mut e_prev = i64::MIN; // E_{k-1}, -inf before the first frame
    for (k, &ok) in o.iter().enumerate() {
        let top = ok + h;
        let from = e_prev.max(top - max_step).max(lo);
        for b in from..top {
            let f = window_flags(b, k, n, h, &o, frames);
            rows[(b - lo) as usize] = RowPlan {
                row: b,
                first_frame: Some(k),
                flags: f,
            };
        }
        e_prev = e_prev.max(top);
    }
    rows
}

/// Window flags of board row `b` entering at frame `w` (step 4).
fn window_flags(
    b: i64,
    w: usize,
    n: usize,
    h: i64,
    o: &[i64],
    frames: &[crate::recording::FrameEntry],
) -> u16 {
    let mut f = 0;
    for j in 0..n {
        let k = w + j;
        if k >= o.len() {
            f |= flags::INCOMPLETE;
            break;
        }
        if !(o[k] <= b && b < o[k] + h) {
            f |= flags::INCOMPLETE;
        }
        if j > 0 {
            if frames[k].seq != frames[k - 1].seq.wrapping_add(1) {
                f |= flags::FRAME_GAP;
            }
            if frames[k].latch < frames[k - 1].latch {
                f |= flags::ENCODER_REVERSAL;
            }
        }
    }
    f
}

/// Noise gain `g = sqrt(n / (2 lambda_min(A)))` of a shift set (rad), `docs/model.md`.
///
/// `A` is the centred 2x2 matrix of the model; `g = 1` for `n` equally spaced shifts over a
/// full turn. Returns `+inf` when `A` is singular (`lambda_min <= 0`: stalled conveyor, shifts
/// confined to two phases) or `n = 0`. Shift sets that are singular only up to rounding
/// (e.g. whole fringe periods) give a very large finite gain.
pub fn noise_gain(shifts_rad: &[f64]) -> f64 {
    let n = shifts_rad.len() as f64;
    if shifts_rad.is_empty() {
        return f64::INFINITY;
    }
    let mc = shifts_rad.iter().map(|t| t.cos()).sum::<f64>() / n;
    let ms = shifts_rad.iter().map(|t| t.sin()).sum::<f64>() / n;
    let (mut suu, mut suw, mut sww) = (0.0, 0.0, 0.0);
    for t in shifts_rad {
        let u = t.cos() - mc;
        let w = -(t.sin() - ms);
        suu += u * u;
        suw += u * w;
        sww += w * w;
    }
    let a = Matrix2::new(suu, suw, suw, sww);
    let lambda_min = SymmetricEigen::new(a).eigenvalues.min();
    if lambda_min > 0.0 {
        (n / (2.0 * lambda_min)).sqrt()
    } else {
        f64::INFINITY
    }
}

/// Wraps a phase into `[-pi, pi)`, rad. Non-finite input gives NaN.
pub fn wrap_phase(x: f64) -> f64 {
    let mut d = x - TAU * ((x + PI) / TAU).floor();
    // Guard the boundaries against rounding.
    if d >= PI {
        d -= TAU;
    }
    if d < -PI {
        d += TAU;
    }
    d
}

/// The least-squares projector of a shift set: rows 2 and 3 of `P = (M^T M)^-1 M^T`, where
/// `M` (`n x 3`) has rows `[1, cos theta_j, -sin theta_j]`.
#[derive(Clone, Debug, PartialEq)]
pub struct PhaseFit {
    /// Row 2 of `P`: `v_2 = C cos Phi = sum_j cos_coef[j] * i_j`.
    pub cos_coef: Vec<f64>,
    /// Row 3 of `P`: `v_3 = C sin Phi = sum_j sin_coef[j] * i_j`.
    pub sin_coef: Vec<f64>,
}

impl PhaseFit {
    /// Builds `M`, inverts `M^T M` (3x3, f64) and keeps rows 2 and 3 of `P`. `None` when
    /// `M^T M` is exactly singular or the result is not finite.
    pub fn new(shifts_rad: &[f64]) -> Option<PhaseFit> {
        let n = shifts_rad.len();
        let m = OMatrix::<f64, Dyn, U3>::from_fn(n, |j, col| match col {
            0 => 1.0,
            1 => shifts_rad[j].cos(),
            _ => -shifts_rad[j].sin(),
        });
        let mt = m.transpose();
        let mtm: Matrix3<f64> = &mt * &m;
        let p = mtm.try_inverse()? * mt; // 3 x n
        if !p.iter().all(|x| x.is_finite()) {
            return None;
        }
        Some(PhaseFit {
            cos_coef: p.row(1).iter().copied().collect(),
            sin_coef: p.row(2).iter().copied().collect(),
        })
    }

    /// Fits samples `i_j` (DN, same order as the shifts): returns
    /// `(Phi = atan2(v_3, v_2) in rad, modulation C^ = sqrt(v_2^2 + v_3^2) in DN)`.
    /// Extra samples beyond the shift count are ignored; missing ones count as 0.
    pub fn fit(&self, samples: &[f64]) -> (f64, f64) {
        let v2: f64 = self.cos_coef.iter().zip(samples).map(|(p, i)| p * i).sum();
        let v3: f64 = self.sin_coef.iter().zip(samples).map(|(p, i)| p * i).sum();
        (v3.atan2(v2), v2.hypot(v3))
    }
}

/// The frames and shifts forming one board row's least-squares problem.
#[derive(Clone, Debug, PartialEq)]
pub struct Window {
    /// Indices into `manifest.frames` of frames `w..w+n-1`.
    pub frames: Vec<usize>,
    /// Offsets `o_{w+j}`, px.
    pub offsets: Vec<i64>,
    /// Shifts `theta_j`, rad (actual `-2 pi f_x (o_{w+j} - o_w)` for [`reconstruct`],
    /// nominal `-j delta` for [`psp`]).
    pub shifts_rad: Vec<f64>,
    /// Noise gain `g` of the shifts (see [`noise_gain`]); `+inf` when singular.
    pub noise_gain: f64,
}

impl Window {
    /// Builds a window and computes its noise gain.
    pub fn new(frames: Vec<usize>, offsets: Vec<i64>, shifts_rad: Vec<f64>) -> Window {
        let noise_gain = noise_gain(&shifts_rad);
        Window {
            frames,
            offsets,
            shifts_rad,
            noise_gain,
        }
    }
}

/// One board row of the reference output. Per-pixel vectors always have `width` entries;
/// where no samples could be gathered (no window, line not visible or not delivered) the
/// phase, height and modulation are NaN, `height_lsb` is 0 and the pixel is invalid.
#[derive(Clone, Debug, PartialEq)]
pub struct RefRow {
    /// Board row `b`.
    pub row: i64,
    /// Row flags ([`flags`]): registration flags plus `FRAME_GAP` for undelivered lines,
    /// `ILL_CONDITIONED`, and the pixel summaries `SATURATED` / `LOW_MODULATION`. The
    /// summaries are evaluated whenever all `n` lines were gathered, also for rows that
    /// another flag invalidates.
    pub flags: u16,
    /// The row's window, when all `n` window frames exist in the recording.
    pub window: Option<Window>,
    /// Wrapped phase difference `D = wrap(Phi - phi_r)` in `[-pi, pi)`, rad.
    pub phase_rad: Vec<f64>,
    /// Height `h = D / (2 pi) * T_z`, um.
    pub height_um: Vec<f64>,
    /// `round(h / lsb)` clamped to `[-32767, 32767]`, LSB.
    pub height_lsb: Vec<i32>,
    /// Pixel validity: row not invalidated, no saturated sample, modulation above threshold,
    /// finite height.
    pub valid: Vec<bool>,
    /// Fitted modulation `C^`, DN.
    pub modulation: Vec<f64>,
}

impl RefRow {
    fn empty(row: i64, flags: u16, width: usize) -> RefRow {
        RefRow {
            row,
            flags,
            window: None,
            phase_rad: vec![f64::NAN; width],
            height_um: vec![f64::NAN; width],
            height_lsb: vec![0; width],
            valid: vec![false; width],
            modulation: vec![f64::NAN; width],
        }
    }

    /// True when the row carries no invalidating flag.
    pub fn is_valid(&self) -> bool {
        !flags::invalidates(self.flags)
    }
}

/// Output of [`reconstruct`] or [`psp`]: one row per planned board row, sorted by `row`.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct RefOutput {
    /// Columns per row, px.
    pub width: usize,
    /// Rows in increasing board-row order.
    pub rows: Vec<RefRow>,
}

impl RefOutput {
    /// The row for board row `row`, if present.
    pub fn get(&self, row: i64) -> Option<&RefRow> {
        self.rows
            .binary_search_by_key(&row, |r| r.row)
            .ok()
            .map(|i| &self.rows[i])
    }

    /// Number of valid pixels.
    pub fn valid_pixels(&self) -> usize {
        self.rows
            .iter()
            .map(|r| r.valid.iter().filter(|&&v| v).count())
            .sum()
    }

    /// Converts to a [`HeightMap`] with the manifest's LSB. `latch` is the latch of the
    /// row's first window frame `w` (0 without a window); heights are `height_lsb` (which is
    /// already clamped to the i16 range).
    pub fn to_height_map(&self, manifest: &Manifest) -> HeightMap {
        let rows = self
            .rows
            .iter()
            .map(|r| HeightRow {
                row: r.row,
                latch: r
                    .window
                    .as_ref()
                    .and_then(|w| w.frames.first())
                    .and_then(|&k| manifest.frames.get(k))
                    .map_or(0, |f| f.latch),
                flags: r.flags,
                heights: r
                    .height_lsb
                    .iter()
                    .map(|&h| h.clamp(-32767, 32767) as i16)
                    .collect(),
                valid: r.valid.clone(),
            })
            .collect();
        HeightMap {
            width: self.width,
            lsb_um: manifest.calibration.height_lsb_um,
            rows,
        }
    }
}

/// How the shifts of a window are obtained.
#[derive(Clone, Copy, Debug)]
enum Shifts {
    /// D-PSA: `theta_j = -2 pi f_x (o_{w+j} - o_w)`.
    Actual,
    /// Conventional PSP: `theta_j = -j delta`, rad per frame.
    Nominal(f64),
}

/// D-PSA reconstruction per `docs/model.md` steps 1-8 and the validity rules.
///
/// `frames[k]` must correspond to `manifest.frames[k]`. Window frames missing from `frames`,
/// frames of the wrong width and frames with fewer lines than the row's image row flag the row
/// `FRAME_GAP` (the frame did not deliver its line). One [`PhaseFit`] is computed per window
/// (rows entering at the same frame share it); each pixel then costs two dot products and an
/// `atan2`. A window with `g > max_noise_gain` (or a singular `M^T M`) is `ILL_CONDITIONED`.
/// Pixels of rows whose samples are available are computed even when the row is invalid (for
/// diagnostics), but are marked invalid.
pub fn reconstruct(manifest: &Manifest, frames: &[Frame]) -> RefOutput {
    run(manifest, frames, Shifts::Actual)
}

/// Nominal frame-to-frame step of a recording, px: `(o_last - o_first) / (frames - 1)`, the
/// mean step a conventional system calibrated to the nominal conveyor speed would assume.
/// 0 with fewer than two frames or unusable offsets.
pub fn nominal_step_px(manifest: &Manifest) -> f64 {
    match offsets(manifest) {
        Some(o) if o.len() >= 2 => (o[o.len() - 1] - o[0]) as f64 / (o.len() - 1) as f64,
        _ => 0.0,
    }
}

/// Conventional phase-shift baseline: same registration, samples, reference phase, height and
/// validity rules as [`reconstruct`], but the shifts are the nominal uniform set
/// `theta_j = -j delta`, `delta = 2 pi f_x * nominal_step` ([`nominal_step_px`]; 90 degrees
/// for the default scene, i.e. the classic 4-step formula).
///
/// The actual motion is not used for conditioning, so rows are never flagged
/// `ILL_CONDITIONED` because of it. The noise-gain test is applied to the nominal set
/// instead (the same for every window): only when that set itself is degenerate (e.g. a
/// recording with no net motion, or a nominal step of a whole fringe period) is every
/// windowed row flagged `ILL_CONDITIONED`.
pub fn psp(manifest: &Manifest, frames: &[Frame]) -> RefOutput {
    let f_x = 1.0 / manifest.calibration.fringe_period_px;
    run(
        manifest,
        frames,
        Shifts::Nominal(TAU * f_x * nominal_step_px(manifest)),
    )
}

/// Lines of `frame` actually delivered at `width` columns.
fn delivered_lines(frame: &Frame, width: usize) -> usize {
    if width == 0 {
        frame.rows
    } else if frame.width != width {
        0
    } else {
        frame.rows.min(frame.data.len() / width)
    }
}

fn run(manifest: &Manifest, frames: &[Frame], shifts: Shifts) -> RefOutput {
    let width = manifest.camera.width as usize;
    let cal = &manifest.calibration;
    let proc_ = &manifest.processing;
    let n = usize::from(proc_.n);
    let f_x = 1.0 / cal.fringe_period_px;
    let phi0: Vec<f64> = (0..width)
        .map(|c| cal.reference_phase_rad.get(c).copied().unwrap_or(f64::NAN))
        .collect();

    let plan = plan(manifest);
    let o = offsets(manifest).unwrap_or_default();

    // One window + projector per entry frame w.
    let mut windows: HashMap<usize, (Window, Option<PhaseFit>)> = HashMap::new();
    let mut rows = Vec::with_capacity(plan.len());

    for p in &plan {
        let mut row = RefRow::empty(p.row, p.flags, width);
        let Some(w) = p.first_frame else {
            rows.push(row);
            continue;
        };
        if w + n > o.len() {
            // Runs past the last frame: plan() already flagged INCOMPLETE.
            rows.push(row);
            continue;
        }
        let (window, fit) = windows
            .entry(w)
            .or_insert_with(|| {
                let offs: Vec<i64> = o[w..w + n].to_vec();
                let th: Vec<f64> = match shifts {
                    Shifts::Actual => offs
                        .iter()
                        .map(|&ok| -TAU * f_x * (ok - offs[0]) as f64)
                        .collect(),
                    Shifts::Nominal(delta) => (0..n).map(|j| -(j as f64) * delta).collect(),
                };
                let fit = PhaseFit::new(&th);
                (Window::new((w..w + n).collect(), offs, th), fit)
            })
            .clone();

        let ill = match shifts {
            Shifts::Actual => {
                let g = window.noise_gain;
                fit.is_none() || g.is_nan() || g > proc_.max_noise_gain
            }
            // The nominal set is the same for every window: this only fires when the
            // conventional design itself is degenerate.
            Shifts::Nominal(_) => {
                let g = window.noise_gain;
                fit.is_none() || g.is_nan() || g > proc_.max_noise_gain
            }
        };
        if ill {
            row.flags |= flags::ILL_CONDITIONED;
        }

        // Gather the row's line from each window frame.
        let b = p.row;
        let h = i64::from(manifest.camera.rows);
        let mut lines: Vec<&[u16]> = Vec::with_capacity(n);
        for (j, &k) in window.frames.iter().enumerate() {
            let r = b - window.offsets[j];
            if r < 0 || r >= h {
                continue; // not visible: INCOMPLETE from plan()
            }
            let r = r as usize;
            match frames.get(k) {
                Some(fr) if r < delivered_lines(fr, width) => {
                    lines.push(&fr.data[r * width..(r + 1) * width]);
                }
                _ => row.flags |= flags::FRAME_GAP,
            }
        }

        if let (Some(fit), true) = (&fit, lines.len() == n) {
            let phi_r_row = TAU * f_x * (b - window.offsets[0]) as f64;
            let row_ok = !flags::invalidates(row.flags);
            let summary = fill_pixels(&mut row, fit, &lines, phi_r_row, &phi0, manifest, row_ok);
            row.flags |= summary;
        }
        row.window = Some(window);
        rows.push(row);
    }
    // Pixel-level flags may have been added after the row flag decision; make the validity
    // consistent with the final row flags.
    for r in &mut rows {
        if flags::invalidates(r.flags) {
            r.valid.iter_mut().for_each(|v| *v = false);
        }
    }
    RefOutput { width, rows }
}

/// Computes all pixels of one row from its `n` lines; returns the summary flags
/// (`SATURATED`, `LOW_MODULATION`).
fn fill_pixels(
    row: &mut RefRow,
    fit: &PhaseFit,
    lines: &[&[u16]],
    phi_r_row: f64,
    phi0: &[f64],
    manifest: &Manifest,
    row_ok: bool,
) -> u16 {
    let width = phi0.len();
    let saturation = manifest.camera.saturation;
    let min_mod = manifest.processing.min_modulation;
    let t_z = manifest.calibration.height_per_turn_um;
    let lsb = manifest.calibration.height_lsb_um;

    let mut v2 = vec![0.0f64; width];
    let mut v3 = vec![0.0f64; width];
    let mut max_sample = vec![0u16; width];
    for (j, line) in lines.iter().enumerate() {
        let (pc, ps) = (fit.cos_coef[j], fit.sin_coef[j]);
        for c in 0..width {
            let s = line[c];
            let x = f64::from(s);
            v2[c] += pc * x;
            v3[c] += ps * x;
            max_sample[c] = max_sample[c].max(s);
        }
    }

    let mut summary = 0;
    for c in 0..width {
        let phi = v3[c].atan2(v2[c]);
        let modulation = v2[c].hypot(v3[c]);
        let d = wrap_phase(phi - (phi_r_row + phi0[c]));
        let h = d / TAU * t_z;
        let saturated = max_sample[c] >= saturation;
        let low = modulation.is_nan() || modulation < min_mod;
        if saturated {
            summary |= flags::SATURATED;
        }
        if low {
            summary |= flags::LOW_MODULATION;
        }
        row.phase_rad[c] = d;
        row.height_um[c] = h;
        row.height_lsb[c] = (h / lsb).round().clamp(-32767.0, 32767.0) as i32;
        row.modulation[c] = modulation;
        row.valid[c] = row_ok && !saturated && !low && h.is_finite();
    }
    summary
}

/// Cramer-Rao bound on the height variance, um^2, of each pixel of `out` (which must come
/// from [`reconstruct`]: the actual window shifts are used). Indexed `[i][c]` for
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
pub fn crb(manifest: &Manifest, truth: &Truth, out: &RefOutput) -> Vec<Vec<Option<f64>>> {
    let width = out.width;
    let Some(noise) = &manifest.noise else {
        return out.rows.iter().map(|_| vec![None; width]).collect();
    };
    let cal = &manifest.calibration;
    let f_x = 1.0 / cal.fringe_period_px;
    let scale = (cal.height_per_turn_um / TAU).powi(2);
    let read_var = noise.read_noise_dn * noise.read_noise_dn;

    out.rows
        .iter()
        .map(|row| {
            let mut v = vec![None; width];
            let Some(window) = row.window.as_ref().filter(|_| row.is_valid()) else {
                return v;
            };
            let Some(ti) = truth_row_index(truth, row.row) else {
                return v;
            };
            let phi_r_row =
                TAU * f_x * (row.row - window.offsets.first().copied().unwrap_or(0)) as f64;
            for (c, slot) in v.iter_mut().enumerate() {
                let Some((h_true, bg, ct)) = truth_at(truth, ti, c) else {
                    continue;
                };
                let phi0 = cal.reference_phase_rad.get(c).copied().unwrap_or(f64::NAN);
                let phi = phi_r_row + phi0 + TAU * h_true / cal.height_per_turn_um;
                let mut fisher = Matrix3::<f64>::zeros();
                for &t in &window.shifts_rad {
                    let (s, co) = (phi + t).sin_cos();
                    let i = (bg + ct * co).max(0.0);
                    let var = read_var + i / noise.gain_e_per_dn + 1.0 / 12.0;
                    let jac = Vector3::new(1.0, co, -ct * s);
                    fisher += jac * jac.transpose() / var;
                }
                *slot = fisher
                    .try_inverse()
                    .map(|inv| inv[(2, 2)] * scale)
                    .filter(|x| x.is_finite() && *x >= 0.0);
            }
            v
        })
        .collect()
}

/// Index of board row `b` in the truth arrays.
pub(crate) fn truth_row_index(truth: &Truth, b: i64) -> Option<usize> {
    let i = b.checked_sub(truth.first_row)?;
    (i >= 0 && (i as u64) < truth.rows as u64).then_some(i as usize)
}

/// `(height um, background DN, contrast DN)` of truth row index `ti`, column `c`.
fn truth_at(truth: &Truth, ti: usize, c: usize) -> Option<(f64, f64, f64)> {
    if c >= truth.width {
        return None;
    }
    let idx = ti.checked_mul(truth.width)?.checked_add(c)?;
    Some((
        f64::from(*truth.height_um.get(idx)?),
        f64::from(*truth.background.get(idx)?),
        f64::from(*truth.contrast.get(idx)?),
    ))
}

/// True height of board row `b`, column `c`, um, when inside the truth.
pub fn truth_height(truth: &Truth, b: i64, c: usize) -> Option<f64> {
    let ti = truth_row_index(truth, b)?;
    if c >= truth.width {
        return None;
    }
    truth
        .height_um
        .get(ti * truth.width + c)
        .map(|&h| f64::from(h))
}

/// Flat-pixel mask of the truth, row-major `truth.rows x truth.width`.
///
/// A pixel is flat when it and its 8 neighbours (board rows `b-1..=b+1`, columns
/// `c-1..=c+1`) have exactly the same truth height; border pixels are never flat. Errors
/// against truth are measured only on flat pixels: registration rounds each frame's offset to
/// a whole pixel, so a sample can come from up to half a pixel away along the motion, and on
/// deposit walls the error would measure that lateral sampling rather than the phase
/// algorithm.
pub fn flat_mask(truth: &Truth) -> Vec<bool> {
    let (rows, w) = (truth.rows, truth.width);
    let mut mask = vec![false; rows.saturating_mul(w)];
    if rows < 3 || w < 3 || truth.height_um.len() < rows * w {
        return mask;
    }
    let h = &truth.height_um;
    for r in 1..rows - 1 {
        for c in 1..w - 1 {
            let v = h[r * w + c];
            mask[r * w + c] =
                (r - 1..=r + 1).all(|rr| (c - 1..=c + 1).all(|cc| h[rr * w + cc] == v));
        }
    }
    mask
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recording::{Calibration, Camera, FrameEntry, Noise, Processing};

    const F: u16 = flags::INCOMPLETE;
    const S: u16 = flags::SKIPPED;
    const G: u16 = flags::FRAME_GAP;
    const R: u16 = flags::ENCODER_REVERSAL;

    fn manifest(width: u32, h: u32, n: u8, max_step: u32, cpp: f64, fr: &[(u32, i64)]) -> Manifest {
        Manifest {
            format: crate::recording::FORMAT.into(),
            version: crate::recording::VERSION,
            camera: Camera {
                id: 0,
                width,
                rows: h,
                bit_depth: 16,
                saturation: 65535,
            },
            calibration: Calibration {
                counts_per_pixel: cpp,
                fringe_period_px: 32.0,
                reference_phase_rad: (0..width).map(|c| 0.1 * c as f64).collect(),
                height_per_turn_um: 500.0,
                height_lsb_um: 0.25,
            },
            processing: Processing {
                n,
                max_step_rows: max_step,
                min_modulation: 60.0,
                max_noise_gain: 2.0,
            },
            frames: fr
                .iter()
                .map(|&(seq, latch)| FrameEntry {
                    seq,
                    latch,
                    file: String::new(),
                })
                .collect(),
            noise: None,
            truth: None,
        }
    }

    fn seqs(latches: &[i64]) -> Vec<(u32, i64)> {
        latches
            .iter()
            .enumerate()
            .map(|(i, &l)| (i as u32, l))
            .collect()
    }

    /// (row, first_frame, flags) triples.
    fn summary(p: &[RowPlan]) -> Vec<(i64, Option<usize>, u16)> {
        p.iter().map(|r| (r.row, r.first_frame, r.flags)).collect()
    }

    #[test]
    fn offset_rounds_half_up() {
        assert_eq!(offset(41, 10.25), Some(4));
        assert_eq!(offset(5, 10.0), Some(1));
        assert_eq!(offset(-5, 10.0), Some(0));
        assert_eq!(offset(15, 10.0), Some(2));
        assert_eq!(offset(-15, 10.0), Some(-1));
        assert_eq!(offset(14, 10.0), Some(1));
        assert_eq!(offset(1, 0.0), None);
        assert_eq!(offset(1, f64::NAN), None);
    }

    #[test]
    fn plan_uniform_steps() {
        let m = manifest(1, 6, 3, 4, 1.0, &seqs(&[0, 2, 4, 6, 8]));
        let expect = vec![
            (0, None, S),
            (1, None, S),
            (2, Some(0), F),
            (3, Some(0), F),
            (4, Some(0), 0),
            (5, Some(0), 0),
            (6, Some(1), 0),
            (7, Some(1), 0),
            (8, Some(2), 0),
            (9, Some(2), 0),
            (10, Some(3), F),
            (11, Some(3), F),
            (12, Some(4), F),
            (13, Some(4), F),
        ];
        assert_eq!(summary(&plan(&m)), expect);
        // Same with a fractional calibration: latches scaled by cpp.
        let m2 = manifest(1, 6, 3, 4, 10.25, &seqs(&[0, 20, 41, 62, 82]));
        assert_eq!(summary(&plan(&m2)), expect);
    }

    #[test]
    fn plan_stall() {
        let m = manifest(1, 6, 3, 4, 1.0, &seqs(&[0, 2, 2, 4, 6, 8]));
        let expect = vec![
            (0, None, S),
            (1, None, S),
            (2, Some(0), 0),
            (3, Some(0), 0),
            (4, Some(0), 0),
            (5, Some(0), 0),
            (6, Some(1), 0),
            (7, Some(1), 0),
            (8, Some(3), 0),
            (9, Some(3), 0),
            (10, Some(4), F),
            (11, Some(4), F),
            (12, Some(5), F),
            (13, Some(5), F),
        ];
        assert_eq!(summary(&plan(&m)), expect);
    }

    #[test]
    fn plan_reversal() {
        let m = manifest(1, 6, 3, 4, 1.0, &seqs(&[0, 2, 4, 3, 6, 8, 10]));
        let expect = vec![
            (0, None, S),
            (1, None, S),
            (2, Some(0), F),
            (3, Some(0), F),
            (4, Some(0), 0),
            (5, Some(0), 0),
            (6, Some(1), R),
            (7, Some(1), R),
            (8, Some(2), R),
            (9, Some(2), R | F),
            (10, Some(4), 0),
            (11, Some(4), 0),
            (12, Some(5), F),
            (13, Some(5), F),
            (14, Some(6), F),
            (15, Some(6), F),
        ];
        assert_eq!(summary(&plan(&m)), expect);
    }

    #[test]
    fn plan_seq_gap() {
        let m = manifest(1, 6, 3, 4, 1.0, &[(0, 0), (1, 2), (3, 4), (4, 6), (5, 8)]);
        let expect = vec![
            (0, None, S),
            (1, None, S),
            (2, Some(0), F | G),
            (3, Some(0), F | G),
            (4, Some(0), G),
            (5, Some(0), G),
            (6, Some(1), G),
            (7, Some(1), G),
            (8, Some(2), 0),
            (9, Some(2), 0),
            (10, Some(3), F),
            (11, Some(3), F),
            (12, Some(4), F),
            (13, Some(4), F),
        ];
        assert_eq!(summary(&plan(&m)), expect);
    }

    #[test]
    fn plan_large_step() {
        let m = manifest(1, 6, 3, 4, 1.0, &seqs(&[0, 2, 4, 12, 14, 16, 18]));
        let mut expect = vec![
            (0, None, S),
            (1, None, S),
            (2, Some(0), F),
            (3, Some(0), F),
            (4, Some(0), 0),
            (5, Some(0), 0),
            (6, Some(1), F), // frames 1,2,3: frame 3 shows rows 12..17
            (7, Some(1), F),
            (8, Some(2), F),
            (9, Some(2), F),
        ];
        expect.extend((10..14).map(|b| (b, None, S)));
        expect.extend([
            (14, Some(3), F),
            (15, Some(3), F),
            (16, Some(3), 0),
            (17, Some(3), 0),
            (18, Some(4), 0),
            (19, Some(4), 0),
            (20, Some(5), F),
            (21, Some(5), F),
            (22, Some(6), F),
            (23, Some(6), F),
        ]);
        assert_eq!(summary(&plan(&m)), expect);
    }

    #[test]
    fn plan_degenerate_inputs() {
        assert!(plan(&manifest(1, 6, 3, 4, 1.0, &[])).is_empty());
        assert!(plan(&manifest(1, 0, 3, 4, 1.0, &seqs(&[0, 1]))).is_empty());
        assert!(plan(&manifest(1, 6, 3, 4, 0.0, &seqs(&[0, 1]))).is_empty());
        assert!(plan(&manifest(1, 6, 3, 4, 1.0, &seqs(&[0, i64::MAX]))).is_empty());
        // A single frame: everything skipped or incomplete, nothing panics.
        let p = plan(&manifest(1, 6, 3, 4, 1.0, &seqs(&[5])));
        assert_eq!(p.len(), 6);
        assert!(p.iter().all(|r| r.flags != 0));
        let out = reconstruct(&manifest(2, 6, 3, 4, 1.0, &seqs(&[5])), &[]);
        assert_eq!(out.rows.len(), 6);
        assert_eq!(out.valid_pixels(), 0);
    }

    proptest::proptest! {
        #[test]
        fn plan_covers_each_row_once(steps in proptest::collection::vec(-3i64..9, 0..30),
                                     h in 1u32..12, max_step in 0u32..10) {
            let mut latches = vec![0i64];
            for s in steps { latches.push(latches.last().unwrap() + s); }
            let m = manifest(1, h, 3, max_step, 1.0, &seqs(&latches));
            let p = plan(&m);
            let lo = &latches[0];
            let end = latches.iter().max().unwrap() + i64::from(h);
            let rows: Vec<i64> = p.iter().map(|r| r.row).collect();
            proptest::prop_assert_eq!(rows, (*lo..end).collect::<Vec<_>>());
            for r in &p {
                match r.first_frame {
                    None => proptest::prop_assert_eq!(r.flags, S),
                    Some(w) => {
                        proptest::prop_assert!(r.flags & S == 0);
                        // A valid row is visible in all window frames.
                        if r.flags == 0 {
                            for &o in &latches[w..w + 3] {
                                proptest::prop_assert!(o <= r.row && r.row < o + i64::from(h));
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn noise_gain_values() {
        let four: Vec<f64> = (0..4).map(|j| -(j as f64) * PI / 2.0).collect();
        assert!((noise_gain(&four) - 1.0).abs() < 1e-12);
        let five: Vec<f64> = (0..5).map(|j| -(j as f64) * TAU / 5.0).collect();
        assert!((noise_gain(&five) - 1.0).abs() < 1e-12);
        assert_eq!(noise_gain(&[0.0; 4]), f64::INFINITY);
        assert_eq!(noise_gain(&[0.0, 0.0, -0.5, -0.5]), f64::INFINITY);
        assert_eq!(noise_gain(&[]), f64::INFINITY);
        // Uneven: worse than ideal.
        assert!(noise_gain(&[0.0, -0.3, -2.0, -3.5]) > 1.0);
        assert!(PhaseFit::new(&[0.0; 4]).is_none());
    }

    #[test]
    fn wrap_phase_range() {
        for x in [-10.0, -PI, -PI + 1e-9, 0.0, PI - 1e-9, PI, 3.0 * PI, 100.0] {
            let d = wrap_phase(x);
            assert!((-PI..PI).contains(&d), "{x} -> {d}");
            let k = (x - d) / TAU;
            assert!((k - k.round()).abs() < 1e-9);
        }
        assert_eq!(wrap_phase(PI), -PI);
    }

    #[test]
    fn phase_fit_exact_on_nonuniform_shifts() {
        // Arbitrary non-uniform shifts, noiseless f64 samples.
        let shifts = [0.0, -1.1, -2.9, -4.0, -5.3];
        let (b, c, t_z, h_true, phi_r) = (1000.0, 400.0, 500.0, 37.125, 2.2);
        let phi = phi_r + TAU * h_true / t_z;
        let samples: Vec<f64> = shifts.iter().map(|t| b + c * (phi + t).cos()).collect();
        let fit = PhaseFit::new(&shifts).unwrap();
        let (p, m) = fit.fit(&samples);
        assert!((m - c).abs() < 1e-9);
        let h = wrap_phase(p - phi_r) / TAU * t_z;
        assert!((h - h_true).abs() < 1e-6, "{h}");
    }

    /// Renders frames of a board with known height from the model formula.
    fn render(m: &Manifest, height: impl Fn(i64, usize) -> f64, bg: f64, ct: f64) -> Vec<Frame> {
        let w = m.camera.width as usize;
        let h = m.camera.rows as usize;
        let cal = &m.calibration;
        let f_x = 1.0 / cal.fringe_period_px;
        m.frames
            .iter()
            .map(|fe| {
                let o = offset(fe.latch, cal.counts_per_pixel).unwrap();
                let mut data = Vec::with_capacity(w * h);
                for r in 0..h {
                    for c in 0..w {
                        let hb = height(r as i64 + o, c);
                        let ph = TAU * f_x * r as f64
                            + cal.reference_phase_rad[c]
                            + TAU * hb / cal.height_per_turn_um;
                        data.push((bg + ct * ph.cos()).round().clamp(0.0, 65535.0) as u16);
                    }
                }
                Frame {
                    seq: fe.seq,
                    latch: fe.latch,
                    rows: h,
                    width: w,
                    data,
                }
            })
            .collect()
    }

    fn board_height(b: i64, c: usize) -> f64 {
        -200.0 + 7.3 * b as f64 + 11.9 * c as f64
    }

    #[test]
    fn reconstruct_nonuniform_motion() {
        // Steps 7, 9, 5, 8, 6, 10, ... rows: non-uniform shifts (period 32 px).
        let steps = [7, 9, 5, 8, 6, 10, 7, 9];
        let mut lat = vec![0i64];
        for s in steps {
            lat.push(lat.last().unwrap() + s);
        }
        let m = manifest(5, 40, 4, 10, 1.0, &seqs(&lat));
        let frames = render(&m, board_height, 30000.0, 20000.0);
        let out = reconstruct(&m, &frames);
        assert_eq!(out.width, 5);
        let mut checked = 0;
        for r in &out.rows {
            if !r.is_valid() {
                assert!(r.valid.iter().all(|&v| !v));
                continue;
            }
            let win = r.window.as_ref().unwrap();
            assert!(win.noise_gain < 2.0);
            for c in 0..5 {
                assert!(r.valid[c]);
                let truth = board_height(r.row, c);
                // Heights are defined modulo T_z = 500 um.
                let err = wrap_phase(TAU * (r.height_um[c] - truth) / 500.0) / TAU * 500.0;
                // Only u16 rounding of the rendered samples limits the accuracy here.
                assert!(err.abs() < 0.01, "{} {}", r.height_um[c], truth);
                assert!((-250.0..250.0).contains(&r.height_um[c]));
                assert!((r.modulation[c] - 20000.0).abs() < 1.0);
                assert_eq!(r.height_lsb[c], (r.height_um[c] / 0.25).round() as i32);
                checked += 1;
            }
        }
        assert!(checked >= 5 * 40);
    }

    #[test]
    fn reconstruct_flags_stall_saturation_and_gaps() {
        let mut m = manifest(3, 6, 3, 4, 1.0, &seqs(&[0, 2, 2, 4, 6, 8]));
        // 2 px steps = 120 degrees: an ideal 3-step set when the conveyor moves.
        m.calibration.fringe_period_px = 6.0;
        let mut frames = render(&m, |_, _| 10.0, 1000.0, 500.0);
        // Rows 2..5 (offsets 0,2,2) and 6,7 (2,2,4) have two-phase windows: singular.
        let out = reconstruct(&m, &frames);
        for r in &out.rows {
            let ill = r.flags & flags::ILL_CONDITIONED != 0;
            assert_eq!(ill, (2..8).contains(&r.row), "row {}", r.row);
            if (2..8).contains(&r.row) {
                assert_eq!(r.window.as_ref().unwrap().noise_gain, f64::INFINITY);
            }
        }
        assert!(out.get(8).unwrap().valid.iter().all(|&v| v));

        // Saturate one sample of board row 9 (frame 4 at o=6: image row 3), column 1.
        frames[4].data[3 * 3 + 1] = 65535;
        // Truncate frame 5 (o=8) to 1 line: board row 9 (image row 1) not delivered.
        let out = reconstruct(&m, &frames);
        let r9 = out.get(9).unwrap();
        assert_eq!(r9.flags, flags::SATURATED);
        assert_eq!(r9.valid, [true, false, true]);
        frames[5].rows = 1;
        let out = reconstruct(&m, &frames);
        let r9 = out.get(9).unwrap();
        assert!(r9.flags & flags::FRAME_GAP != 0);
        assert!(r9.valid.iter().all(|&v| !v));
        assert!(out.get(8).unwrap().valid.iter().all(|&v| v));
        // Missing frames: FRAME_GAP as well.
        let out = reconstruct(&m, &frames[..5]);
        assert!(out.get(8).unwrap().flags & flags::FRAME_GAP != 0);

        // Low modulation.
        let frames = render(&m, |_, _| 10.0, 1000.0, 30.0);
        let out = reconstruct(&m, &frames);
        let r8 = out.get(8).unwrap();
        assert_eq!(r8.flags, flags::LOW_MODULATION);
        assert!(r8.valid.iter().all(|&v| !v));
    }

    #[test]
    fn psp_equals_reconstruct_for_nominal_motion() {
        // 8 px steps with period 32: exactly 90 degrees.
        let lat: Vec<i64> = (0..10).map(|k| 8 * k).collect();
        let m = manifest(4, 40, 4, 10, 1.0, &seqs(&lat));
        assert_eq!(nominal_step_px(&m), 8.0);
        let frames = render(&m, board_height, 2000.0, 800.0);
        let a = reconstruct(&m, &frames);
        let b = psp(&m, &frames);
        assert_eq!(a.rows.len(), b.rows.len());
        assert!(a.valid_pixels() > 0);
        for (ra, rb) in a.rows.iter().zip(&b.rows) {
            assert_eq!(ra.flags, rb.flags);
            assert_eq!(ra.valid, rb.valid);
            for c in 0..4 {
                if ra.valid[c] {
                    assert!((ra.height_um[c] - rb.height_um[c]).abs() < 1e-9);
                }
            }
        }
        // Non-uniform motion: PSP is never flagged ill-conditioned but D-PSA may be.
        let m = manifest(4, 40, 4, 10, 1.0, &seqs(&[0, 8, 8, 8, 16, 24, 32, 40, 48]));
        assert_eq!(nominal_step_px(&m), 6.0);
        let frames = render(&m, board_height, 2000.0, 800.0);
        let b = psp(&m, &frames);
        assert!(b.rows.iter().all(|r| r.flags & flags::ILL_CONDITIONED == 0));
        let a = reconstruct(&m, &frames);
        assert!(a.rows.iter().any(|r| r.flags & flags::ILL_CONDITIONED != 0));
    }

    fn truth_for(out_rows: std::ops::Range<i64>, w: usize, h: f32, bg: f32, ct: f32) -> Truth {
        let rows = (out_rows.end - out_rows.start) as usize;
        Truth {
            first_row: out_rows.start,
            rows,
            width: w,
            height_um: vec![h; rows * w],
            background: vec![bg; rows * w],
            contrast: vec![ct; rows * w],
        }
    }

    #[test]
    fn crb_matches_textbook_for_equal_steps() {
        for (n, step) in [(4u8, 8i64), (8, 4)] {
            let lat: Vec<i64> = (0..12).map(|k| step * k).collect();
            let mut m = manifest(3, 40, n, 10, 1.0, &seqs(&lat));
            let sigma = 3.0;
            m.noise = Some(Noise {
                gain_e_per_dn: 1e15,
                read_noise_dn: sigma,
            });
            let frames = render(&m, |_, _| 42.0, 1000.0, 300.0);
            let out = reconstruct(&m, &frames);
            let truth = truth_for(-50..200, 3, 42.0, 1000.0, 300.0);
            let v = crb(&m, &truth, &out);
            let var = sigma * sigma + 1.0 / 12.0;
            let var_phi = 2.0 * var / (f64::from(n) * 300.0 * 300.0);
            let expect = var_phi * (500.0 / TAU).powi(2);
            let mut seen = 0;
            for (r, vr) in out.rows.iter().zip(&v) {
                for x in vr {
                    if r.is_valid() && r.window.is_some() {
                        let got = x.unwrap();
                        assert!((got / expect - 1.0).abs() < 1e-9, "{got} {expect}");
                        seen += 1;
                    } else {
                        assert!(x.is_none());
                    }
                }
            }
            assert!(seen > 0);
            // No noise model: nothing.
            m.noise = None;
            assert!(crb(&m, &truth, &out).iter().flatten().all(|x| x.is_none()));
        }
    }

    #[test]
    fn flat_mask_neighbourhood() {
        let mut t = truth_for(0..4, 5, 1.0, 0.0, 0.0);
        t.height_um[3 * 5 + 4] = 2.0; // corner (border) pixel changes
        t.height_um[5 + 1] = 3.0; // interior pixel (1,1)
        let m = flat_mask(&t);
        let expect_row1 = [false, false, false, true, false];
        let expect_row2 = [false; 5]; // (2,3) sees the changed corner (3,4)
        assert_eq!(&m[5..10], &expect_row1);
        assert_eq!(&m[10..15], &expect_row2);
        assert!(m[..5].iter().all(|&v| !v));
        assert!(m[15..].iter().all(|&v| !v));
        assert!(flat_mask(&truth_for(0..2, 5, 1.0, 0.0, 0.0))
            .iter()
            .all(|&v| !v));
    }

    #[test]
    fn to_height_map_roundtrip() {
        let lat: Vec<i64> = (0..8).map(|k| 8 * k).collect();
        let m = manifest(4, 40, 4, 10, 1.0, &seqs(&lat));
        let frames = render(&m, board_height, 2000.0, 800.0);
        let out = reconstruct(&m, &frames);
        let hm = out.to_height_map(&m);
        assert_eq!(hm.len(), out.rows.len());
        assert_eq!(hm.valid_pixels(), out.valid_pixels());
        let r = out.rows.iter().find(|r| r.is_valid()).unwrap();
        let hr = hm.get(r.row).unwrap();
        assert_eq!(
            hr.latch,
            m.frames[r.window.as_ref().unwrap().frames[0]].latch
        );
        assert_eq!(i32::from(hr.heights[2]), r.height_lsb[2]);
    }

    /// Timing check of a full 2048 x 2048 board (run with `--release -- --ignored`).
    #[test]
    #[ignore]
    fn full_board_timing() {
        let steps = [8i64, 7, 9, 8, 8, 9, 7, 8];
        let mut lat = vec![0i64];
        while *lat.last().unwrap() < 2048 {
            let k = lat.len();
            lat.push(lat.last().unwrap() + steps[k % steps.len()]);
        }
        let m = manifest(2048, 40, 4, 10, 1.0, &seqs(&lat));
        let frames = render(
            &m,
            |b, c| ((b as usize / 50 + c / 50) % 2) as f64 * 80.0,
            2000.0,
            800.0,
        );
        let t0 = std::time::Instant::now();
        let out = reconstruct(&m, &frames);
        let t_ref = t0.elapsed();
        let t0 = std::time::Instant::now();
        let base = psp(&m, &frames);
        let t_psp = t0.elapsed();
        eprintln!(
            "{} rows, {} valid px: reconstruct {t_ref:?}, psp {t_psp:?} ({} valid px)",
            out.rows.len(),
            out.valid_pixels(),
            base.valid_pixels()
        );
        assert!(out.valid_pixels() > 2000 * 2000);
    }
}
