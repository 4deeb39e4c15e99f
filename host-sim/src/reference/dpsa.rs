//! The f64 reference implementation of D-PSA, written from the measurement model in
//! `docs/model.md` (registration steps 1-8 and the validity rules).
//!
//! It is deliberately independent of the fixed-point core (`dpsa-core`): everything is f64,
//! the least squares uses the full `n x 3` design matrix `M` with rows
//! `[1, cos theta_j, -sin theta_j]` and `P = (M^T M)^-1 M^T` computed by nalgebra (not the
//! centred 2x2 shortcut, which is only used for the noise gain, as the model defines it), the
//! phase is an f64 `atan2` and the output is f64-rounded.
//!
//! Besides [`reconstruct`] this module provides the conventional baseline [`psp`](fn@super::psp) (nominal
//! uniform shifts), the Cramer-Rao bound [`crb`](fn@super::crb) of the height variance and the truth mask
//! [`flat_mask`](super::flat_mask) used by [`crate::reference::compare`].

use crate::heightmap::{flags, HeightMap, HeightRow};
use crate::simulation::recording::{Frame, Manifest};
pub use dpsa_board::provenance::{
    offset, plan_triggers, trigger_offsets, Registration, RowPlan, MAX_PLAN_ROWS,
};
use dpsa_core::Trigger;
use nalgebra::{Dyn, Matrix2, Matrix3, OMatrix, SymmetricEigen, U3};
use std::f64::consts::{PI, TAU};

/// Offsets `o_k` of all manifest frames, px; `None` when any is unusable (see [`offset`]).
pub fn offsets(manifest: &Manifest) -> Option<Vec<i64>> {
    let cpp = manifest.calibration.counts_per_pixel;
    manifest
        .frames
        .iter()
        .map(|f| offset(f.latch, cpp))
        .collect()
}

/// Registration steps 1-4 of `docs/model.md` on a manifest's frames
/// ([`plan_triggers`], which the production board map
/// replays on a stream's trigger log: one implementation of the rule, in `dpsa-board`).
/// `first_frame` indexes `manifest.frames`. Frame-content checks (a frame that did not deliver
/// the row's line) are added by [`reconstruct`].
pub fn plan(manifest: &Manifest) -> Vec<RowPlan> {
    let triggers: Vec<Trigger> = manifest.frames.iter().map(|f| f.trigger()).collect();
    plan_triggers(
        &triggers,
        &Registration {
            rows: manifest.camera.rows,
            n: manifest.processing.n,
            max_step_rows: manifest.processing.max_step_rows,
            counts_per_pixel: manifest.calibration.counts_per_pixel,
        },
    )
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
///
/// The reference's own wrap, not the host's ([`dpsa_formats::calibration::wrap_phase`]): the
/// reference is written from the model apart from the production code, and this form returns
/// a phase already in range exactly. The two differ by an ulp or so; the calibration's core
/// table is computed through this one, so sharing either would move every calibration file
/// and board map in its last bits.
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
    /// nominal `-j delta` for [`psp`](fn@super::psp)).
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

/// Output of [`reconstruct`] or [`psp`](fn@super::psp): one row per planned board row, sorted by `row`.
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
pub(super) enum Shifts {
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
    let mut src = frames;
    infallible(run(manifest, &mut src, Shifts::Actual))
}

/// [`reconstruct`] on frames read on demand (e.g. [`LazyFrames`]): the same result, bit for
/// bit, with only the window's frames in memory.
pub fn reconstruct_from(
    manifest: &Manifest,
    frames: &mut dyn FrameSource,
) -> crate::Result<RefOutput> {
    run(manifest, frames, Shifts::Actual)
}

/// A result whose frame source cannot fail (frames in memory).
pub(super) fn infallible(r: crate::Result<RefOutput>) -> RefOutput {
    match r {
        Ok(o) => o,
        Err(e) => unreachable!("in-memory frames cannot fail: {e}"),
    }
}

/// Where the reference takes its frames from: all in memory (`&[Frame]`) or read on demand
/// ([`LazyFrames`]). Rows are evaluated in board-row order, so the frames a window needs move
/// forward through the recording.
pub trait FrameSource {
    /// Makes frames `range` available to [`FrameSource::get`]; frames outside it may be dropped.
    fn window(&mut self, range: std::ops::Range<usize>) -> crate::Result<()>;
    /// Frame `k`, if it exists (and is inside the last [`FrameSource::window`]).
    fn get(&self, k: usize) -> Option<&Frame>;
}

impl FrameSource for &[Frame] {
    fn window(&mut self, _: std::ops::Range<usize>) -> crate::Result<()> {
        Ok(())
    }
    fn get(&self, k: usize) -> Option<&Frame> {
        <[Frame]>::get(self, k)
    }
}

/// The frames of a recording, decoded when a window first needs them and dropped when the
/// window has moved past them: at most one window (`n` frames) is held.
pub struct LazyFrames<'a> {
    rec: &'a crate::simulation::recording::Recording,
    held: Vec<(usize, Frame)>,
    /// Frames decoded so far (a frame is decoded again only if a later window goes back).
    pub loads: usize,
}

