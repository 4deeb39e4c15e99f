//! The board map on disk (`dpsa board --out DIR`):
//!
//! | file | what |
//! | --- | --- |
//! | `heights.png` | 16-bit grey: `round(h / lsb_um) + 32768` (clamped to 1..=65535), 0 invalid |
//! | `heights_um.tiff` | 32-bit float grey, heights in um, NaN invalid (ImageJ, GDAL, numpy + tifffile read it) |
//! | `heights.colour.png` | false colour of the height above the local board surface (the bow removed; the absolute heights with [`Outputs::absolute_colour`]), turned as a Gerber viewer shows the design (x right, y up), axes in mm, a colour bar in um ([`crate::colour`]); by default a preview at most [`PREVIEW_PX`] on its longer side (each pixel the mean of a `k x k` block of the map, `board.json`'s `files.colour_png_scale`), full size with [`Outputs::full_colour`] |
//! | `camera.png` | 8-bit indexed: each pixel's value is its camera's index (255 invalid), and the palette draws the cameras in distinct colours ([`CAMERA_COLOURS`]), invalid dark grey |
//! | `board.json` | [`Metadata`] |
//!
//! Image row `i` is board `x = x0 + (i + 1/2) pitch` (along the motion), column `j` is
//! `y = y0 + (j + 1/2) pitch`.

use crate::blend::{Blended, NO_CAMERA};
use crate::resample::BoardGrid;
use crate::Grid;

use serde::Serialize;
use std::path::Path;

