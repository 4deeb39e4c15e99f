//! Comparison of a fixed-point result against the f64 reference, the conventional PSP
//! baseline, the ground truth and the Cramer-Rao bound.
//!
//! Heights are only determined modulo one fringe turn `T_z` (`height_per_turn_um`), so every
//! height difference here (fixed vs reference, any result vs truth) is folded into
//! `[-T_z/2, T_z/2)` before it is squared: a phase that crosses the wrap boundary is a small
//! error, not a `T_z` error.

use crate::heightmap::{flags, HeightMap, HeightRow};
use crate::reference::crb::crb_row;
use crate::reference::truth::{flat_mask, truth_row, CameraTruthReader, CameraTruthRow};
use crate::reference::{LazyFrames, RefOutput, RefRow, RowEval};
use crate::simulation::recording::{CameraTruth, Manifest, Recording};
use crate::{At, Result, SimError};
use serde::Serialize;
use std::collections::BTreeMap;
use std::fmt::Write as _;

/// Fixed-point result against the f64 reference, in LSB of the output.
#[derive(Serialize, Clone, Debug, PartialEq, Default)]
pub struct FixedVsRef {
    /// Pixels valid in both results.
    pub pixels_compared: u64,
    /// Largest `|fixed - ref|` over the compared pixels (null when none), LSB.
    pub max_abs_lsb: Option<f64>,
    /// RMS of `fixed - ref`, LSB.
    pub rms_lsb: Option<f64>,
    /// Mean of `fixed - ref`, LSB.
    pub mean_lsb: Option<f64>,
    /// Compared pixels with `|fixed - ref| > 1` LSB.
    pub pixels_over_1_lsb: u64,
    /// Pixels valid in exactly one of the two (rows missing on one side count as invalid).
    pub valid_mismatch: u64,
    /// Pixels valid only in the fixed result.
    pub valid_only_fixed: u64,
    /// Pixels valid only in the reference.
    pub valid_only_ref: u64,
    /// Board rows present only in the fixed result.
    pub rows_only_fixed: u64,
    /// Board rows present only in the reference.
    pub rows_only_ref: u64,
    /// Rows present in both whose row validity (no invalidating flag) differs.
    pub row_validity_mismatch: u64,
    /// Rows present in both whose flags differ in any bit.
    pub row_flags_mismatch: u64,
}

/// Errors against the simulator ground truth, um. All null without truth.
///
/// The fixed, reference and CRB figures use one pixel set: pixels flat in truth
/// ([`flat_mask`]), valid in the fixed result, valid in the reference and, when the manifest
/// has a noise model, with a defined CRB. The PSP figures use the flat pixels valid in the PSP
/// result.
#[derive(Serialize, Clone, Debug, PartialEq, Default)]
pub struct HeightAccuracy {
    /// Flat pixels in the truth.
    pub flat_pixels: Option<u64>,
    /// Pixels used for the fixed / reference / CRB figures.
    pub pixels: Option<u64>,
    /// RMS of `fixed - truth`, um (fixed heights are `h_lsb * lsb`).
    pub fixed_rms_um: Option<f64>,
    /// Mean of `fixed - truth`, um.
    pub fixed_bias_um: Option<f64>,
    /// Largest `|fixed - truth|`, um.
    pub fixed_max_abs_um: Option<f64>,
    /// RMS of `ref - truth` (unrounded f64 heights), um.
    pub ref_rms_um: Option<f64>,
    /// Mean of `ref - truth`, um.
    pub ref_bias_um: Option<f64>,
    /// `sqrt(mean CRB variance)` over the same pixels, um.
    pub crb_rms_um: Option<f64>,
    /// `fixed_rms_um / crb_rms_um`.
    pub fixed_over_crb: Option<f64>,
    /// `ref_rms_um / crb_rms_um`.
    pub ref_over_crb: Option<f64>,
    /// Pixels used for the PSP figures.
    pub psp_pixels: Option<u64>,
    /// RMS of `psp - truth`, um.
    pub psp_rms_um: Option<f64>,
    /// Mean of `psp - truth`, um.
    pub psp_bias_um: Option<f64>,
    /// `psp_rms_um / fixed_rms_um`.
    pub psp_over_fixed: Option<f64>,
    /// Quantisation noise of the i16 output, `lsb / sqrt(12)`, um.
    pub quantization_rms_um: Option<f64>,
    /// `quantization_rms_um / ref_rms_um`: must stay under 0.1 so the LSB never limits the
    /// measurement (the per-pixel height noise is measured by the f64 reference).
    pub quantization_over_noise: Option<f64>,
}

