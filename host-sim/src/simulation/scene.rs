//! Simulator scene: every knob of `dpsa simulate`, loaded from TOML.
//!
//! Every field has a default, so a scene file only lists what it changes; [`Scene::default`]
//! is the built-in default scene. Knobs, units and defaults are documented in the README (section "Scene files").

use crate::simulation::checks;
use crate::simulation::recording::{
    self, Calibration, Camera, Noise, Processing, MAX_ROWS, MAX_WIDTH,
};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use std::path::{Path, PathBuf};

/// Largest number of board rows a scene may simulate.
pub const MAX_BOARD_LENGTH: u32 = 1 << 20;
/// Largest number of board pixels (`board_length * width`): the truth files hold 12 bytes each.
pub const MAX_BOARD_PIXELS: u64 = 1 << 27;
/// Largest number of deposits a scene may request.
pub const MAX_DEPOSITS: u32 = 100_000;
/// Largest number of frames a scene may produce (estimated from the slowest possible motion).
pub const MAX_FRAMES: u64 = 1_000_000;

/// A rectangle of the board whose background and/or contrast is overridden.
///
/// Coordinates are board pixels: rows `row..row + rows` (along the motion), columns
/// `col..col + cols`. The override applies on top of board and paste and is then scaled by the
/// column illumination factor like everything else.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Patch {
    /// First board row, px.
    pub row: i64,
    /// First column, px.
    pub col: i64,
    /// Height of the rectangle along the motion, px (>= 1).
    pub rows: u32,
    /// Width of the rectangle, px (>= 1).
    pub cols: u32,
    /// Background `B` inside the rectangle, DN; absent = unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub background: Option<f64>,
    /// Contrast `C` inside the rectangle, DN; absent = unchanged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub contrast: Option<f64>,
}

impl Patch {
    /// `true` if board pixel (`b`, `c`) is inside the rectangle.
    pub fn contains(&self, b: i64, c: i64) -> bool {
        self.contains_row(b) && c >= self.col && c - self.col < i64::from(self.cols)
    }

    /// `true` if board row `b` crosses the rectangle.
    pub fn contains_row(&self, b: i64) -> bool {
        b >= self.row && b - self.row < i64::from(self.rows)
    }
}

/// A conveyor stop: the steps after frames `frame, frame + 1, ..., frame + frames - 1` are 0,
/// so frames `frame + 1 ..= frame + frames` are taken at the same position as frame `frame`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Stall {
    /// Frame index after which the conveyor stops.
    pub frame: u32,
    /// Number of zero steps.
    pub frames: u32,
}

