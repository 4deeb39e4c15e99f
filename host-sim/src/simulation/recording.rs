//! Recordings on disk: `manifest.json`, 16-bit PNG frames and optional ground truth.
//! The format is specified in `docs/model.md`.

use image::codecs::png::{CompressionType, FilterType, PngDecoder, PngEncoder};
use image::{ColorType, ExtendedColorType, ImageDecoder, ImageEncoder};
use serde::{Deserialize, Serialize};
use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};

/// Format tag in every manifest.
pub const FORMAT: &str = dpsa_formats::kind::markers::RECORDING_FORMAT;
/// Manifest version this build reads and writes.
pub const VERSION: u32 = 1;

/// Contents of `manifest.json` (see `docs/model.md`).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub format: String,
    pub version: u32,
    pub camera: Camera,
    pub calibration: Calibration,
    pub processing: Processing,
    pub frames: Vec<FrameEntry>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise: Option<Noise>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub truth: Option<TruthInfo>,
    /// The identity of the board this camera recorded, shared by every camera of one array
    /// board recording (absent in single-camera recordings): [`Recording::run_id`] returns it,
    /// so all cameras' streams of one board carry one run id.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub board_id: Option<BoardId>,
}

pub use dpsa_formats::BoardId;

/// Camera geometry and sample range.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Camera {
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

/// An opened, validated recording.
#[derive(Clone, Debug)]
pub struct Recording {
    pub dir: PathBuf,
    pub manifest: Manifest,
    /// Every frame decoded in memory ([`Recording::preload`], for benchmarks that time the
    /// processing without the file reading); `None`: frames are read on demand.
    preloaded: Option<std::sync::Arc<Vec<Frame>>>,
}

/// One decoded frame, row-major `rows x width`.
#[derive(Clone, Debug)]
pub struct Frame {
    pub seq: u32,
    pub latch: i64,
    pub rows: usize,
    pub width: usize,
    pub data: Vec<u16>,
}

/// Simulator ground truth on the board grid, row-major `rows x width`.
#[derive(Clone, Debug)]
pub struct Truth {
    pub first_row: i64,
    pub rows: usize,
    pub width: usize,
    pub height_um: Vec<f32>,
    pub background: Vec<f32>,
    pub contrast: Vec<f32>,
}

