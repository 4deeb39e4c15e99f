//! The calibration file (`dpsa calibrate --out CAL`): TOML, versioned, documented in
//! `docs/calibration.md`. It is everything a camera's frame grabber is configured with: per
//! camera the blocks of the core's configuration ([`CalFile::core_blocks`]: the same camera,
//! calibration and processing blocks a recording's manifest has, so one function makes the
//! core's `Config` of either), and what the host needs to place and mask its rows (lateral
//! mapping, dead pixels, the per-column height per turn).

pub mod validate;

use crate::array::{ArrayManifest, DesignCamera};
use crate::recording::{Calibration, Camera, Processing};
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};
use std::path::Path;

pub use validate::CalInvalid;

/// Format tag of a calibration file.
pub const CAL_FORMAT: &str = crate::kind::markers::CALIBRATION_FORMAT;
/// Version this build reads and writes: 2 added `[processing]` and each camera's
/// `bit_depth` and `saturation` (the frame grabber's whole configuration).
pub const CAL_VERSION: u32 = 2;

/// A calibration file that cannot be read, or does not fit what it is used with.
#[derive(Debug, thiserror::Error)]
pub enum CalError {
    /// The file could not be read (the sentence names it).
    #[error(transparent)]
    Read(#[from] crate::files::FileError),
    /// Not TOML of a calibration file's keys and types.
    #[error("not a valid calibration file: {0}")]
    Toml(String),
    /// Another format or version.
    #[error("format {found:?} version {version}, this build reads {CAL_FORMAT:?} version {CAL_VERSION}{hint}")]
    Version {
        /// The file's `format`.
        found: String,
        /// The file's `version`.
        version: u32,
        /// What to do about it (a version 1 file: calibrate again).
        hint: &'static str,
    },
    /// A field out of range or inconsistent with the rest of the file.
    #[error(transparent)]
    Invalid(#[from] CalInvalid),
    /// The calibration does not fit the array, recording or stream it is used with (one
    /// sentence saying how).
    #[error("{0}")]
    Mismatch(String),
    /// The file could not be written as TOML.
    #[error("cannot write the calibration as TOML: {0}")]
    Write(String),
}

/// Rounds `cpp` to the nearest multiple of 2^-16 (counts per pixel): the core's Q16.16
/// encoder step.
pub fn round_counts_per_pixel(cpp: f64) -> f64 {
    (cpp * 65536.0).round() / 65536.0
}

/// Wraps a phase into `[-pi, pi)`, rad: the one phase wrap of the host (the core's
/// reference-phase tables, the calibration, the f64 reference). Non-finite input gives NaN.
pub fn wrap_phase(x: f64) -> f64 {
    let w = (x + PI).rem_euclid(TAU) - PI;
    if w >= PI {
        -PI
    } else {
        w
    }
}

/// Lateral mapping of one camera: image pixel `(r, c)` at conveyor travel `s` (mm, encoder
/// count / `counts_per_mm`) sees board point
/// `X = s + x0 + p (r cos a - c sin a)`, `Y = y0 + p (r sin a + c cos a)`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Lateral {
    /// Along-motion position of pixel (0, 0) at travel 0, mm.
    pub x0_mm: f64,
    /// Across position of pixel (0, 0), mm.
    pub y0_mm: f64,
    /// Pixel pitch on the board, mm.
    pub pitch_mm: f64,
    /// Rotation `a` of the image rows against the motion, rad.
    pub rotation_rad: f64,
    /// Along-motion length of one board row of the core's registration, `cpp / counts_per_mm`, mm.
    pub row_pitch_mm: f64,
    /// Residual of the mark fit, um rms.
    pub fit_rms_um: f64,
    /// Marks used.
    pub marks: u32,
}

/// Calibration of one camera.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraCal {
    /// The camera's place in the array (the `[[camera]]` block's index).
    pub id: u8,
    /// Frame columns `W`.
    pub width: u32,
    /// Frame rows `H`.
    pub rows: u32,
    /// Significant bits per sample (8..=16), as the camera delivers them.
    pub bit_depth: u8,
    /// A sample `>= saturation` (DN) is saturated: the core flags its window.
    pub saturation: u16,
    /// Encoder counts per board row (per image row of travel), a multiple of 2^-16: the core's
    /// `counts_per_pixel`.
    pub counts_per_pixel: f64,
    /// This camera's estimate of the encoder scale, counts/mm.
    pub counts_per_mm: f64,
    /// The core's single fringe period (its motion shifts use `1 / fringe_period_px`), px:
    /// the field mean of `f_x(c)`.
    pub fringe_period_px: f64,
    /// `f_x(c) = f0 + f1 u + f2 u^2` cycles/row, `u = (c - W/2) / (W/2)`.
    pub fringe_frequency_poly: [f64; 3],
    /// Worst height error the field variation of `f_x` causes with the core's single value, um.
    pub fx_height_error_um: f64,
    /// `true` when `fx_height_error_um` exceeds the file's `fx_budget_um`.
    pub fx_over_budget: bool,
    /// Height per fringe turn `T_z(c)` per column, um.
    pub height_per_turn_um: Vec<f64>,
    /// Physical reference phase `phi_0(c)` at image row 0 for height 0, rad.
    pub reference_phase_rad: Vec<f64>,
    /// The reference-phase table for the core (its single `f_x` and registration), rad.
    pub core_reference_phase_rad: Vec<f64>,
    /// Flat field: fringe background per column (mean over rows), DN.
    pub background_dn: Vec<f64>,
    /// Fringe modulation per column (mean over rows), DN.
    pub modulation_dn: Vec<f64>,
    /// Image pixels `[row, column]` that are dead or whose modulation is below half their
    /// column's: the board stage masks every board pixel they feed.
    pub dead_pixels: Vec<[u32; 2]>,
    /// Per-pixel flat field: every image pixel's fringe background against its column's
    /// (`background_dn`), in units of 1/10000 (`10000` = the column's level), `rows` rows of
    /// `width` values. Absent in files written before it (version 1 files stay readable).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub background_map: Vec<Vec<u16>>,
    /// Per-pixel modulation against the column's (`modulation_dn`), the same units and shape.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub modulation_map: Vec<Vec<u16>>,
    /// Where its pixels lie on the board.
    pub lateral: Lateral,
}

