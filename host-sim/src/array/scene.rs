//! Array scenes: several projector/camera pairs over one board in millimetres (issue 10).
//!
//! A scene file is an array scene when it has a `[[cameras]]` table; every other key has a
//! default ([`ArrayScene::default`] is a three-camera array over a short board). Knobs, units
//! and the geometry are documented in `docs/calibration.md`.

use crate::array::frames::FrameFormat;
use crate::array::print::PrintParams;
use crate::inspection::pads::{Pad, Rigid};
use crate::simulation::recording::{Calibration, Camera, Noise, Processing};
use crate::simulation::scene::{round_counts_per_pixel, Stall};
use crate::{At, SimError};
use serde::{Deserialize, Serialize};
use std::f64::consts::TAU;
use std::path::{Path, PathBuf};

pub use dpsa_formats::array::MAX_CAMERAS;
/// Largest |row rotation| of a camera, degrees.
pub const MAX_ROTATION_DEG: f64 = 0.3;
/// Largest |pixel pitch error| of a camera, percent.
pub const MAX_PITCH_ERROR_PCT: f64 = 0.5;
/// Largest |height-per-turn variation| across a camera's columns, percent.
pub const MAX_TZ_VARIATION_PCT: f64 = 2.0;
/// Largest |fringe-period variation| across a camera's field, percent.
pub const MAX_FX_VARIATION_PCT: f64 = 0.2;
/// Largest |board warp|, um.
pub const MAX_WARP_UM: f64 = 1000.0;

/// One projector/camera pair: its optics and its mounting.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ArrayCamera {
    /// Columns `W`, px.
    pub width: u32,
    /// Design position across the board of column 0's centre, mm (an input of calibration).
    pub y_mm: f64,
    /// Design position along the motion of image row 0's centre, mm (cameras may be staggered).
    pub x_mm: f64,
    /// Mounting error `[along, across]`, mm: the true position is the design plus this.
    pub mount_error_mm: [f64; 2],
    /// Rotation of the image rows against the motion, degrees (|.| <= 0.3).
    pub rotation_deg: f64,
    /// Pixel pitch (magnification) error against the nominal `pixel_mm`, percent (|.| <= 0.5).
    pub pitch_error_pct: f64,
    /// Fringe period along image rows at the field centre, px.
    pub fringe_period_px: f64,
    /// Fringe-period variation across the field: `period(c) = P (1 + v u)`, `u = (c - W/2)/(W/2)`, percent (|.| <= 0.2).
    pub fringe_period_variation_pct: f64,
    /// Fringe tilt: `phi_0` grows by `2 pi * tilt` over `W` columns.
    pub fringe_tilt_cycles: f64,
    /// `phi_0` at column 0, rad.
    pub reference_phase_rad: f64,
    /// Height per fringe turn at the field centre, um.
    pub height_per_turn_um: f64,
    /// Height-per-turn variation across the columns: `T_z(c) = T (1 + v u)`, percent (|.| <= 2).
    pub height_per_turn_variation_pct: f64,
    /// Illumination drop at the field edges, percent.
    pub illumination_falloff_pct: f64,
    /// Dead image pixels (stuck dark), placed at random.
    pub dead_pixels: u32,
}

impl Default for ArrayCamera {
    fn default() -> Self {
        ArrayCamera {
            width: 160,
            y_mm: 0.0,
            x_mm: 0.0,
            mount_error_mm: [0.0, 0.0],
            rotation_deg: 0.0,
            pitch_error_pct: 0.0,
            fringe_period_px: 32.0,
            fringe_period_variation_pct: 0.0,
            fringe_tilt_cycles: 1.5,
            reference_phase_rad: 0.5,
            height_per_turn_um: 500.0,
            height_per_turn_variation_pct: 0.0,
            illumination_falloff_pct: 15.0,
            dead_pixels: 0,
        }
    }
}

/// What `dpsa simulate --calibration` records.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct CalibrationPlan {
    /// Heights of the flat matte plane, um (at least 3 different values).
    pub plane_heights_um: Vec<f64>,
    /// Height of the held-out plane (measured with the calibrated configuration), um.
    pub holdout_height_um: f64,
    /// Length of each plane carried through, mm.
    pub plane_length_mm: f64,
    /// Pitch of the lateral target's mark grid (both directions), mm.
    pub target_pitch_mm: f64,
    /// Length of the lateral target, mm (it spans the whole board width).
    pub target_length_mm: f64,
    /// Board coordinates of the target's first mark `[along, across]`, mm.
    pub target_origin_mm: [f64; 2],
    /// Gaussian radius (sigma) of a printed mark, mm.
    pub target_mark_sigma_mm: f64,
    /// Reflectance drop at a mark's centre (0..1).
    pub target_mark_depth: f64,
}

impl Default for CalibrationPlan {
    fn default() -> Self {
        CalibrationPlan {
            plane_heights_um: vec![0.0, 300.0, 600.0, 900.0],
            holdout_height_um: 450.0,
            plane_length_mm: 60.0,
            target_pitch_mm: 1.0,
            target_length_mm: 12.0,
            target_origin_mm: [1.0, 0.5],
            target_mark_sigma_mm: 0.07,
            target_mark_depth: 0.6,
        }
    }
}

/// Where the paste layer's design frame lands on the board (scene table `[placement]`): the
/// program's nominal [`Placement`](dpsa_inspect::program::Placement) ([`ScenePlacement::design`])
/// and the spread of the simulated board's placement error around it.
///
/// The nominal placement turns the design by `orientation_deg` and puts `design_origin_mm` at
/// the board corner (0, 0); the board then arrives with a small unknown error, drawn from the
/// seed: a rotation about the board centre and an offset (Gaussians truncated at 3 sigma).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ScenePlacement {
    /// The design point that lands at the board corner (0, 0), mm.
    pub design_origin_mm: [f64; 2],
    /// The board turned on the conveyor, counter-clockwise: 0, 90, 180 or 270 degrees.
    pub orientation_deg: f64,
    /// Placement offset, sigma per axis, mm (0..=1).
    pub offset_sigma_mm: f64,
    /// Placement rotation, sigma, degrees (0..=1).
    pub rotation_sigma_deg: f64,
    /// Draw the placement error from this seed instead of the run's: every run places the
    /// board the same way (the noise stays the run's), as `dpsa grr` repeats a placement.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

