//! Zoom and pan over a board's measured map: the map the line kept
//! (`dpsa_formats::kept_map`) drawn as 256-pixel PNG tiles of the height above the local
//! board surface, each made once and cached.
//!
//! - **The pyramid.** On a board's first request its map is read, its local surface
//!   (`dpsa_formats::surface`, as `heights.colour.png` draws) taken off, and the rest turned as
//!   the design is drawn (board `x` to the right, `y` up) into the pyramid's finest level, 16
//!   bits a pixel (0.25 um steps). Each coarser level is the mean of the valid pixels of 2 x 2
//!   of the finer (invalid where all four are). Level 0 fits one tile. The colour scale is the
//!   0.5th to 99.7th percentile of the finest level (as `heights.colour.png`'s); invalid
//!   pixels dark grey, beyond the map transparent.
//! - **The caches.** The newest [`PYRAMIDS_KEPT`] boards' pyramids (about 125 MB a paper
//!   board) and up to [`TILE_BYTES`] of encoded tiles, the oldest dropped first. A tile is
//!   drawn once ([`MapCache::renders`] counts the drawings); one pyramid is built at a time.
//!   The caches live in the server's memory: the store and the maps stay read-only.

use dpsa_formats::grid::Grid;
use dpsa_formats::images::colour;
use dpsa_formats::kept_map::{self, KeptMap, KeptMapError};
use std::collections::{HashMap, VecDeque};
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

/// The viewer's script (ours: the viewer is one image pyramid, about 200 lines; a map
/// library such as Leaflet is 150 kB with its style sheet for the same).
pub const SCRIPT: &str = include_str!("mapview.js");

/// Where the pages load [`SCRIPT`] from.
pub const SCRIPT_PATH: &str = "/js/mapview.js";

/// A tile's side, px.
pub const TILE: usize = 256;
/// Boards whose pyramids stay in memory.
pub const PYRAMIDS_KEPT: usize = 2;
/// Encoded tiles kept, bytes at most.
pub const TILE_BYTES: usize = 64 << 20;
/// An invalid pixel's colour.
pub const INVALID: [u8; 3] = [40, 40, 40];
/// A tile's palette index beyond the map (transparent).
pub const OUTSIDE: u8 = 0;
/// A tile's palette index of a pixel without a height ([`INVALID`]).
pub const NO_HEIGHT: u8 = 1;
/// The first palette index of the colour ramp (the scale's bottom).
pub const RAMP: u8 = 2;
/// Colours of the ramp in the palette: 254 steps, 0.4 um each on a 100 um scale.
pub const RAMP_STEPS: u8 = 254;

/// The tiles' palette: [`OUTSIDE`], [`NO_HEIGHT`], then the ramp from the scale's bottom to
/// its top (an indexed PNG is about a third of an RGBA one: 40 kB a tile, not 124).
pub fn palette() -> Vec<[u8; 3]> {
    let mut p = vec![[0, 0, 0], INVALID];
    p.extend((0..RAMP_STEPS).map(|i| colour(f64::from(i) / f64::from(RAMP_STEPS - 1))));
    p
}

/// The colour scale's percentiles.
const RANGE: (f64, f64) = (0.005, 0.997);
/// The pyramid's height step, um.
const LSB_UM: f32 = 0.25;
/// An invalid pixel in the pyramid.
const NONE: i16 = i16::MIN;

/// One level of the pyramid: heights above the local surface in [`LSB_UM`] steps, the
/// design's orientation (column `u`: board `x`; row `v`: board `y` from the top).
struct Level {
    w: usize,
    h: usize,
    data: Vec<i16>,
}

/// A board's map ready to draw.
pub struct Pyramid {
    levels: Vec<Level>,
    /// The map's description.
    pub kept: KeptMap,
    /// The colour scale, um above the local surface.
    pub range_um: (f32, f32),
    /// The share of the map's pixels with a height.
    pub valid_fraction: f64,
}