/// How far a calibrated camera position may lie from its design position, mm. `dpsa
/// calibrate` identifies the target's marks from the design position (within 0.3 of the
/// 1 mm target pitch), the simulator mounts cameras within 0.2 mm of their design, and the
/// shipped arrays' cameras are 4.3 mm (small) and 55 mm (paper) apart.
pub const DESIGN_TOLERANCE_MM: f64 = 1.0;
/// How far a calibrated pitch may lie from `array.json`'s nominal `pixel_mm` (relative): the
/// simulator's magnification errors are within 0.5 %.
pub const PITCH_TOLERANCE: f64 = 0.1;

/// Units of the flat-field maps: `MAP_ONE` is the column's own level.
pub const MAP_ONE: f64 = 10000.0;

/// A per-pixel map relative to its column's level (see [`CameraCal::background_map`]):
/// `value / column * MAP_ONE`, rounded and clamped to `u16`.
pub fn relative_map(values: &[f64], column: &[f64], rows: usize) -> Vec<Vec<u16>> {
    let w = column.len();
    (0..rows)
        .map(|r| {
            (0..w)
                .map(|c| {
                    let v = values.get(r * w + c).copied().unwrap_or(f64::NAN);
                    let rel = v / column[c] * MAP_ONE;
                    if rel.is_finite() {
                        rel.round().clamp(0.0, f64::from(u16::MAX)) as u16
                    } else {
                        0
                    }
                })
                .collect()
        })
        .collect()
}

/// A calibration file.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CalFile {
    /// [`CAL_FORMAT`].
    pub format: String,
    /// [`CAL_VERSION`].
    pub version: u32,
    /// Encoder scale (mean of the cameras' estimates), counts/mm.
    pub counts_per_mm: f64,
    /// Height LSB of the core's i16 output, um.
    pub height_lsb_um: f64,
    /// Budget of `fx_height_error_um`, um.
    pub fx_budget_um: f64,
    /// The core's processing settings on every camera (observations per row, largest encoder
    /// step, modulation floor, noise-gain ceiling): part of the configuration each stream's
    /// configuration hash is checked against.
    pub processing: Processing,
    /// The cameras, camera `i` at index `i`.
    pub camera: Vec<CameraCal>,
}

impl CameraCal {
    /// `f_x(c)`, cycles/row.
    pub fn fringe_frequency(&self, c: f64) -> f64 {
        let half = f64::from(self.width) / 2.0;
        let u = (c - half) / half;
        let [a, b, d] = self.fringe_frequency_poly;
        a + b * u + d * u * u
    }