impl Default for ScenePlacement {
    fn default() -> Self {
        ScenePlacement {
            design_origin_mm: [0.0, 0.0],
            orientation_deg: 0.0,
            offset_sigma_mm: 0.1,
            rotation_sigma_deg: 0.1,
            seed: None,
        }
    }
}

impl ScenePlacement {
    /// The nominal placement, as the board's inspection program states it.
    pub fn design(&self) -> dpsa_inspect::program::Placement {
        dpsa_inspect::program::Placement {
            design_origin_mm: self.design_origin_mm,
            orientation_deg: self.orientation_deg,
        }
    }

    /// The nominal design-to-board transform (no placement error): the program's.
    pub fn nominal(&self) -> Rigid {
        self.design().nominal()
    }

    /// The design-to-board transform of a board of `length x width` mm: the nominal one
    /// followed by the placement error drawn from `seed`.
    pub fn design_to_board(&self, length_mm: f64, width_mm: f64, seed: u64) -> Rigid {
        let mut rng = crate::simulation::simulate::rng(self.seed.unwrap_or(seed), 0x706c_6163);
        let n3 = crate::array::print::normal3;
        let (dx, dy) = (
            self.offset_sigma_mm * n3(&mut rng),
            self.offset_sigma_mm * n3(&mut rng),
        );
        let rot = (self.rotation_sigma_deg * n3(&mut rng)).to_radians();
        let c = [length_mm / 2.0, width_mm / 2.0];
        let turn = Rigid {
            rotation_rad: rot,
            tx: 0.0,
            ty: 0.0,
        };
        let rc = turn.apply(c);
        let error = Rigid {
            rotation_rad: rot,
            tx: c[0] - rc[0] + dx,
            ty: c[1] - rc[1] + dy,
        };
        error.after(&self.nominal())
    }
}

/// Reads the pads of a paste layer (Gerber RS-274X / X2; design frame, mm) with the
/// inspection's own reader: the one place scenes get their pads from.
pub fn load_paste_layer(path: &Path) -> crate::Result<Vec<Pad>> {
    let layer = crate::inspection::gerber::read_file(path)
        .at(|| format!("paste layer {}", path.display()))?;
    if layer.pads.is_empty() {
        return Err(SimError::Refused(format!(
            "paste layer {}: no pads",
            path.display()
        )));
    }
    Ok(layer.pads)
}

/// An array scene (see the module docs).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ArrayScene {
    /// Board length along the motion, mm.
    pub board_length_mm: f64,
    /// Board width across the motion, mm.
    pub board_width_mm: f64,
    /// Board bow: height at the board centre relative to its edges, um (|.| <= 1000).
    pub warp_um: f64,
    /// Deposits placed at random.
    pub deposits: u32,
    /// Deposit footprints `[along, across]`, mm.
    pub deposit_sizes_mm: Vec<[f64; 2]>,
    /// Deposit height range, um.
    pub deposit_height_um: [f64; 2],
    /// Corner radius of a deposit, mm.
    pub deposit_corner_mm: f64,
    /// Width of the sloped deposit wall, mm.
    pub deposit_edge_mm: f64,
    /// Board background `B`, DN.
    pub background: f64,
    /// Board fringe contrast `C`, DN.
    pub contrast: f64,
    /// Paste background `B`, DN.
    pub paste_background: f64,
    /// Paste fringe contrast `C`, DN.
    pub paste_contrast: f64,
    /// Encoder counts per mm of conveyor travel (true value; calibration measures it).
    pub counts_per_mm: f64,
    /// Encoder scale the operator types before calibration, counts/mm.
    pub nominal_counts_per_mm: f64,
    /// Mean conveyor step between frames, nominal pixels.
    pub mean_step_px: f64,
    /// Step jitter, percent.
    pub jitter_pct: f64,
    /// Conveyor stops.
    pub stalls: Vec<Stall>,
    /// Nominal pixel pitch on the board, mm.
    pub pixel_mm: f64,
    /// ROI rows per frame `H` (all cameras).
    pub rows: u32,
    /// Observations per board row.
    pub n: u8,
    /// Camera bit depth (8..=16), all cameras.
    pub bit_depth: u8,
    /// Conversion gain, electrons per DN (shot noise).
    pub gain_e_per_dn: f64,
    /// Read noise, DN rms.
    pub read_noise_dn: f64,
    /// Height LSB of the core's i16 output, um.
    pub height_lsb_um: f64,
    /// Minimum fringe modulation of a valid pixel, DN.
    pub min_modulation: f64,
    /// Largest window noise gain accepted (1..=8).
    pub max_noise_gain: f64,
    /// Optical blur (Gaussian sigma), px; pixels also integrate over their area.
    pub blur_px: f64,
    /// Frame files: `zfr` (compressed binary) or `png`.
    pub frame_format: FrameFormat,
    /// Write each camera's truth files (board rows x W, 12 bytes per pixel).
    pub camera_truth: bool,
    /// Pitch of the board truth raster, mm.
    pub truth_pitch_mm: f64,
    /// The projector/camera pairs (`[[cameras]]`), 1..=`MAX_CAMERAS`.
    pub cameras: Vec<ArrayCamera>,
    /// What a calibration recording holds (`[calibration]`).
    pub calibration: CalibrationPlan,
    /// The machine's own seed: its cameras' dead pixels (a run's `--seed` draws the noise,
    /// the conveyor and the placement).
    pub seed: u64,
    /// Paste layer (Gerber) printed on the board, relative to the scene file; with it,
    /// `deposits` must be 0.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub paste_layer: Option<String>,
    /// Fiducial centres `[x, y]`, design frame, mm: copper discs (with a paste layer only).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub fiducials: Vec<[f64; 2]>,
    /// Fiducial diameter, mm (0.2..=5).
    pub fiducial_diameter_mm: f64,
    /// The print (stencil, slump, wall, dog-ears, offsets, scatter, defects).
    pub print: PrintParams,
    /// Where the design lands on the board, and its random placement error.
    pub placement: ScenePlacement,
    /// The machine's scatter of a measured point as `dpsa grr`'s pixel study finds it on this
    /// machine (`pixels` in its JSON), written into the board's inspection program
    /// (`measure.lateral_sigma_um`, `.row_sigma_um`, `.row_correlation`) so that each pad's
    /// stated uncertainty is this machine's; absent: the program's defaults (the small
    /// array's figures).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scatter: Option<MachineScatter>,
    /// The paste's reflectance as this machine takes it out of the deposits' walls, written
    /// into the board's inspection program (`[reflectance] background_step`): the paste's
    /// background above the board's over the board's fringe contrast, as the machine's builder
    /// measured it (`crate::array::render::paste_background_step` is what the scene's
    /// rendering gives; the shipped scenes' tests hold the two within 1 %). The pads' stated
    /// uncertainty ([`Self::scatter`]) is then the corrected maps'. Absent: the programs leave
    /// the reflectance in.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reflectance: Option<MachineReflectance>,
    /// Directory of the scene file (`paste_layer` is relative to it); set by [`Self::load`].
    #[serde(skip)]
    pub scene_dir: Option<PathBuf>,
}