/// Pixel counts.
#[derive(Serialize, Clone, Debug, PartialEq, Default)]
pub struct PixelStats {
    /// Pixels of the fixed result (`rows x width`).
    pub total: u64,
    /// Valid pixels of the fixed result.
    pub valid: u64,
    /// Valid pixels of the reference.
    pub ref_valid: u64,
    /// Valid pixels of the PSP baseline (null without it).
    pub psp_valid: Option<u64>,
}

/// Row counts of the fixed result (and the reference totals).
#[derive(Serialize, Clone, Debug, PartialEq, Default)]
pub struct RowStats {
    /// Rows of the fixed result.
    pub total: u64,
    /// Rows without an invalidating flag.
    pub valid: u64,
    /// Rows flagged `ILL_CONDITIONED` (window noise gain above `max_noise_gain`).
    pub ill_conditioned: u64,
    /// Rows flagged `INCOMPLETE` (not seen in `n` consecutive frames).
    pub incomplete: u64,
    /// Rows flagged `SKIPPED` (never admitted).
    pub skipped: u64,
    /// Rows flagged `ENCODER_REVERSAL` (the encoder count decreased while open).
    pub encoder_reversal: u64,
    /// Rows flagged `FRAME_GAP` (a lost frame or an undelivered line).
    pub frame_gap: u64,
    /// Rows flagged `SATURATED` (a pixel with a saturated sample).
    pub saturated: u64,
    /// Rows flagged `LOW_MODULATION` (a pixel below `min_modulation`).
    pub low_modulation: u64,
    /// Rows flagged `OVERFLOW` (the core ran out of line slots).
    pub overflow: u64,
    /// Rows of the reference.
    pub ref_total: u64,
    /// Reference rows without an invalidating flag.
    pub ref_valid: u64,
}

/// Result of [`compare`]; serialises to the JSON report.
#[derive(Serialize, Clone, Debug, PartialEq, Default)]
pub struct Comparison {
    /// The fixed-point result against the f64 reference, LSB.
    pub fixed_vs_ref: FixedVsRef,
    /// Errors against the ground truth, um (null without truth).
    pub truth: HeightAccuracy,
    /// Pixel counts.
    pub pixels: PixelStats,
    /// Row counts.
    pub rows: RowStats,
}

/// Running sums of an error.
#[derive(Default, Clone, Copy)]
struct Acc {
    n: u64,
    sum: f64,
    sum_sq: f64,
    max_abs: f64,
}

impl Acc {
    fn add(&mut self, x: f64) {
        self.n += 1;
        self.sum += x;
        self.sum_sq += x * x;
        self.max_abs = self.max_abs.max(x.abs());
    }
    fn mean(&self) -> Option<f64> {
        (self.n > 0).then(|| self.sum / self.n as f64)
    }
    fn rms(&self) -> Option<f64> {
        (self.n > 0).then(|| (self.sum_sq / self.n as f64).sqrt())
    }
    fn max_abs(&self) -> Option<f64> {
        (self.n > 0).then_some(self.max_abs)
    }
}

/// Folds `d` into `[-period/2, period/2)`; unchanged when `period` is not positive and finite.
fn fold(d: f64, period: f64) -> f64 {
    if period > 0.0 && period.is_finite() {
        d - period * ((d + period / 2.0) / period).floor()
    } else {
        d
    }
}

fn ratio(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    match (a, b) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    }
}

/// Height of a valid fixed pixel, um.
fn fixed_um(row: &HeightRow, c: usize, lsb_um: f64) -> Option<f64> {
    if !row.pixel_valid(c) {
        return None;
    }
    row.heights.get(c).map(|&h| f64::from(h) * lsb_um)
}

/// A reference pixel is valid when its valid bit is set (and its values exist).
fn ref_valid(row: &RefRow, c: usize) -> bool {
    row.valid.get(c).copied().unwrap_or(false)
        && c < row.height_lsb.len()
        && c < row.height_um.len()
}

