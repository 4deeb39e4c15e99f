//! The board map as the inspection reads it: `board.json` and `heights_um.tiff` of a
//! `dpsa board --out DIR` (docs/board.md), heights in um on a grid in board mm.

use anyhow::{bail, Context, Result};
use dpsa_formats::grid::BoardGrid;
use dpsa_formats::grid::Grid;
use std::path::Path;

/// Largest map read: 400 Mpx (a 220 x 168 mm board at 10 um).
pub const MAX_PIXELS: u64 = 400_000_000;

/// Heights (um, NaN invalid) on the board grid.
#[derive(Clone, Debug)]
pub struct BoardMap {
    /// The board's identity from `board.json` (None in maps written without one).
    pub board_id: Option<dpsa_formats::BoardId>,
    /// Where the pixels lie: row `i` along x, column `j` along y, board mm.
    pub grid: BoardGrid,
    /// Heights above the board's datum, um, row-major (`grid.rows` x `grid.width`); NaN
    /// where the map has no valid height.
    pub heights: Grid,
}

#[derive(serde::Deserialize)]
struct MetaIn {
    format: String,
    version: u32,
    grid: BoardGrid,
    units: UnitsIn,
    /// The board's identity (`array.json`'s `board_id`), in maps of recordings that have one.
    #[serde(default)]
    board_id: Option<dpsa_formats::BoardId>,
}

#[derive(serde::Deserialize)]
struct UnitsIn {
    lengths: String,
    heights: String,
    png_lsb_um: f64,
}

/// The `board.json` version this build reads.
pub(crate) const MAP_VERSION: u32 = 1;

impl BoardMap {
    /// Reads a map directory (`board.json`, `heights_um.tiff`), checking its format, version,
    /// units and grid (at most [`MAX_PIXELS`]) against each other.
    pub fn open(dir: &Path) -> Result<BoardMap> {
        let json_path = dir.join("board.json");
        let bytes = dpsa_formats::files::read_capped(&json_path, 1 << 20, "board map metadata")?;
        let meta: MetaIn = serde_json::from_slice(&bytes)
            .with_context(|| format!("{} is not a board map's board.json", json_path.display()))?;
        if meta.format != dpsa_formats::board_map::FORMAT {
            bail!(
                "{}: format {:?}, expected {:?}",
                json_path.display(),
                meta.format,
                dpsa_formats::board_map::FORMAT
            );
        }
        if meta.version != MAP_VERSION {
            bail!(
                "{}: version {}, this build reads version {MAP_VERSION} of {:?}",
                json_path.display(),
                meta.version,
                dpsa_formats::board_map::FORMAT
            );
        }
        let u = &meta.units;
        if u.lengths != "mm" || u.heights != "um" {
            bail!(
                "{}: units lengths {:?} and heights {:?}, this build reads \"mm\" and \"um\" (the TIFF's heights and the grid would be misread)",
                json_path.display(),
                u.lengths,
                u.heights
            );
        }
        if !(u.png_lsb_um.is_finite() && u.png_lsb_um > 0.0) {
            bail!(
                "{}: units.png_lsb_um = {}, expected a finite value > 0 (the height of one heights.png step)",
                json_path.display(),
                u.png_lsb_um
            );
        }
        let g = meta.grid;
        let px = (g.rows as u64).saturating_mul(g.width as u64);
        if g.rows == 0 || g.width == 0 || px > MAX_PIXELS {
            bail!(
                "{}: a {} x {} grid is absurd",
                json_path.display(),
                g.rows,
                g.width
            );
        }
        let sane = g.pitch_mm.is_finite()
            && g.pitch_mm > 1e-4
            && g.pitch_mm < 1.0
            && g.x0_mm.is_finite()
            && g.y0_mm.is_finite();
        if !sane {
            bail!(
                "{}: grid origin or pitch not sane: {g:?}",
                json_path.display()
            );
        }
        let tiff_path = dir.join("heights_um.tiff");
        let f = dpsa_formats::files::open_regular(&tiff_path, "board heights")?;
        let mut dec = tiff::decoder::Decoder::new(std::io::BufReader::new(f))
            .with_context(|| format!("{} is not a TIFF", tiff_path.display()))?;
        let (w, h) = dec
            .dimensions()
            .with_context(|| format!("{}: no image size", tiff_path.display()))?;
        if w as usize != g.width || h as usize != g.rows {
            bail!(
                "{}: {} x {} pixels, but board.json says {} x {}",
                tiff_path.display(),
                w,
                h,
                g.width,
                g.rows
            );
        }
        let mut limits = tiff::decoder::Limits::default();
        limits.decoding_buffer_size = (px * 4 + 1024) as usize;
        limits.intermediate_buffer_size = (px * 4 + 1024) as usize;
        dec = dec.with_limits(limits);
        let data = match dec
            .read_image()
            .with_context(|| format!("{}: cannot decode", tiff_path.display()))?
        {
            tiff::decoder::DecodingResult::F32(v) => v,
            _ => bail!("{}: not 32-bit float heights", tiff_path.display()),
        };
        if data.len() as u64 != px {
            bail!(
                "{}: truncated ({} of {px} pixels)",
                tiff_path.display(),
                data.len()
            );
        }
        Ok(BoardMap {
            board_id: meta.board_id,
            grid: g,
            heights: Grid {
                width: g.width,
                rows: g.rows,
                data,
            },
        })
    }

    /// Pixel `(i, j)` (row along x, column along y) nearest to board point `p` (may be
    /// outside the grid).
    pub(crate) fn pixel_of(&self, p: [f64; 2]) -> (i64, i64) {
        let g = &self.grid;
        (
            ((p[0] - g.x0_mm) / g.pitch_mm - 0.5).round() as i64,
            ((p[1] - g.y0_mm) / g.pitch_mm - 0.5).round() as i64,
        )
    }

    /// Pixel index ranges (rows, columns; half open, clipped) covering `bbox` in board mm.
    pub fn window(&self, b: [f64; 4]) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
        let g = &self.grid;
        let i0 = ((b[0] - g.x0_mm) / g.pitch_mm - 0.5).floor().max(0.0);
        let i1 = ((b[2] - g.x0_mm) / g.pitch_mm - 0.5).ceil() + 1.0;
        let j0 = ((b[1] - g.y0_mm) / g.pitch_mm - 0.5).floor().max(0.0);
        let j1 = ((b[3] - g.y0_mm) / g.pitch_mm - 0.5).ceil() + 1.0;
        let clip = |v: f64, n: usize| (v.max(0.0) as usize).min(n);
        (
            clip(i0, g.rows)..clip(i1, g.rows),
            clip(j0, g.width)..clip(j1, g.width),
        )
    }

    /// Whether `bbox` (board mm) lies inside the grid.
    pub(crate) fn covers(&self, b: [f64; 4]) -> bool {
        let g = &self.grid;
        b[0] >= g.x0_mm
            && b[1] >= g.y0_mm
            && b[2] <= g.x0_mm + g.rows as f64 * g.pitch_mm
            && b[3] <= g.y0_mm + g.width as f64 * g.pitch_mm
    }
}