impl Default for ArrayScene {
    fn default() -> Self {
        let cams = [
            (0.0, 0.1, -0.2, 0.2),
            (4.3, -0.15, 0.25, -0.2),
            (8.6, 0.05, 0.1, 0.15),
        ];
        ArrayScene {
            board_length_mm: 20.0,
            board_width_mm: 13.9,
            warp_um: 300.0,
            deposits: 10,
            deposit_sizes_mm: vec![[0.8, 0.5], [0.5, 0.8]],
            deposit_height_um: [60.0, 150.0],
            deposit_corner_mm: 0.08,
            deposit_edge_mm: 0.06,
            background: 1800.0,
            contrast: 700.0,
            paste_background: 2200.0,
            paste_contrast: 900.0,
            counts_per_mm: 402.0,
            nominal_counts_per_mm: 400.0,
            mean_step_px: 8.0,
            jitter_pct: 5.0,
            stalls: Vec::new(),
            pixel_mm: 0.0277,
            rows: 40,
            n: 4,
            bit_depth: 12,
            gain_e_per_dn: 3.0,
            read_noise_dn: 3.0,
            height_lsb_um: 0.25,
            min_modulation: 60.0,
            max_noise_gain: 2.0,
            blur_px: 0.4,
            frame_format: FrameFormat::Zfr,
            camera_truth: true,
            truth_pitch_mm: 0.05,
            cameras: cams
                .iter()
                .enumerate()
                .map(|(i, &(y, rot, pitch, var))| ArrayCamera {
                    width: 192,
                    y_mm: y,
                    mount_error_mm: [0.02 * i as f64, -0.03 + 0.02 * i as f64],
                    rotation_deg: rot,
                    pitch_error_pct: pitch,
                    fringe_period_variation_pct: var,
                    height_per_turn_variation_pct: 1.5 - 1.2 * i as f64,
                    reference_phase_rad: 0.5 + i as f64,
                    dead_pixels: 3,
                    ..ArrayCamera::default()
                })
                .collect(),
            calibration: CalibrationPlan::default(),
            seed: 10,
            paste_layer: None,
            fiducials: Vec::new(),
            fiducial_diameter_mm: 1.0,
            print: PrintParams::default(),
            placement: ScenePlacement::default(),
            scatter: None,
            reflectance: None,
            scene_dir: None,
        }
    }
}

/// A scene knob out of range, or an unreadable scene.
#[derive(Debug, thiserror::Error)]
pub enum ArraySceneError {
    /// The scene file could not be read, or its TOML does not parse (unknown key, wrong type).
    #[error("{path}: {message}")]
    Parse {
        /// The scene file (`scene` for text not read from a file).
        path: String,
        /// The reader's or parser's error.
        message: String,
    },
    /// A knob out of its range.
    #[error("{path}: invalid `{knob}`: {message}")]
    Invalid {
        /// The scene file (empty for text not read from a file).
        path: String,
        /// The knob's name, e.g. `cameras[0].rotation_deg`.
        knob: String,
        /// The value found and the range expected.
        message: String,
    },
}

/// The true geometry and optics of one camera, derived from the scene (the simulator renders
/// with these; calibration estimates them; `truth.json` records them).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraModel {
    /// Camera index in the array.
    pub id: u8,
    /// Columns `W`, px.
    pub width: u32,
    /// ROI rows per frame `H`, px.
    pub rows: u32,
    /// True position along the motion of image row 0, column 0 (conveyor frame), mm.
    pub x0_mm: f64,
    /// True position across the board of image row 0, column 0, mm.
    pub y0_mm: f64,
    /// True pixel pitch, mm.
    pub pitch_mm: f64,
    /// True rotation of the image rows, rad.
    pub rotation_rad: f64,
    /// Encoder counts per image row of travel, `pitch * counts_per_mm / cos(rotation)`.
    pub counts_per_pixel: f64,
    /// `f_x(c)`, cycles per image row.
    pub fringe_frequency: Vec<f64>,
    /// `phi_0(c)` at image row 0, rad (not wrapped).
    pub reference_phase_rad: Vec<f64>,
    /// `T_z(c)`, um.
    pub height_per_turn_um: Vec<f64>,
    /// Illumination factor per column.
    pub illumination: Vec<f64>,
    /// Dead image pixels `[row, column]`.
    pub dead_pixels: Vec<[u32; 2]>,
}