impl Pyramid {
    /// The pyramid of `heights` described by `kept`.
    pub fn new(kept: KeptMap, heights: &Grid) -> Pyramid {
        let cell =
            ((dpsa_formats::surface::SURFACE_CELL_MM / kept.grid.pitch_mm).round() as usize).max(2);
        let surface = dpsa_formats::surface::local_surface(heights, cell);
        // Turned: u = map row, v = (width - 1 - map column).
        let (w, h) = (heights.rows, heights.width);
        let mut base = vec![NONE; w * h];
        let mut valid = 0usize;
        for r in 0..heights.rows {
            let (row, srow) = (
                &heights.data[r * heights.width..(r + 1) * heights.width],
                &surface.data[r * heights.width..(r + 1) * heights.width],
            );
            for (c, (a, s)) in row.iter().zip(srow).enumerate() {
                let d = a - s;
                if d.is_finite() {
                    valid += 1;
                    base[(h - 1 - c) * w + r] =
                        (d / LSB_UM).round().clamp(-32767.0, 32767.0) as i16;
                }
            }
        }
        drop(surface);
        let range_um = range(&base);
        let mut levels = vec![Level { w, h, data: base }];
        while levels.last().is_some_and(|l| l.w.max(l.h) > TILE) {
            let next = halve(levels.last().expect("a level"));
            levels.push(next);
        }
        levels.reverse();
        Pyramid {
            levels,
            valid_fraction: valid as f64 / (w * h).max(1) as f64,
            kept,
            range_um,
        }
    }

    /// Levels: 0 fits one tile, the last is the map's own pixels.
    pub fn levels(&self) -> usize {
        self.levels.len()
    }

    /// The finest level's size (the map turned: board `x` across), px.
    pub fn size(&self) -> (usize, usize) {
        let l = self.levels.last().expect("a level");
        (l.w, l.h)
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.levels.iter().map(|l| 2 * l.data.len()).sum()
    }

    /// Tile `(x, y)` of level `z` as indices into [`palette`] (`TILE x TILE`), `None`
    /// outside the pyramid.
    pub fn tile_indices(&self, z: usize, x: usize, y: usize) -> Option<Vec<u8>> {
        let l = self.levels.get(z)?;
        if x >= l.w.div_ceil(TILE) || y >= l.h.div_ceil(TILE) {
            return None;
        }
        let (lo, hi) = self.range_um;
        let steps = f32::from(RAMP_STEPS - 1);
        let mut out = vec![OUTSIDE; TILE * TILE];
        for py in 0..TILE {
            let v = y * TILE + py;
            if v >= l.h {
                break;
            }
            for px in 0..TILE {
                let u = x * TILE + px;
                if u >= l.w {
                    break;
                }
                out[py * TILE + px] = match l.data[v * l.w + u] {
                    NONE => NO_HEIGHT,
                    q => {
                        let t = ((f32::from(q) * LSB_UM - lo) / (hi - lo)).clamp(0.0, 1.0);
                        RAMP + (t * steps).round() as u8
                    }
                };
            }
        }
        Some(out)
    }

    /// The height above the local surface at finest-level pixel `(u, v)`, um (`None`:
    /// invalid or outside).
    pub fn height_um(&self, u: usize, v: usize) -> Option<f32> {
        let l = self.levels.last()?;
        if u >= l.w || v >= l.h {
            return None;
        }
        match l.data[v * l.w + u] {
            NONE => None,
            q => Some(f32::from(q) * LSB_UM),
        }
    }

    /// What the viewer needs (`info.json`): sizes, levels, scale, placement in mm.
    pub fn json(&self) -> String {
        let (w, h) = self.size();
        let g = &self.kept.grid;
        let ramp: Vec<String> = (0..5)
            .map(|i| {
                let c = colour(f64::from(i) / 4.0);
                format!("[{},{},{}]", c[0], c[1], c[2])
            })
            .collect();
        format!(
            "{{\"board\":{},\"run_id\":\"{}\",\"width\":{w},\"height\":{h},\"tile\":{TILE},\
             \"levels\":{},\"pitch_mm\":{},\"x0_mm\":{},\"y_top_mm\":{},\"range_um\":[{:.1},{:.1}],\
             \"ramp\":[{}],\"invalid\":[{},{},{}],\"valid_fraction\":{:.6},\"clipped\":{}}}",
            self.kept.board,
            self.kept.run_id,
            self.levels(),
            g.pitch_mm,
            g.x0_mm,
            g.y0_mm + g.width as f64 * g.pitch_mm,
            self.range_um.0,
            self.range_um.1,
            ramp.join(","),
            INVALID[0],
            INVALID[1],
            INVALID[2],
            self.valid_fraction,
            self.kept.clipped
        )
    }
}