/// The comparison folded one board row at a time: every statistic of [`Comparison`] is a sum,
/// a count or a maximum, so nothing of a row is kept once it has been added. [`compare`] feeds
/// it from results in memory, [`compare_recording`] straight from the three producers (core,
/// reference, PSP) and the truth files, in memory bounded by one window of frames.
///
/// - fixed vs ref: over pixels valid in both (a fixed pixel is valid when its valid bit is set
///   and its row has no invalidating flag), the difference `fixed - ref.height_lsb` in LSB of
///   the manifest's `height_lsb_um`, folded modulo the column's turn in LSB,
///   `T_z(c) / lsb` (`height_per_turn_um`, or `height_per_turn_um_per_column[c]`), into
///   `[-T_z(c)/lsb/2, T_z(c)/lsb/2)`;
/// - vs truth: see [`HeightAccuracy`] for the pixel sets; errors in um, folded modulo `T_z(c)`. The
///   CRB comes from [`crb_row`] on the reference row (needs `manifest.noise`).
pub struct Comparer<'m> {
    manifest: &'m Manifest,
    fixed_lsb_um: f64,
    fvr: FixedVsRef,
    diff: Acc,
    fe: Acc,
    re: Acc,
    pe: Acc,
    crb_sum: f64,
    pixels: PixelStats,
    rows: RowStats,
    psp: bool,
    truth: bool,
}

impl<'m> Comparer<'m> {
    /// `fixed_lsb_um` labels the fixed heights; `psp` and `truth` say whether those results
    /// take part (their figures are null otherwise).
    pub fn new(manifest: &'m Manifest, fixed_lsb_um: f64, psp: bool, truth: bool) -> Self {
        Comparer {
            manifest,
            fixed_lsb_um,
            fvr: FixedVsRef::default(),
            diff: Acc::default(),
            fe: Acc::default(),
            re: Acc::default(),
            pe: Acc::default(),
            crb_sum: 0.0,
            pixels: PixelStats {
                psp_valid: psp.then_some(0),
                ..PixelStats::default()
            },
            rows: RowStats::default(),
            psp,
            truth,
        }
    }

    /// Adds one board row: whichever results have it, and its truth.
    pub fn row(
        &mut self,
        fixed: Option<&HeightRow>,
        reference: Option<&RefRow>,
        psp: Option<&RefRow>,
        truth: Option<&CameraTruthRow<'_>>,
    ) {
        let m = self.manifest;
        let lsb = m.calibration.height_lsb_um;
        // Heights fold modulo their column's turn (per-column with a calibrated T_z(c)).
        let t_z = |c: usize| m.calibration.height_per_turn_at(c);
        if let Some(f) = fixed {
            let rs = &mut self.rows;
            rs.total += 1;
            rs.valid += u64::from(f.is_valid());
            let has = |mask: u16| u64::from(f.flags & mask != 0);
            rs.ill_conditioned += has(flags::ILL_CONDITIONED);
            rs.incomplete += has(flags::INCOMPLETE);
            rs.skipped += has(flags::SKIPPED);
            rs.encoder_reversal += has(flags::ENCODER_REVERSAL);
            rs.frame_gap += has(flags::FRAME_GAP);
            rs.saturated += has(flags::SATURATED);
            rs.low_modulation += has(flags::LOW_MODULATION);
            rs.overflow += has(flags::OVERFLOW);
            self.pixels.total += f.heights.len() as u64;
            self.pixels.valid += f.valid_count() as u64;
        }
        if let Some(r) = reference {
            self.rows.ref_total += 1;
            self.rows.ref_valid += u64::from(r.is_valid());
            self.pixels.ref_valid += r.valid.iter().filter(|&&v| v).count() as u64;
        }
        if let (Some(p), Some(n)) = (psp, self.pixels.psp_valid.as_mut()) {
            *n += p.valid.iter().filter(|&&v| v).count() as u64;
        }

        // Fixed against the reference.
        let fvr = &mut self.fvr;
        match (fixed, reference) {
            (Some(_), None) => fvr.rows_only_fixed += 1,
            (None, Some(_)) => fvr.rows_only_ref += 1,
            (Some(f), Some(r)) => {
                fvr.row_validity_mismatch += u64::from(f.is_valid() != r.is_valid());
                fvr.row_flags_mismatch += u64::from(f.flags != r.flags);
            }
            (None, None) => {}
        }
        let width = fixed
            .map_or(0, |f| f.valid.len().max(f.heights.len()))
            .max(reference.map_or(0, |r| r.valid.len()));
        for c in 0..width {
            let fh = fixed.and_then(|f| fixed_um(f, c, self.fixed_lsb_um));
            let rv = reference.is_some_and(|r| ref_valid(r, c));
            match (fh, rv) {
                (Some(fh), true) => {
                    let rh = f64::from(reference.map_or(0, |r| r.height_lsb[c])) * lsb;
                    let d = fold((fh - rh) / lsb, t_z(c) / lsb);
                    self.diff.add(d);
                    fvr.pixels_over_1_lsb += u64::from(d.abs() > 1.0);
                }
                (Some(_), false) => fvr.valid_only_fixed += 1,
                (None, true) => fvr.valid_only_ref += 1,
                (None, false) => {}
            }
        }

        // Everything against the truth.
        let Some(t) = truth.filter(|_| self.truth) else {
            return;
        };
        if let (Some(f), Some(r)) = (fixed, reference) {
            let crb = m.noise.as_ref().map(|_| crb_row(m, r, |c| t.at(c)));
            for c in 0..t.flat.len() {
                if !t.is_flat(c) || !ref_valid(r, c) {
                    continue;
                }
                let Some(fh) = fixed_um(f, c, self.fixed_lsb_um) else {
                    continue;
                };
                let var = match &crb {
                    Some(v) => match v.get(c).copied().flatten() {
                        Some(v) => v,
                        None => continue,
                    },
                    None => 0.0,
                };
                let h = f64::from(t.height_um[c]);
                self.fe.add(fold(fh - h, t_z(c)));
                self.re.add(fold(r.height_um[c] - h, t_z(c)));
                self.crb_sum += var;
            }
        }
        if let Some(p) = psp.filter(|_| self.psp) {
            for c in 0..t.flat.len() {
                if t.is_flat(c) && ref_valid(p, c) {
                    self.pe
                        .add(fold(p.height_um[c] - f64::from(t.height_um[c]), t_z(c)));
                }
            }
        }
    }