impl<'a> LazyFrames<'a> {
    /// The frames of `rec`, none decoded yet.
    pub fn new(rec: &'a crate::simulation::recording::Recording) -> Self {
        LazyFrames {
            rec,
            held: Vec::new(),
            loads: 0,
        }
    }
}

impl FrameSource for LazyFrames<'_> {
    fn window(&mut self, range: std::ops::Range<usize>) -> crate::Result<()> {
        self.held.retain(|(k, _)| range.contains(k));
        for k in range.start..range.end.min(self.rec.len()) {
            if !self.held.iter().any(|(j, _)| *j == k) {
                self.held.push((k, self.rec.frame(k)?));
                self.loads += 1;
            }
        }
        Ok(())
    }
    fn get(&self, k: usize) -> Option<&Frame> {
        self.held.iter().find(|(j, _)| *j == k).map(|(_, f)| f)
    }
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

pub(super) fn run(
    manifest: &Manifest,
    frames: &mut dyn FrameSource,
    shifts: Shifts,
) -> crate::Result<RefOutput> {
    let mut eval = RowEval::new(manifest, shifts);
    let mut rows = Vec::with_capacity(eval.len());
    while let Some(row) = eval.next_row(frames) {
        rows.push(row?);
    }
    Ok(RefOutput {
        width: eval.width,
        rows,
    })
}

/// The reference evaluated one board row at a time, in the plan's increasing board-row order:
/// `run` collects the rows; the comparison ([`super::compare`]) folds each row into its
/// statistics and drops it, so its memory is one window of frames plus one row per result.
///
/// The entry frame `w` of the planned rows never decreases (rows enter at the frame whose top
/// first passes them, and the admitted ranges follow the running maximum `E_k`), so one
/// cached window serves every row that entered at the same frame.
pub struct RowEval<'m> {
    manifest: &'m Manifest,
    shifts: Shifts,
    plan: Vec<RowPlan>,
    next: usize,
    o: Vec<i64>,
    phi0: Vec<f64>,
    f_x: f64,
    width: usize,
    /// The window (and its projector) of entry frame `w`.
    cache: Option<(usize, Window, Option<PhaseFit>)>,
}

impl<'m> RowEval<'m> {
    /// The f64 D-PSA reference ([`reconstruct`]).
    pub fn dpsa(manifest: &'m Manifest) -> Self {
        RowEval::new(manifest, Shifts::Actual)
    }

    /// The conventional baseline ([`super::psp`](fn@super::psp)).
    pub fn psp(manifest: &'m Manifest) -> Self {
        let f_x = 1.0 / manifest.calibration.fringe_period_px;
        RowEval::new(
            manifest,
            Shifts::Nominal(TAU * f_x * super::psp::nominal_step_px(manifest)),
        )
    }