impl CameraModel {
    /// Board point `(X, Y)` (mm) seen by image pixel `(r, c)` (continuous, px) at conveyor
    /// travel `s` (mm): `X = s + x0 + p (r cos a - c sin a)`, `Y = y0 + p (r sin a + c cos a)`.
    pub fn board_point(&self, s: f64, r: f64, c: f64) -> (f64, f64) {
        let (sn, cs) = self.rotation_rad.sin_cos();
        let p = self.pitch_mm;
        (
            s + self.x0_mm + p * (r * cs - c * sn),
            self.y0_mm + p * (r * sn + c * cs),
        )
    }

    /// Field coordinate `u = (c - W/2) / (W/2)` of column `c`.
    pub fn u(&self, c: f64) -> f64 {
        let half = f64::from(self.width) / 2.0;
        (c - half) / half
    }
}

fn check(ok: bool, knob: &str, message: impl FnOnce() -> String) -> Result<(), ArraySceneError> {
    if ok {
        Ok(())
    } else {
        Err(ArraySceneError::Invalid {
            path: String::new(),
            knob: knob.into(),
            message: message(),
        })
    }
}

fn finite_in(v: f64, lo: f64, hi: f64, knob: &str) -> Result<(), ArraySceneError> {
    check(v.is_finite() && (lo..=hi).contains(&v), knob, || {
        format!("{v}, expected a finite value in {lo}..={hi}")
    })
}

/// A machine's scatter of a measured point (`[scatter]`, see [`ArrayScene::scatter`]).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MachineScatter {
    /// A pixel's scatter along the slope it lies on, um (0..=100).
    pub lateral_sigma_um: f64,
    /// A row's scatter along the motion over a pad cell's width of one camera's pixels, um
    /// (0..=100).
    pub row_sigma_um: f64,
    /// The correlation of neighbouring rows' shifts (0..=1).
    pub row_correlation: f64,
}

/// The paste's reflectance a machine takes out of the walls (`[reflectance]`, see
/// [`ArrayScene::reflectance`]).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MachineReflectance {
    /// The paste's background step over the board's fringe contrast (-10..=10).
    pub background_step: f64,
}

/// `true` if the TOML text describes an array (it has a `cameras` table array).
pub fn is_array_scene(text: &str) -> bool {
    toml::from_str::<toml::Table>(text).is_ok_and(|t| t.contains_key("cameras"))
}

impl ArrayScene {
    /// Parses and validates an array scene.
    pub fn from_toml_str(text: &str) -> Result<ArrayScene, ArraySceneError> {
        let s: ArrayScene = toml::from_str(text).map_err(|e| ArraySceneError::Parse {
            path: "scene".into(),
            message: e.to_string(),
        })?;
        s.validate()?;
        Ok(s)
    }

    /// Reads an array scene file; errors name it.
    pub fn load(path: &Path) -> Result<ArrayScene, ArraySceneError> {
        let name = path.display().to_string();
        let bytes =
            crate::files::read_capped_io(path, crate::files::MAX_SCENE_BYTES).map_err(|e| {
                ArraySceneError::Parse {
                    path: name.clone(),
                    message: crate::files::io_cause(&e),
                }
            })?;
        let text = String::from_utf8_lossy(&bytes);
        let mut scene = ArrayScene::from_toml_str(&text).map_err(|e| match e {
            ArraySceneError::Parse { message, .. } => ArraySceneError::Parse {
                path: name,
                message,
            },
            ArraySceneError::Invalid { knob, message, .. } => ArraySceneError::Invalid {
                path: name,
                knob,
                message,
            },
        })?;
        scene.scene_dir = Some(
            path.parent()
                .map_or_else(|| PathBuf::from("."), Path::to_path_buf),
        );
        Ok(scene)
    }

    /// The paste layer's path (relative to the scene file's directory, or to the current
    /// directory for a scene not read from a file).
    pub fn paste_layer_path(&self) -> Option<PathBuf> {
        let name = self.paste_layer.as_ref()?;
        Some(match &self.scene_dir {
            Some(dir) => dir.join(name),
            None => PathBuf::from(name),
        })
    }

    /// The print parameters of this scene (the fiducial diameter is the scene's).
    pub fn print_params(&self) -> PrintParams {
        PrintParams {
            fiducial_diameter_mm: self.fiducial_diameter_mm,
            ..self.print.clone()
        }
    }