    /// The report; `flat_pixels` is the truth's flat-pixel count (null without truth).
    pub fn finish(self, flat_pixels: Option<u64>) -> Comparison {
        let mut fvr = self.fvr;
        let diff = self.diff;
        fvr.pixels_compared = diff.n;
        fvr.max_abs_lsb = diff.max_abs();
        fvr.rms_lsb = diff.rms();
        fvr.mean_lsb = diff.mean();
        fvr.valid_mismatch = fvr.valid_only_fixed + fvr.valid_only_ref;
        let truth = if self.truth {
            let (fe, re, pe) = (self.fe, self.re, self.pe);
            let lsb_um = self.manifest.calibration.height_lsb_um;
            let crb_rms = (self.manifest.noise.is_some() && fe.n > 0)
                .then(|| (self.crb_sum / fe.n as f64).sqrt());
            HeightAccuracy {
                flat_pixels,
                pixels: Some(fe.n),
                fixed_rms_um: fe.rms(),
                fixed_bias_um: fe.mean(),
                fixed_max_abs_um: fe.max_abs(),
                ref_rms_um: re.rms(),
                ref_bias_um: re.mean(),
                crb_rms_um: crb_rms,
                fixed_over_crb: ratio(fe.rms(), crb_rms),
                ref_over_crb: ratio(re.rms(), crb_rms),
                psp_pixels: self.psp.then_some(pe.n),
                psp_rms_um: pe.rms(),
                psp_bias_um: pe.mean(),
                psp_over_fixed: ratio(pe.rms(), fe.rms()),
                quantization_rms_um: Some(lsb_um / 12f64.sqrt()),
                quantization_over_noise: ratio(Some(lsb_um / 12f64.sqrt()), re.rms()),
            }
        } else {
            HeightAccuracy::default()
        };
        Comparison {
            fixed_vs_ref: fvr,
            truth,
            pixels: self.pixels,
            rows: self.rows,
        }
    }
}

