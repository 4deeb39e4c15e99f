//! Recordings on disk: `manifest.json` (its types and checks are `dpsa_formats::recording`,
//! re-exported here), 16-bit PNG or `.zfr` frames and optional ground truth. The format is
//! specified in `docs/recording.md`.

pub use dpsa_formats::recording::*;

use crate::error::chain;
use image::codecs::png::{CompressionType, FilterType, PngDecoder, PngEncoder};
use image::{ColorType, ExtendedColorType, ImageDecoder, ImageEncoder};
use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};

/// An opened, validated recording.
#[derive(Clone, Debug)]
pub struct Recording {
    /// The recording's directory.
    pub dir: PathBuf,
    /// Its `manifest.json`, parsed and validated.
    pub manifest: Manifest,
    /// Every frame decoded in memory ([`Recording::preload`], for benchmarks that time the
    /// processing without the file reading); `None`: frames are read on demand.
    preloaded: Option<std::sync::Arc<Vec<Frame>>>,
}

/// One decoded frame, row-major `rows x width`.
#[derive(Clone, Debug)]
pub struct Frame {
    /// The frame's trigger: camera frame counter (a gap means a lost frame) and the encoder
    /// count latched at it.
    pub trigger: dpsa_core::Trigger,
    /// Rows `H`, px.
    pub rows: usize,
    /// Columns `W`, px.
    pub width: usize,
    /// The samples, DN.
    pub data: Vec<u16>,
}

/// Simulator ground truth on the board grid, row-major `rows x width`.
#[derive(Clone, Debug)]
pub struct CameraTruth {
    /// Board row held at index 0.
    pub first_row: i64,
    /// Board rows held.
    pub rows: usize,
    /// Columns `W`, px.
    pub width: usize,
    /// True height per board pixel, um.
    pub height_um: Vec<f32>,
    /// Background `B` per board pixel, DN.
    pub background: Vec<f32>,
    /// Contrast `C` per board pixel, DN.
    pub contrast: Vec<f32>,
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
    pub fn truth(&self) -> Result<Option<CameraTruth>, RecordingError> {
        let Some(info) = &self.manifest.truth else {
            return Ok(None);
        };
        let (rows, width) = (info.rows as usize, self.width());
        let read = |name: &str| read_f32(&self.dir.join(name), rows * width);
        Ok(Some(CameraTruth {
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

impl CameraTruth {
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
        message: chain(&e),
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
        // The whole `source()` chain of a non-I/O encoder error.
        message: chain(&e),
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
        return decode_zfr(manifest, k, bytes, path, entry.trigger());
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
    in_range(k, path, bit_depth, entry.trigger(), rows, width, data)
}

/// The decoded samples as a [`Frame`], refused when a sample exceeds `2^bit_depth - 1`.
fn in_range(
    k: usize,
    path: PathBuf,
    bit_depth: u8,
    trigger: dpsa_core::Trigger,
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
        trigger,
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
    trigger: dpsa_core::Trigger,
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
    in_range(k, path, bit_depth, trigger, rows, width, data)
}

/// Loads every frame of a recording (the f64 reference needs them all at once).
pub fn load_frames(rec: &Recording, progress: bool) -> crate::Result<Vec<Frame>> {
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
                (f.trigger.seq, f.trigger.latch, f.rows, f.width),
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