    pub(super) fn new(manifest: &'m Manifest, shifts: Shifts) -> Self {
        let width = manifest.camera.width as usize;
        let cal = &manifest.calibration;
        RowEval {
            manifest,
            shifts,
            plan: plan(manifest),
            next: 0,
            o: offsets(manifest).unwrap_or_default(),
            phi0: (0..width)
                .map(|c| cal.reference_phase_rad.get(c).copied().unwrap_or(f64::NAN))
                .collect(),
            f_x: 1.0 / cal.fringe_period_px,
            width,
            cache: None,
        }
    }

    /// Rows of the plan (the rows [`RowEval::next_row`] will give).
    pub fn len(&self) -> usize {
        self.plan.len()
    }

    /// True when the plan is empty.
    pub fn is_empty(&self) -> bool {
        self.plan.is_empty()
    }

    /// Columns per row.
    pub fn width(&self) -> usize {
        self.width
    }

    /// The next planned board row, `None` after the last; an error only when `frames` fails
    /// to read a frame.
    pub fn next_row(&mut self, frames: &mut dyn FrameSource) -> Option<crate::Result<RefRow>> {
        let p = self.plan.get(self.next)?.clone();
        self.next += 1;
        Some(self.evaluate(&p, frames))
    }

    fn window(&mut self, w: usize) -> (Window, Option<PhaseFit>) {
        if let Some((cw, window, fit)) = &self.cache {
            if *cw == w {
                return (window.clone(), fit.clone());
            }
        }
        let n = usize::from(self.manifest.processing.n);
        let offs: Vec<i64> = self.o[w..w + n].to_vec();
        let th: Vec<f64> = match self.shifts {
            Shifts::Actual => offs
                .iter()
                .map(|&ok| -TAU * self.f_x * (ok - offs[0]) as f64)
                .collect(),
            Shifts::Nominal(delta) => (0..n).map(|j| -(j as f64) * delta).collect(),
        };
        let fit = PhaseFit::new(&th);
        let window = Window::new((w..w + n).collect(), offs, th);
        self.cache = Some((w, window.clone(), fit.clone()));
        (window, fit)
    }

    fn evaluate(&mut self, p: &RowPlan, frames: &mut dyn FrameSource) -> crate::Result<RefRow> {
        let manifest = self.manifest;
        let width = self.width;
        let n = usize::from(manifest.processing.n);
        let mut row = RefRow::empty(p.row, p.flags, width);
        let Some(w) = p.first_frame else {
            return Ok(row);
        };
        if w + n > self.o.len() {
            // Runs past the last frame: plan() already flagged INCOMPLETE.
            return Ok(row);
        }
        let (window, fit) = self.window(w);

        // The noise-gain test. For the nominal set (the same for every window) this only
        // fires when the conventional design itself is degenerate.
        let g = window.noise_gain;
        if fit.is_none() || g.is_nan() || g > manifest.processing.max_noise_gain {
            row.flags |= flags::ILL_CONDITIONED;
        }

        // Gather the row's line from each window frame.
        frames.window(w..w + n)?;
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
            let phi_r_row = TAU * self.f_x * (b - window.offsets[0]) as f64;
            let row_ok = !flags::invalidates(row.flags);
            let summary = fill_pixels(
                &mut row, fit, &lines, phi_r_row, &self.phi0, manifest, row_ok,
            );
            row.flags |= summary;
        }
        row.window = Some(window);
        // Pixel-level flags may have been added after the row flag decision; make the
        // validity consistent with the final row flags.
        if flags::invalidates(row.flags) {
            row.valid.iter_mut().for_each(|v| *v = false);
        }
        Ok(row)
    }
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
    let cal = &manifest.calibration;
    let lsb = cal.height_lsb_um;

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
        // T_z of this column (the per-column calibration when the manifest has one).
        let h = d / TAU * cal.height_per_turn_at(c);
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