/// Everything the simulator needs to render a recording. Units are in the field docs and in
/// the README (section "Scene files").
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Scene {
    /// Frame width `W`, px (1..=8192).
    pub width: u32,
    /// ROI rows read per frame `H`, px (1..=4096).
    pub rows: u32,
    /// Board rows to simulate, px.
    pub board_length: u32,
    /// Observations per board row (3..=8).
    pub n: u8,
    /// Camera bit depth (8..=16).
    pub bit_depth: u8,
    /// Saturation threshold, DN; absent = `2^bit_depth - 1`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub saturation: Option<u16>,
    /// Fringe period along image rows, px (>= 2).
    pub fringe_period_px: f64,
    /// Height of one full fringe turn, um.
    pub height_per_turn_um: f64,
    /// Height LSB of the i16 output, um.
    pub height_lsb_um: f64,
    /// Encoder counts per pixel of travel (rounded to a multiple of 2^-16 on load).
    pub counts_per_pixel: f64,
    /// Reference phase `phi_0` at column 0, rad.
    pub reference_phase_rad: f64,
    /// Fringe tilt across the frame: `phi_0` grows by `2 pi * fringe_tilt_cycles` over `W` columns.
    pub fringe_tilt_cycles: f64,
    /// Mean conveyor step between frames, px.
    pub mean_step_px: f64,
    /// Step jitter: each step is `mean_step_px * (1 + jitter_pct/100 * U(-1, 1))`, percent (0..100).
    pub jitter_pct: f64,
    /// Board background `B`, DN.
    pub background: f64,
    /// Board contrast `C`, DN.
    pub contrast: f64,
    /// Paste background, DN.
    pub paste_background: f64,
    /// Paste contrast, DN.
    pub paste_contrast: f64,
    /// Illumination drop at the frame edges, percent (0..=100).
    pub illumination_falloff_pct: f64,
    /// Conversion gain, electrons per DN (> 0).
    pub gain_e_per_dn: f64,
    /// Read noise, DN rms (>= 0).
    pub read_noise_dn: f64,
    /// Number of paste deposits to place.
    pub deposits: u32,
    /// Deposit footprints `[rows along motion, cols]`, px; each deposit picks one at random.
    pub deposit_sizes: Vec<[u32; 2]>,
    /// Deposit height range `[min, max]`, um (uniform).
    pub deposit_height_um: [f64; 2],
    /// Corner radius of the deposit footprint, px.
    pub deposit_corner_px: f64,
    /// Width of the sloped deposit wall, px.
    pub deposit_edge_px: f64,
    /// Minimum modulation of a valid pixel, DN.
    pub min_modulation: f64,
    /// Largest accepted window noise gain (1..=8).
    pub max_noise_gain: f64,
    /// Largest admitted encoder step, rows; absent = `min(ceil(1.25 * mean_step_px), rows)`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_step_rows: Option<u32>,
    /// Rectangles with overridden background / contrast.
    pub patches: Vec<Patch>,
    /// Conveyor stops.
    pub stalls: Vec<Stall>,
    /// Random seed (the command line `--seed` overrides it).
    pub seed: u64,
}

impl Default for Scene {
    fn default() -> Self {
        Scene {
            width: 2048,
            rows: 40,
            board_length: 2048,
            n: 4,
            bit_depth: 12,
            saturation: None,
            fringe_period_px: 32.0,
            height_per_turn_um: 500.0,
            height_lsb_um: 0.25,
            counts_per_pixel: 10.25,
            reference_phase_rad: 0.5,
            fringe_tilt_cycles: 1.5,
            mean_step_px: 8.0,
            jitter_pct: 10.0,
            background: 1800.0,
            contrast: 700.0,
            paste_background: 2000.0,
            paste_contrast: 800.0,
            illumination_falloff_pct: 15.0,
            gain_e_per_dn: 3.0,
            read_noise_dn: 3.0,
            deposits: 300,
            deposit_sizes: vec![[12, 12], [16, 24], [24, 16], [30, 30], [40, 20], [20, 60]],
            deposit_height_um: [60.0, 200.0],
            deposit_corner_px: 3.0,
            deposit_edge_px: 2.0,
            min_modulation: 60.0,
            max_noise_gain: 2.0,
            max_step_rows: None,
            patches: Vec::new(),
            stalls: Vec::new(),
            seed: 1,
        }
    }
}

/// Errors loading or validating a scene.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The scene file could not be read.
    #[error("{} {}", path.display(), crate::files::io_cause(cause))]
    Io {
        /// The scene file.
        path: PathBuf,
        /// The I/O error.
        cause: std::io::Error,
    },
    /// The TOML is malformed or does not match the schema (unknown key, wrong type).
    #[error("{}scene TOML: {message}", origin(path))]
    Parse {
        /// The scene file (`None` when parsed from or written to a string).
        path: Option<PathBuf>,
        /// The TOML parser's message.
        message: String,
    },
    /// A knob is out of range.
    #[error("{}invalid scene knob `{knob}`: {message}", origin(path))]
    Invalid {
        /// The scene file (`None` when parsed from a string).
        path: Option<PathBuf>,
        /// The knob's name (its TOML key).
        knob: String,
        /// What is wrong with its value.
        message: String,
    },
}