/// Compares a fixed-point height map with the f64 reference, and (optionally) the PSP
/// baseline and all of them with the ground truth, all held in memory (see [`Comparer`] for
/// the definitions). Rows are matched by board row over the union of the three results.
pub fn compare(
    manifest: &Manifest,
    fixed: &HeightMap,
    reference: &RefOutput,
    psp: Option<&RefOutput>,
    truth: Option<&CameraTruth>,
) -> Comparison {
    type Slot<'a> = (
        Option<&'a HeightRow>,
        Option<&'a RefRow>,
        Option<&'a RefRow>,
    );
    let mut union: BTreeMap<i64, Slot<'_>> = BTreeMap::new();
    for r in &fixed.rows {
        union.entry(r.row).or_default().0 = Some(r);
    }
    for r in &reference.rows {
        union.entry(r.row).or_default().1 = Some(r);
    }
    for r in psp.iter().flat_map(|p| &p.rows) {
        union.entry(r.row).or_default().2 = Some(r);
    }
    let mut cmp = Comparer::new(manifest, fixed.lsb_um, psp.is_some(), truth.is_some());
    for (&b, &(f, r, p)) in &union {
        let t = truth.and_then(|t| truth_row(t, b));
        cmp.row(f, r, p, t.as_ref());
    }
    let flat = truth.map(|t| flat_mask(t).iter().filter(|&&v| v).count() as u64);
    cmp.finish(flat)
}

fn opt(x: Option<f64>, prec: usize) -> String {
    x.map_or_else(|| "n/a".to_string(), |v| format!("{v:.prec$}"))
}

impl Comparison {
    /// A short human-readable multi-line summary.
    pub fn summary(&self) -> String {
        let mut s = String::new();
        let r = &self.rows;
        let _ = writeln!(
            s,
            "rows: {} total, {} valid (ill-conditioned {}, incomplete {}, skipped {}, \
             reversal {}, frame gap {}, overflow {}; saturated {}, low modulation {})",
            r.total,
            r.valid,
            r.ill_conditioned,
            r.incomplete,
            r.skipped,
            r.encoder_reversal,
            r.frame_gap,
            r.overflow,
            r.saturated,
            r.low_modulation
        );
        let p = &self.pixels;
        let _ = writeln!(
            s,
            "pixels: {} valid of {} (reference {} valid{})",
            p.valid,
            p.total,
            p.ref_valid,
            p.psp_valid
                .map_or(String::new(), |v| format!(", PSP {v} valid"))
        );
        let f = &self.fixed_vs_ref;
        let _ = writeln!(
            s,
            "fixed vs ref: {} px compared, max |d| {} LSB, rms {} LSB, mean {} LSB, {} px > 1 LSB; \
             validity mismatch {} px ({} only fixed, {} only ref), rows only fixed {}, only ref {}",
            f.pixels_compared,
            opt(f.max_abs_lsb, 0),
            opt(f.rms_lsb, 3),
            opt(f.mean_lsb, 3),
            f.pixels_over_1_lsb,
            f.valid_mismatch,
            f.valid_only_fixed,
            f.valid_only_ref,
            f.rows_only_fixed,
            f.rows_only_ref
        );
        let t = &self.truth;
        match t.pixels {
            None => s.push_str("truth: none\n"),
            Some(n) => {
                let _ = writeln!(
                    s,
                    "truth ({n} flat px): fixed rms {} um (bias {}), ref rms {} um, CRB {} um, \
                     fixed/CRB {}",
                    opt(t.fixed_rms_um, 3),
                    opt(t.fixed_bias_um, 3),
                    opt(t.ref_rms_um, 3),
                    opt(t.crb_rms_um, 3),
                    opt(t.fixed_over_crb, 2)
                );
                let _ = writeln!(
                    s,
                    "output LSB: quantisation {} um rms = {} of the height noise",
                    opt(t.quantization_rms_um, 3),
                    opt(t.quantization_over_noise, 3)
                );
                if let Some(pn) = t.psp_pixels {
                    let _ = writeln!(
                        s,
                        "PSP baseline ({pn} flat px): rms {} um (bias {}), PSP/fixed {}",
                        opt(t.psp_rms_um, 3),
                        opt(t.psp_bias_um, 3),
                        opt(t.psp_over_fixed, 2)
                    );
                }
            }
        }
        s
    }
}

