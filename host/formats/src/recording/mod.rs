//! The recording format's manifest (`manifest.json`): the camera, its calibration, the
//! processing and the trigger log, validated on reading (`docs/recording.md`). What reads the
//! frames the manifest names (PNG and the simulator's `.zfr`) is the simulator crate's
//! `Recording`; the manifest and its checks are here, so that the calibration file and the
//! core's configuration are made of the same blocks without it.

pub mod checks;

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Format tag in every manifest.
pub const FORMAT: &str = crate::kind::markers::RECORDING_FORMAT;
/// Manifest version this build reads and writes.
pub const VERSION: u32 = 1;

/// Contents of `manifest.json` (see `docs/model.md`).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// [`FORMAT`].
    pub format: String,
    /// [`VERSION`].
    pub version: u32,
    /// The camera's geometry and sample range.
    pub camera: Camera,
    /// What the core's configuration is made of: encoder, fringe and height scale.
    pub calibration: Calibration,
    /// The processing settings of the core.
    pub processing: Processing,
    /// The trigger log: one entry per frame delivered, in acquisition order.
    pub frames: Vec<FrameEntry>,
    /// The simulator's noise model (simulated recordings only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<Noise>,
    /// The extent of the ground truth (simulated recordings only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<TruthInfo>,
    /// The identity of the board this camera recorded, shared by every camera of one array
    /// board recording (absent in single-camera recordings): `Recording::run_id` (simulator crate) returns it,
    /// so all cameras' streams of one board carry one run id.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board_id: Option<BoardId>,
}

pub use crate::BoardId;

/// Camera geometry and sample range.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// The camera's place in the array (0 for a single camera).
    pub id: u8,
    /// Columns `W`.
    pub width: u32,
    /// Rows per frame `H`.
    pub rows: u32,
    /// Significant bits per pixel (8..=16).
    pub bit_depth: u8,
    /// A sample `>= saturation` (DN) is saturated.
    pub saturation: u16,
}

/// Calibration of the encoder, the fringe pattern and the height scale.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// Encoder counts per pixel of travel; a multiple of 2^-16.
    pub counts_per_pixel: f64,
    /// Fringe period along image rows, px.
    pub fringe_period_px: f64,
    /// `phi_0(c)`, one value per column, rad.
    pub reference_phase_rad: Vec<f64>,
    /// Height for one full fringe turn `1/f_z`, um: every column's, or the nominal value when
    /// `height_per_turn_um_per_column` is given (then the core's `lsb_per_turn`, and each
    /// column's value must lie within a factor of 2 of it).
    pub height_per_turn_um: f64,
    /// Height LSB of the i16 output, um.
    pub height_lsb_um: f64,
    /// Height per fringe turn per column `T_z(c)`, um (non-telecentric optics; from the
    /// calibration): the core scales column `c` with it, so every column's heights are in
    /// calibrated LSB. Absent: `height_per_turn_um` everywhere (manifests written before it
    /// existed read unchanged, with the same run identity).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub height_per_turn_um_per_column: Option<Vec<f64>>,
}

impl Calibration {
    /// `T_z` of column `c`, um: the per-column value if there is a table, else the uniform one.
    pub fn height_per_turn_at(&self, c: usize) -> f64 {
        match &self.height_per_turn_um_per_column {
            Some(t) => t.get(c).copied().unwrap_or(f64::NAN),
            None => self.height_per_turn_um,
        }
    }
}

/// Processing parameters of the reconstruction.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Processing {
    /// Observations per board row, 3..=8.
    pub n: u8,
    /// Largest encoder step (rows per frame) whose rows are admitted.
    pub max_step_rows: u32,
    /// Minimum fringe modulation `C` (DN) of a valid pixel.
    pub min_modulation: f64,
    /// Largest window noise gain `g` accepted (1..=8).
    pub max_noise_gain: f64,
}

/// One acquired frame as listed in the manifest.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct FrameEntry {
    /// Camera frame counter.
    pub seq: u32,
    /// Encoder count latched at the trigger.
    pub latch: i64,
    /// Path relative to the recording directory.
    pub file: String,
}

impl FrameEntry {
    /// The frame's trigger (`seq`, `latch`), as the core takes it.
    pub fn trigger(&self) -> dpsa_core::Trigger {
        dpsa_core::Trigger {
            seq: self.seq,
            latch: self.latch,
        }
    }
}