    /// The core's nominal (uniform) height per turn, the field mean, um: its
    /// `lsb_per_turn`, around which the per-column table ([`CameraCal::core_calibration`]) lies.
    pub fn core_height_per_turn_um(&self) -> f64 {
        self.height_per_turn_um.iter().sum::<f64>() / self.height_per_turn_um.len().max(1) as f64
    }

    /// Board point `(X, Y)` (mm) of image pixel `(r, c)` at conveyor travel `s` mm.
    pub fn board_point(&self, s: f64, r: f64, c: f64) -> (f64, f64) {
        let l = &self.lateral;
        let (sn, cs) = l.rotation_rad.sin_cos();
        (
            s + l.x0_mm + l.pitch_mm * (r * cs - c * sn),
            l.y0_mm + l.pitch_mm * (r * sn + c * cs),
        )
    }

    /// The calibration block of the core's configuration: the encoder step rounded to the
    /// core's Q16.16, the core's single fringe period and reference-phase table (wrapped), its
    /// nominal height per turn and the per-column `T_z(c)` (the core emits every column in
    /// calibrated LSB of `height_lsb_um`).
    pub fn core_calibration(&self, height_lsb_um: f64) -> Calibration {
        Calibration {
            counts_per_pixel: round_counts_per_pixel(self.counts_per_pixel),
            fringe_period_px: self.fringe_period_px,
            reference_phase_rad: self
                .core_reference_phase_rad
                .iter()
                .map(|&p| wrap_phase(p))
                .collect(),
            height_per_turn_um: self.core_height_per_turn_um(),
            height_lsb_um,
            height_per_turn_um_per_column: Some(self.height_per_turn_um.clone()),
        }
    }

    /// The camera block of the core's configuration.
    pub fn core_camera(&self) -> Camera {
        Camera {
            id: self.id,
            width: self.width,
            rows: self.rows,
            bit_depth: self.bit_depth,
            saturation: self.saturation,
        }
    }
}

impl CalFile {
    /// The file's text.
    pub fn to_toml(&self) -> Result<String, CalError> {
        toml::to_string(self).map_err(|e| CalError::Write(e.to_string()))
    }

    /// Parses and checks a calibration file's text ([`CalFile::validate`]).
    pub fn from_toml(text: &str) -> Result<CalFile, CalError> {
        // Format and version first, so that an older file is named as such rather than by
        // the first key it lacks.
        #[derive(Deserialize)]
        struct Tag {
            format: Option<String>,
            version: Option<u32>,
        }
        if let Ok(Tag {
            format: Some(format),
            version: Some(version),
        }) = toml::from_str::<Tag>(text)
        {
            if format != CAL_FORMAT || version != CAL_VERSION {
                let hint = if format == CAL_FORMAT && version == 1 {
                    " (version 1 files lack the frame grabber's processing and sample range: run `dpsa calibrate` again)"
                } else {
                    ""
                };
                return Err(CalError::Version {
                    found: format,
                    version,
                    hint,
                });
            }
        }
        let cal: CalFile = toml::from_str(text).map_err(|e| CalError::Toml(e.to_string()))?;
        if cal.format != CAL_FORMAT || cal.version != CAL_VERSION {
            return Err(CalError::Version {
                found: cal.format,
                version: cal.version,
                hint: "",
            });
        }
        cal.validate()?;
        Ok(cal)
    }

    /// Reads a calibration file; errors name it.
    pub fn load(path: &Path) -> Result<CalFile, CalError> {
        let bytes = crate::files::read_capped(path, 1 << 28, "calibration file")?;
        CalFile::from_toml(&String::from_utf8_lossy(&bytes)).map_err(|e| match e {
            CalError::Read(e) => CalError::Read(e),
            e => CalError::Mismatch(format!("calibration file {}: {e}", path.display())),
        })
    }

    /// Camera `i`'s blocks of the core's configuration (camera, calibration, processing): the
    /// same blocks a recording's manifest holds, so the one function that makes the core's
    /// `Config` of a manifest makes it of the calibration file (`dpsa_stream::config`).
    /// `None` when the file has no camera `i`.
    pub fn core_blocks(&self, i: usize) -> Option<(Camera, Calibration, Processing)> {
        let c = self.camera.get(i)?;
        Some((
            c.core_camera(),
            c.core_calibration(self.height_lsb_um),
            self.processing.clone(),
        ))
    }