/// Fixed-point core vs f64 reference vs PSP baseline vs ground truth on one recording, in
/// memory bounded by the pipeline window: the core runs in its own thread and hands over its
/// rows as they leave it (the rows its stream carries, through a queue of
/// [`ROW_QUEUE`] rows); the reference and the PSP baseline are evaluated row by row from one
/// window of frames; the truth is read row by row ([`CameraTruthReader`]). Each board row is folded
/// into the [`Comparer`] and dropped.
pub fn compare_recording(rec: &Recording, progress: bool) -> Result<Comparison> {
    let m = &rec.manifest;
    let mut truth = CameraTruthReader::open(rec).at(|| "reading the ground truth")?;
    let mut cmp = Comparer::new(m, m.calibration.height_lsb_um, true, truth.is_some());
    std::thread::scope(|s| -> Result<()> {
        let (tx, rx) = std::sync::mpsc::sync_channel::<HeightRow>(ROW_QUEUE);
        let core = s.spawn(move || {
            crate::reconstruct::reconstruct_rows(rec, progress, |row| {
                tx.send(row)
                    .map_err(|_| SimError::Core("the comparison stopped".into()))
            })
        });
        let consumed = (|| -> Result<()> {
            let mut frames = LazyFrames::new(rec);
            let mut dpsa = RowEval::dpsa(m);
            let mut psp = RowEval::psp(m);
            let mut pending: Option<HeightRow> = None;
            while let Some(r) = dpsa.next_row(&mut frames) {
                let r = r?;
                let p = match psp.next_row(&mut frames) {
                    Some(p) => Some(p?).filter(|p| p.row == r.row),
                    None => None,
                };
                // Core rows before this board row have no reference row.
                let f = loop {
                    if pending.is_none() {
                        pending = rx.recv().ok();
                    }
                    match pending.take() {
                        Some(f) if f.row < r.row => cmp.row(Some(&f), None, None, None),
                        Some(f) if f.row == r.row => break Some(f),
                        other => {
                            pending = other;
                            break None;
                        }
                    }
                };
                let t = match truth.as_mut() {
                    Some(t) => t.row(r.row).at(|| "reading the ground truth")?,
                    None => None,
                };
                cmp.row(f.as_ref(), Some(&r), p.as_ref(), t.as_ref());
            }
            for f in pending.into_iter().chain(rx.iter()) {
                cmp.row(Some(&f), None, None, None);
            }
            Ok(())
        })();
        // The core's own error first: the comparison may have stopped because of it.
        match core.join() {
            Ok(Ok(_)) => consumed,
            Ok(Err(e)) => consumed.and(Err(e)),
            Err(_) => Err(SimError::Internal("the core thread panicked".into())),
        }
    })?;
    let flat = match truth {
        Some(t) => Some(t.finish().at(|| "reading the ground truth")?),
        None => None,
    };
    Ok(cmp.finish(flat))
}