/// Noise model used by the simulator (simulated recordings only).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Noise {
    /// Conversion gain, electrons per DN (shot noise variance = I / gain, DN^2).
    pub gain_e_per_dn: f64,
    /// Gaussian read noise, DN rms.
    pub read_noise_dn: f64,
}

/// Extent of the ground truth files (simulated recordings only).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TruthInfo {
    /// Board row of the first truth row.
    pub first_row: i64,
    /// Truth rows (each `W` wide).
    pub rows: u32,
}

/// Name of the manifest inside a recording directory.
pub const MANIFEST_FILE: &str = crate::kind::markers::RECORDING_MANIFEST;
/// Truth file: height per board pixel, um.
pub const TRUTH_HEIGHT_FILE: &str = "truth/height_um.f32";
/// Truth file: background `B` per board pixel, DN.
pub const TRUTH_BACKGROUND_FILE: &str = "truth/background.f32";
/// Truth file: contrast `C` per board pixel, DN.
pub const TRUTH_CONTRAST_FILE: &str = "truth/contrast.f32";

/// Largest frame width accepted, px.
pub const MAX_WIDTH: u32 = 8192;
/// Largest number of rows per frame accepted, px.
pub const MAX_ROWS: u32 = 4096;

/// A serde_json error as one sentence that names the key it failed at; a NaN or infinity
/// (not JSON numbers) is said so.
fn json_message(text: &str, e: &serde_json::Error) -> String {
    let offset: usize = text
        .split_inclusive('\n')
        .take(e.line().saturating_sub(1))
        .map(str::len)
        .sum::<usize>()
        + e.column().saturating_sub(1);
    let offset = offset.min(text.len());
    let (before, rest) = text.split_at(
        (0..=offset)
            .rev()
            .find(|&i| text.is_char_boundary(i))
            .unwrap_or(0),
    );
    let key = before.rfind(':').and_then(|colon| {
        let k = before[..colon].trim_end().strip_suffix('"')?;
        let start = k.rfind('"')?;
        Some(k[start + 1..].to_string())
    });
    let token: String = rest
        .trim_start()
        .chars()
        .take_while(|c| c.is_ascii_alphanumeric() || *c == '-' || *c == '+' || *c == '.')
        .collect();
    let lower = token.to_ascii_lowercase();
    let non_finite = [
        "nan",
        "inf",
        "infinity",
        "-inf",
        "-infinity",
        "+inf",
        "+infinity",
    ]
    .contains(&lower.as_str());
    match key {
        Some(k) if non_finite => format!(
            "`{k}` is {token}: JSON has no NaN or infinity, expected a finite number (line {}, column {})",
            e.line(),
            e.column()
        ),
        Some(k) if e.is_syntax() || e.is_data() => format!("{e} (at `{k}`)"),
        _ => e.to_string(),
    }
}