    /// Refuses a calibration whose cameras are not where the array's design puts them
    /// (`array.json`): camera `i`'s calibrated position of pixel (0, 0) must lie within
    /// [`DESIGN_TOLERANCE_MM`] of design camera `i`'s, and its pitch within [`PITCH_TOLERANCE`]
    /// of the nominal `pixel_mm`. A `[[camera]]` block swapped with another (ids renumbered or
    /// not) is caught here: the sentence names the design camera it does match.
    pub fn check_design(&self, arr: &ArrayManifest) -> Result<(), CalError> {
        for (i, (c, d)) in self.camera.iter().zip(&arr.cameras).enumerate() {
            let off = |d: &DesignCamera| {
                (c.lateral.x0_mm - d.x_mm)
                    .abs()
                    .max((c.lateral.y0_mm - d.y_mm).abs())
            };
            if off(d) > DESIGN_TOLERANCE_MM {
                let other = arr
                    .cameras
                    .iter()
                    .find(|o| off(o) <= DESIGN_TOLERANCE_MM)
                    .map_or_else(String::new, |o| {
                        format!(
                            "; it is where design camera {} is: the [[camera]] blocks of the calibration (or the camera directories) are swapped",
                            o.id
                        )
                    });
                return Err(CalError::Mismatch(format!(
                    "calibration camera {i} has pixel (0, 0) at x {:.3} mm, y {:.3} mm, but array.json puts camera {i} at x {:.3} mm, y {:.3} mm (more than {DESIGN_TOLERANCE_MM} mm off){other}",
                    c.lateral.x0_mm,
                    c.lateral.y0_mm,
                    d.x_mm,
                    d.y_mm
                )));
            }
            if !(arr.pixel_mm.is_finite()
                && (c.lateral.pitch_mm / arr.pixel_mm - 1.0).abs() <= PITCH_TOLERANCE)
            {
                return Err(CalError::Mismatch(format!(
                    "array.json says pixel_mm = {} mm, but camera {i}'s calibrated pitch is {} mm (more than {} % apart): the board map's grid would not be the cameras' pixels",
                    arr.pixel_mm,
                    c.lateral.pitch_mm,
                    PITCH_TOLERANCE * 100.0
                )));
            }
        }
        Ok(())
    }

    /// Refuses a calibration for another array (camera count, widths, rows).
    pub fn check_array(&self, cameras: &[(u32, u32)]) -> Result<(), CalError> {
        if self.camera.len() != cameras.len() {
            return Err(CalError::Mismatch(format!(
                "the calibration is for {} cameras, the recording has {}",
                self.camera.len(),
                cameras.len()
            )));
        }
        for (i, (c, &(w, r))) in self.camera.iter().zip(cameras).enumerate() {
            if (c.width, c.rows) != (w, r) {
                return Err(CalError::Mismatch(format!(
                    "camera {i}: the calibration is for {} x {} px frames, the recording has {} x {}",
                    c.rows,
                    c.width,
                    r,
                    w
                )));
            }
        }
        Ok(())
    }
}

/// `2 pi / T`: phase per um of height.
pub fn turn_rate(t: f64) -> f64 {
    TAU / t
}

#[cfg(test)]
mod tests {
    use super::wrap_phase;
    use std::f64::consts::{PI, TAU};

    #[test]
    fn wrap_phase_range_and_turns() {
        for x in [
            -10.0,
            -PI,
            -PI + 1e-9,
            0.0,
            PI - 1e-9,
            PI,
            3.0 * PI,
            100.0,
            -1e6,
        ] {
            let d = wrap_phase(x);
            assert!((-PI..PI).contains(&d), "{x} -> {d}");
            let k = (x - d) / TAU;
            assert!((k - k.round()).abs() < 1e-9, "{x} -> {d}: not whole turns");
        }
        assert_eq!(wrap_phase(PI), -PI);
        assert!(wrap_phase(f64::NAN).is_nan());
        assert!(wrap_phase(f64::INFINITY).is_nan());
        // In range it moves a phase by at most the rounding of `x + pi` and `- pi`.
        for x in [1e-12, -0.5, 2.0, PI - 1e-6, -PI] {
            assert!((wrap_phase(x) - x).abs() <= 2.0 * f64::EPSILON * PI, "{x}");
        }
    }
}
