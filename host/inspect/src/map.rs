//! The board map as the inspection reads it: `board.json` and `heights_um.tiff` of a
//! `dpsa board --out DIR` (docs/board.md), heights in um on a grid in board mm.

use crate::error::InspectError;
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

/// `v.round() as i64` (halves away from zero; NaN 0, saturating) without libm's `round`, a
/// call on the x86-64 baseline, which has no rounding instruction: the truncation, moved by
/// one where the part it dropped is a half or more (that part is exact below 2^52).
#[inline]
pub(crate) fn round_i64(v: f64) -> i64 {
    let i = v as i64;
    let f = v - i as f64;
    if f >= 0.5 {
        i.saturating_add(1)
    } else if f <= -0.5 {
        i.saturating_sub(1)
    } else {
        i
    }
}

impl BoardMap {
    /// Reads a map directory (`board.json`, `heights_um.tiff`), checking its format, version,
    /// units and grid (at most [`MAX_PIXELS`]) against each other.
    pub fn open(dir: &Path) -> Result<BoardMap, InspectError> {
        let json_path = dir.join("board.json");
        let bad = |why: String| InspectError::Map {
            path: json_path.clone(),
            why,
        };
        let bytes = dpsa_formats::files::read_capped(&json_path, 1 << 20, "board map metadata")?;
        let meta: MetaIn =
            serde_json::from_slice(&bytes).map_err(|source| InspectError::MapJson {
                path: json_path.clone(),
                source,
            })?;
        if meta.format != dpsa_formats::board_map::FORMAT {
            return Err(bad(format!(
                "format {:?}, expected {:?}",
                meta.format,
                dpsa_formats::board_map::FORMAT
            )));
        }
        if meta.version != MAP_VERSION {
            return Err(bad(format!(
                "version {}, this build reads version {MAP_VERSION} of {:?}",
                meta.version,
                dpsa_formats::board_map::FORMAT
            )));
        }
        let u = &meta.units;
        if u.lengths != "mm" || u.heights != "um" {
            return Err(bad(format!(
                "units lengths {:?} and heights {:?}, this build reads \"mm\" and \"um\" (the TIFF's heights and the grid would be misread)",
                u.lengths,
                u.heights
            )));
        }
        if !(u.png_lsb_um.is_finite() && u.png_lsb_um > 0.0) {
            return Err(bad(format!(
                "units.png_lsb_um = {}, expected a finite value > 0 (the height of one heights.png step)",
                u.png_lsb_um
            )));
        }
        let g = meta.grid;
        let px = (g.rows as u64).saturating_mul(g.width as u64);
        if g.rows == 0 || g.width == 0 || px > MAX_PIXELS {
            return Err(bad(format!("a {} x {} grid is absurd", g.rows, g.width)));
        }
        let sane = g.pitch_mm.is_finite()
            && g.pitch_mm > 1e-4
            && g.pitch_mm < 1.0
            && g.x0_mm.is_finite()
            && g.y0_mm.is_finite();
        if !sane {
            return Err(bad(format!("grid origin or pitch not sane: {g:?}")));
        }
        let tiff_path = dir.join("heights_um.tiff");
        let bad_tiff = |why: String| InspectError::Map {
            path: tiff_path.clone(),
            why,
        };
        let tiff_error = |what: &'static str, source| InspectError::Tiff {
            path: tiff_path.clone(),
            what,
            source,
        };
        let f = dpsa_formats::files::open_regular(&tiff_path, "board heights")?;
        let mut dec =
            tiff::decoder::Decoder::new(std::io::BufReader::new(f)).map_err(|source| {
                InspectError::NotTiff {
                    path: tiff_path.clone(),
                    source,
                }
            })?;
        let (w, h) = dec
            .dimensions()
            .map_err(|e| tiff_error("no image size", e))?;
        if w as usize != g.width || h as usize != g.rows {
            return Err(bad_tiff(format!(
                "{} x {} pixels, but board.json says {} x {}",
                w, h, g.width, g.rows
            )));
        }
        let mut limits = tiff::decoder::Limits::default();
        limits.decoding_buffer_size = (px * 4 + 1024) as usize;
        limits.intermediate_buffer_size = (px * 4 + 1024) as usize;
        dec = dec.with_limits(limits);
        let data = match dec
            .read_image()
            .map_err(|e| tiff_error("cannot decode", e))?
        {
            tiff::decoder::DecodingResult::F32(v) => v,
            _ => return Err(bad_tiff("not 32-bit float heights".into())),
        };
        if data.len() as u64 != px {
            return Err(bad_tiff(format!(
                "truncated ({} of {px} pixels)",
                data.len()
            )));
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
            round_i64((p[0] - g.x0_mm) / g.pitch_mm - 0.5),
            round_i64((p[1] - g.y0_mm) / g.pitch_mm - 0.5),
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

    /// A hint that row `i`'s pixels `cols` of the heights will be read soon: a pad's window
    /// is a few cache lines of each of many map rows 24 KB apart, which the processor's own
    /// prefetcher does not foresee, so each row's first read would wait on memory. A hint
    /// only (nothing is read, an index beyond the map is ignored); no code on other
    /// processors.
    #[inline]
    pub(crate) fn prefetch_row(&self, i: usize, cols: std::ops::Range<usize>) {
        #[cfg(target_arch = "x86_64")]
        {
            let w = self.grid.width;
            if i >= self.grid.rows || cols.start >= cols.end || cols.end > w {
                return;
            }
            let row = &self.heights.data[i * w + cols.start..i * w + cols.end];
            // 16 heights (f32) to a 64-byte line, and the line of the last one.
            for at in row.iter().step_by(16).chain(row.last()) {
                // SAFETY: SSE, the intrinsic's feature, is in the x86-64 baseline, and a
                // prefetch reads nothing (and the address is inside the heights anyway).
                #[allow(unsafe_code)]
                unsafe {
                    std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                        (at as *const f32).cast(),
                    );
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (i, cols);
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;
    use tiff::encoder::{colortype, TiffEncoder};

    /// Exactly `round() as i64`: at every half and its neighbours, at random values of
    /// every size, at the ends of the range, for NaN and the infinities.
    #[test]
    fn round_i64_is_the_rounding_of_libm() {
        let mut vs = vec![
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            9.3e18,
            -9.3e18,
            4.5e15,
            -4.5e15,
            0.49999999999999994,
            -0.49999999999999994,
            0.0,
            -0.0,
        ];
        for k in -2000..2000 {
            let h = f64::from(k) + 0.5;
            vs.extend([h, h.next_up(), h.next_down(), f64::from(k)]);
        }
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..100_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let m = (x >> 11) as f64 / (1u64 << 53) as f64;
            let e = (x % 60) as i32 - 8;
            vs.push((m - 0.5) * 2f64.powi(e));
        }
        for v in vs {
            assert_eq!(round_i64(v), v.round() as i64, "{v:e}");
        }
    }

    /// The message as `dpsa` prints it (`{e:#}`): each error of the chain, `: ` between.
    fn chain(e: &dyn std::error::Error) -> String {
        let mut s = e.to_string();
        let mut c = e.source();
        while let Some(x) = c {
            s += &format!(": {x}");
            c = x.source();
        }
        s
    }

    /// A map directory: `board.json` (a 3 x 2 grid, `edit` applied) and `heights` as the
    /// TIFF (`rows` x `width`, f32 or u8).
    fn map_dir(
        edit: impl Fn(&mut serde_json::Value),
        rows: u32,
        width: u32,
        float: bool,
    ) -> (tempfile::TempDir, PathBuf, PathBuf) {
        let d = tempfile::tempdir().unwrap();
        let mut j = serde_json::json!({
            "format": dpsa_formats::board_map::FORMAT,
            "version": MAP_VERSION,
            "grid": { "x0_mm": 0.0, "y0_mm": 0.0, "pitch_mm": 0.01, "rows": 3, "width": 2 },
            "units": { "lengths": "mm", "heights": "um", "png_lsb_um": 0.25 },
        });
        edit(&mut j);
        let json = d.path().join("board.json");
        std::fs::write(&json, serde_json::to_vec(&j).unwrap()).unwrap();
        let tiff = d.path().join("heights_um.tiff");
        let mut f = std::fs::File::create(&tiff).unwrap();
        let mut enc = TiffEncoder::new(&mut f).unwrap();
        let n = (rows * width) as usize;
        if float {
            enc.write_image::<colortype::Gray32Float>(width, rows, &vec![1.5f32; n])
                .unwrap();
        } else {
            enc.write_image::<colortype::Gray8>(width, rows, &vec![7u8; n])
                .unwrap();
        }
        (d, json, tiff)
    }

    #[test]
    fn a_map_is_read_and_each_refusal_is_its_sentence() {
        let (d, _, _) = map_dir(|_| {}, 3, 2, true);
        let m = BoardMap::open(d.path()).unwrap();
        assert_eq!((m.heights.rows, m.heights.width), (3, 2));
        assert!(m.heights.data.iter().all(|&h| h == 1.5));

        let refused = |d: &tempfile::TempDir| chain(&BoardMap::open(d.path()).unwrap_err());
        let (d, json, _) = map_dir(|j| j["version"] = 9.into(), 3, 2, true);
        assert_eq!(
            refused(&d),
            format!(
                "{}: version 9, this build reads version 1 of \"dpsa-board-map\"",
                json.display()
            )
        );
        let (d, json, _) = map_dir(|j| j["units"]["lengths"] = "inch".into(), 3, 2, true);
        assert_eq!(
            refused(&d),
            format!(
                "{}: units lengths \"inch\" and heights \"um\", this build reads \"mm\" and \"um\" (the TIFF's heights and the grid would be misread)",
                json.display()
            )
        );
        let (d, json, _) = map_dir(|j| j["grid"]["rows"] = 0.into(), 3, 2, true);
        assert_eq!(
            refused(&d),
            format!("{}: a 0 x 2 grid is absurd", json.display())
        );
        let (d, _, tiff) = map_dir(|_| {}, 4, 2, true);
        assert_eq!(
            refused(&d),
            format!(
                "{}: 2 x 4 pixels, but board.json says 2 x 3",
                tiff.display()
            )
        );
        let (d, _, tiff) = map_dir(|_| {}, 3, 2, false);
        assert_eq!(
            refused(&d),
            format!("{}: not 32-bit float heights", tiff.display())
        );
        // Not JSON / not a TIFF: the sentence, then the parser's own error.
        let (d, json, _) = map_dir(|_| {}, 3, 2, true);
        std::fs::write(&json, b"{nope").unwrap();
        let parser = serde_json::from_slice::<serde_json::Value>(b"{nope").unwrap_err();
        assert_eq!(
            refused(&d),
            format!(
                "{} is not a board map's board.json: {parser}",
                json.display()
            )
        );
        let (d, _, tiff) = map_dir(|_| {}, 3, 2, true);
        std::fs::write(&tiff, b"not a tiff at all").unwrap();
        let e = refused(&d);
        let head = format!("{} is not a TIFF: ", tiff.display());
        assert!(e.starts_with(&head) && e.len() > head.len(), "{e}");
    }
}
