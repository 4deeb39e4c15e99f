//! Every field of a calibration file checked when it is read (`docs/calibration.md`, "Checks
//! on reading"): its range (physical, and what the fixed-point core takes: the core's part goes
//! through [`check_calibration`], the manifest's own checks), and
//! its consistency with the file's redundancy:
//!
//! - `counts_per_pixel = pitch_mm * counts_per_mm / cos(rotation_rad)` (the core's encoder step
//!   is derived from the lateral fit), and `lateral.row_pitch_mm = pitch_mm / cos(rotation_rad)`;
//! - the cameras share one encoder: each camera's `counts_per_mm` is within
//!   [`ENCODER_SPREAD`] of their median, and the top-level `counts_per_mm` is their mean;
//! - `fringe_period_px = 1 / mean_c f_x(c)` of `fringe_frequency_poly`;
//! - `fx_over_budget` says whether `fx_height_error_um` exceeds `fx_budget_um`;
//! - `height_per_turn_um[c]`: one smooth optical field, every column within
//!   [`TZ_COLUMN_SPREAD`] of the camera's median.
//!
//! The position of each camera against the array's design (a swapped `[[camera]]` block) is
//! checked against the array's design in [`CalFile::check_design`].

use super::{CalFile, CameraCal};
use crate::array::MAX_CAMERAS;
use crate::recording::checks::{check_blocks, check_calibration};
use crate::recording::{MAX_ROWS, MAX_WIDTH};
use std::fmt;

/// Largest relative spread of the cameras' `counts_per_mm` (one encoder for all of them). The
/// estimates of the shipped scenes agree within 5e-5 (`docs/calibration.md`, figures); a
/// camera 0.1 % off would misplace the far end of a 220 mm board by 220 um.
pub const ENCODER_SPREAD: f64 = 1e-3;
/// Largest relative distance of a column's `T_z(c)` from the camera's median. The optics vary
/// it smoothly by at most +-2 % across the field (the simulator's range, `docs/calibration.md`)
/// and the estimate's error is 1e-4 (the figures): 10 % is five times the optics' range and
/// refuses a column that was doubled or halved.
pub const TZ_COLUMN_SPREAD: f64 = 0.10;
/// Pixel pitch on the board, mm: 1 um (finer than a fringe projector resolves at its working
/// distance) to 1 mm (coarser than the smallest paste deposit an SPI camera must measure).
pub const PITCH_RANGE_MM: (f64, f64) = (0.001, 1.0);
/// Largest |rotation| of the image rows against the motion, rad (2 degrees: seven times the
/// simulator's mounting range of 0.3 degrees). The core registers a board point by its image
/// row; at 2 degrees a 2048 px row already sweeps 72 rows along the motion.
pub const MAX_ROTATION_RAD: f64 = 2.0 * std::f64::consts::PI / 180.0;
/// Largest |x0|, |y0|: 10 m, larger than any board a conveyor carries.
pub const MAX_POSITION_MM: f64 = 10_000.0;
/// Largest fringe period, px: the core's single `f_x` is the Q0.32 fraction `2^32 / P`; up to
/// `2^16` px it keeps at least 16 significant bits (relative step 1.5e-5, the calibration's own
/// `f_x` precision).
pub const MAX_FRINGE_PERIOD_PX: f64 = 65536.0;
/// Largest encoder scale, counts/mm (1 nm per count).
pub const MAX_COUNTS_PER_MM: f64 = 1e6;
/// Largest DN of a 16-bit camera (background and modulation).
pub const MAX_DN: f64 = 65535.0;

/// A field of a calibration file out of range or inconsistent with the rest of the file.
#[derive(Clone, Debug, PartialEq)]
pub struct CalInvalid {
    /// The camera (`[[camera]]` index), `None` for a top-level field.
    pub camera: Option<usize>,
    /// The field, as the file spells it (`lateral.pitch_mm`, `height_per_turn_um[17]`).
    pub field: String,
    /// What is wrong with it, one sentence.
    pub message: String,
}

impl fmt::Display for CalInvalid {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.camera {
            Some(i) => write!(f, "camera {i}: {}: {}", self.field, self.message),
            None => write!(f, "{}: {}", self.field, self.message),
        }
    }
}

impl std::error::Error for CalInvalid {}

struct Ctx(Option<usize>);