/// Everything that can go wrong reading or writing a recording.
// The variants' fields are what each variant's sentence names (path, index, values).
#[allow(missing_docs)]
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    /// `manifest.json` does not exist.
    #[error("{}: no manifest (is this a recording directory?)", path.display())]
    MissingManifest { path: PathBuf },
    /// A file could not be read or written.
    #[error("{} {}", path.display(), crate::files::io_cause(cause))]
    Io {
        path: PathBuf,
        cause: std::io::Error,
    },
    /// The manifest is not valid JSON or does not match the schema (unknown or missing key, wrong type).
    #[error("{}: {message}", path.display())]
    Json { path: PathBuf, message: String },
    /// The manifest's `format` tag is not [`FORMAT`].
    #[error("{}: format is {found:?}, expected {expected:?}", path.display())]
    Format {
        path: PathBuf,
        found: String,
        expected: &'static str,
    },
    /// The manifest's `version` is not [`VERSION`].
    #[error("{}: version is {found}, this build reads version {expected}", path.display())]
    Version {
        path: PathBuf,
        found: u32,
        expected: u32,
    },
    /// A manifest value is out of range.
    #[error("{}: invalid {field}: {message}", path.display())]
    Invalid {
        path: PathBuf,
        field: String,
        message: String,
    },
    /// `frame(k)` was asked for a frame the manifest does not list.
    #[error("frame index {index} out of range: the recording has {count} frames")]
    FrameIndex { index: usize, count: usize },
    /// A frame file listed in the manifest does not exist.
    #[error("frame {index}: file {} is missing", path.display())]
    MissingFrame { index: usize, path: PathBuf },
    /// A frame file is not a decodable PNG (truncated, corrupt, not a PNG).
    #[error("frame {index}: cannot decode {}: {message}", path.display())]
    Decode {
        index: usize,
        path: PathBuf,
        message: String,
    },
    /// A frame has the wrong dimensions.
    #[error(
        "frame {index}: {} is {actual_rows} rows x {actual_width} columns, expected {expected_rows} x {expected_width}",
        path.display()
    )]
    FrameSize {
        index: usize,
        path: PathBuf,
        expected_rows: usize,
        expected_width: usize,
        actual_rows: usize,
        actual_width: usize,
    },
    /// A frame's pixel type does not match the camera bit depth.
    #[error(
        "frame {index}: {} is {found}, expected 16-bit greyscale (or 8-bit greyscale when bit_depth is 8; camera bit_depth is {bit_depth})",
        path.display()
    )]
    BitDepth {
        index: usize,
        path: PathBuf,
        found: String,
        bit_depth: u8,
    },
    /// A sample exceeds `2^bit_depth - 1`.
    #[error(
        "frame {index}: {} pixel (row {row}, column {col}) is {value}, above the {bit_depth}-bit maximum {max}",
        path.display()
    )]
    PixelRange {
        index: usize,
        path: PathBuf,
        row: usize,
        col: usize,
        value: u16,
        bit_depth: u8,
        max: u16,
    },
    /// A truth file does not hold `rows x width` f32 values.
    #[error("{}: {actual} bytes, expected {expected} (truth rows x width x 4)", path.display())]
    TruthLength {
        path: PathBuf,
        expected: u64,
        actual: u64,
    },
    /// The writer was given a buffer of the wrong length or impossible dimensions.
    #[error("{}: {message}", path.display())]
    BadData { path: PathBuf, message: String },
    /// A file could not be written (one sentence with its cause).
    #[error("{message}")]
    Write { path: PathBuf, message: String },
    /// PNG encoding failed.
    #[error("{}: cannot encode PNG: {message}", path.display())]
    Encode { path: PathBuf, message: String },
}

/// Maps an I/O error on `path` to [`RecordingError::Io`].
pub fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RecordingError + '_ {
    move |cause| RecordingError::Io {
        path: path.to_path_buf(),
        cause,
    }
}

/// Collects manifest range checks; the first failure becomes [`RecordingError::Invalid`].
struct Checker<'a> {
    path: &'a Path,
}

impl Checker<'_> {
    fn check(
        &self,
        ok: bool,
        field: impl Into<String>,
        message: impl FnOnce() -> String,
    ) -> Result<(), RecordingError> {
        if ok {
            Ok(())
        } else {
            Err(RecordingError::Invalid {
                path: self.path.to_path_buf(),
                field: field.into(),
                message: message(),
            })
        }
    }
}

impl Manifest {
    /// Checks every value against the ranges of `docs/model.md` (see `Recording::open` in the simulator crate).
    /// Errors name `manifest.json` as the path.
    pub fn validate(&self) -> Result<(), RecordingError> {
        self.validate_at(Path::new(MANIFEST_FILE))
    }

    /// [`Manifest::validate`] with `path` named in the errors.
    /// Parses and validates the bytes of a `manifest.json` (`path` names it in errors).
    pub fn parse(bytes: &[u8], path: &Path) -> Result<Manifest, RecordingError> {
        let text = String::from_utf8_lossy(bytes);
        let manifest: Manifest = serde_json::from_str(&text).map_err(|e| RecordingError::Json {
            path: path.to_path_buf(),
            message: json_message(&text, &e),
        })?;
        manifest.validate_at(path)?;
        Ok(manifest)
    }

