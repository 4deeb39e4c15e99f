//! A board's measured map as the line keeps it for its pages (`[maps]` of `LINE.toml`, the
//! board page's zoom and pan): two files per board in the maps directory, named by the line
//! and the board's store id only (a line name is letters, digits, `-`, `_` and `.`; the id an
//! integer), so lines sharing a directory keep and prune their own.
//!
//! - `LINE.board-ID.heights.png`: the heights as a 16-bit grey PNG in the board map's
//!   `heights.png` convention (value `h / 0.25 um + 32768`, 0 invalid), the map's rows as the
//!   image's rows. A PNG because every image tool opens it and the board map already writes
//!   one; its chunks carry CRCs and its data an Adler-32, so a damaged file is refused.
//! - `LINE.board-ID.json` ([`KeptMap`]): the grid, the quantisation, where the design lies on the
//!   map, and the PNG's length. Written after the PNG, each atomically: a map whose JSON is
//!   there is whole; a PNG without one is an unfinished write, never read.
//!
//! Heights beyond the 16 bits (`|h| > 8191.75 um`, far outside any measuring range) are kept
//! invalid and counted (`clipped`), never stored as the nearest value. The quantisation (0.25
//! um, an error of 0.07 um rms) is a twentieth of a pixel's noise on the paper board.

use crate::files::FileError;
use crate::grid::{BoardGrid, Grid};
use std::io::Read;
use std::path::{Path, PathBuf};

/// The `format` of a kept map's JSON.
pub const FORMAT: &str = "dpsa-kept-map";
/// Its version.
pub const VERSION: u32 = 1;
/// The PNG's height step, um, and its value for a height of zero (0 is invalid): the board
/// map's code ([`crate::height_code`]).
pub use crate::height_code::{LSB_UM, ZERO};
/// Most pixels a kept map may have (a 220 x 168 mm board at 28 um is 48 M).
pub const MAX_PIXELS: u64 = 200_000_000;
/// Largest kept JSON, bytes.
const MAX_JSON: u64 = 64 << 10;

/// A kept map's description (`board-ID.json`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeptMap {
    /// [`FORMAT`].
    pub format: String,
    /// [`VERSION`].
    pub version: u32,
    /// The line that kept it.
    pub line: String,
    /// The board's id in the store.
    pub board: i64,
    /// The board's run id, 16 hex digits.
    pub run_id: String,
    /// The map's grid (rows along the motion, board `x`; columns board `y`).
    pub grid: BoardGrid,
    /// The PNG's height step, um ([`LSB_UM`]).
    pub lsb_um: f64,
    /// The PNG's value of height zero ([`ZERO`]).
    pub zero: u16,
    /// Where the design lies on the map: a design point `p` is at `R(rotation_rad) p + (tx_mm,
    /// ty_mm)` on the board (the inspection's registration); `None` (`null`) when the design
    /// could not be registered on it (the board is incomplete: its map is kept to see why).
    pub design_to_board: Option<DesignToBoard>,
    /// Valid pixels kept.
    pub valid: u64,
    /// Valid pixels beyond the 16 bits, kept invalid.
    pub clipped: u64,
    /// The PNG's length, bytes.
    pub png_bytes: u64,
}

/// The design-to-board transform: a rotation about the design's origin, then a shift.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DesignToBoard {
    /// Counter-clockwise, radians.
    pub rotation_rad: f64,
    /// Shift along board `x`, mm.
    pub tx_mm: f64,
    /// Shift along board `y`, mm.
    pub ty_mm: f64,
}

impl DesignToBoard {
    /// Where design point `(x, y)` (mm) lies on the board, mm.
    pub fn apply(&self, x: f64, y: f64) -> (f64, f64) {
        let (s, c) = self.rotation_rad.sin_cos();
        (c * x - s * y + self.tx_mm, s * x + c * y + self.ty_mm)
    }
}

/// Why a kept map could not be read.
#[derive(Debug, thiserror::Error)]
pub enum KeptMapError {
    /// A file could not be read.
    #[error(transparent)]
    File(#[from] FileError),
    /// A file is not a kept map, or not this one.
    #[error("{}: {why}", .path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// Why, one sentence.
        why: String,
    },
}

/// The PNG and the JSON of line `line`'s board `board` in `dir`.
pub fn paths(dir: &Path, line: &str, board: i64) -> (PathBuf, PathBuf) {
    (
        dir.join(format!("{line}.board-{board}.heights.png")),
        dir.join(format!("{line}.board-{board}.json")),
    )
}

