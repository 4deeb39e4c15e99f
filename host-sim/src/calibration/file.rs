//! The calibration file (`dpsa calibrate --out CAL`): TOML, versioned, documented in
//! `docs/calibration.md`.

use crate::simulation::recording::Manifest;
use crate::simulation::scene::round_counts_per_pixel;
use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;
use std::path::Path;

/// Format tag of a calibration file.
pub const CAL_FORMAT: &str = dpsa_formats::kind::markers::CALIBRATION_FORMAT;
/// Version this build reads and writes.
pub const CAL_VERSION: u32 = 1;

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
    pub id: u8,
    pub width: u32,
    pub rows: u32,
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
    pub format: String,
    pub version: u32,
    /// Encoder scale (mean of the cameras' estimates), counts/mm.
    pub counts_per_mm: f64,
    /// Height LSB of the core's i16 output, um.
    pub height_lsb_um: f64,
    /// Budget of `fx_height_error_um`, um.
    pub fx_budget_um: f64,
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
    /// `lsb_per_turn`, around which the per-column table ([`CameraCal::apply`]) lies.
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

    /// Puts this calibration into a single-camera manifest (what `reconstruct` and the
    /// firmware take): encoder scale, the core's fringe period and reference-phase table, the
    /// core's nominal height per turn and the per-column `T_z(c)`
    /// (`height_per_turn_um_per_column`: the core emits every column in calibrated LSB).
    /// Refuses a manifest of another camera geometry.
    pub fn apply(&self, manifest: &mut Manifest, height_lsb_um: f64) -> Result<()> {
        if manifest.camera.id != self.id {
            bail!(
                "the recording is camera {}'s (its manifest says camera.id = {}), the calibration given is camera {}'s: a camera's frames measured with another camera's calibration give wrong heights and positions",
                manifest.camera.id,
                manifest.camera.id,
                self.id
            );
        }
        if (manifest.camera.width, manifest.camera.rows) != (self.width, self.rows) {
            bail!(
                "calibration of camera {} is for {} x {} px frames, the recording has {} x {}",
                self.id,
                self.rows,
                self.width,
                manifest.camera.rows,
                manifest.camera.width
            );
        }
        let c = &mut manifest.calibration;
        c.counts_per_pixel = round_counts_per_pixel(self.counts_per_pixel);
        c.fringe_period_px = self.fringe_period_px;
        c.reference_phase_rad = self
            .core_reference_phase_rad
            .iter()
            .map(|&p| crate::array::scene::wrap(p))
            .collect();
        c.height_per_turn_um = self.core_height_per_turn_um();
        c.height_per_turn_um_per_column = Some(self.height_per_turn_um.clone());
        c.height_lsb_um = height_lsb_um;
        Ok(())
    }
}

impl CalFile {
    pub fn to_toml(&self) -> Result<String> {
        Ok(toml::to_string(self)?)
    }

    /// Parses and checks a calibration file's text ([`CalFile::validate`]).
    pub fn from_toml(text: &str) -> Result<CalFile> {
        let cal: CalFile = toml::from_str(text).context("not a valid calibration file")?;
        if cal.format != CAL_FORMAT || cal.version != CAL_VERSION {
            bail!(
                "format {:?} version {}, this build reads {CAL_FORMAT:?} version {CAL_VERSION}",
                cal.format,
                cal.version
            );
        }
        cal.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(cal)
    }

    /// Reads a calibration file; errors name it.
    pub fn load(path: &Path) -> Result<CalFile> {
        let bytes = crate::files::read_capped(path, 1 << 28, "calibration file")?;
        CalFile::from_toml(&String::from_utf8_lossy(&bytes))
            .with_context(|| format!("calibration file {}", path.display()))
    }

    /// Refuses a calibration whose cameras are not where the array's design puts them
    /// (`array.json`): camera `i`'s calibrated position of pixel (0, 0) must lie within
    /// [`DESIGN_TOLERANCE_MM`] of design camera `i`'s, and its pitch within [`PITCH_TOLERANCE`]
    /// of the nominal `pixel_mm`. A `[[camera]]` block swapped with another (ids renumbered or
    /// not) is caught here: the sentence names the design camera it does match.
    pub fn check_design(&self, arr: &crate::array::record::ArrayManifest) -> Result<()> {
        for (i, (c, d)) in self.camera.iter().zip(&arr.cameras).enumerate() {
            let off = |d: &crate::array::record::DesignCamera| {
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
                bail!(
                    "calibration camera {i} has pixel (0, 0) at x {:.3} mm, y {:.3} mm, but array.json puts camera {i} at x {:.3} mm, y {:.3} mm (more than {DESIGN_TOLERANCE_MM} mm off){other}",
                    c.lateral.x0_mm,
                    c.lateral.y0_mm,
                    d.x_mm,
                    d.y_mm
                );
            }
            if !(arr.pixel_mm.is_finite()
                && (c.lateral.pitch_mm / arr.pixel_mm - 1.0).abs() <= PITCH_TOLERANCE)
            {
                bail!(
                    "array.json says pixel_mm = {} mm, but camera {i}'s calibrated pitch is {} mm (more than {} % apart): the board map's grid would not be the cameras' pixels",
                    arr.pixel_mm,
                    c.lateral.pitch_mm,
                    PITCH_TOLERANCE * 100.0
                );
            }
        }
        Ok(())
    }

    /// Refuses a calibration for another array (camera count, widths, rows).
    pub fn check_array(&self, cameras: &[(u32, u32)]) -> Result<()> {
        if self.camera.len() != cameras.len() {
            bail!(
                "the calibration is for {} cameras, the recording has {}",
                self.camera.len(),
                cameras.len()
            );
        }
        for (i, (c, &(w, r))) in self.camera.iter().zip(cameras).enumerate() {
            if (c.width, c.rows) != (w, r) {
                bail!(
                    "camera {i}: the calibration is for {} x {} px frames, the recording has {} x {}",
                    c.rows,
                    c.width,
                    r,
                    w
                );
            }
        }
        Ok(())
    }
}

/// `2 pi / T`: phase per um of height.
pub fn turn_rate(t: f64) -> f64 {
    TAU / t
}