    /// Checks every knob's range.
    pub fn validate(&self) -> Result<(), ArraySceneError> {
        check(
            (1..=MAX_CAMERAS).contains(&self.cameras.len()),
            "cameras",
            || format!("{} cameras, expected 1..={MAX_CAMERAS}", self.cameras.len()),
        )?;
        finite_in(self.board_length_mm, 1.0, 2000.0, "board_length_mm")?;
        finite_in(self.board_width_mm, 1.0, 2000.0, "board_width_mm")?;
        finite_in(self.warp_um, -MAX_WARP_UM, MAX_WARP_UM, "warp_um")?;
        check(self.deposits <= 100_000, "deposits", || {
            "at most 100000".into()
        })?;
        check(
            self.deposits == 0 || !self.deposit_sizes_mm.is_empty(),
            "deposit_sizes_mm",
            || "empty, but deposits > 0".into(),
        )?;
        for &[a, b] in &self.deposit_sizes_mm {
            finite_in(a, 0.01, 100.0, "deposit_sizes_mm")?;
            finite_in(b, 0.01, 100.0, "deposit_sizes_mm")?;
        }
        let [lo, hi] = self.deposit_height_um;
        check(
            lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo <= hi,
            "deposit_height_um",
            || format!("[{lo}, {hi}], expected 0 <= min <= max"),
        )?;
        finite_in(self.deposit_corner_mm, 0.0, 100.0, "deposit_corner_mm")?;
        finite_in(self.deposit_edge_mm, 0.0, 100.0, "deposit_edge_mm")?;
        for (v, k) in [
            (self.background, "background"),
            (self.contrast, "contrast"),
            (self.paste_background, "paste_background"),
            (self.paste_contrast, "paste_contrast"),
        ] {
            finite_in(v, 0.0, 1e6, k)?;
        }
        finite_in(self.counts_per_mm, 1e-3, 1e6, "counts_per_mm")?;
        finite_in(
            self.nominal_counts_per_mm,
            1e-3,
            1e6,
            "nominal_counts_per_mm",
        )?;
        check(
            (self.counts_per_mm / self.nominal_counts_per_mm - 1.0).abs() <= 0.01,
            "nominal_counts_per_mm",
            || "differs from counts_per_mm by more than 1 %".into(),
        )?;
        finite_in(self.mean_step_px, 0.5, 1000.0, "mean_step_px")?;
        finite_in(self.jitter_pct, 0.0, 99.0, "jitter_pct")?;
        if let Some(m) = &self.scatter {
            finite_in(m.lateral_sigma_um, 0.0, 100.0, "scatter.lateral_sigma_um")?;
            finite_in(m.row_sigma_um, 0.0, 100.0, "scatter.row_sigma_um")?;
            finite_in(m.row_correlation, 0.0, 1.0, "scatter.row_correlation")?;
        }
        if let Some(r) = &self.reflectance {
            finite_in(
                r.background_step,
                -10.0,
                10.0,
                "reflectance.background_step",
            )?;
        }
        finite_in(self.pixel_mm, 1e-4, 10.0, "pixel_mm")?;
        finite_in(self.blur_px, 0.0, 5.0, "blur_px")?;
        finite_in(self.truth_pitch_mm, 1e-3, 10.0, "truth_pitch_mm")?;
        let truth_px = (self.board_length_mm / self.truth_pitch_mm)
            * (self.board_width_mm / self.truth_pitch_mm);
        check(truth_px <= 1e8, "truth_pitch_mm", || {
            format!("the board truth raster would have {truth_px:.0} pixels, at most 1e8")
        })?;
        for (i, c) in self.cameras.iter().enumerate() {
            let k = |name: &str| format!("cameras[{i}].{name}");
            finite_in(
                c.rotation_deg,
                -MAX_ROTATION_DEG,
                MAX_ROTATION_DEG,
                &k("rotation_deg"),
            )?;
            finite_in(
                c.pitch_error_pct,
                -MAX_PITCH_ERROR_PCT,
                MAX_PITCH_ERROR_PCT,
                &k("pitch_error_pct"),
            )?;
            finite_in(
                c.height_per_turn_variation_pct,
                -MAX_TZ_VARIATION_PCT,
                MAX_TZ_VARIATION_PCT,
                &k("height_per_turn_variation_pct"),
            )?;
            finite_in(
                c.fringe_period_variation_pct,
                -MAX_FX_VARIATION_PCT,
                MAX_FX_VARIATION_PCT,
                &k("fringe_period_variation_pct"),
            )?;
            finite_in(c.fringe_period_px, 2.0, 1e4, &k("fringe_period_px"))?;
            finite_in(c.height_per_turn_um, 1.0, 1e6, &k("height_per_turn_um"))?;
            finite_in(
                c.illumination_falloff_pct,
                0.0,
                90.0,
                &k("illumination_falloff_pct"),
            )?;
            for (v, n) in [
                (c.y_mm, "y_mm"),
                (c.x_mm, "x_mm"),
                (c.mount_error_mm[0], "mount_error_mm"),
                (c.mount_error_mm[1], "mount_error_mm"),
                (c.fringe_tilt_cycles, "fringe_tilt_cycles"),
                (c.reference_phase_rad, "reference_phase_rad"),
            ] {
                finite_in(v, -1e4, 1e4, &k(n))?;
            }
            check(
                c.mount_error_mm.iter().all(|e| e.abs() <= 0.2),
                &k("mount_error_mm"),
                || {
                    "at most 0.2 mm either way (calibration identifies target marks from the design position)".into()
                },
            )?;
            check((1..=8192).contains(&c.width), &k("width"), || {
                format!("{} px, expected 1..=8192", c.width)
            })?;
            check(
                u64::from(c.dead_pixels) * 10 <= u64::from(c.width) * u64::from(self.rows),
                &k("dead_pixels"),
                || "at most 10 % of the image".into(),
            )?;
        }
        // Camera, calibration and processing blocks must be valid recordings.
        for i in 0..self.cameras.len() {
            crate::simulation::checks::check_blocks(
                &self.camera_block(i),
                &self.nominal_calibration(i),
                &self.processing(),
            )
            .map_err(|e| ArraySceneError::Invalid {
                path: String::new(),
                knob: format!("cameras[{i}] ({})", e.field),
                message: e.message,
            })?;
        }
        self.validate_print()?;
        let plan = &self.calibration;
        for &h in plan
            .plane_heights_um
            .iter()
            .chain([&plan.holdout_height_um])
        {
            finite_in(h, -1e4, 1e4, "calibration.plane_heights_um")?;
        }
        finite_in(
            plan.plane_length_mm,
            1.0,
            1000.0,
            "calibration.plane_length_mm",
        )?;
        finite_in(
            plan.target_pitch_mm,
            0.2,
            50.0,
            "calibration.target_pitch_mm",
        )?;
        finite_in(
            plan.target_length_mm,
            1.0,
            1000.0,
            "calibration.target_length_mm",
        )?;
        finite_in(
            plan.target_mark_sigma_mm,
            1e-3,
            5.0,
            "calibration.target_mark_sigma_mm",
        )?;
        finite_in(
            plan.target_mark_depth,
            0.05,
            1.0,
            "calibration.target_mark_depth",
        )?;
        Ok(())
    }