/// Keeps `heights` (um, NaN invalid, on `grid`) as line `line`'s board `board`'s map in
/// `dir`: the PNG, then the JSON, each atomically. The description written.
pub fn write(
    dir: &Path,
    line: &str,
    board: i64,
    run_id: u64,
    grid: &BoardGrid,
    heights: &Grid,
    design_to_board: Option<DesignToBoard>,
) -> Result<KeptMap, FileError> {
    let (png, json) = paths(dir, line, board);
    let (mut valid, mut clipped) = (0u64, 0u64);
    crate::images::save_png16_rows(&png, heights.width, heights.rows, |i, out| {
        let row = &heights.data[i * heights.width..(i + 1) * heights.width];
        let (v, c) = crate::height_code::code_or_clip(row, out);
        valid += v;
        clipped += c;
    })?;
    let png_bytes = std::fs::metadata(&png)
        .map_err(|io| FileError::Write {
            path: png.clone(),
            io,
        })?
        .len();
    let kept = KeptMap {
        format: FORMAT.into(),
        version: VERSION,
        line: line.to_owned(),
        board,
        run_id: format!("{run_id:016x}"),
        grid: *grid,
        lsb_um: LSB_UM,
        zero: ZERO,
        design_to_board,
        valid,
        clipped,
        png_bytes,
    };
    let text =
        serde_json::to_string_pretty(&kept).map_err(|e| crate::files::write_error(&json, e))?;
    crate::files::write_bytes(&json, text.as_bytes())?;
    Ok(kept)
}

/// Line `line`'s board `board`'s kept description, checked; `None` when its map is not kept.
pub fn read_meta(dir: &Path, line: &str, board: i64) -> Result<Option<KeptMap>, KeptMapError> {
    let (_, json) = paths(dir, line, board);
    let bytes = match crate::files::read_capped_io(&json, MAX_JSON) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(io) => {
            return Err(FileError::Read {
                what: "kept map description".into(),
                path: json,
                io,
            }
            .into())
        }
    };
    let bad = |why: String| KeptMapError::Invalid {
        path: json.clone(),
        why,
    };
    let k: KeptMap = serde_json::from_slice(&bytes).map_err(|e| bad(e.to_string()))?;
    if k.format != FORMAT || k.version != VERSION {
        return Err(bad(format!(
            "format {} version {}, not {FORMAT} version {VERSION}",
            k.format, k.version
        )));
    }
    if k.board != board || k.line != line {
        return Err(bad(format!(
            "describes board {} of line {}, not {board} of {line}",
            k.board, k.line
        )));
    }
    if k.lsb_um != LSB_UM || k.zero != ZERO {
        return Err(bad(format!(
            "a height step of {} um from {}, not {LSB_UM} from {ZERO}",
            k.lsb_um, k.zero
        )));
    }
    let g = &k.grid;
    let px = (g.rows as u64).saturating_mul(g.width as u64);
    if g.rows == 0 || g.width == 0 || px > MAX_PIXELS || g.rows > u32::MAX as usize {
        return Err(bad(format!(
            "a grid of {} x {} pixels (1 to {MAX_PIXELS} pixels)",
            g.rows, g.width
        )));
    }
    if !(g.pitch_mm.is_finite() && g.pitch_mm > 0.0 && g.x0_mm.is_finite() && g.y0_mm.is_finite()) {
        return Err(bad("a grid without a finite pitch and origin".into()));
    }
    if let Some(t) = &k.design_to_board {
        if !(t.rotation_rad.is_finite() && t.tx_mm.is_finite() && t.ty_mm.is_finite()) {
            return Err(bad("a design-to-board transform that is not finite".into()));
        }
    }
    Ok(Some(k))
}

/// Line `line`'s board `board`'s kept map: its description and heights (um, NaN invalid);
/// `None` when it is not kept. A PNG of another size or length, or damaged, is refused.
pub fn read(dir: &Path, line: &str, board: i64) -> Result<Option<(KeptMap, Grid)>, KeptMapError> {
    let Some(k) = read_meta(dir, line, board)? else {
        return Ok(None);
    };
    let (png, _) = paths(dir, line, board);
    let bad = |why: String| KeptMapError::Invalid {
        path: png.clone(),
        why,
    };
    let file = std::fs::File::open(&png).map_err(|io| FileError::Read {
        what: "kept map".into(),
        path: png.clone(),
        io,
    })?;
    let len = file.metadata().map(|m| m.len()).unwrap_or(0);
    if len != k.png_bytes {
        return Err(bad(format!(
            "{len} bytes where its description says {}",
            k.png_bytes
        )));
    }
    let (rows, width) = (k.grid.rows, k.grid.width);
    let mut decoder = png::Decoder::new_with_limits(
        std::io::BufReader::new(file.take(k.png_bytes)),
        png::Limits {
            bytes: rows * width * 2 + (1 << 20),
        },
    );
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder.read_info().map_err(|e| bad(e.to_string()))?;
    let info = reader.info();
    if (info.width as usize, info.height as usize) != (width, rows)
        || info.color_type != png::ColorType::Grayscale
        || info.bit_depth != png::BitDepth::Sixteen
    {
        return Err(bad(format!(
            "a {}-bit {:?} image of {} x {}, not 16-bit grey of {width} x {rows}",
            info.bit_depth as u8, info.color_type, info.width, info.height
        )));
    }
    let mut data = Vec::with_capacity(rows * width);
    while let Some(row) = reader.next_row().map_err(|e| bad(e.to_string()))? {
        data.extend(
            row.data()
                .chunks_exact(2)
                .map(|b| match u16::from_be_bytes([b[0], b[1]]) {
                    0 => f32::NAN,
                    v => ((f64::from(v) - f64::from(ZERO)) * LSB_UM) as f32,
                }),
        );
    }
    if data.len() != rows * width {
        return Err(bad(format!(
            "{} pixels where {} were expected",
            data.len(),
            rows * width
        )));
    }
    Ok(Some((k, Grid { width, rows, data })))
}