fn origin(path: &Option<PathBuf>) -> String {
    path.as_ref()
        .map(|p| format!("{}: ", p.display()))
        .unwrap_or_default()
}

pub use dpsa_formats::calibration::round_counts_per_pixel;

fn invalid(knob: impl Into<String>, message: String) -> SceneError {
    SceneError::Invalid {
        path: None,
        knob: knob.into(),
        message,
    }
}

fn check(ok: bool, knob: &str, message: impl FnOnce() -> String) -> Result<(), SceneError> {
    if ok {
        Ok(())
    } else {
        Err(invalid(knob, message()))
    }
}

fn check_finite_min(value: f64, min: f64, knob: &str, unit: &str) -> Result<(), SceneError> {
    check(value.is_finite() && value >= min, knob, || {
        format!("{value} {unit}, expected a finite value >= {min}")
    })
}

impl Scene {
    /// Parses a scene from TOML, rounds `counts_per_pixel` to a multiple of 2^-16 and validates.
    pub fn from_toml_str(text: &str) -> Result<Scene, SceneError> {
        let mut scene: Scene = toml::from_str(text).map_err(|e| SceneError::Parse {
            path: None,
            message: e.to_string(),
        })?;
        scene.validate()?;
        scene.counts_per_pixel = round_counts_per_pixel(scene.counts_per_pixel);
        Ok(scene)
    }