    fn validate_at(&self, path: &Path) -> Result<(), RecordingError> {
        if self.format != FORMAT {
            return Err(RecordingError::Format {
                path: path.to_path_buf(),
                found: self.format.clone(),
                expected: FORMAT,
            });
        }
        if self.version != VERSION {
            return Err(RecordingError::Version {
                path: path.to_path_buf(),
                found: self.version,
                expected: VERSION,
            });
        }
        let ck = Checker { path };
        checks::check_blocks(&self.camera, &self.calibration, &self.processing).map_err(|e| {
            RecordingError::Invalid {
                path: path.to_path_buf(),
                field: e.field,
                message: e.message,
            }
        })?;

        ck.check(!self.frames.is_empty(), "frames", || {
            "the recording lists no frames".into()
        })?;
        for (i, pair) in self.frames.windows(2).enumerate() {
            let (prev, cur) = (pair[0].seq, pair[1].seq);
            ck.check(cur > prev, format!("frames[{}].seq", i + 1), || {
                format!("{cur} after {prev} (frames[{i}]): seq must be strictly increasing (gaps mean lost frames)")
            })?;
        }
        let mut seen = std::collections::HashSet::new();
        for (i, f) in self.frames.iter().enumerate() {
            let p = Path::new(&f.file);
            let plain = !f.file.is_empty()
                && p.components()
                    .all(|c| matches!(c, std::path::Component::Normal(_)));
            ck.check(plain, format!("frames[{i}].file"), || {
                format!(
                    "{:?}: a frame path must be relative to the recording directory, without `..`",
                    f.file
                )
            })?;
            let key: PathBuf = p.components().collect();
            ck.check(seen.insert(key), format!("frames[{i}].file"), || {
                format!(
                    "{:?} is listed twice: every frame needs its own file",
                    f.file
                )
            })?;
        }
        if let Some(t) = &self.truth {
            ck.check(t.rows > 0, "truth.rows", || "0, expected > 0".into())?;
        }
        if let Some(nz) = &self.noise {
            ck.check(
                nz.gain_e_per_dn.is_finite() && nz.gain_e_per_dn > 0.0,
                "noise.gain_e_per_dn",
                || format!("{} e-/DN, expected a finite value > 0", nz.gain_e_per_dn),
            )?;
            ck.check(
                nz.read_noise_dn.is_finite() && nz.read_noise_dn >= 0.0,
                "noise.read_noise_dn",
                || format!("{} DN, expected a finite value >= 0", nz.read_noise_dn),
            )?;
        }
        Ok(())
    }

    /// Legal settings that make the result useless, one sentence each (see
    /// [`checks::warnings`]); also a recording whose
    /// latches all round to the same board-row offset (the encoder does not resolve the motion).
    pub fn warnings(&self) -> Vec<String> {
        let mut w = checks::warnings(&self.camera, &self.calibration, &self.processing);
        let q = (self.calibration.counts_per_pixel * 65536.0) as i128;
        let offset = |latch: i64| (((latch as i128) << 17) + q).div_euclid(2 * q.max(1));
        if self.frames.len() > 1 {
            let o0 = offset(self.frames[0].latch);
            if self.frames.iter().all(|f| offset(f.latch) == o0) {
                w.push(format!(
                    "all {} frame latches round to the same board-row offset at counts_per_pixel = {}: the encoder does not resolve the motion and no board row can be measured",
                    self.frames.len(),
                    self.calibration.counts_per_pixel
                ));
            }
        }
        w
    }

    /// Writes `dir/manifest.json` (pretty JSON). The directory must exist.
    pub fn save(&self, dir: &Path) -> Result<(), RecordingError> {
        let path = dir.join(MANIFEST_FILE);
        let mut text = serde_json::to_string_pretty(self).map_err(|e| RecordingError::Json {
            path: path.clone(),
            message: e.to_string(),
        })?;
        text.push('\n');
        crate::files::write_bytes(&path, text.as_bytes()).map_err(|e| RecordingError::Write {
            path: path.clone(),
            message: format!("{e:#}"),
        })
    }

    /// Largest sample value of the camera, `2^bit_depth - 1` (DN).
    pub fn max_value(&self) -> u16 {
        max_value(self.camera.bit_depth)
    }
}

/// `2^bit_depth - 1`, saturating at 65535 (DN).
pub fn max_value(bit_depth: u8) -> u16 {
    if bit_depth >= 16 {
        u16::MAX
    } else {
        ((1u32 << bit_depth) - 1) as u16
    }
}