/// Name of the manifest inside a recording directory.
pub const MANIFEST_FILE: &str = dpsa_formats::kind::markers::RECORDING_MANIFEST;
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

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RecordingError + '_ {
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
    /// Checks every value against the ranges of `docs/model.md` (see [`Recording::open`]).
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
        crate::simulation::checks::check_blocks(&self.camera, &self.calibration, &self.processing)
            .map_err(|e| RecordingError::Invalid {
                path: path.to_path_buf(),
                field: e.field,
                message: e.message,
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
    /// [`checks::warnings`](crate::simulation::checks::warnings)); also a recording whose
    /// latches all round to the same board-row offset (the encoder does not resolve the motion).
    pub fn warnings(&self) -> Vec<String> {
        let mut w =
            crate::simulation::checks::warnings(&self.camera, &self.calibration, &self.processing);
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

impl Recording {
    /// Opens the recording in `dir`: reads and validates `manifest.json`.
    ///
    /// Frames and truth are read on demand by [`Recording::frame`] and [`Recording::truth`].
    /// Encoder latches are deliberately not checked (repeated or decreasing latches are real
    /// conveyor conditions that the processing flags).
    pub fn open(dir: impl AsRef<Path>) -> Result<Recording, RecordingError> {
        let dir = dir.as_ref().to_path_buf();
        let path = dir.join(MANIFEST_FILE);
        match std::fs::metadata(&dir) {
            Ok(m) if !m.is_dir() => {
                return Err(RecordingError::Io {
                    path: dir,
                    cause: std::io::Error::new(
                        std::io::ErrorKind::InvalidInput,
                        "is not a directory (a recording is a directory with a manifest.json)",
                    ),
                })
            }
            Err(cause) => return Err(RecordingError::Io { path: dir, cause }),
            Ok(_) => {}
        }
        let bytes = match crate::files::read_capped_io(&path, crate::files::MAX_MANIFEST_BYTES) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(RecordingError::MissingManifest { path })
            }
            Err(cause) => return Err(RecordingError::Io { path, cause }),
        };
        let manifest = Manifest::parse(&bytes, &path)?;
        Ok(Recording {
            dir,
            manifest,
            preloaded: None,
        })
    }

    /// Number of frames listed in the manifest.
    pub fn len(&self) -> usize {
        self.manifest.frames.len()
    }

    /// `true` if the manifest lists no frames (never the case for an opened recording).
    pub fn is_empty(&self) -> bool {
        self.manifest.frames.is_empty()
    }

    /// Frame width `W`, px.
    pub fn width(&self) -> usize {
        self.manifest.camera.width as usize
    }

    /// Rows per frame `H`, px.
    pub fn rows(&self) -> usize {
        self.manifest.camera.rows as usize
    }

    /// Decodes every frame into memory; [`Recording::frame`] then hands out copies of them
    /// (clones of the recording share them). Returns the bytes of samples held.
    pub fn preload(&mut self) -> Result<u64, RecordingError> {
        let frames = (0..self.len())
            .map(|k| self.frame(k))
            .collect::<Result<Vec<_>, _>>()?;
        let bytes = frames.iter().map(|f| f.data.len() as u64 * 2).sum();
        self.preloaded = Some(std::sync::Arc::new(frames));
        Ok(bytes)
    }

    /// Absolute path of frame `k`'s file.
    pub fn frame_path(&self, k: usize) -> Option<PathBuf> {
        self.manifest.frames.get(k).map(|f| self.dir.join(&f.file))
    }

    /// Decodes frame `k` (in acquisition order) and checks its size and sample range.
    ///
    /// Accepts 16-bit greyscale PNG, and 8-bit greyscale PNG only when `bit_depth` is 8.
    pub fn frame(&self, k: usize) -> Result<Frame, RecordingError> {
        if let Some(f) = self.preloaded.as_ref().and_then(|p| p.get(k)) {
            return Ok(f.clone());
        }
        let entry = self
            .manifest
            .frames
            .get(k)
            .ok_or(RecordingError::FrameIndex {
                index: k,
                count: self.len(),
            })?;
        let path = self.dir.join(&entry.file);
        let cap = crate::files::max_frame_png_bytes(self.rows(), self.width());
        let bytes = match crate::files::read_capped_io(&path, cap) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(RecordingError::MissingFrame { index: k, path })
            }
            Err(cause) => {
                return Err(RecordingError::Io {
                    path,
                    cause: std::io::Error::new(
                        cause.kind(),
                        format!("(frame {k}) {}", crate::files::io_cause(&cause)),
                    ),
                })
            }
        };
        decode_frame(&self.manifest, k, &bytes, &path)
    }

    /// The recording's identity, written as the run id of every packet stream made from it
    /// (`reconstruct` on the host, the firmware through the feed). A camera of an array board
    /// recording: the board identity in its manifest (`board_id`), the same for every camera
    /// of the board and unchanged by a calibration put into the manifest. Otherwise FNV-1a 64
    /// of the manifest in its canonical JSON form (camera, calibration, processing, every
    /// frame's file, seq and latch). Two streams of one recording carry the same id, streams
    /// of two boards (or two passes of one board) different ones, so a receiver can tell them
    /// apart.
    pub fn run_id(&self) -> u64 {
        if let Some(b) = self.manifest.board_id {
            return b.0;
        }
        let json = serde_json::to_vec(&self.manifest).unwrap_or_default();
        dpsa_core::frames::fnv1a64(&json)
    }

    /// Reads the simulator ground truth, `Ok(None)` if the manifest has no `truth` block.
    pub fn truth(&self) -> Result<Option<Truth>, RecordingError> {
        let Some(info) = &self.manifest.truth else {
            return Ok(None);
        };
        let (rows, width) = (info.rows as usize, self.width());
        let read = |name: &str| read_f32(&self.dir.join(name), rows * width);
        Ok(Some(Truth {
            first_row: info.first_row,
            rows,
            width,
            height_um: read(TRUTH_HEIGHT_FILE)?,
            background: read(TRUTH_BACKGROUND_FILE)?,
            contrast: read(TRUTH_CONTRAST_FILE)?,
        }))
    }
}