    /// The paste layer, fiducials, `[print]` and `[placement]`.
    fn validate_print(&self) -> Result<(), ArraySceneError> {
        if let Some(layer) = &self.paste_layer {
            check(!layer.trim().is_empty(), "paste_layer", || "empty".into())?;
            check(self.deposits == 0, "deposits", || {
                format!(
                    "{}, but a paste_layer is set: its pads are printed instead, set deposits = 0",
                    self.deposits
                )
            })?;
        } else {
            check(self.fiducials.is_empty(), "fiducials", || {
                "fiducials need a paste_layer (they are placed with it)".into()
            })?;
            check(self.print.defects.pads() == 0, "print.defects", || {
                "defects need a paste_layer to print".into()
            })?;
        }
        check(self.fiducials.len() <= 16, "fiducials", || {
            format!("{} fiducials, at most 16", self.fiducials.len())
        })?;
        for f in &self.fiducials {
            finite_in(f[0], -1e4, 1e4, "fiducials")?;
            finite_in(f[1], -1e4, 1e4, "fiducials")?;
        }
        finite_in(self.fiducial_diameter_mm, 0.2, 5.0, "fiducial_diameter_mm")?;
        check(
            self.print.fiducial_diameter_mm == PrintParams::default().fiducial_diameter_mm
                || self.print.fiducial_diameter_mm == self.fiducial_diameter_mm,
            "print.fiducial_diameter_mm",
            || "set the top-level fiducial_diameter_mm instead".into(),
        )?;
        self.print.validate().map_err(|e| match e {
            crate::array::print::PrintError::Param { knob, message } => ArraySceneError::Invalid {
                path: String::new(),
                knob: format!("print.{knob}"),
                message,
            },
            other => ArraySceneError::Invalid {
                path: String::new(),
                knob: "print".into(),
                message: other.to_string(),
            },
        })?;
        let p = &self.placement;
        finite_in(
            p.design_origin_mm[0],
            -1e4,
            1e4,
            "placement.design_origin_mm",
        )?;
        finite_in(
            p.design_origin_mm[1],
            -1e4,
            1e4,
            "placement.design_origin_mm",
        )?;
        check(
            [0.0, 90.0, 180.0, 270.0].contains(&p.orientation_deg),
            "placement.orientation_deg",
            || format!("{}, expected 0, 90, 180 or 270", p.orientation_deg),
        )?;
        finite_in(p.offset_sigma_mm, 0.0, 1.0, "placement.offset_sigma_mm")?;
        finite_in(
            p.rotation_sigma_deg,
            0.0,
            1.0,
            "placement.rotation_sigma_deg",
        )?;
        Ok(())
    }

    /// Largest admitted encoder step, rows.
    pub fn max_step_rows(&self) -> u32 {
        ((1.25 * self.mean_step_px).ceil() as u32).clamp(1, self.rows.max(1))
    }

    /// Camera block of camera `i`'s sub-recording.
    pub fn camera_block(&self, i: usize) -> Camera {
        Camera {
            id: i as u8,
            width: self.cameras[i].width,
            rows: self.rows,
            bit_depth: self.bit_depth,
            saturation: crate::simulation::recording::max_value(self.bit_depth),
        }
    }

    /// What an operator types before calibration: design pitch, nominal encoder scale, the
    /// design fringe period and height per turn, a flat zero reference phase.
    pub fn nominal_calibration(&self, i: usize) -> Calibration {
        let c = &self.cameras[i];
        Calibration {
            counts_per_pixel: round_counts_per_pixel(self.nominal_counts_per_mm * self.pixel_mm),
            fringe_period_px: c.fringe_period_px,
            reference_phase_rad: vec![0.0; c.width as usize],
            height_per_turn_um: c.height_per_turn_um,
            height_lsb_um: self.height_lsb_um,
            height_per_turn_um_per_column: None,
        }
    }

    /// Processing block of every sub-recording.
    pub fn processing(&self) -> Processing {
        Processing {
            n: self.n,
            max_step_rows: self.max_step_rows(),
            min_modulation: self.min_modulation,
            max_noise_gain: self.max_noise_gain,
        }
    }

    /// Noise block of every sub-recording.
    pub fn noise(&self) -> Noise {
        Noise {
            gain_e_per_dn: self.gain_e_per_dn,
            read_noise_dn: self.read_noise_dn,
        }
    }

    /// The true model of camera `i` (dead pixels drawn from `seed`).
    pub fn camera_model(&self, i: usize) -> CameraModel {
        use rand::RngExt;
        let c = &self.cameras[i];
        let w = c.width as usize;
        let half = f64::from(c.width) / 2.0;
        let u = |col: usize| (col as f64 - half) / half;
        let pitch = self.pixel_mm * (1.0 + c.pitch_error_pct / 100.0);
        let rot = c.rotation_deg.to_radians();
        // Dead pixels belong to the machine (the scene's own `seed`), not to the run: a
        // calibration recorded with one run seed lists the dead pixels of every board run.
        let mut rng = crate::simulation::simulate::rng(self.seed, 0x100 + i as u64);
        let mut dead: Vec<[u32; 2]> = Vec::new();
        while dead.len() < c.dead_pixels as usize {
            let p = [rng.random_range(0..self.rows), rng.random_range(0..c.width)];
            if !dead.contains(&p) {
                dead.push(p);
            }
        }
        dead.sort_unstable();
        CameraModel {
            id: i as u8,
            width: c.width,
            rows: self.rows,
            x0_mm: c.x_mm + c.mount_error_mm[0],
            y0_mm: c.y_mm + c.mount_error_mm[1],
            pitch_mm: pitch,
            rotation_rad: rot,
            counts_per_pixel: pitch * self.counts_per_mm / rot.cos(),
            fringe_frequency: (0..w)
                .map(|col| {
                    1.0 / (c.fringe_period_px
                        * (1.0 + c.fringe_period_variation_pct / 100.0 * u(col)))
                })
                .collect(),
            reference_phase_rad: (0..w)
                .map(|col| {
                    c.reference_phase_rad
                        + TAU * c.fringe_tilt_cycles * col as f64 / f64::from(c.width)
                })
                .collect(),
            height_per_turn_um: (0..w)
                .map(|col| {
                    c.height_per_turn_um * (1.0 + c.height_per_turn_variation_pct / 100.0 * u(col))
                })
                .collect(),
            illumination: (0..w)
                .map(|col| 1.0 - c.illumination_falloff_pct / 100.0 * u(col) * u(col))
                .collect(),
            dead_pixels: dead,
        }
    }