/// The names of the entries of `dir` (none when `dir` is missing).
fn names_in(dir: &Path) -> std::io::Result<Vec<String>> {
    match std::fs::read_dir(dir) {
        Ok(entries) => entries
            .map(|e| e.map(|e| e.file_name().to_string_lossy().into_owned()))
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(e),
    }
}

/// Line `line`'s board ids with a kept map in `dir` (their JSON present), ascending; none
/// when `dir` is missing.
pub fn kept(dir: &Path, line: &str) -> std::io::Result<Vec<i64>> {
    let prefix = format!("{line}.board-");
    let mut ids: Vec<i64> = names_in(dir)?
        .iter()
        .filter_map(|n| {
            n.strip_prefix(prefix.as_str())?
                .strip_suffix(".json")?
                .parse::<i64>()
                .ok()
        })
        .collect();
    ids.sort_unstable();
    Ok(ids)
}

/// Removes the unfinished writes of line `line`'s maps in `dir` (the temporaries an atomic
/// write leaves when its process is killed: `.LINE.board-ID....`); the names removed. For the
/// line's own writer at its start, when no write of its can be under way.
pub fn remove_unfinished(dir: &Path, line: &str) -> std::io::Result<Vec<String>> {
    let prefix = format!(".{line}.board-");
    let mut gone = Vec::new();
    for name in names_in(dir)? {
        // Line "a"'s prefix may start line "a.board-5"'s names: the id and one of the two
        // files' names must follow.
        let ours = name.strip_prefix(prefix.as_str()).is_some_and(|rest| {
            rest.split_once('.').is_some_and(|(id, file)| {
                id.parse::<i64>().is_ok()
                    && (file.starts_with("heights.png.") || file.starts_with("json."))
            })
        });
        let path = dir.join(&name);
        if ours && std::fs::symlink_metadata(&path)?.is_file() {
            std::fs::remove_file(path)?;
            gone.push(name);
        }
    }
    gone.sort();
    Ok(gone)
}