/// The colour scale of the finest level: its 0.5th and 99.7th percentiles (of at most 4 M
/// of its pixels, evenly strided), um; `(0, 1)` without a valid pixel.
fn range(base: &[i16]) -> (f32, f32) {
    let stride = (base.len() / 4_000_000).max(1);
    let mut v: Vec<i16> = base
        .iter()
        .step_by(stride)
        .copied()
        .filter(|&q| q != NONE)
        .collect();
    if v.is_empty() {
        return (0.0, 1.0);
    }
    let mut at = |q: f64| {
        let k = (((v.len() - 1) as f64) * q).round() as usize;
        f32::from(*v.select_nth_unstable(k).1) * LSB_UM
    };
    let (lo, hi) = (at(RANGE.0), at(RANGE.1));
    (lo, hi.max(lo + 1.0))
}

/// The next coarser level: the mean of the valid pixels of each 2 x 2.
fn halve(l: &Level) -> Level {
    let (w, h) = (l.w.div_ceil(2), l.h.div_ceil(2));
    let mut data = vec![NONE; w * h];
    for v in 0..h {
        for u in 0..w {
            let (mut sum, mut n) = (0i32, 0i32);
            for (du, dv) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (uu, vv) = (2 * u + du, 2 * v + dv);
                if uu < l.w && vv < l.h {
                    let q = l.data[vv * l.w + uu];
                    if q != NONE {
                        sum += i32::from(q);
                        n += 1;
                    }
                }
            }
            if n > 0 {
                // Rounded to nearest, halves away from zero.
                let m = (2 * sum + sum.signum() * n) / (2 * n);
                data[v * w + u] = m as i16;
            }
        }
    }
    Level { w, h, data }
}

/// A tile's key: board, run, level, column, row.
type TileKey = (i64, String, u8, u32, u32);

#[derive(Default)]
struct Tiles {
    map: HashMap<TileKey, Arc<Vec<u8>>>,
    order: VecDeque<TileKey>,
    bytes: usize,
}

/// The pyramids and tiles made so far (see the module docs).
#[derive(Default)]
pub struct MapCache {
    pyramids: Mutex<VecDeque<(i64, Arc<Pyramid>)>>,
    building: Mutex<()>,
    tiles: Mutex<Tiles>,
    renders: AtomicUsize,
    builds: AtomicUsize,
}

impl std::fmt::Debug for MapCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MapCache")
            .field("renders", &self.renders())
            .field("builds", &self.builds())
            .finish()
    }
}

impl MapCache {
    /// Tiles drawn so far (a tile served from the cache is not drawn again).
    pub fn renders(&self) -> usize {
        self.renders.load(Ordering::Relaxed)
    }

    /// Pyramids built so far.
    pub fn builds(&self) -> usize {
        self.builds.load(Ordering::Relaxed)
    }

    /// Whether board `board`'s pyramid of run `run` is built and kept.
    pub fn has(&self, board: i64, run: &str) -> bool {
        self.cached(board, run).is_some()
    }

    fn cached(&self, board: i64, run: &str) -> Option<Arc<Pyramid>> {
        let p = self.pyramids.lock().ok()?;
        p.iter()
            .find(|(b, p)| *b == board && p.kept.run_id == run)
            .map(|(_, p)| Arc::clone(p))
    }

    /// Line `line`'s board `board`'s pyramid from the maps in `dir`, of the board of run id
    /// `run` (16 hex digits): cached, else built (one at a time); `None` when no map of that
    /// run is kept under the id (a map another store kept under the same id is never shown
    /// for this board).
    pub fn pyramid(
        &self,
        dir: &Path,
        line: &str,
        board: i64,
        run: &str,
    ) -> Result<Option<Arc<Pyramid>>, KeptMapError> {
        if let Some(p) = self.cached(board, run) {
            return Ok(Some(p));
        }
        let _one = self.building.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(p) = self.cached(board, run) {
            return Ok(Some(p));
        }
        // The description first: another run's map is not read at all.
        if kept_map::read_meta(dir, line, board)?.is_none_or(|k| k.run_id != run) {
            return Ok(None);
        }
        let Some((kept, heights)) = kept_map::read(dir, line, board)? else {
            return Ok(None);
        };
        if kept.run_id != run {
            return Ok(None);
        }
        let p = Arc::new(Pyramid::new(kept, &heights));
        drop(heights);
        self.builds.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut all) = self.pyramids.lock() {
            all.retain(|(b, _)| *b != board);
            all.push_back((board, Arc::clone(&p)));
            while all.len() > PYRAMIDS_KEPT {
                all.pop_front();
            }
        }
        Ok(Some(p))
    }

    /// Tile `(z, x, y)` of line `line`'s board `board` of run `run` as PNG: cached, else
    /// drawn and kept; `None` when no map of that run is kept or the tile is outside it.
    #[allow(clippy::too_many_arguments)]
    pub fn tile_png(
        &self,
        dir: &Path,
        line: &str,
        board: i64,
        run: &str,
        z: u8,
        x: u32,
        y: u32,
    ) -> Result<Option<Arc<Vec<u8>>>, KeptMapError> {
        let key = (board, run.to_owned(), z, x, y);
        if let Some(t) = self
            .tiles
            .lock()
            .ok()
            .and_then(|t| t.map.get(&key).cloned())
        {
            return Ok(Some(t));
        }
        let Some(p) = self.pyramid(dir, line, board, run)? else {
            return Ok(None);
        };
        let Some(indices) = p.tile_indices(usize::from(z), x as usize, y as usize) else {
            return Ok(None);
        };
        let png = Arc::new(encode(&indices));
        self.renders.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut t) = self.tiles.lock() {
            if t.map.insert(key.clone(), Arc::clone(&png)).is_none() {
                t.order.push_back(key);
                t.bytes += png.len();
            }
            while t.bytes > TILE_BYTES {
                let Some(old) = t.order.pop_front() else {
                    break;
                };
                if let Some(gone) = t.map.remove(&old) {
                    t.bytes -= gone.len();
                }
            }
        }
        Ok(Some(png))
    }
}