/// Core rows queued between the core's thread and the comparison.
pub const ROW_QUEUE: usize = 256;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::Window;
    use crate::simulation::recording::{Calibration, Camera, Noise, Processing};
    use std::f64::consts::{PI, TAU};

    fn manifest() -> Manifest {
        Manifest {
            format: crate::simulation::recording::FORMAT.into(),
            version: crate::simulation::recording::VERSION,
            camera: Camera {
                id: 0,
                width: 3,
                rows: 40,
                bit_depth: 12,
                saturation: 4095,
            },
            calibration: Calibration {
                counts_per_pixel: 1.0,
                fringe_period_px: 32.0,
                reference_phase_rad: vec![0.0; 3],
                height_per_turn_um: 500.0,
                height_lsb_um: 0.25,
                height_per_turn_um_per_column: None,
            },
            processing: Processing {
                n: 4,
                max_step_rows: 10,
                min_modulation: 60.0,
                max_noise_gain: 2.0,
            },
            frames: Vec::new(),
            noise: None,
            truth: None,
            board_id: None,
        }
    }

    fn hrow(row: i64, flags: u16, heights: [i16; 3], valid: [bool; 3]) -> HeightRow {
        HeightRow {
            row,
            latch: 0,
            flags,
            heights: heights.to_vec(),
            valid: valid.to_vec(),
        }
    }

    fn rrow(row: i64, lsb: [i32; 3], um: [f64; 3], valid: [bool; 3]) -> RefRow {
        RefRow {
            row,
            flags: 0,
            window: None,
            phase_rad: um.iter().map(|h| h / 500.0 * TAU).collect(),
            height_um: um.to_vec(),
            height_lsb: lsb.to_vec(),
            valid: valid.to_vec(),
            modulation: vec![250.0; 3],
        }
    }

    fn fixture() -> (HeightMap, RefOutput, RefOutput, CameraTruth) {
        let fixed = HeightMap {
            width: 3,
            lsb_um: 0.25,
            rows: vec![
                hrow(10, 0, [4, 1999, 8], [true, true, false]),
                hrow(11, 0, [0, 0, 0], [true, true, true]),
                hrow(12, flags::INCOMPLETE, [0, 0, 0], [true, true, true]),
            ],
        };
        let reference = RefOutput {
            width: 3,
            rows: vec![
                rrow(10, [5, -1, 8], [1.25, -0.25, 2.0], [true, true, true]),
                rrow(11, [0, 2, 0], [0.0, 0.5, 0.0], [true, true, false]),
                rrow(13, [0, 0, 0], [0.0, 0.0, 0.0], [true, false, false]),
            ],
        };
        let psp = RefOutput {
            width: 3,
            rows: vec![
                rrow(10, [0; 3], [0.0, 1.75, 0.0], [false, true, false]),
                rrow(11, [0; 3], [0.0, 9.0, 0.0], [true, false, true]),
                rrow(12, [0; 3], [0.0, -2.25, 0.0], [false, true, false]),
            ],
        };
        // Board rows 9..=13, all at -0.25 um: flat pixels are column 1 of rows 10..=12.
        let truth = CameraTruth {
            first_row: 9,
            rows: 5,
            width: 3,
            height_um: vec![-0.25; 15],
            background: vec![1000.0; 15],
            contrast: vec![250.0; 15],
        };
        (fixed, reference, psp, truth)
    }

    fn close(a: Option<f64>, b: f64) -> bool {
        a.is_some_and(|a| (a - b).abs() < 1e-12)
    }

    #[test]
    fn crafted_case() {
        let m = manifest();
        let (fixed, reference, psp, truth) = fixture();
        let cmp = compare(&m, &fixed, &reference, Some(&psp), Some(&truth));

        // Diffs: -1, 1999-(-1)=2000 folds to 0, 0, -2.
        let f = &cmp.fixed_vs_ref;
        assert_eq!(f.pixels_compared, 4);
        assert!(close(f.max_abs_lsb, 2.0));
        assert!(close(f.rms_lsb, 1.25f64.sqrt()));
        assert!(close(f.mean_lsb, -0.75));
        assert_eq!(f.pixels_over_1_lsb, 1);
        assert_eq!(
            (f.valid_only_fixed, f.valid_only_ref, f.valid_mismatch),
            (1, 2, 3)
        );
        assert_eq!((f.rows_only_fixed, f.rows_only_ref), (1, 1));
        assert_eq!(f.row_validity_mismatch, 0);

        // Truth set: (10,1) and (11,1); (12,1) is invalid in the fixed result.
        let t = &cmp.truth;
        assert_eq!(t.flat_pixels, Some(3));
        assert_eq!(t.pixels, Some(2));
        // fixed errors: 499.75+0.25 = 500 -> 0, and 0.25.
        assert!(close(t.fixed_rms_um, (0.0625f64 / 2.0).sqrt()));
        assert!(close(t.fixed_bias_um, 0.125));
        assert!(close(t.fixed_max_abs_um, 0.25));
        // ref errors: 0 and 0.75.
        assert!(close(t.ref_rms_um, (0.5625f64 / 2.0).sqrt()));
        assert_eq!(t.crb_rms_um, None); // no noise model
        assert_eq!(t.fixed_over_crb, None);
        // PSP: (10,1) +2, (12,1) -2.
        assert_eq!(t.psp_pixels, Some(2));
        assert!(close(t.psp_rms_um, 2.0));
        assert!(close(t.psp_bias_um, 0.0));
        assert!(close(t.psp_over_fixed, 2.0 / (0.0625f64 / 2.0).sqrt()));

        assert_eq!(cmp.pixels.total, 9);
        assert_eq!(cmp.pixels.valid, 5);
        assert_eq!(cmp.pixels.ref_valid, 6);
        assert_eq!(cmp.pixels.psp_valid, Some(4));
        assert_eq!(
            (cmp.rows.total, cmp.rows.valid, cmp.rows.incomplete),
            (3, 2, 1)
        );
        assert_eq!((cmp.rows.ref_total, cmp.rows.ref_valid), (3, 3));

        let json = serde_json::to_value(&cmp).unwrap();
        assert_eq!(json["fixed_vs_ref"]["max_abs_lsb"], 2.0);
        assert_eq!(json["truth"]["pixels"], 2);
        assert!(json["truth"]["crb_rms_um"].is_null());
        assert_eq!(json["rows"]["valid"], 2);
        let s = cmp.summary();
        assert!(s.contains("fixed vs ref: 4 px compared"), "{s}");
        assert!(s.contains("PSP baseline"), "{s}");
    }

    #[test]
    fn crb_over_same_pixels() {
        let mut m = manifest();
        m.noise = Some(Noise {
            gain_e_per_dn: 1e15,
            read_noise_dn: 2.0,
        });
        let (fixed, mut reference, _, truth) = fixture();
        let shifts: Vec<f64> = (0..4).map(|j| -(j as f64) * PI / 2.0).collect();
        for r in &mut reference.rows {
            r.window = Some(Window::new(
                vec![0, 1, 2, 3],
                vec![0, 8, 16, 24],
                shifts.clone(),
            ));
        }
        let cmp = compare(&m, &fixed, &reference, None, Some(&truth));
        let t = &cmp.truth;
        assert_eq!(t.pixels, Some(2));
        // Textbook: var_Phi = 2 sigma^2 / (n C^2), sigma^2 = 4 + 1/12.
        let var_h = 2.0 * (4.0 + 1.0 / 12.0) / (4.0 * 250.0 * 250.0) * (500.0 / TAU).powi(2);
        let crb = t.crb_rms_um.unwrap();
        assert!((crb / var_h.sqrt() - 1.0).abs() < 1e-9);
        assert!((t.fixed_over_crb.unwrap() - t.fixed_rms_um.unwrap() / crb).abs() < 1e-12);
        assert_eq!(t.psp_pixels, None);
        assert_eq!(t.psp_rms_um, None);
    }

    #[test]
    fn no_truth_gives_nulls() {
        let m = manifest();
        let cmp = compare(&m, &HeightMap::default(), &RefOutput::default(), None, None);
        let json = serde_json::to_value(&cmp).unwrap();
        for key in [
            "fixed_rms_um",
            "ref_rms_um",
            "crb_rms_um",
            "psp_rms_um",
            "fixed_bias_um",
            "pixels",
            "fixed_over_crb",
            "psp_over_fixed",
        ] {
            assert!(json["truth"][key].is_null(), "{key}");
        }
        assert!(json["fixed_vs_ref"]["max_abs_lsb"].is_null());
        assert_eq!(json["fixed_vs_ref"]["pixels_compared"], 0);
        assert_eq!(json["pixels"]["total"], 0);
        assert!(cmp.summary().contains("truth: none"));
    }

    /// The streaming comparison (core in its thread, reference and PSP row by row, truth read
    /// row by row) gives exactly the figures of the comparison of whole results in memory.
    #[test]
    fn streaming_equals_in_memory() {
        use crate::simulation::{recording, scene::Scene, scene::Stall, simulate};
        let dir = tempfile::tempdir().unwrap();
        let scene = Scene {
            width: 48,
            board_length: 400,
            deposits: 12,
            jitter_pct: 30.0,
            stalls: vec![Stall {
                frame: 10,
                frames: 2,
            }],
            ..Scene::default()
        };
        let out = dir.path().join("rec");
        simulate::simulate(&scene, 7, &out, false).unwrap();
        let rec = Recording::open(&out).unwrap();
        let m = &rec.manifest;
        let frames = recording::load_frames(&rec, false).unwrap();
        let (_, _, fixed) = crate::reconstruct::reconstruct_map(&rec, false).unwrap();
        let reference = crate::reference::reconstruct(m, &frames);
        let psp = crate::reference::psp(m, &frames);
        let truth = rec.truth().unwrap().unwrap();
        let whole = compare(m, &fixed, &reference, Some(&psp), Some(&truth));
        let streamed = compare_recording(&rec, false).unwrap();
        assert_eq!(streamed, whole);
        assert!(whole.truth.pixels.unwrap() > 10_000);
        assert!(whole.rows.total >= 400 && whole.fixed_vs_ref.pixels_compared > 0);
    }

    #[test]
    fn identical_results_agree() {
        // The reference converted to a height map compares to itself with zero difference.
        let (_, reference, _, truth) = fixture();
        let m = manifest();
        let fixed = reference.to_height_map(&m);
        let cmp = compare(&m, &fixed, &reference, Some(&reference), Some(&truth));
        assert_eq!(cmp.fixed_vs_ref.valid_mismatch, 0);
        assert_eq!(cmp.fixed_vs_ref.max_abs_lsb, Some(0.0));
        assert_eq!(cmp.fixed_vs_ref.row_flags_mismatch, 0);
    }
}