impl Frame {
    /// Image row `r` (`width` samples, DN). Panics if `r >= rows`.
    pub fn row(&self, r: usize) -> &[u16] {
        &self.data[r * self.width..(r + 1) * self.width]
    }
}

impl Truth {
    /// Index into the truth arrays of board row `b`, column `c`, if inside the truth area.
    pub fn index(&self, b: i64, c: usize) -> Option<usize> {
        let i = b.checked_sub(self.first_row)?;
        (i >= 0 && (i as u64) < self.rows as u64 && c < self.width)
            .then(|| i as usize * self.width + c)
    }
}

/// Reads a raw little-endian f32 file that must hold exactly `count` values.
pub fn read_f32(path: &Path, count: usize) -> Result<Vec<f32>, RecordingError> {
    let expected = count as u64 * 4;
    let meta = crate::files::check_regular(path).map_err(io_err(path))?;
    if meta.len() != expected {
        return Err(RecordingError::TruthLength {
            path: path.to_path_buf(),
            expected,
            actual: meta.len(),
        });
    }
    let bytes = crate::files::read_capped_io(path, expected).map_err(io_err(path))?;
    if bytes.len() as u64 != expected {
        return Err(RecordingError::TruthLength {
            path: path.to_path_buf(),
            expected,
            actual: bytes.len() as u64,
        });
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

/// Writes `data` as raw little-endian f32 (the truth file format).
pub fn write_f32(path: &Path, data: &[f32]) -> Result<(), RecordingError> {
    crate::files::write_atomic(path, |w| {
        for v in data {
            w.write_all(&v.to_le_bytes())?;
        }
        Ok::<(), std::io::Error>(())
    })
    .map_err(|e| RecordingError::Write {
        path: path.to_path_buf(),
        message: format!("{:#}", anyhow::Error::new(e)),
    })
}

/// Writes a `rows x width` frame (row-major, DN) as a 16-bit greyscale PNG with fast compression.
pub fn write_frame_png(
    path: &Path,
    rows: usize,
    width: usize,
    data: &[u16],
) -> Result<(), RecordingError> {
    let bad = |message: String| RecordingError::BadData {
        path: path.to_path_buf(),
        message,
    };
    if rows == 0 || width == 0 || rows > u32::MAX as usize || width > u32::MAX as usize {
        return Err(bad(format!("cannot write a {rows} x {width} frame")));
    }
    if rows.checked_mul(width) != Some(data.len()) {
        return Err(bad(format!(
            "{} samples for a {rows} x {width} frame",
            data.len()
        )));
    }
    let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_ne_bytes()).collect();
    crate::files::write_atomic(path, |w| {
        PngEncoder::new_with_quality(&mut *w, CompressionType::Fast, FilterType::Sub).write_image(
            &bytes,
            width as u32,
            rows as u32,
            ExtendedColorType::L16,
        )
    })
    .map_err(|e| RecordingError::Write {
        path: path.to_path_buf(),
        // Through anyhow for the whole `source()` chain of a non-I/O encoder error.
        message: format!("{:#}", anyhow::Error::new(e)),
    })
}

/// Decodes the PNG `bytes` of frame `k` of `manifest` (the file at `path`, named in errors):
/// checks its size against the camera before decoding (the decoder may allocate no more than
/// the frame's size cap), its colour type against the bit depth and every sample's range.
///
/// Accepts 16-bit greyscale PNG, and 8-bit greyscale PNG only when `bit_depth` is 8.
pub fn decode_frame(
    manifest: &Manifest,
    k: usize,
    bytes: &[u8],
    path: &Path,
) -> Result<Frame, RecordingError> {
    let entry = manifest.frames.get(k).ok_or(RecordingError::FrameIndex {
        index: k,
        count: manifest.frames.len(),
    })?;
    let (rows, width) = (
        manifest.camera.rows as usize,
        manifest.camera.width as usize,
    );
    let cap = crate::files::max_frame_png_bytes(rows, width);
    let path = path.to_path_buf();
    if path
        .extension()
        .is_some_and(|e| e == crate::array::frames::EXTENSION)
    {
        return decode_zfr(manifest, k, bytes, path, (entry.seq, entry.latch));
    }
    let decode_err = |e: image::ImageError| RecordingError::Decode {
        index: k,
        path: path.clone(),
        message: e.to_string(),
    };
    // Dimensions are checked against the camera below, before the pixels are decoded;
    // the decoder itself may allocate no more than the frame's size cap.
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(cap);
    let decoder = PngDecoder::with_limits(Cursor::new(bytes), limits).map_err(decode_err)?;
    let (w, h) = decoder.dimensions();
    if (h as usize, w as usize) != (rows, width) {
        return Err(RecordingError::FrameSize {
            index: k,
            path,
            expected_rows: rows,
            expected_width: width,
            actual_rows: h as usize,
            actual_width: w as usize,
        });
    }
    let bit_depth = manifest.camera.bit_depth;
    let color = decoder.color_type();
    let data: Vec<u16> = match color {
        ColorType::L16 => {
            let mut buf = vec![0u8; rows * width * 2];
            decoder.read_image(&mut buf).map_err(decode_err)?;
            buf.chunks_exact(2)
                .map(|b| u16::from_ne_bytes([b[0], b[1]]))
                .collect()
        }
        ColorType::L8 if bit_depth == 8 => {
            let mut buf = vec![0u8; rows * width];
            decoder.read_image(&mut buf).map_err(decode_err)?;
            buf.into_iter().map(u16::from).collect()
        }
        other => {
            return Err(RecordingError::BitDepth {
                index: k,
                path,
                found: format!("{other:?}"),
                bit_depth,
            })
        }
    };
    in_range(
        k,
        path,
        bit_depth,
        (entry.seq, entry.latch),
        rows,
        width,
        data,
    )
}

/// The decoded samples as a [`Frame`], refused when a sample exceeds `2^bit_depth - 1`.
fn in_range(
    k: usize,
    path: PathBuf,
    bit_depth: u8,
    (seq, latch): (u32, i64),
    rows: usize,
    width: usize,
    data: Vec<u16>,
) -> Result<Frame, RecordingError> {
    let max = max_value(bit_depth);
    if let Some(i) = data.iter().position(|&v| v > max) {
        return Err(RecordingError::PixelRange {
            index: k,
            path,
            row: i / width,
            col: i % width,
            value: data[i],
            bit_depth,
            max,
        });
    }
    Ok(Frame {
        seq,
        latch,
        rows,
        width,
        data,
    })
}

/// [`decode_frame`] for a `.zfr` binary frame (`crate::array::frames`).
fn decode_zfr(
    manifest: &Manifest,
    k: usize,
    bytes: &[u8],
    path: PathBuf,
    (seq, latch): (u32, i64),
) -> Result<Frame, RecordingError> {
    use crate::array::frames;
    let (rows, width) = (
        manifest.camera.rows as usize,
        manifest.camera.width as usize,
    );
    let decode_err = |message: String| RecordingError::Decode {
        index: k,
        path: path.clone(),
        message,
    };
    let (h, w) = frames::header(bytes).map_err(decode_err)?;
    if (h, w) != (rows, width) {
        return Err(RecordingError::FrameSize {
            index: k,
            path,
            expected_rows: rows,
            expected_width: width,
            actual_rows: h,
            actual_width: w,
        });
    }
    let data = frames::decode_body(bytes, rows, width).map_err(decode_err)?;
    let bit_depth = manifest.camera.bit_depth;
    in_range(k, path, bit_depth, (seq, latch), rows, width, data)
}

/// Loads every frame of a recording (the f64 reference needs them all at once).
pub fn load_frames(rec: &Recording, progress: bool) -> anyhow::Result<Vec<Frame>> {
    let bar =
        crate::progress::progress_bar(progress, rec.manifest.frames.len() as u64, "load frames");
    let mut frames = Vec::with_capacity(rec.manifest.frames.len());
    for k in 0..rec.manifest.frames.len() {
        frames.push(rec.frame(k)?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(frames)
}

#[cfg(test)]
mod tests {
    use super::*;

    const ROWS: usize = 3;
    const WIDTH: usize = 5;

    fn manifest(frames: usize) -> Manifest {
        Manifest {
            format: FORMAT.into(),
            version: VERSION,
            camera: Camera {
                id: 0,
                width: WIDTH as u32,
                rows: ROWS as u32,
                bit_depth: 12,
                saturation: 4095,
            },
            calibration: Calibration {
                counts_per_pixel: 10.25,
                fringe_period_px: 32.0,
                reference_phase_rad: vec![0.1; WIDTH],
                height_per_turn_um: 500.0,
                height_lsb_um: 0.25,
                height_per_turn_um_per_column: None,
            },
            processing: Processing {
                n: 4,
                max_step_rows: 2,
                min_modulation: 60.0,
                max_noise_gain: 2.0,
            },
            frames: (0..frames)
                .map(|k| FrameEntry {
                    seq: k as u32,
                    latch: 10 * k as i64,
                    file: format!("frames/{k:06}.png"),
                })
                .collect(),
            noise: Some(Noise {
                gain_e_per_dn: 3.0,
                read_noise_dn: 3.0,
            }),
            truth: Some(TruthInfo {
                first_row: 0,
                rows: 2,
            }),
            board_id: None,
        }
    }

    fn frame_data(k: usize) -> Vec<u16> {
        (0..ROWS * WIDTH).map(|i| (i * 200 + k) as u16).collect()
    }

    /// Writes a complete tiny recording and returns its directory.
    fn write_recording(m: &Manifest) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("frames")).unwrap();
        std::fs::create_dir_all(dir.path().join("truth")).unwrap();
        for (k, f) in m.frames.iter().enumerate() {
            write_frame_png(&dir.path().join(&f.file), ROWS, WIDTH, &frame_data(k)).unwrap();
        }
        let n = 2 * WIDTH;
        write_f32(&dir.path().join(TRUTH_HEIGHT_FILE), &vec![1.5; n]).unwrap();
        write_f32(&dir.path().join(TRUTH_BACKGROUND_FILE), &vec![1800.0; n]).unwrap();
        write_f32(&dir.path().join(TRUTH_CONTRAST_FILE), &vec![700.0; n]).unwrap();
        m.save(dir.path()).unwrap();
        dir
    }

    #[test]
    fn round_trip() {
        let m = manifest(3);
        let dir = write_recording(&m);
        let rec = Recording::open(dir.path()).unwrap();
        assert_eq!(rec.manifest, m);
        assert_eq!(rec.len(), 3);
        for k in 0..3 {
            let f = rec.frame(k).unwrap();
            assert_eq!(
                (f.seq, f.latch, f.rows, f.width),
                (k as u32, 10 * k as i64, ROWS, WIDTH)
            );
            assert_eq!(f.data, frame_data(k));
        }
        assert!(matches!(
            rec.frame(3),
            Err(RecordingError::FrameIndex { index: 3, count: 3 })
        ));
        let t = rec.truth().unwrap().unwrap();
        assert_eq!((t.first_row, t.rows, t.width), (0, 2, WIDTH));
        assert_eq!(t.height_um, vec![1.5; 2 * WIDTH]);
        assert_eq!(t.contrast[3], 700.0);
        assert_eq!(t.index(1, 4), Some(9));
        assert_eq!(t.index(2, 0), None);
    }

    #[test]
    fn board_id_is_the_run_id_when_present_and_absent_otherwise() {
        let mut m = manifest(2);
        // A single-camera manifest has no board id: its JSON and run id are as before.
        let json = serde_json::to_string(&m).unwrap();
        assert!(!json.contains("board_id"));
        let rec = Recording {
            dir: PathBuf::new(),
            manifest: m.clone(),
            preloaded: None,
        };
        assert_eq!(rec.run_id(), dpsa_core::frames::fnv1a64(json.as_bytes()));
        // With one, the run id is it, whatever the calibration says.
        m.board_id = Some(BoardId(0x0123_4567_89ab_cdef));
        let json = serde_json::to_string(&m).unwrap();
        assert!(json.contains(r#""board_id":"0123456789abcdef""#), "{json}");
        let back: Manifest = serde_json::from_str(&json).unwrap();
        assert_eq!(back, m);
        let mut rec = Recording {
            dir: PathBuf::new(),
            manifest: m,
            preloaded: None,
        };
        assert_eq!(rec.run_id(), 0x0123_4567_89ab_cdef);
        rec.manifest.calibration.fringe_period_px = 31.0;
        assert_eq!(rec.run_id(), 0x0123_4567_89ab_cdef);
        // Anything but 16 hex digits, or 0, is refused with the key named.
        for bad in [
            "\"123\"",
            "\"0000000000000000\"",
            "\"0123456789abcdeg\"",
            "12",
        ] {
            let text = json.replace("\"0123456789abcdef\"", bad);
            let e = Manifest::parse(text.as_bytes(), Path::new("m.json")).unwrap_err();
            assert!(e.to_string().contains("board_id"), "{bad}: {e}");
        }
    }

    #[test]
    fn truncated_png_is_an_error() {
        let dir = write_recording(&manifest(2));
        let path = dir.path().join("frames/000001.png");
        let bytes = std::fs::read(&path).unwrap();
        let rec = Recording::open(dir.path()).unwrap();
        for len in [0, 8, 30, bytes.len() / 2, bytes.len() - 13] {
            std::fs::write(&path, &bytes[..len]).unwrap();
            let err = rec.frame(1).unwrap_err();
            assert!(
                matches!(err, RecordingError::Decode { index: 1, .. }),
                "len {len}: {err}"
            );
        }
        std::fs::remove_file(&path).unwrap();
        assert!(matches!(
            rec.frame(1),
            Err(RecordingError::MissingFrame { index: 1, .. })
        ));
        assert!(rec.frame(0).is_ok());
    }

    #[test]
    fn wrong_frame_size() {
        let dir = write_recording(&manifest(2));
        write_frame_png(
            &dir.path().join("frames/000000.png"),
            ROWS + 1,
            WIDTH,
            &[0; (ROWS + 1) * WIDTH],
        )
        .unwrap();
        let err = Recording::open(dir.path()).unwrap().frame(0).unwrap_err();
        assert!(
            matches!(
                err,
                RecordingError::FrameSize {
                    actual_rows: 4,
                    expected_rows: 3,
                    actual_width: 5,
                    ..
                }
            ),
            "{err}"
        );
        assert!(
            err.to_string()
                .contains("4 rows x 5 columns, expected 3 x 5"),
            "{err}"
        );
    }

    #[test]
    fn pixel_above_bit_depth() {
        let dir = write_recording(&manifest(1));
        let mut data = frame_data(0);
        data[7] = 4096;
        write_frame_png(&dir.path().join("frames/000000.png"), ROWS, WIDTH, &data).unwrap();
        let err = Recording::open(dir.path()).unwrap().frame(0).unwrap_err();
        assert!(
            matches!(
                err,
                RecordingError::PixelRange {
                    row: 1,
                    col: 2,
                    value: 4096,
                    max: 4095,
                    ..
                }
            ),
            "{err}"
        );
    }

    #[test]
    fn unknown_manifest_key() {
        let dir = write_recording(&manifest(1));
        let path = dir.path().join(MANIFEST_FILE);
        let text = std::fs::read_to_string(&path).unwrap();
        std::fs::write(
            &path,
            text.replace("\"min_modulation\"", "\"min_modulaton\""),
        )
        .unwrap();
        let err = Recording::open(dir.path()).unwrap_err();
        assert!(matches!(err, RecordingError::Json { .. }), "{err}");
        assert!(err.to_string().contains("min_modulaton"), "{err}");
    }

    #[test]
    fn non_increasing_seq() {
        for seqs in [[0, 1, 1], [0, 2, 1]] {
            let mut m = manifest(3);
            for (f, s) in m.frames.iter_mut().zip(seqs) {
                f.seq = s;
            }
            let dir = write_recording(&m);
            let err = Recording::open(dir.path()).unwrap_err();
            assert!(
                matches!(&err, RecordingError::Invalid { field, .. } if field == "frames[2].seq"),
                "{err}"
            );
        }
        // Gaps (lost frames) and repeated / decreasing latches are fine.
        let mut m = manifest(3);
        m.frames[2].seq = 7;
        m.frames[1].latch = 0;
        m.frames[2].latch = -5;
        Recording::open(write_recording(&m).path()).unwrap();
    }

    #[test]
    fn invalid_values() {
        type Edit = fn(&mut Manifest);
        let cases: Vec<(Edit, &str)> = vec![
            (|m| m.format = "other".into(), "format"),
            (|m| m.version = 2, "version"),
            (|m| m.camera.width = 0, "camera.width"),
            (|m| m.camera.bit_depth = 17, "camera.bit_depth"),
            (|m| m.calibration.counts_per_pixel = 0.1, "counts_per_pixel"),
            (
                |m| {
                    m.calibration
                        .reference_phase_rad
                        .pop()
                        .map(drop)
                        .unwrap_or(())
                },
                "reference_phase_rad",
            ),
            (|m| m.calibration.height_lsb_um = 0.01, "height_per_turn_um"),
            (|m| m.processing.n = 9, "processing.n"),
            (
                |m| m.processing.max_step_rows = 4,
                "processing.max_step_rows",
            ),
            (|m| m.processing.max_noise_gain = f64::NAN, "max_noise_gain"),
            (|m| m.frames.clear(), "frames"),
            (|m| m.truth.as_mut().unwrap().rows = 0, "truth.rows"),
        ];
        for (edit, needle) in cases {
            let mut m = manifest(1);
            edit(&mut m);
            let err = m.validate().unwrap_err();
            assert!(err.to_string().contains(needle), "{needle}: {err}");
        }
    }

    /// `T_z(c)` of a per-column table: +-2 % around 500 um.
    fn per_column(w: usize) -> Vec<f64> {
        (0..w)
            .map(|c| 500.0 * (1.0 + 0.02 * (c as f64 * 1.7).sin()))
            .collect()
    }

    #[test]
    fn per_column_height_per_turn_is_optional_and_keeps_old_manifests() {
        // Without the table nothing is written for it: an old manifest's JSON, hence its run
        // identity, is unchanged; reading it back gives None.
        let m = manifest(1);
        let json = serde_json::to_string(&m).unwrap();
        assert!(!json.contains("per_column"), "{json}");
        let dir = write_recording(&m);
        let rec = Recording::open(dir.path()).unwrap();
        assert_eq!(rec.manifest.calibration.height_per_turn_um_per_column, None);
        assert_eq!(
            rec.run_id(),
            dpsa_core::frames::fnv1a64(&serde_json::to_vec(&m).unwrap())
        );
        assert_eq!(rec.manifest.calibration.height_per_turn_at(3), 500.0);
        // With it: read back, per column, a different run identity.
        let mut t = manifest(1);
        t.calibration.height_per_turn_um_per_column = Some(per_column(WIDTH));
        let dir = write_recording(&t);
        let back = Recording::open(dir.path()).unwrap();
        assert_eq!(back.manifest, t);
        assert_eq!(
            back.manifest.calibration.height_per_turn_at(2),
            per_column(WIDTH)[2]
        );
        assert_ne!(back.run_id(), rec.run_id());
    }

    #[test]
    fn per_column_height_per_turn_is_checked() {
        type Edit = fn(&mut Vec<f64>);
        let f = "calibration.height_per_turn_um_per_column";
        let cases: Vec<(Edit, String, &str)> = vec![
            (
                |t| t.truncate(4),
                f.into(),
                "4 values, expected one per column (5)",
            ),
            (|t| t.push(500.0), f.into(), "6 values"),
            (
                |t| t[1] = 0.0,
                format!("{f}[1]"),
                "expected a finite value > 0",
            ),
            (
                |t| t[2] = -500.0,
                format!("{f}[2]"),
                "expected a finite value > 0",
            ),
            (|t| t[3] = f64::NAN, format!("{f}[3]"), "finite"),
            (|t| t[4] = f64::INFINITY, format!("{f}[4]"), "finite"),
            // 32768 LSB of 0.25 um: beyond the core's i16 turn.
            (|t| t[0] = 8192.0, format!("{f}[0]"), "32768"),
            // More than a factor of 2 from the uniform 500 um.
            (|t| t[2] = 1000.5, format!("{f}[2]"), "factor of 2"),
            (|t| t[4] = 249.0, format!("{f}[4]"), "factor of 2"),
        ];
        for (edit, field, needle) in cases {
            let mut m = manifest(1);
            let mut t = per_column(WIDTH);
            edit(&mut t);
            m.calibration.height_per_turn_um_per_column = Some(t);
            let err = m.validate().unwrap_err();
            assert!(
                matches!(&err, RecordingError::Invalid { field: g, .. } if *g == field),
                "{field}: {err}"
            );
            assert!(err.to_string().contains(needle), "{needle}: {err}");
            // The core's configuration is refused the same way (no panic).
            let e = crate::reconstruct::config(&m).unwrap_err().to_string();
            assert!(e.contains(&field), "{field}: {e}");
        }
        // Exactly a factor of 2 either way is accepted, and the table reaches the core.
        let mut m = manifest(1);
        m.calibration.height_per_turn_um_per_column =
            Some(vec![250.0, 1000.0, 500.0, 499.9, 501.0]);
        m.validate().unwrap();
        let core = crate::reconstruct::config(&m).unwrap();
        let (shift, mant) = core.column_scale.clone().unwrap();
        assert_eq!(mant.len(), WIDTH);
        for (c, &tz) in [250.0, 1000.0, 500.0, 499.9, 501.0].iter().enumerate() {
            let k = core
                .columns()
                .unwrap()
                .lsb_per_turn(c)
                .unwrap()
                .to_num::<f64>();
            let want = tz / 0.25;
            // Q16.16 rounding, then the mantissa's 2^(shift-16) LSB per turn.
            let step = f64::from(1u32 << shift) / 65536.0;
            assert!(
                (k - want).abs() <= step / 2.0 + 1.0 / 131072.0,
                "{c}: {k} {want}"
            );
        }
        assert_eq!(
            core.layout().bytes(),
            dpsa_core::Layout::of(&core.cfg).bytes() + 2 * WIDTH
        );
        // No table: none for the core either.
        let core = crate::reconstruct::config(&manifest(1)).unwrap();
        assert_eq!((&core.column_scale, core.columns()), (&None, None));
    }

    #[test]
    fn truth_of_wrong_length() {
        let dir = write_recording(&manifest(1));
        write_f32(&dir.path().join(TRUTH_CONTRAST_FILE), &[0.0; 3]).unwrap();
        let err = Recording::open(dir.path()).unwrap().truth().unwrap_err();
        assert!(
            matches!(
                err,
                RecordingError::TruthLength {
                    expected: 40,
                    actual: 12,
                    ..
                }
            ),
            "{err}"
        );
    }

    #[test]
    fn missing_manifest() {
        let dir = tempfile::tempdir().unwrap();
        assert!(matches!(
            Recording::open(dir.path()),
            Err(RecordingError::MissingManifest { .. })
        ));
    }
}