impl Ctx {
    fn check(
        &self,
        ok: bool,
        field: &str,
        message: impl FnOnce() -> String,
    ) -> Result<(), CalInvalid> {
        if ok {
            Ok(())
        } else {
            Err(CalInvalid {
                camera: self.0,
                field: field.to_string(),
                message: message(),
            })
        }
    }

    /// `lo <= v <= hi` and finite.
    fn range(&self, v: f64, field: &str, lo: f64, hi: f64, unit: &str) -> Result<(), CalInvalid> {
        self.check(v.is_finite() && v >= lo && v <= hi, field, || {
            format!("{v} {unit}, expected a finite value in {lo} ..= {hi}")
        })
    }

    /// `0 < v <= hi` and finite.
    fn positive(&self, v: f64, field: &str, hi: f64, unit: &str) -> Result<(), CalInvalid> {
        self.check(v.is_finite() && v > 0.0 && v <= hi, field, || {
            format!("{v} {unit}, expected a finite value > 0 and <= {hi}")
        })
    }

    /// One finite value per column, each in `lo ..= hi`.
    fn columns(
        &self,
        v: &[f64],
        field: &str,
        w: usize,
        lo: f64,
        hi: f64,
        unit: &str,
    ) -> Result<(), CalInvalid> {
        self.check(v.len() == w, field, || {
            format!("{} values, expected one per column ({w})", v.len())
        })?;
        if let Some(c) = v
            .iter()
            .position(|x| !(x.is_finite() && *x >= lo && *x <= hi))
        {
            return self.check(false, &format!("{field}[{c}]"), || {
                format!("{} {unit}, expected a finite value in {lo} ..= {hi}", v[c])
            });
        }
        Ok(())
    }
}

/// `|a - b| <= rel * |b| + abs`.
fn close(a: f64, b: f64, rel: f64, abs: f64) -> bool {
    (a - b).abs() <= rel * b.abs() + abs
}

impl CalFile {
    /// Checks every field (see the module docs); the first problem found, naming the camera
    /// and the field.
    pub fn validate(&self) -> Result<(), CalInvalid> {
        let top = Ctx(None);
        top.check(!self.camera.is_empty(), "camera", || {
            "no [[camera]] blocks: the file calibrates no camera".into()
        })?;
        top.check(self.camera.len() <= MAX_CAMERAS, "camera", || {
            format!(
                "{} [[camera]] blocks, an array has at most {}",
                self.camera.len(),
                MAX_CAMERAS
            )
        })?;
        top.positive(self.height_lsb_um, "height_lsb_um", 1000.0, "um")?;
        top.positive(self.fx_budget_um, "fx_budget_um", 1e6, "um")?;
        top.positive(
            self.counts_per_mm,
            "counts_per_mm",
            MAX_COUNTS_PER_MM,
            "counts/mm",
        )?;
        let mut cpm: Vec<f64> = self.camera.iter().map(|c| c.counts_per_mm).collect();
        cpm.sort_by(f64::total_cmp);
        let median = cpm[cpm.len() / 2];
        for (i, c) in self.camera.iter().enumerate() {
            self.validate_camera(i, c, median)?;
        }
        let mean = cpm.iter().sum::<f64>() / cpm.len() as f64;
        top.check(
            close(self.counts_per_mm, mean, 1e-9, 0.0),
            "counts_per_mm",
            || {
                format!(
                "{} counts/mm, but it is the mean of the cameras' counts_per_mm, which is {mean}",
                self.counts_per_mm
            )
            },
        )?;
        Ok(())
    }