    /// Board warp at `(X, Y)`, um: `warp * (1 - xi^2) (1 - eta^2)` with `xi`, `eta` in -1..1
    /// across the board (0 at the edges, `warp_um` at the centre).
    pub fn warp(&self, x: f64, y: f64) -> f64 {
        let xi = (2.0 * x / self.board_length_mm - 1.0).clamp(-1.0, 1.0);
        let eta = (2.0 * y / self.board_width_mm - 1.0).clamp(-1.0, 1.0);
        self.warp_um * (1.0 - xi * xi) * (1.0 - eta * eta)
    }

    /// Nominal conveyor step, mm.
    pub fn step_mm(&self) -> f64 {
        self.mean_step_px * self.pixel_mm
    }

    /// Legal settings that make the result useless, one sentence each.
    pub fn warnings(&self) -> Vec<String> {
        let mut w = Vec::new();
        let mut spans: Vec<(f64, f64)> = self
            .cameras
            .iter()
            .map(|c| (c.y_mm, c.y_mm + f64::from(c.width) * self.pixel_mm))
            .collect();
        spans.sort_by(|a, b| a.0.total_cmp(&b.0));
        for p in spans.windows(2) {
            if p[1].0 > p[0].1 - 0.5 {
                w.push(format!(
                    "cameras at {:.2} mm and {:.2} mm overlap by less than 0.5 mm: the board map would have gaps",
                    p[0].0, p[1].0
                ));
            }
        }
        let per_step = 360.0 * self.mean_step_px / self.cameras[0].fringe_period_px;
        if !(20.0..=160.0).contains(&(per_step % 360.0)) {
            w.push(format!(
                "{per_step:.0} degrees of phase per frame step: windows may be ill-conditioned"
            ));
        }
        w
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_and_shipped_scenes_parse() {
        let d = ArrayScene::from_toml_str("[[cameras]]\n").unwrap();
        assert_eq!(d.cameras.len(), 1);
        for f in ["paper-board.toml", "array-small.toml", "array-paste.toml"] {
            let path = Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../scenes")
                .join(f);
            let s = ArrayScene::load(&path).unwrap();
            assert!(s.warnings().is_empty(), "{f}: {:?}", s.warnings());
        }
        let paper = ArrayScene::load(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/paper-board.toml"),
        )
        .unwrap();
        assert_eq!(paper.cameras.len(), 3);
        assert!(paper.cameras.iter().all(|c| c.width == 2048));
        assert_eq!(
            (paper.board_length_mm, paper.board_width_mm),
            (220.0, 168.0)
        );
        assert!(paper.warp_um.abs() >= 500.0);
        for p in paper.cameras.windows(2) {
            let overlap = p[0].y_mm + 2048.0 * paper.pixel_mm - p[1].y_mm;
            assert!(overlap >= 1.0, "{overlap}");
        }
        let last = paper.cameras.last().unwrap();
        assert!(last.y_mm + 2048.0 * paper.pixel_mm >= 168.0);
        // Each printed board's machine states its scatter and the paste's reflectance it takes
        // out, and both reach its boards' program; the stated step is the rendering's own.
        let small = ArrayScene::load(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-paste.toml"),
        )
        .unwrap();
        let turned = ArrayScene::load(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-paste-turned.toml"),
        )
        .unwrap();
        for (name, scene) in [("paper", &paper), ("small", &small), ("turned", &turned)] {
            let scatter = scene
                .scatter
                .expect("the scene states its machine's scatter");
            let step = scene
                .reflectance
                .expect("the scene states the paste's reflectance")
                .background_step;
            let program = crate::array::record::inspection_program(scene);
            let m = program.measure;
            assert_eq!(
                (m.lateral_sigma_um, m.row_sigma_um, m.row_correlation),
                (
                    scatter.lateral_sigma_um,
                    scatter.row_sigma_um,
                    scatter.row_correlation
                ),
                "{name}"
            );
            assert_eq!(program.reflectance.background_step, step, "{name}");
            let rendered = crate::array::render::paste_background_step(scene);
            assert!(
                (step / rendered - 1.0).abs() < 0.01,
                "{name}: {step} {rendered}"
            );
        }
        // Without them, the program's defaults and no reflectance taken out.
        let bare = ArrayScene::from_toml_str("[[cameras]]\n").unwrap();
        let program = crate::array::record::inspection_program(&bare);
        assert_eq!(program.measure, dpsa_inspect::program::Measure::default());
        assert_eq!(program.reflectance.background_step, 0.0);
    }

    #[test]
    fn bad_knobs_are_named() {
        for (text, knob) in [
            (
                "[[cameras]]\nrotation_deg = 0.5\n",
                "cameras[0].rotation_deg",
            ),
            (
                "[[cameras]]\npitch_error_pct = -0.6\n",
                "cameras[0].pitch_error_pct",
            ),
            (
                "[[cameras]]\nheight_per_turn_variation_pct = 3.0\n",
                "cameras[0].height_per_turn_variation_pct",
            ),
            (
                "[[cameras]]\nfringe_period_variation_pct = 0.3\n",
                "cameras[0].fringe_period_variation_pct",
            ),
            ("warp_um = 1500.0\n[[cameras]]\n", "warp_um"),
            (
                "paste_layer = \"x.gbr\"\ndeposits = 0\n[print]\nstencil_um = 1000.0\n[[cameras]]\n",
                "print.stencil_um",
            ),
            (
                "paste_layer = \"x.gbr\"\ndeposits = 0\n[placement]\norientation_deg = 45.0\n[[cameras]]\n",
                "placement.orientation_deg",
            ),
            ("paste_layer = \"x.gbr\"\ndeposits = 5\n[[cameras]]\n", "deposits"),
            ("fiducials = [[1.0, 1.0]]\n[[cameras]]\n", "fiducials"),
            (
                "[scatter]\nlateral_sigma_um = 1.0\nrow_sigma_um = 3.0\nrow_correlation = 1.5\n[[cameras]]\n",
                "scatter.row_correlation",
            ),
            ("[print.defects]\nmissing = 1\n[[cameras]]\n", "print.defects"),
            (
                "paste_layer = \"x.gbr\"\ndeposits = 0\nfiducial_diameter_mm = 0.0\n[[cameras]]\n",
                "fiducial_diameter_mm",
            ),
        ] {
            match ArrayScene::from_toml_str(text) {
                Err(ArraySceneError::Invalid { knob: k, .. }) => assert_eq!(k, knob, "{text}"),
                other => panic!("{text}: {other:?}"),
            }
        }
        let nine = "[[cameras]]\n".repeat(9);
        assert!(ArrayScene::from_toml_str(&nine).is_err());
        assert!(ArrayScene::from_toml_str("cameras = []\n").is_err());
        assert!(matches!(
            ArrayScene::from_toml_str("[[cameras]]\nwidht = 3\n"),
            Err(ArraySceneError::Parse { .. })
        ));
        assert!(is_array_scene("[[cameras]]\n") && !is_array_scene("width = 64\n"));
    }

    #[test]
    fn placement_puts_the_design_origin_at_the_board_corner() {
        for (deg, origin, corner) in [
            (0.0, [0.0, 0.0], [0.0, 0.0]),
            (90.0, [0.0, 20.0], [0.0, 20.0]),
            (180.0, [20.0, 13.9], [20.0, 13.9]),
            (270.0, [13.9, 0.0], [13.9, 0.0]),
        ] {
            let p = ScenePlacement {
                design_origin_mm: origin,
                orientation_deg: deg,
                offset_sigma_mm: 0.0,
                rotation_sigma_deg: 0.0,
                seed: None,
            };
            let t = p.nominal();
            let o = t.apply(corner);
            assert!(o[0].abs() < 1e-12 && o[1].abs() < 1e-12, "{deg}: {o:?}");
            assert_eq!(t, p.design_to_board(20.0, 13.9, 3));
        }
        // The placement error: small, from the seed, within 3 sigma.
        let p = ScenePlacement::default();
        let (a, b) = (
            p.design_to_board(220.0, 168.0, 1),
            p.design_to_board(220.0, 168.0, 2),
        );
        assert_ne!(a, b);
        assert_eq!(a, p.design_to_board(220.0, 168.0, 1));
        let c = a.apply([110.0, 84.0]);
        assert!((c[0] - 110.0).abs() <= 0.3 + 1e-9 && (c[1] - 84.0).abs() <= 0.3 + 1e-9);
        assert!(a.rotation_rad.abs() <= 0.3f64.to_radians() + 1e-12);
    }

    #[test]
    fn the_generated_layers_read_back_through_the_gerber_reader() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("other.gbr");
        std::fs::write(&f, "%FSLAX46Y46*%\n%MOMM*%\nM02*\n").unwrap();
        let e = load_paste_layer(&f).unwrap_err().to_string();
        assert!(e.contains("no pads"), "{e}");
        for (board, file) in [
            (
                crate::array::layout::LayoutBoard::Small,
                "array-small.paste.gbr",
            ),
            (
                crate::array::layout::LayoutBoard::Paper,
                "paper-board.paste.gbr",
            ),
        ] {
            let read = load_paste_layer(
                &Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join("../scenes")
                    .join(file),
            )
            .unwrap();
            let made = crate::array::layout::generate(board).pads;
            assert_eq!(read.len(), made.len(), "{file}");
            for (r, m) in read.iter().zip(&made) {
                assert_eq!((&r.component, &r.pin), (&m.component, &m.pin), "{file}");
                // Arcs become chords within 1 um where the reader does not keep the exact shape.
                let rel = (r.outline.area() - m.outline.area()).abs() / m.outline.area();
                assert!(rel < 5e-3, "{file}: {r:?} vs {m:?}");
                let (a, b) = (r.outline.centroid(), m.outline.centroid());
                assert!(
                    (a[0] - b[0]).abs() < 1e-5 && (a[1] - b[1]).abs() < 1e-5,
                    "{file}"
                );
            }
        }
    }

    #[test]
    fn model_geometry() {
        let s = ArrayScene::default();
        let m = s.camera_model(1);
        // A board point keeps its board row b = r + e / cpp as the conveyor moves.
        let (x, y) = m.board_point(0.0, 20.0, 50.0);
        let s1 = 1.3;
        // Find (r, c) seeing (x, y) at s1 by Newton steps on the linear map.
        let (sn, cs) = m.rotation_rad.sin_cos();
        let (dx, dy) = (x - s1 - m.x0_mm, y - m.y0_mm);
        let r = (dx * cs + dy * sn) / m.pitch_mm;
        let c = (-dx * sn + dy * cs) / m.pitch_mm;
        let (x2, y2) = m.board_point(s1, r, c);
        assert!((x2 - x).abs() < 1e-12 && (y2 - y).abs() < 1e-12);
        let b0 = 20.0;
        let b1 = r + s1 * s.counts_per_mm / m.counts_per_pixel;
        assert!((b1 - b0).abs() < 1e-9, "{b0} {b1}");
        assert_eq!(m.dead_pixels.len(), 3);
        assert!(m
            .fringe_frequency
            .iter()
            .all(|f| (f * 32.0 - 1.0).abs() <= 0.0021));
    }
}