/// Why a board map could not be written.
#[derive(Debug, thiserror::Error)]
pub enum BoardError {
    /// A file or the directory could not be written (the sentence names it).
    #[error(transparent)]
    File(#[from] dpsa_formats::files::FileError),
    /// `board.json` could not be serialised.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// An input refused before any file is written: the calibration, `array.json`, a stream
    /// (one sentence saying which and why).
    #[error("{0}")]
    Refused(String),
    /// The calibration file does not fit the array.
    #[error(transparent)]
    Calibration(#[from] dpsa_formats::calibration::CalError),
    /// `array.json` missing or out of range.
    #[error(transparent)]
    Array(#[from] dpsa_formats::array::ArrayError),
    /// What a caller's hook reported (the simulator's Cramer-Rao bound per pixel).
    #[error(transparent)]
    Hook(Box<dyn std::error::Error + Send + Sync>),
    /// A thread panicked or an invariant broke (a bug: please report it).
    #[error("internal error: {0}")]
    Internal(String),
}

type Result<T> = std::result::Result<T, BoardError>;

/// `valid / total`, 0 for an empty map.
pub fn valid_fraction(valid: u64, total: u64) -> f64 {
    if total > 0 {
        valid as f64 / total as f64
    } else {
        0.0
    }
}

/// LSB of `heights.png`, um: 0.25 um over +-8.19 mm ([`dpsa_formats::height_code`]).
pub const PNG_LSB_UM: f64 = dpsa_formats::height_code::LSB_UM;

/// What `board.json` says about the map.
#[derive(Clone, Debug, Serialize)]
pub struct Metadata {
    /// [`FORMAT`].
    pub format: &'static str,
    /// The layout's version (1).
    pub version: u32,
    /// The board's identity (`array.json`'s `board_id`, 16 hex digits), when the recording has
    /// one: `dpsa inspect` refuses a print truth of another board with it and reports it as the
    /// CFX `UnitIdentifier`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub board_id: Option<dpsa_formats::BoardId>,
    /// Where the map's pixels lie on the board, mm.
    pub grid: BoardGrid,
    /// Units of every height file.
    pub units: Units,
    /// Pixel counts.
    pub pixels: Pixels,
    /// Whole turns each camera's layer was moved by, in camera order.
    pub turns: Vec<i32>,
    /// Board rows each camera's input lacked (`dpsa board --streams`: missing or damaged
    /// packets, a truncated stream), in camera order; their board pixels are invalid (0 in
    /// `heights.png`, NaN in the TIFF) unless another camera saw them. All 0 for a complete
    /// map.
    pub missing_rows: Vec<u64>,
    /// The files written.
    pub files: Files,
}

/// The units of `board.json` and the height files.
#[derive(Clone, Debug, Serialize)]
pub struct Units {
    /// Of lengths (`mm`).
    pub lengths: &'static str,
    /// Of heights (`um`).
    pub heights: &'static str,
    /// `heights.png`: height = (value - 32768) * lsb_um; value 0 is invalid.
    pub png_lsb_um: f64,
    /// The value of height 0 in `heights.png` (32768).
    pub png_zero: u16,
}

/// The map's pixel counts.
#[derive(Clone, Debug, Serialize)]
pub struct Pixels {
    /// Board grid pixels.
    pub total: u64,
    /// Of which valid (a finite height).
    pub valid: u64,
    /// `valid / total` (0 for an empty grid).
    pub valid_fraction: f64,
    /// Valid pixels per camera (the camera each came from).
    pub per_camera: Vec<u64>,
}

/// The files of the map directory, by role.
#[derive(Clone, Debug, Serialize)]
pub struct Files {
    /// 16-bit heights ([`Units::png_lsb_um`], 0 invalid).
    pub heights_png: &'static str,
    /// 32-bit float heights, um (NaN invalid).
    pub heights_tiff: &'static str,
    /// False colour with axes and a colour bar.
    pub colour_png: &'static str,
    /// What the false colour shows.
    pub colour_png_shows: crate::colour::Shows,
    /// Map pixels per pixel of the false-colour image along each axis (1: full size; a
    /// preview's pixel is the mean of the valid heights of its `k x k` block).
    pub colour_png_scale: usize,
    /// The camera each pixel came from.
    pub camera_png: &'static str,
}

pub use dpsa_formats::board_map::{colour_range, FORMAT};

/// Longer side of the default false-colour preview, px.
pub const PREVIEW_PX: usize = 2048;

/// What to write besides the cheap default files (measured on the paper board's 47 Mpx map,
/// `timing.files_s` of `dpsa board --json`): the TIFF (0.15 s: uncompressed, and what
/// `dpsa inspect` reads), `heights.png` (0.25 - 0.32 s: 95 MB of 16-bit samples through PNG's
/// fastest compression, encoded in a thread of its own beside the other files), `camera.png`
/// (0.03 s, indexed), a false-colour preview above the local surface (0.35 - 0.45 s) are
/// always written (about 0.6 s of wall time for all of them); the full-size false colour on
/// request.
#[derive(Clone, Copy, Debug, Default)]
pub struct Outputs {
    /// `heights.colour.png` at the map's full size, not a preview.
    pub full_colour: bool,
    /// `heights.colour.png` of the absolute heights, not of the height above the local board
    /// surface.
    pub absolute_colour: bool,
}

/// The cameras' colours in `camera.png`'s palette, camera `k` the `k % 8`-th (Okabe and
/// Ito's eight, told apart with the common colour-vision deficiencies).
pub const CAMERA_COLOURS: [[u8; 3]; 8] = [
    [230, 159, 0],
    [86, 180, 233],
    [0, 158, 115],
    [240, 228, 66],
    [0, 114, 178],
    [213, 94, 0],
    [204, 121, 167],
    [0, 0, 0],
];

/// The files [`write`](fn@write) writes into its directory.
pub const FILE_NAMES: [&str; 5] = [
    "heights.png",
    "heights_um.tiff",
    "heights.colour.png",
    "camera.png",
    "board.json",
];

/// Whether `dir` holds a board map (its `board.json` of format [`FORMAT`]): an earlier map,
/// which a new one may replace.
pub fn is_board_map(dir: &Path) -> bool {
    dpsa_formats::files::read_capped_io(&dir.join("board.json"), 1 << 20)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .is_some_and(|v| v.get("format").and_then(|f| f.as_str()) == Some(FORMAT))
}

/// Refuses (before any work) a destination that a board map may not replace: a file, or a
/// non-empty directory holding no earlier map (see [`dpsa_formats::files::OutputDir`]).
pub fn check_destination(dir: &Path) -> Result<()> {
    Ok(dpsa_formats::files::check_output_dir(dir, DIR_KIND)?)
}

/// A board map directory, for [`dpsa_formats::files::OutputDir`].
pub const DIR_KIND: dpsa_formats::files::DirKind = dpsa_formats::files::DirKind {
    format: FORMAT,
    noun: "board map",
    ours: is_board_map,
};

/// Writes the map into `dir`, whole or not at all: built in a hidden directory beside it and
/// swapped in at the end (an earlier map there is replaced, see [`dpsa_formats::files::OutputDir`]);
/// returns the metadata.
pub fn write(
    dir: &Path,
    grid: &BoardGrid,
    b: &Blended,
    cameras: usize,
    missing_rows: &[u64],
    board_id: Option<dpsa_formats::BoardId>,
    outputs: Outputs,
) -> Result<Written> {
    let staging = dpsa_formats::files::OutputDir::create(dir, DIR_KIND)?;
    let written = write_files(
        staging.path(),
        grid,
        b,
        cameras,
        missing_rows,
        board_id,
        outputs,
    )?;
    staging.commit()?;
    Ok(written)
}

/// What [`write`](fn@write) wrote: `board.json`'s metadata, and the seconds each file took
/// (rendering and encoding included), by file name, in the order written.
#[derive(Clone, Debug)]
pub struct Written {
    /// `board.json`.
    pub meta: Metadata,
    /// Seconds per file.
    pub seconds: Vec<(&'static str, f64)>,
}

fn write_files(
    dir: &Path,
    grid: &BoardGrid,
    b: &Blended,
    cameras: usize,
    missing_rows: &[u64],
    board_id: Option<dpsa_formats::BoardId>,
    outputs: Outputs,
) -> Result<Written> {
    let h = &b.heights;
    let colour_scale = if outputs.full_colour {
        1
    } else {
        h.width.max(h.rows).div_ceil(PREVIEW_PX).max(1)
    };
    let files = Files {
        heights_png: "heights.png",
        heights_tiff: "heights_um.tiff",
        colour_png: "heights.colour.png",
        colour_png_shows: if outputs.absolute_colour {
            crate::colour::Shows::Absolute
        } else {
            crate::colour::Shows::AboveLocalSurface
        },
        colour_png_scale: colour_scale,
        camera_png: "camera.png",
    };
    let (w, rows) = (h.width as u32, h.rows as u32);
    // `heights.png` (the largest encoding) in a thread of its own beside the other files;
    // each file's seconds are its own.
    let timed = |name: &'static str, f: &dyn Fn() -> Result<()>| -> Result<(&'static str, f64)> {
        let t = std::time::Instant::now();
        f()?;
        Ok((name, t.elapsed().as_secs_f64()))
    };
    let (png, rest) = std::thread::scope(|s| {
        let png = s.spawn(|| {
            timed(files.heights_png, &|| {
                dpsa_formats::images::save_png16_rows(
                    &dir.join(files.heights_png),
                    h.width,
                    h.rows,
                    |i, out| {
                        let row = &h.data[i * h.width..(i + 1) * h.width];
                        dpsa_formats::height_code::code_clamped(row, out);
                    },
                )?;
                Ok(())
            })
        });
        let rest = (|| -> Result<Vec<(&'static str, f64)>> {
            Ok(vec![
                timed(files.heights_tiff, &|| {
                    write_tiff(&dir.join(files.heights_tiff), h)
                })?,
                timed(files.colour_png, &|| {
                    let preview;
                    let shown = if colour_scale == 1 {
                        h
                    } else {
                        preview = block_mean(h, colour_scale);
                        &preview
                    };
                    let v = crate::colour::view(shown, grid, colour_scale, files.colour_png_shows);
                    Ok(dpsa_formats::images::save_png(
                        &v.image,
                        &dir.join(files.colour_png),
                    )?)
                })?,
                timed(files.camera_png, &|| {
                    let mut palette = vec![[40u8; 3]; 256];
                    for (k, c) in palette.iter_mut().take(255).enumerate() {
                        *c = CAMERA_COLOURS[k % CAMERA_COLOURS.len()];
                    }
                    Ok(dpsa_formats::images::save_png_indexed(
                        &dir.join(files.camera_png),
                        w,
                        rows,
                        &b.camera,
                        &palette,
                    )?)
                })?,
            ])
        })();
        (png.join(), rest)
    });
    let png = png.map_err(|_| BoardError::Internal("the heights.png thread panicked".into()))??;
    let mut seconds = vec![png];
    seconds.extend(rest?);
    let t = std::time::Instant::now();

    let mut per_camera = vec![0u64; cameras];
    for &c in &b.camera {
        if c != NO_CAMERA {
            if let Some(n) = per_camera.get_mut(usize::from(c)) {
                *n += 1;
            }
        }
    }
    let valid = h.valid() as u64;
    let total = h.data.len() as u64;
    let meta = Metadata {
        format: FORMAT,
        version: 1,
        board_id,
        grid: *grid,
        units: Units {
            lengths: "mm",
            heights: "um",
            png_lsb_um: PNG_LSB_UM,
            png_zero: dpsa_formats::height_code::ZERO,
        },
        pixels: Pixels {
            total,
            valid,
            valid_fraction: valid_fraction(valid, total),
            per_camera,
        },
        turns: b.turns.clone(),
        missing_rows: missing_rows.to_vec(),
        files,
    };
    let json = serde_json::to_string_pretty(&meta)?;
    dpsa_formats::files::write_bytes(&dir.join("board.json"), json.as_bytes())?;
    seconds.push(("board.json", t.elapsed().as_secs_f64()));
    Ok(Written { meta, seconds })
}

/// Heights as a 32-bit float TIFF, um (NaN invalid).
pub fn write_tiff(path: &Path, h: &Grid) -> Result<()> {
    Ok(dpsa_formats::files::write_atomic(path, |f| {
        let mut enc = tiff::encoder::TiffEncoder::new(f)?;
        enc.write_image::<tiff::encoder::colortype::Gray32Float>(
            h.width as u32,
            h.rows as u32,
            &h.data,
        )?;
        Ok::<(), tiff::TiffError>(())
    })?)
}

/// The mean of the valid heights of each `k x k` block of `h` (NaN where none is valid); the
/// last row and column of blocks may be cut short.
pub fn block_mean(h: &Grid, k: usize) -> Grid {
    let k = k.max(1);
    let (w, rows) = (h.width.div_ceil(k), h.rows.div_ceil(k));
    let mut sum = vec![0f64; w * rows];
    let mut n = vec![0u32; w * rows];
    for r in 0..h.rows {
        let row = &h.data[r * h.width..(r + 1) * h.width];
        let out = (r / k) * w;
        for (c, &v) in row.iter().enumerate() {
            if v.is_finite() {
                sum[out + c / k] += f64::from(v);
                n[out + c / k] += 1;
            }
        }
    }
    Grid {
        width: w,
        rows,
        data: sum
            .iter()
            .zip(&n)
            .map(|(&s, &n)| {
                if n > 0 {
                    (s / f64::from(n)) as f32
                } else {
                    f32::NAN
                }
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_read_back_with_the_documented_encoding() {
        let dir = tempfile::tempdir().unwrap();
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 30,
            width: 40,
        };
        let mut h = Grid::invalid(40, 30);
        for (i, v) in h.data.iter_mut().enumerate() {
            if i % 7 != 0 {
                *v = (i as f32) * 0.75 - 300.0;
            }
        }
        let b = Blended {
            variance: None,
            camera: h
                .data
                .iter()
                .enumerate()
                .map(|(i, v)| {
                    if v.is_finite() {
                        (i % 40 / 20) as u8
                    } else {
                        NO_CAMERA
                    }
                })
                .collect(),
            heights: h.clone(),
            turns: vec![0, 1],
            edge_median_um: Some(0.0),
            edge_off_bands: 0,
            seams: Vec::new(),
        };
        let id = dpsa_formats::BoardId(0x0123_4567_89ab_cdef);
        let meta = write(
            dir.path(),
            &grid,
            &b,
            2,
            &[0, 0],
            Some(id),
            Outputs::default(),
        )
        .unwrap()
        .meta;
        assert_eq!(meta.pixels.valid, h.valid() as u64);
        assert_eq!(
            meta.pixels.per_camera.iter().sum::<u64>(),
            meta.pixels.valid
        );

        let png = image::open(dir.path().join("heights.png"))
            .unwrap()
            .into_luma16();
        let f = std::fs::File::open(dir.path().join("heights_um.tiff")).unwrap();
        let mut dec = tiff::decoder::Decoder::new(std::io::BufReader::new(f)).unwrap();
        let tiff::decoder::DecodingResult::F32(t) = dec.read_image().unwrap() else {
            panic!("not f32")
        };
        for (i, v) in h.data.iter().enumerate() {
            let p = png.as_raw()[i];
            if v.is_finite() {
                let back = (f64::from(p) - 32768.0) * PNG_LSB_UM;
                assert!((back - f64::from(*v)).abs() <= PNG_LSB_UM / 2.0 + 1e-9);
                assert_eq!(t[i], *v);
            } else {
                assert_eq!(p, 0);
                assert!(t[i].is_nan());
            }
        }
        let colour = image::open(dir.path().join("heights.colour.png")).unwrap();
        let (pw, ph) = (30, 40);
        assert!(
            colour.width() > pw && colour.height() > ph,
            "the map with its margins"
        );
        // camera.png: the camera's index per pixel, drawn through the palette.
        let (idx, palette) =
            dpsa_formats::images::read_png_indexed(&dir.path().join("camera.png")).unwrap();
        assert_eq!(idx, b.camera);
        assert_eq!(palette[0], CAMERA_COLOURS[0]);
        assert_eq!(palette[usize::from(NO_CAMERA)], [40; 3]);
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.path().join("board.json")).unwrap())
                .unwrap();
        assert_eq!(v["format"], FORMAT);
        assert_eq!(v["board_id"], "0123456789abcdef");
        assert_eq!(v["grid"]["pitch_mm"], 0.03);
        assert_eq!(v["files"]["colour_png_scale"], 1);
    }

    /// A map longer than [`PREVIEW_PX`] gets a preview of block means (the same colour scale
    /// as the full map), unless the full size is asked for; the report times every file.
    #[test]
    fn a_large_map_gets_a_preview_unless_the_full_colour_is_asked_for() {
        let (w, rows) = (3, 2 * PREVIEW_PX + 5);
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows,
            width: w,
        };
        let mut h = Grid::invalid(w, rows);
        for (i, v) in h.data.iter_mut().enumerate() {
            if i % 5 != 0 {
                *v = (i % 97) as f32;
            }
        }
        let b = Blended {
            variance: None,
            camera: vec![0; w * rows],
            heights: h.clone(),
            turns: vec![0],
            edge_median_um: None,
            edge_off_bands: 0,
            seams: Vec::new(),
        };
        let k = rows.div_ceil(PREVIEW_PX);
        assert_eq!(k, 3);
        for full in [false, true] {
            let dir = tempfile::tempdir().unwrap();
            let out = dir.path().join("map");
            let written = write(
                &out,
                &grid,
                &b,
                1,
                &[0],
                None,
                Outputs {
                    full_colour: full,
                    absolute_colour: false,
                },
            )
            .unwrap();
            let names: Vec<&str> = written.seconds.iter().map(|f| f.0).collect();
            assert_eq!(names, FILE_NAMES, "every file timed, in order");
            let colour = image::open(out.join("heights.colour.png")).unwrap();
            let want = if full {
                (w, rows)
            } else {
                (1, rows.div_ceil(k))
            };
            // Turned: the map's rows run across the image, inside its margins.
            assert!(
                colour.width() as usize > want.1 && colour.height() as usize > want.0,
                "{want:?} in {:?}",
                (colour.width(), colour.height())
            );
            assert_eq!(
                written.meta.files.colour_png_scale,
                if full { 1 } else { k }
            );
        }
        // Block means: NaN only where the whole block is invalid.
        let m = block_mean(&h, k);
        assert_eq!((m.width, m.rows), (1, rows.div_ceil(k)));
        for (bi, &v) in m.data.iter().enumerate() {
            let vals: Vec<f64> = (bi * k..((bi + 1) * k).min(rows))
                .flat_map(|r| (0..w).map(move |c| r * w + c))
                .map(|i| h.data[i])
                .filter(|v| v.is_finite())
                .map(f64::from)
                .collect();
            let mean = vals.iter().sum::<f64>() / vals.len() as f64;
            assert!((f64::from(v) - mean).abs() < 1e-4, "block {bi}");
        }
    }
}