    /// Reads and parses a scene file (see [`Scene::from_toml_str`]); errors name the file.
    pub fn load(path: impl AsRef<Path>) -> Result<Scene, SceneError> {
        let path = path.as_ref();
        let io = |cause| SceneError::Io {
            path: path.to_path_buf(),
            cause,
        };
        let bytes =
            crate::files::read_capped_io(path, crate::files::MAX_SCENE_BYTES).map_err(io)?;
        let text = String::from_utf8(bytes).map_err(|_| {
            io(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                "is not UTF-8 text (a scene is a TOML file)",
            ))
        })?;
        Scene::from_toml_str(&text).map_err(|e| match e {
            SceneError::Parse { message, .. } => SceneError::Parse {
                path: Some(path.to_path_buf()),
                message,
            },
            SceneError::Invalid { knob, message, .. } => SceneError::Invalid {
                path: Some(path.to_path_buf()),
                knob,
                message,
            },
            other => other,
        })
    }

    /// The scene as TOML (every knob, e.g. to save the resolved scene next to a recording).
    pub fn to_toml_string(&self) -> Result<String, SceneError> {
        toml::to_string_pretty(self).map_err(|e| SceneError::Parse {
            path: None,
            message: e.to_string(),
        })
    }

    /// Checks every knob's range. [`Scene::from_toml_str`] calls it; call it yourself after
    /// editing a scene in code.
    pub fn validate(&self) -> Result<(), SceneError> {
        check((1..=MAX_WIDTH).contains(&self.width), "width", || {
            format!("{} px, expected 1..={MAX_WIDTH}", self.width)
        })?;
        check((1..=MAX_ROWS).contains(&self.rows), "rows", || {
            format!("{} px, expected 1..={MAX_ROWS}", self.rows)
        })?;
        check(
            (1..=MAX_BOARD_LENGTH).contains(&self.board_length),
            "board_length",
            || format!("{} px, expected 1..={MAX_BOARD_LENGTH}", self.board_length),
        )?;
        let pixels = u64::from(self.board_length) * u64::from(self.width);
        check(pixels <= MAX_BOARD_PIXELS, "board_length", || {
            format!("board_length x width = {pixels} board pixels, at most {MAX_BOARD_PIXELS} are supported")
        })?;
        check((3..=8).contains(&self.n), "n", || {
            format!("{}, expected 3..=8", self.n)
        })?;
        check((8..=16).contains(&self.bit_depth), "bit_depth", || {
            format!("{} bits, expected 8..=16", self.bit_depth)
        })?;
        let cpp = round_counts_per_pixel(self.counts_per_pixel);
        check(
            self.counts_per_pixel.is_finite() && cpp > 0.0 && cpp * 65536.0 < 4_294_967_296.0,
            "counts_per_pixel",
            || {
                format!(
                    "{} counts/px rounds to {cpp} (a multiple of 2^-16), expected 2^-16 ..< 65536",
                    self.counts_per_pixel
                )
            },
        )?;
        for (v, knob) in [
            (self.reference_phase_rad, "reference_phase_rad"),
            (self.fringe_tilt_cycles, "fringe_tilt_cycles"),
        ] {
            check(v.is_finite(), knob, || {
                format!("{v}, expected a finite value")
            })?;
        }

        check(
            self.mean_step_px.is_finite() && self.mean_step_px > 0.0,
            "mean_step_px",
            || format!("{} px, expected a finite value > 0", self.mean_step_px),
        )?;
        check(
            (0.0..100.0).contains(&self.jitter_pct),
            "jitter_pct",
            || format!("{} %, expected 0 <= jitter_pct < 100", self.jitter_pct),
        )?;

        check_finite_min(self.background, 0.0, "background", "DN")?;
        check_finite_min(self.contrast, 0.0, "contrast", "DN")?;
        check_finite_min(self.paste_background, 0.0, "paste_background", "DN")?;
        check_finite_min(self.paste_contrast, 0.0, "paste_contrast", "DN")?;
        check(
            (0.0..=100.0).contains(&self.illumination_falloff_pct),
            "illumination_falloff_pct",
            || format!("{} %, expected 0..=100", self.illumination_falloff_pct),
        )?;
        check(
            self.gain_e_per_dn.is_finite() && self.gain_e_per_dn > 0.0,
            "gain_e_per_dn",
            || format!("{} e-/DN, expected a finite value > 0", self.gain_e_per_dn),
        )?;
        check_finite_min(self.read_noise_dn, 0.0, "read_noise_dn", "DN")?;

        check(self.deposits <= MAX_DEPOSITS, "deposits", || {
            format!("{}, expected at most {MAX_DEPOSITS}", self.deposits)
        })?;
        check(
            self.deposits == 0 || !self.deposit_sizes.is_empty(),
            "deposit_sizes",
            || "empty list, but deposits > 0 need at least one footprint".into(),
        )?;
        for (i, &[r, c]) in self.deposit_sizes.iter().enumerate() {
            check(r >= 1 && c >= 1, "deposit_sizes", || {
                format!("entry {i} is [{r}, {c}], sizes must be >= 1 px")
            })?;
        }
        let [lo, hi] = self.deposit_height_um;
        check(
            lo.is_finite() && hi.is_finite() && 0.0 <= lo && lo <= hi,
            "deposit_height_um",
            || format!("[{lo}, {hi}] um, expected finite 0 <= min <= max"),
        )?;
        check_finite_min(self.deposit_corner_px, 0.0, "deposit_corner_px", "px")?;
        check_finite_min(self.deposit_edge_px, 0.0, "deposit_edge_px", "px")?;

        // Camera, calibration and processing: the same checks as a manifest's.
        checks::check_blocks(&self.camera(), &self.calibration(), &self.processing()).map_err(
            |e| {
                let (knob, note) = self.knob_of(&e.field);
                invalid(knob, e.message + &note)
            },
        )?;

        for (i, p) in self.patches.iter().enumerate() {
            let knob = format!("patches[{i}]");
            check(p.rows >= 1 && p.cols >= 1, &knob, || {
                format!("{} x {} px, expected >= 1 x 1", p.rows, p.cols)
            })?;
            for v in [p.background, p.contrast].into_iter().flatten() {
                check(v.is_finite() && v >= 0.0, &knob, || {
                    format!("{v} DN, expected a finite value >= 0")
                })?;
            }
        }

        let frames = self.max_frame_estimate();
        check(frames <= MAX_FRAMES as f64, "mean_step_px", || {
            format!("the scene could need up to {frames:.0} frames (board_length, mean_step_px, jitter_pct, stalls), at most {MAX_FRAMES} are supported")
        })?;
        Ok(())
    }

    /// The scene knob behind a manifest field (`camera.saturation` -> `saturation`; a derived
    /// `max_step_rows` is named through `mean_step_px`).
    fn knob_of(&self, field: &str) -> (String, String) {
        let name = field.rsplit('.').next().unwrap_or(field);
        let name = name.split('[').next().unwrap_or(name);
        if name == "max_step_rows" && self.max_step_rows.is_none() {
            let note = format!(
                " (max_step_rows is derived from mean_step_px: min(ceil(1.25 * mean_step_px), rows) = {}; lower mean_step_px or set max_step_rows)",
                self.max_step_rows()
            );
            return ("mean_step_px".into(), note);
        }
        (name.into(), String::new())
    }

    /// Legal knob settings that make the recording useless, one sentence each (printed as
    /// `warning: ...` by `dpsa simulate` and `dpsa demo`).
    pub fn warnings(&self) -> Vec<String> {
        let mut w = checks::warnings(&self.camera(), &self.calibration(), &self.processing());
        let cpp = round_counts_per_pixel(self.counts_per_pixel);
        if cpp * self.mean_step_px < 2.0 {
            w.push(format!(
                "counts_per_pixel = {} gives {:.3} encoder counts per mean frame step ({} px): latches cannot resolve the motion and most rows are lost",
                self.counts_per_pixel,
                cpp * self.mean_step_px,
                self.mean_step_px
            ));
        }
        let fx = 1.0 / self.fringe_period_px;
        let shifts: Vec<f64> = (0..self.n)
            .map(|j| -2.0 * PI * fx * (f64::from(j) * self.mean_step_px).round())
            .collect();
        let g = crate::reference::noise_gain(&shifts);
        if w.is_empty() && (g.is_nan() || g > self.max_noise_gain) {
            w.push(format!(
                "the nominal window ({} frames {} px apart, {:.1} degrees of phase per step) has noise gain {g:.3e}, above max_noise_gain {}: most windows will be ILL_CONDITIONED",
                self.n,
                self.mean_step_px,
                360.0 * fx * self.mean_step_px,
                self.max_noise_gain
            ));
        }
        w
    }

    /// Upper bound of the number of frames the scene produces.
    fn max_frame_estimate(&self) -> f64 {
        let travel =
            f64::from(self.board_length) + f64::from(self.rows) + self.travel_beyond_board();
        let min_step = self.mean_step_px * (1.0 - self.jitter_pct / 100.0);
        let stalled: f64 = self.stalls.iter().map(|s| f64::from(s.frames)).sum();
        (travel / min_step).ceil() + 2.0 + stalled
    }

    /// Travel past the end of the board before the last frame, `n * max_step_rows`, px.
    pub fn travel_beyond_board(&self) -> f64 {
        f64::from(self.n) * f64::from(self.max_step_rows())
    }

    /// Saturation threshold, DN (`2^bit_depth - 1` unless set).
    pub fn saturation(&self) -> u16 {
        self.saturation.unwrap_or_else(|| self.max_value())
    }

    /// Largest sample value `2^bit_depth - 1`, DN.
    pub fn max_value(&self) -> u16 {
        recording::max_value(self.bit_depth)
    }

    /// Resolved `max_step_rows`: the knob, or `ceil(1.25 * mean_step_px)` clamped to `1..=rows`.
    pub fn max_step_rows(&self) -> u32 {
        self.max_step_rows.unwrap_or_else(|| {
            let m = (1.25 * self.mean_step_px).ceil();
            if m.is_finite() {
                (m.max(1.0) as u32).min(self.rows.max(1))
            } else {
                self.rows.max(1)
            }
        })
    }

    /// `phi_0(c)` for every column, wrapped into `[-pi, pi)`, rad.
    pub fn reference_phase(&self) -> Vec<f64> {
        let w = f64::from(self.width);
        (0..self.width)
            .map(|c| {
                let p = self.reference_phase_rad
                    + 2.0 * PI * self.fringe_tilt_cycles * f64::from(c) / w;
                let wrapped = (p + PI).rem_euclid(2.0 * PI) - PI;
                if wrapped >= PI {
                    -PI
                } else {
                    wrapped
                }
            })
            .collect()
    }

    /// Illumination factor of every column, `1 - falloff/100 * ((c - W/2) / (W/2))^2`.
    pub fn illumination(&self) -> Vec<f64> {
        let half = f64::from(self.width) / 2.0;
        (0..self.width)
            .map(|c| {
                let u = (f64::from(c) - half) / half;
                1.0 - self.illumination_falloff_pct / 100.0 * u * u
            })
            .collect()
    }

    /// Camera block of the manifest (camera id 0).
    pub fn camera(&self) -> Camera {
        Camera {
            id: 0,
            width: self.width,
            rows: self.rows,
            bit_depth: self.bit_depth,
            saturation: self.saturation(),
        }
    }

    /// Calibration block of the manifest (`counts_per_pixel` rounded to a multiple of 2^-16).
    pub fn calibration(&self) -> Calibration {
        Calibration {
            counts_per_pixel: round_counts_per_pixel(self.counts_per_pixel),
            fringe_period_px: self.fringe_period_px,
            reference_phase_rad: self.reference_phase(),
            height_per_turn_um: self.height_per_turn_um,
            height_lsb_um: self.height_lsb_um,
            height_per_turn_um_per_column: None,
        }
    }

    /// Processing block of the manifest.
    pub fn processing(&self) -> Processing {
        Processing {
            n: self.n,
            max_step_rows: self.max_step_rows(),
            min_modulation: self.min_modulation,
            max_noise_gain: self.max_noise_gain,
        }
    }

    /// Noise block of the manifest.
    pub fn noise(&self) -> Noise {
        Noise {
            gain_e_per_dn: self.gain_e_per_dn,
            read_noise_dn: self.read_noise_dn,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn empty_file_is_the_default_scene() {
        let s = Scene::from_toml_str("").unwrap();
        assert_eq!(s, Scene::default());
        assert_eq!(s.max_step_rows(), 10);
        assert_eq!(s.saturation(), 4095);
        assert_eq!(s.processing().max_step_rows, 10);
    }

    #[test]
    fn partial_file_overrides_only_its_knobs() {
        let s = Scene::from_toml_str(
            "width = 64\nboard_length = 200\ncounts_per_pixel = 0.1\n\
             [[patches]]\nrow = 10\ncol = 5\nrows = 3\ncols = 4\ncontrast = 0.0\n\
             [[stalls]]\nframe = 5\nframes = 3\n",
        )
        .unwrap();
        assert_eq!((s.width, s.board_length, s.rows), (64, 200, 40));
        assert_eq!(s.counts_per_pixel * 65536.0, (0.1f64 * 65536.0).round());
        assert_eq!(s.patches[0].contrast, Some(0.0));
        assert_eq!(s.patches[0].background, None);
        assert!(
            s.patches[0].contains(12, 8)
                && !s.patches[0].contains(13, 8)
                && !s.patches[0].contains(12, 9)
        );
        assert_eq!(
            s.stalls,
            vec![Stall {
                frame: 5,
                frames: 3
            }]
        );
        assert_eq!(s.reference_phase().len(), 64);
    }

    #[test]
    fn unknown_key_is_named() {
        let err = Scene::from_toml_str("widht = 64\n").unwrap_err();
        assert!(matches!(err, SceneError::Parse { .. }));
        assert!(err.to_string().contains("widht"), "{err}");
        let err = Scene::from_toml_str(
            "[[patches]]\nrow = 0\ncol = 0\nrows = 1\ncols = 1\nbackgound = 5\n",
        )
        .unwrap_err();
        assert!(err.to_string().contains("backgound"), "{err}");
    }

    #[test]
    fn out_of_range_knobs() {
        for (text, knob) in [
            ("n = 2", "n"),
            ("width = 0", "width"),
            ("bit_depth = 7", "bit_depth"),
            ("saturation = 5000", "saturation"),
            ("jitter_pct = 100.0", "jitter_pct"),
            ("mean_step_px = 0.0", "mean_step_px"),
            ("mean_step_px = 0.0001", "mean_step_px"),
            ("deposit_height_um = [200.0, 60.0]", "deposit_height_um"),
            ("deposit_sizes = []", "deposit_sizes"),
            ("max_step_rows = 41", "max_step_rows"),
            ("max_noise_gain = 0.5", "max_noise_gain"),
            ("height_lsb_um = 0.001", "height_per_turn_um"),
            ("gain_e_per_dn = 0.0", "gain_e_per_dn"),
            (
                "[[patches]]\nrow = 0\ncol = 0\nrows = 0\ncols = 1",
                "patches[0]",
            ),
        ] {
            let err = Scene::from_toml_str(text).unwrap_err();
            assert!(
                matches!(&err, SceneError::Invalid { knob: k, .. } if k == knob),
                "{text}: {err}"
            );
        }
    }

    #[test]
    fn toml_round_trip() {
        let mut s = Scene::default();
        s.patches.push(Patch {
            row: 1,
            col: 2,
            rows: 3,
            cols: 4,
            background: Some(5000.0),
            contrast: None,
        });
        s.max_step_rows = Some(12);
        let text = s.to_toml_string().unwrap();
        assert_eq!(Scene::from_toml_str(&text).unwrap(), s);
    }

    #[test]
    fn reference_phase_and_illumination() {
        let s = Scene {
            width: 4,
            fringe_tilt_cycles: 1.0,
            reference_phase_rad: 0.5,
            ..Scene::default()
        };
        let p = s.reference_phase();
        for (c, &v) in p.iter().enumerate() {
            let expected = 0.5 + 2.0 * PI * c as f64 / 4.0;
            assert!((-PI..PI).contains(&v));
            assert!(
                ((v - expected).rem_euclid(2.0 * PI)).min((expected - v).rem_euclid(2.0 * PI))
                    < 1e-12
            );
        }
        let ill = s.illumination();
        assert_eq!(ill[2], 1.0);
        assert!((ill[0] - 0.85).abs() < 1e-12);
    }

    /// The README documents every scene knob and its example parses.
    #[test]
    fn documentation_is_in_sync() {
        let doc = include_str!("../../../README.md");
        let start = doc.find("```toml\n").expect("example block") + 8;
        let end = start + doc[start..].find("```").expect("end of example");
        let scene = Scene::from_toml_str(&doc[start..end]).unwrap();
        assert_eq!(
            (scene.width, scene.patches.len(), scene.stalls.len()),
            (256, 2, 1)
        );
        let mut full = Scene {
            saturation: Some(4095),
            max_step_rows: Some(10),
            ..Scene::default()
        };
        full.patches.push(Patch {
            row: 0,
            col: 0,
            rows: 1,
            cols: 1,
            background: None,
            contrast: None,
        });
        let table: toml::Table = toml::from_str(&full.to_toml_string().unwrap()).unwrap();
        for key in table.keys() {
            assert!(
                doc.contains(&format!("| `{key}` |")),
                "knob {key} is not documented"
            );
        }
    }
}