    fn validate_camera(&self, i: usize, c: &CameraCal, median_cpm: f64) -> Result<(), CalInvalid> {
        let x = Ctx(Some(i));
        x.check(usize::from(c.id) == i, "id", || {
            format!(
                "the [[camera]] block at place {i} says id {}: the blocks are out of order or one is missing",
                c.id
            )
        })?;
        x.check((1..=MAX_WIDTH).contains(&c.width), "width", || {
            format!("{} px, expected 1..={MAX_WIDTH}", c.width)
        })?;
        x.check((1..=MAX_ROWS).contains(&c.rows), "rows", || {
            format!("{} px, expected 1..={MAX_ROWS}", c.rows)
        })?;
        let w = c.width as usize;
        x.positive(
            c.counts_per_mm,
            "counts_per_mm",
            MAX_COUNTS_PER_MM,
            "counts/mm",
        )?;
        x.check(
            close(c.counts_per_mm, median_cpm, ENCODER_SPREAD, 0.0),
            "counts_per_mm",
            || {
                format!(
                    "{} counts/mm is more than {} % from the cameras' median {median_cpm}: the cameras share one encoder, so their estimates must agree",
                    c.counts_per_mm,
                    ENCODER_SPREAD * 100.0
                )
            },
        )?;

        // Lateral.
        let l = &c.lateral;
        x.range(
            l.x0_mm,
            "lateral.x0_mm",
            -MAX_POSITION_MM,
            MAX_POSITION_MM,
            "mm",
        )?;
        x.range(
            l.y0_mm,
            "lateral.y0_mm",
            -MAX_POSITION_MM,
            MAX_POSITION_MM,
            "mm",
        )?;
        x.range(
            l.pitch_mm,
            "lateral.pitch_mm",
            PITCH_RANGE_MM.0,
            PITCH_RANGE_MM.1,
            "mm",
        )?;
        x.range(
            l.rotation_rad,
            "lateral.rotation_rad",
            -MAX_ROTATION_RAD,
            MAX_ROTATION_RAD,
            "rad",
        )?;
        let row_pitch = l.pitch_mm / l.rotation_rad.cos();
        x.check(
            l.row_pitch_mm.is_finite() && close(l.row_pitch_mm, row_pitch, 1e-5, 0.0),
            "lateral.row_pitch_mm",
            || {
                format!(
                    "{} mm, but pitch_mm / cos(rotation_rad) is {row_pitch} mm",
                    l.row_pitch_mm
                )
            },
        )?;
        x.check(
            l.fit_rms_um.is_finite() && l.fit_rms_um >= 0.0 && l.fit_rms_um <= l.pitch_mm * 1e3,
            "lateral.fit_rms_um",
            || {
                format!(
                    "{} um, expected a finite value from 0 to one pixel ({} um): a worse mark fit is no lateral calibration",
                    l.fit_rms_um,
                    l.pitch_mm * 1e3
                )
            },
        )?;

        // The core's part, as the manifest checks it (encoder step, fringe period, tables).
        x.check(c.fringe_period_px.is_finite(), "fringe_period_px", || {
            format!("{}, expected a finite period (px)", c.fringe_period_px)
        })?;
        x.range(
            c.fringe_period_px,
            "fringe_period_px",
            2.0,
            MAX_FRINGE_PERIOD_PX,
            "px",
        )?;
        x.columns(
            &c.height_per_turn_um,
            "height_per_turn_um",
            w,
            0.0,
            1e6,
            "um",
        )?;
        x.columns(
            &c.reference_phase_rad,
            "reference_phase_rad",
            w,
            -1e4,
            1e4,
            "rad",
        )?;
        x.columns(
            &c.core_reference_phase_rad,
            "core_reference_phase_rad",
            w,
            -1e4,
            1e4,
            "rad",
        )?;
        x.columns(&c.background_dn, "background_dn", w, 0.0, MAX_DN, "DN")?;
        x.columns(&c.modulation_dn, "modulation_dn", w, 0.0, MAX_DN, "DN")?;
        let mut tz = c.height_per_turn_um.clone();
        tz.sort_by(f64::total_cmp);
        let median = tz[tz.len() / 2];
        if let Some(col) = c
            .height_per_turn_um
            .iter()
            .position(|&t| !close(t, median, TZ_COLUMN_SPREAD, 0.0))
        {
            x.check(false, &format!("height_per_turn_um[{col}]"), || {
                format!(
                    "{} um is more than {} % from the camera's median {median} um: the height per turn varies smoothly and by a few percent over the field",
                    c.height_per_turn_um[col],
                    TZ_COLUMN_SPREAD * 100.0
                )
            })?;
        }
        // `apply` rounds it to the core's Q16.16; the rounded value must be the core's.
        let cpp_bits = (c.counts_per_pixel * 65536.0).round();
        x.check(
            c.counts_per_pixel.is_finite()
                && c.counts_per_pixel > 0.0
                && (1.0..4_294_967_296.0).contains(&cpp_bits),
            "counts_per_pixel",
            || {
                format!(
                    "{} counts/px, expected a finite value that rounds to 2^-16 ..< 65536 in steps of 2^-16 (the core's Q16.16 encoder step)",
                    c.counts_per_pixel
                )
            },
        )?;
        let mut block = crate::recording::Calibration {
            counts_per_pixel: cpp_bits / 65536.0,
            fringe_period_px: c.fringe_period_px,
            reference_phase_rad: c.core_reference_phase_rad.clone(),
            height_per_turn_um: 0.0,
            height_lsb_um: self.height_lsb_um,
            height_per_turn_um_per_column: None,
        };
        block.height_per_turn_um = c.core_height_per_turn_um();
        block.height_per_turn_um_per_column = Some(c.height_per_turn_um.clone());
        check_calibration(&block, c.width).map_err(|e| {
            let field = e
                .field
                .strip_prefix("calibration.")
                .unwrap_or(&e.field)
                .replace("height_per_turn_um_per_column", "height_per_turn_um")
                .replace("reference_phase_rad", "core_reference_phase_rad");
            CalInvalid {
                camera: Some(i),
                field,
                message: format!("{} (as the core takes it)", e.message),
            }
        })?;
        // The camera's sample range and the processing, with the checks a manifest's blocks
        // get (the processing's line pool depends on the camera's width).
        check_blocks(&c.core_camera(), &block, &self.processing).map_err(|e| CalInvalid {
            camera: Some(i),
            field: e
                .field
                .strip_prefix("camera.")
                .unwrap_or(&e.field)
                .to_string(),
            message: e.message,
        })?;

        // Redundancy: the encoder step from the lateral fit.
        let cpp = l.pitch_mm * c.counts_per_mm / l.rotation_rad.cos();
        x.check(
            close(c.counts_per_pixel, cpp, 1e-9, 1.0 / 65536.0),
            "counts_per_pixel",
            || {
                format!(
                    "{} counts/px, but lateral.pitch_mm * counts_per_mm / cos(rotation_rad) = {} * {} / cos({}) = {cpp}: the encoder step and the lateral calibration disagree",
                    c.counts_per_pixel, l.pitch_mm, c.counts_per_mm, l.rotation_rad
                )
            },
        )?;

        // The fringe frequency field and the core's single period.
        x.check(
            c.fringe_frequency_poly.iter().all(|v| v.is_finite()),
            "fringe_frequency_poly",
            || {
                format!(
                    "{:?}, expected finite coefficients",
                    c.fringe_frequency_poly
                )
            },
        )?;
        let half = f64::from(c.width) / 2.0;
        let f_at = |col: f64| c.fringe_frequency(col);
        if let Some(col) = [0.0, half, f64::from(c.width)]
            .into_iter()
            .find(|&col| !(f_at(col) > 0.0 && f_at(col) < 0.5))
        {
            x.check(false, "fringe_frequency_poly", || {
                format!(
                    "f_x = {} cycles/row at column {col}, expected 0 < f_x < 0.5 (a fringe above the Nyquist frequency cannot be measured)",
                    f_at(col)
                )
            })?;
        }
        let f_mean = (0..w).map(|col| f_at(col as f64)).sum::<f64>() / w as f64;
        x.check(
            close(c.fringe_period_px * f_mean, 1.0, 0.0, 1e-6),
            "fringe_period_px",
            || {
                format!(
                    "{} px, but the field mean of fringe_frequency_poly is {f_mean} cycles/row, a period of {} px: the core's single period must be 1 / mean f_x(c)",
                    c.fringe_period_px,
                    1.0 / f_mean
                )
            },
        )?;

        // The field-variation budget flag.
        let e = c.fx_height_error_um;
        x.check(e.is_nan() || e >= 0.0, "fx_height_error_um", || {
            format!("{e} um, expected a value >= 0")
        })?;
        let over = e.is_nan() || e > self.fx_budget_um;
        x.check(c.fx_over_budget == over, "fx_over_budget", || {
            format!(
                "{}, but fx_height_error_um {e} um is {} the file's fx_budget_um {} um",
                c.fx_over_budget,
                if over { "over" } else { "within" },
                self.fx_budget_um
            )
        })?;

        // Per-pixel data.
        for (name, m) in [
            ("background_map", &c.background_map),
            ("modulation_map", &c.modulation_map),
        ] {
            x.check(
                m.is_empty() || (m.len() == c.rows as usize && m.iter().all(|row| row.len() == w)),
                name,
                || format!("must be {} rows of {w} values", c.rows),
            )?;
        }
        if let Some(&[r, col]) = c
            .dead_pixels
            .iter()
            .find(|&&[r, col]| r >= c.rows || col >= c.width)
        {
            x.check(false, "dead_pixels", || {
                format!(
                    "[{r}, {col}] lies outside the {} x {} frame",
                    c.rows, c.width
                )
            })?;
        }
        Ok(())
    }
}