/// Removes all but line `line`'s newest `keep` maps of `dir` (the highest ids): the JSON
/// first, so a map being removed is never read half gone. The ids removed.
pub fn prune(dir: &Path, line: &str, keep: usize) -> std::io::Result<Vec<i64>> {
    let ids = kept(dir, line)?;
    let old = &ids[..ids.len().saturating_sub(keep)];
    for &id in old {
        let (png, json) = paths(dir, line, id);
        std::fs::remove_file(json)?;
        match std::fs::remove_file(png) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(e),
            _ => {}
        }
    }
    Ok(old.to_vec())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(rows: usize, width: usize) -> BoardGrid {
        BoardGrid {
            x0_mm: 1.0,
            y0_mm: -2.0,
            pitch_mm: 0.03,
            rows,
            width,
        }
    }

    fn t() -> Option<DesignToBoard> {
        Some(DesignToBoard {
            rotation_rad: 0.001,
            tx_mm: 0.2,
            ty_mm: -0.1,
        })
    }

    #[test]
    fn a_kept_map_reads_back_within_half_a_step_and_flags_what_it_could_not_keep() {
        let dir = tempfile::tempdir().unwrap();
        let (rows, width) = (37, 23);
        let mut data: Vec<f32> = (0..rows * width)
            .map(|i| (i as f32 * 7.31).sin() * 900.0 + 0.013 * i as f32)
            .collect();
        data[5] = f32::NAN;
        data[6] = f32::INFINITY;
        data[7] = 9000.0; // beyond 8191.75 um: clipped
        data[8] = -8191.75; // the lowest kept
        let h = Grid { width, rows, data };
        let k = write(dir.path(), "l-1", 42, 0xabc, &grid(rows, width), &h, t()).unwrap();
        assert_eq!((k.valid, k.clipped), ((rows * width - 3) as u64, 1));
        let (k2, back) = read(dir.path(), "l-1", 42).unwrap().unwrap();
        assert_eq!(k, k2);
        assert_eq!(k2.run_id, "0000000000000abc");
        for (a, b) in h.data.iter().zip(&back.data) {
            if a.is_finite() && a.abs() <= 8191.75 {
                assert!((a - b).abs() <= 0.125 + 1e-3, "{a} {b}");
            } else {
                assert!(b.is_nan());
            }
        }
        assert!(read(dir.path(), "l-1", 43).unwrap().is_none());
        // Another line's board of that id is not this one.
        assert!(read(dir.path(), "l-2", 42).unwrap().is_none());
    }

    #[test]
    fn a_damaged_or_foreign_kept_map_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let h = Grid {
            width: 30,
            rows: 20,
            data: (0..600).map(|i| i as f32).collect(),
        };
        write(dir.path(), "l", 1, 1, &grid(20, 30), &h, t()).unwrap();
        let (png, json) = paths(dir.path(), "l", 1);
        let good = std::fs::read(&png).unwrap();
        // A flipped byte in the image data: the PNG's CRC refuses it.
        let mut bad = good.clone();
        let n = bad.len();
        bad[n - 20] ^= 0x40;
        std::fs::write(&png, &bad).unwrap();
        let e = read(dir.path(), "l", 1).unwrap_err().to_string();
        assert!(e.contains("l.board-1.heights.png"), "{e}");
        // Truncated: its length is not the description's.
        std::fs::write(&png, &good[..n / 2]).unwrap();
        let e = read(dir.path(), "l", 1).unwrap_err().to_string();
        assert!(e.contains("bytes where its description says"), "{e}");
        std::fs::write(&png, &good).unwrap();
        assert!(read(dir.path(), "l", 1).is_ok());
        // Another board's description under this name, or an absurd grid.
        let text = std::fs::read_to_string(&json).unwrap();
        std::fs::write(&json, text.replace("\"board\": 1", "\"board\": 2")).unwrap();
        let e = read(dir.path(), "l", 1).unwrap_err().to_string();
        assert!(e.contains("describes board 2 of line l"), "{e}");
        std::fs::write(&json, text.replace("\"rows\": 20", "\"rows\": 20000000000")).unwrap();
        let e = read(dir.path(), "l", 1).unwrap_err().to_string();
        assert!(e.contains("pixels"), "{e}");
        std::fs::write(&json, "{").unwrap();
        assert!(read(dir.path(), "l", 1).is_err());
    }

    #[test]
    fn pruning_keeps_the_newest_maps() {
        let dir = tempfile::tempdir().unwrap();
        let h = Grid {
            width: 4,
            rows: 3,
            data: vec![1.0; 12],
        };
        for id in [3, 10, 7, 1] {
            write(dir.path(), "a", id, 0, &grid(3, 4), &h, t()).unwrap();
        }
        // Another line's maps in the same directory, one of them named so that line "a"'s
        // prefix starts its name.
        write(dir.path(), "b", 2, 0, &grid(3, 4), &h, t()).unwrap();
        write(dir.path(), "a.board-5", 4, 0, &grid(3, 4), &h, t()).unwrap();
        // An unfinished write (a PNG without its JSON) is not a kept map.
        std::fs::write(dir.path().join("a.board-11.heights.png"), b"x").unwrap();
        assert_eq!(kept(dir.path(), "a").unwrap(), vec![1, 3, 7, 10]);
        assert_eq!(prune(dir.path(), "a", 2).unwrap(), vec![1, 3]);
        assert_eq!(kept(dir.path(), "a").unwrap(), vec![7, 10]);
        assert!(!paths(dir.path(), "a", 1).0.exists());
        assert_eq!(kept(dir.path(), "b").unwrap(), vec![2]);
        assert_eq!(kept(dir.path(), "a.board-5").unwrap(), vec![4]);
        assert!(kept(&dir.path().join("none"), "a").unwrap().is_empty());
        // A killed write's temporaries: line "a"'s removed, no other's, no map.
        for n in [
            ".a.board-12.heights.png.x7Yq2",
            ".a.board-5.board-9.json.k2",
            ".b.board-3.json.zz",
        ] {
            std::fs::write(dir.path().join(n), b"x").unwrap();
        }
        assert_eq!(
            remove_unfinished(dir.path(), "a").unwrap(),
            vec![".a.board-12.heights.png.x7Yq2".to_owned()]
        );
        assert!(dir.path().join(".b.board-3.json.zz").exists());
        assert!(dir.path().join(".a.board-5.board-9.json.k2").exists());
        assert_eq!(kept(dir.path(), "a").unwrap(), vec![7, 10]);
    }
}