/// `TILE x TILE` palette indices as an 8-bit indexed PNG ([`palette`], [`OUTSIDE`]
/// transparent).
fn encode(indices: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, TILE as u32, TILE as u32);
    enc.set_color(png::ColorType::Indexed);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_palette(palette().concat());
    enc.set_trns(vec![0u8]);
    enc.set_compression(png::Compression::Fast);
    // Writing into memory fails only on a bug in the encoder.
    let written = enc
        .write_header()
        .and_then(|mut w| w.write_image_data(indices).and_then(|()| w.finish()));
    if let Err(e) = written {
        tracing::error!("tile not encoded: {e}");
        out.clear();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_formats::grid::BoardGrid;

    /// The run id of the test's board.
    const RUN: &str = "0000000000000001";

    /// A bowed board with one deposit, written and read as the line keeps it.
    fn board(dir: &Path) -> (BoardGrid, Grid) {
        let g = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.05,
            rows: 700,
            width: 500,
        };
        let mut data = vec![0f32; g.rows * g.width];
        for r in 0..g.rows {
            for c in 0..g.width {
                let x = r as f32 / g.rows as f32 - 0.5;
                // 300 um of bow, a 120 um deposit of 2 x 1.5 mm at (10 mm, 20 mm).
                let mut h = 300.0 * (1.0 - 4.0 * x * x);
                let (xm, ym) = (r as f64 * 0.05, c as f64 * 0.05);
                if (9.0..11.0).contains(&xm) && (19.25..20.75).contains(&ym) {
                    h += 120.0;
                }
                data[r * g.width + c] = h;
            }
        }
        data[123 * g.width + 45] = f32::NAN;
        let heights = Grid {
            width: g.width,
            rows: g.rows,
            data,
        };
        kept_map::write(dir, "l", 7, 1, &g, &heights, None).unwrap();
        (g, heights)
    }

    #[test]
    fn the_tiles_show_the_paste_above_the_board_turned_as_the_design() {
        let dir = tempfile::tempdir().unwrap();
        let (g, _) = board(dir.path());
        let cache = MapCache::default();
        let p = cache.pyramid(dir.path(), "l", 7, RUN).unwrap().unwrap();
        // 700 x 500 turned: three levels (700 -> 350 -> 175).
        assert_eq!(p.size(), (700, 500));
        assert_eq!(p.levels(), 3);
        // The deposit's centre (10 mm, 20 mm): u = 200, v = 500 - 1 - 400; 120 um above
        // the board whatever the bow; the bare board beside it near 0.
        let (u, v) = (200, g.width - 1 - 400);
        let top = p.height_um(u, v).unwrap();
        assert!((top - 120.0).abs() < 3.0, "{top}");
        for (u, v) in [(100, 300), (600, 50), (350, 250)] {
            let bare = p.height_um(u, v).unwrap();
            assert!(bare.abs() < 3.0, "({u}, {v}): {bare}");
        }
        // The invalid pixel: map (123, 45) is (u, v) = (123, 454).
        assert_eq!(p.height_um(123, g.width - 1 - 45), None);
        // The scale spans the bare board to the deposit's top.
        assert!(
            p.range_um.0 > -3.0 && p.range_um.0 < 1.0,
            "{:?}",
            p.range_um
        );
        assert!((p.range_um.1 - 120.0).abs() < 3.0, "{:?}", p.range_um);
        // The finest level's tile over the deposit: its pixel coloured as 120 um is.
        let z = p.levels() - 1;
        let png = cache
            .tile_png(dir.path(), "l", 7, RUN, z as u8, 0, 0)
            .unwrap()
            .unwrap();
        let rgba = decode(&png);
        let (lo, hi) = p.range_um;
        // The palette's step nearest the height's place on the scale.
        let t = f64::from((p.height_um(u, v).unwrap() - lo) / (hi - lo)).clamp(0.0, 1.0);
        let want = colour((t * 253.0).round() / 253.0);
        assert_eq!(
            &rgba[(v * TILE + u) * 4..][..3],
            &want[..],
            "not at ({u}, {v})"
        );
        // Beyond the map (the last column of tiles past u = 700): transparent.
        let png = cache
            .tile_png(dir.path(), "l", 7, RUN, z as u8, 2, 0)
            .unwrap()
            .unwrap();
        let rgba = decode(&png);
        assert_eq!(rgba[((10 * TILE) + (700 - 512)) * 4 + 3], 0);
        assert_eq!(rgba[((10 * TILE) + (699 - 512)) * 4 + 3], 255);
        // Level 0 is one tile; a tile past the pyramid, or of a board without a map, is none.
        let there = |board: i64, z: u8, x: u32| {
            cache
                .tile_png(dir.path(), "l", board, RUN, z, x, 0)
                .unwrap()
                .is_some()
        };
        assert!(there(7, 0, 0));
        assert!(!there(7, 0, 1));
        assert!(!there(7, 3, 0));
        assert!(!there(8, 0, 0));
    }

    #[test]
    fn a_tile_is_drawn_once_and_a_pyramid_built_once() {
        let dir = tempfile::tempdir().unwrap();
        board(dir.path());
        let cache = MapCache::default();
        // Level 1 is 350 x 250: two tiles across, one down.
        let a = cache
            .tile_png(dir.path(), "l", 7, RUN, 1, 0, 0)
            .unwrap()
            .unwrap();
        let b = cache
            .tile_png(dir.path(), "l", 7, RUN, 1, 0, 0)
            .unwrap()
            .unwrap();
        assert_eq!(a, b);
        assert_eq!((cache.renders(), cache.builds()), (1, 1));
        cache
            .tile_png(dir.path(), "l", 7, RUN, 1, 1, 0)
            .unwrap()
            .unwrap();
        assert_eq!((cache.renders(), cache.builds()), (2, 1));
        // Asked for another run's map under that id: none, nothing read or built.
        assert!(cache
            .pyramid(dir.path(), "l", 7, "00000000000000ff")
            .unwrap()
            .is_none());
        // Another store kept another board's map under the same id: the cached pyramid and
        // tiles of the first are not served for it, nor the second's for the first.
        let g = cache
            .pyramid(dir.path(), "l", 7, RUN)
            .unwrap()
            .unwrap()
            .kept
            .grid;
        let flat = Grid {
            width: g.width,
            rows: g.rows,
            data: vec![5.0; g.rows * g.width],
        };
        kept_map::write(dir.path(), "l", 7, 2, &g, &flat, None).unwrap();
        let other = "0000000000000002";
        let c = cache
            .tile_png(dir.path(), "l", 7, other, 1, 0, 0)
            .unwrap()
            .unwrap();
        assert_ne!(c, a);
        assert_eq!(cache.builds(), 2);
        assert!(cache
            .tile_png(dir.path(), "l", 7, RUN, 1, 1, 1)
            .unwrap()
            .is_none());
    }

    #[test]
    fn a_coarser_level_is_the_mean_of_the_valid_pixels() {
        let l = Level {
            w: 3,
            h: 2,
            data: vec![4, NONE, -3, 8, 5, NONE],
        };
        let c = halve(&l);
        assert_eq!((c.w, c.h), (2, 1));
        // (4 + 8 + 5) / 3 = 5.67 -> 6; the last column: -3 alone.
        assert_eq!(c.data, vec![6, -3]);
        let none = halve(&Level {
            w: 1,
            h: 1,
            data: vec![NONE],
        });
        assert_eq!(none.data, vec![NONE]);
    }

    fn decode(png: &[u8]) -> Vec<u8> {
        let mut d = png::Decoder::new(std::io::Cursor::new(png));
        d.set_transformations(png::Transformations::EXPAND);
        let mut r = d.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        r.next_frame(&mut buf).unwrap();
        assert_eq!(buf.len(), TILE * TILE * 4);
        buf
    }
}
