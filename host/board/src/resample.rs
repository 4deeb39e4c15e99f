//! A camera's pixel grid into the board grid in millimetres.
//!
//! A camera's output row `b` (a board row: conveyor travel in pixels since the encoder zero)
//! and column `c` lie on the board at
//!
//! ```text
//! x = x0 + b * row_mm + c * pitch * sin(rot)      (along the motion)
//! y = y0 +              c * pitch * cos(rot)      (across)
//! ```
//!
//! with the camera's [`CameraPlacement`] from the calibration: `row_mm` the travel per board row
//! (encoder scale), `pitch` the column pitch on the board (magnification), `rot` the rotation
//! of the image rows against the board's `y` axis, `(x0, y0)` where row 0, column 0 lies.
//! Resampling inverts that map at every board pixel and interpolates bilinearly over the valid
//! neighbours (at least half the weight valid, else invalid). A camera row that was *lost*
//! (its packet never arrived or was damaged, `dpsa board --streams`) is not an invalid pixel
//! to interpolate around: every board pixel whose footprint touches it stays invalid and is
//! marked in [`Layer::lost`].
//!
//! Where the processor has AVX2 ([`Instructions::best`]), the common pixel (in the rows at
//! hand, four valid neighbours, no lost row, no variance grid) and the search for where a
//! run of pixels was seen go four at a time in `std::arch` intrinsics (`resample/avx2.rs`):
//! the scalar operations in the scalar order, so every layer is the same to the bit
//! (`every_instruction_set_resamples_the_same_bits`). Intrinsics, not a SIMD crate: the
//! gathers from the camera's rows and the exact order of operations are the point, the
//! portable `std::simd` needs a nightly compiler, and the core's kernels
//! (`dpsa_core::lanes`) are written the same way.

use crate::Grid;
use dpsa_formats::instructions::Instructions;
use std::ops::Range;

#[cfg(target_arch = "x86_64")]
mod avx2;

/// Where a camera's pixels lie on the board (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraPlacement {
    /// Board `x` of row 0, column 0, mm.
    pub x0_mm: f64,
    /// Board `y` of row 0, column 0, mm.
    pub y0_mm: f64,
    /// Conveyor travel per board row, mm.
    pub row_mm: f64,
    /// Column pitch on the board, mm.
    pub pitch_mm: f64,
    /// Rotation of the image rows against the board `y` axis, rad.
    pub rotation_rad: f64,
}

impl CameraPlacement {
    /// Board `(x, y)` of camera row `b` (fractional), column `c`, mm.
    pub fn to_board(&self, b: f64, c: f64) -> (f64, f64) {
        let (s, co) = self.rotation_rad.sin_cos();
        (
            self.x0_mm + b * self.row_mm + c * self.pitch_mm * s,
            self.y0_mm + c * self.pitch_mm * co,
        )
    }

    /// Camera `(b, c)` (fractional) of board `(x, y)`, mm.
    pub fn to_camera(&self, x: f64, y: f64) -> (f64, f64) {
        let (s, co) = self.rotation_rad.sin_cos();
        let c = (y - self.y0_mm) / (self.pitch_mm * co);
        let b = (x - self.x0_mm - c * self.pitch_mm * s) / self.row_mm;
        (b, c)
    }
}

pub use dpsa_formats::grid::BoardGrid;

/// One camera on the board grid, over its footprint only: the window `rows x cols` of the
/// board grid its pixels can reach (outside it the camera saw nothing), so that a camera
/// covering a third of the board holds a third of it, not the whole board.
#[derive(Clone, Debug)]
pub struct Layer {
    /// Board grid rows the window covers.
    pub rows: Range<usize>,
    /// Board grid columns the window covers.
    pub cols: Range<usize>,
    /// Heights over the window, um (NaN: not seen or invalid).
    pub heights: Grid,
    /// Height per turn at each pixel of the window, um (to move the layer by whole turns).
    pub period_um: Grid,
    /// Blending weight over the window: 1 inside the camera, falling linearly to 0 over
    /// `feather_px` camera columns at its two side edges.
    pub weight: Grid,
    /// Variance of each height over the window, um^2, through the resampling weights (NaN:
    /// unknown); `None` when the camera came without one.
    pub variance: Option<Grid>,
    /// Window pixels (row-major, as `heights`) that fall on a lost camera row; empty when the
    /// camera lost no row.
    pub lost: Vec<bool>,
}

impl Layer {
    /// An empty layer over the window `rows x cols`, with a variance grid when `variance`.
    pub(crate) fn empty(rows: Range<usize>, cols: Range<usize>, variance: bool) -> Layer {
        let (w, n) = (cols.len(), rows.len());
        Layer {
            heights: Grid::invalid(w, n),
            period_um: Grid::invalid(w, n),
            weight: Grid {
                width: w,
                rows: n,
                data: vec![0.0; w * n],
            },
            variance: variance.then(|| Grid::invalid(w, n)),
            lost: Vec::new(),
            rows,
            cols,
        }
    }

    /// A layer over the window `rows x cols` on kept grids ([`crate::pool`]) whose values are left
    /// over from earlier layers: the caller writes every pixel of every grid.
    fn reused(rows: Range<usize>, cols: Range<usize>, variance: bool) -> Layer {
        let (w, n) = (cols.len(), rows.len());
        let grid = |fill: f32| Grid {
            width: w,
            rows: n,
            data: crate::pool::LAYERS.take(w * n, fill),
        };
        Layer {
            heights: grid(f32::NAN),
            period_um: grid(f32::NAN),
            weight: grid(0.0),
            variance: variance.then(|| grid(f32::NAN)),
            lost: Vec::new(),
            rows,
            cols,
        }
    }

    /// Hands the layer's grids on to later layers (the band it belongs to is blended).
    pub(crate) fn recycle(self) {
        let grids = [
            Some(self.heights),
            Some(self.period_um),
            Some(self.weight),
            self.variance,
        ];
        for g in grids.into_iter().flatten() {
            crate::pool::LAYERS.give(g.data);
        }
    }

    /// Index into the window's grids of board pixel `(r, c)`; `None` outside the window.
    #[inline]
    pub fn index(&self, r: usize, c: usize) -> Option<usize> {
        (self.rows.contains(&r) && self.cols.contains(&c))
            .then(|| (r - self.rows.start) * self.cols.len() + (c - self.cols.start))
    }

    /// Height at board pixel `(r, c)`, um; NaN outside the window.
    pub fn height(&self, r: usize, c: usize) -> f32 {
        self.index(r, c).map_or(f32::NAN, |i| self.heights.data[i])
    }

    /// Height per turn at board pixel `(r, c)`, um; NaN outside the window.
    pub fn period(&self, r: usize, c: usize) -> f32 {
        self.index(r, c)
            .map_or(f32::NAN, |i| self.period_um.data[i])
    }

    /// Blending weight at board pixel `(r, c)`; 0 outside the window.
    pub fn weight_at(&self, r: usize, c: usize) -> f32 {
        self.index(r, c).map_or(0.0, |i| self.weight.data[i])
    }

    /// Whether board pixel `(r, c)` falls on a lost camera row.
    pub fn is_lost(&self, r: usize, c: usize) -> bool {
        self.index(r, c)
            .and_then(|i| self.lost.get(i).copied())
            .unwrap_or(false)
    }

    /// The board pixels the two layers' windows share: rows and columns.
    pub fn overlap(&self, other: &Layer) -> (Range<usize>, Range<usize>) {
        let rows = self.rows.start.max(other.rows.start)..self.rows.end.min(other.rows.end);
        let cols = self.cols.start.max(other.cols.start)..self.cols.end.min(other.cols.end);
        (rows, cols)
    }
}

/// A camera's measurement as the resampling takes it.
#[derive(Clone, Copy, Debug)]
pub struct Source<'a> {
    /// Heights, um: row `i` is camera row `row0 + i` (board row `first_row + row0 + i`),
    /// `heights.width` columns.
    pub heights: &'a Grid,
    /// The camera row of `heights`' row 0 (0 for a whole camera; a band of its rows has
    /// more).
    pub row0: usize,
    /// Their variance, um^2 (same layout), if known.
    pub variance: Option<&'a Grid>,
    /// Height per turn of each column, um.
    pub period_um: &'a [f32],
    /// The board row of the camera's row 0.
    pub first_row: i64,
    /// Where each camera row was seen (`None`: row `i` at its nominal place), see
    /// `dpsa_sim::board::provenance::row_places`.
    pub places: Option<&'a crate::places::RowPlaces>,
    /// Camera rows that never arrived (empty, or one per camera row; `dpsa board
    /// --streams`).
    pub lost_rows: &'a [bool],
}

/// The fractional grid row at nominal row `t` (rows from the first) through the increasing
/// positions `pos` (`inv[i] = 1 / (pos[i + 1] - pos[i])`), searched from `hint` (the row the
/// last call found: a neighbouring pixel's row is within a step or two, where the rows'
/// places may have drifted many rows from their numbers); `None` outside `pos`.
fn row_at(pos: &[f64], inv: &[f64], t: f64, hint: &mut usize) -> Option<f64> {
    let (first, last) = (*pos.first()?, *pos.last()?);
    if !(t >= first && t <= last) {
        return None;
    }
    let mut i = (*hint).min(pos.len() - 1);
    while i > 0 && pos[i] > t {
        i -= 1;
    }
    while i + 1 < pos.len() && pos[i + 1] <= t {
        i += 1;
    }
    *hint = i;
    if i + 1 == pos.len() {
        return Some(i as i64 as f64);
    }
    // Through i64: `usize as f64` is a sequence of several instructions on x86-64 (no
    // unsigned conversion), `i64 as f64` one; the value (far below 2^53) is the same.
    Some(i as i64 as f64 + (t - pos[i]) * inv[i])
}

/// `1 / (pos[i + 1] - pos[i])` for every `i` (for [`row_at`]: a multiplication per pixel, not
/// a division).
fn inverse_steps(pos: &[f64]) -> Vec<f64> {
    pos.windows(2).map(|p| 1.0 / (p[1] - p[0])).collect()
}

/// Resamples a camera's heights onto the board rows `board_rows` of `grid` through its
/// placement (the layer's window: those rows of the camera's footprint).
pub fn resample(
    src: &Source,
    place: &CameraPlacement,
    grid: &BoardGrid,
    board_rows: Range<usize>,
    feather_px: f64,
) -> Layer {
    resample_on(
        Instructions::best(),
        src,
        place,
        grid,
        board_rows,
        feather_px,
    )
}

/// [`resample`] on the given instructions (AVX2 only where this processor has it).
pub fn resample_on(
    instructions: Instructions,
    src: &Source,
    place: &CameraPlacement,
    grid: &BoardGrid,
    board_rows: Range<usize>,
    feather_px: f64,
) -> Layer {
    let (heights, variance) = (src.heights, src.variance);
    let lost_rows = src.lost_rows;
    let (w, rows, row0) = (heights.width, heights.rows, src.row0);
    if w == 0 || rows == 0 {
        return Layer::empty(0..0, 0..0, variance.is_some());
    }
    // The footprint on the grid of the rows at hand: the bounding box of their four corners
    // (shifted by up to one row either way by their places), two pixels wider.
    let (b_lo, b_hi) = (
        (src.first_row + row0 as i64) as f64 - 1.0,
        (src.first_row + (row0 + rows) as i64) as f64,
    );
    let corners = [
        (b_lo, -1.0),
        (b_lo, w as f64),
        (b_hi, -1.0),
        (b_hi, w as f64),
    ]
    .map(|(b, c)| place.to_board(b, c));
    let span = |v: [f64; 4], origin: f64, n: usize| {
        let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let lo = ((lo - origin) / grid.pitch_mm - 2.0).floor().max(0.0) as usize;
        let hi = ((hi - origin) / grid.pitch_mm + 2.0).ceil().max(0.0) as usize;
        lo.min(n)..hi.min(n)
    };
    let (is, js) = (
        span(corners.map(|p| p.0), grid.x0_mm, grid.rows),
        span(corners.map(|p| p.1), grid.y0_mm, grid.width),
    );
    let start = is.start.max(board_rows.start);
    let is = start..is.end.min(board_rows.end).max(start);
    // The layer holds that window only (every pixel of it written below).
    let mut out = Layer::reused(is.clone(), js.clone(), variance.is_some());
    let any_lost = lost_rows.iter().any(|&l| l);
    if any_lost {
        out.lost = vec![false; out.heights.data.len()];
    }
    // `CameraPlacement::to_camera` with its trigonometry and division once: the camera column
    // depends on the grid column only, the row on both through `b_row - along_c`.
    let (sin, cos) = place.rotation_rad.sin_cos();
    let inv_row = 1.0 / place.row_mm;
    let cols: Vec<(f64, f64)> = js
        .clone()
        .map(|j| {
            let c = (grid.centre(0, j).1 - place.y0_mm) / (place.pitch_mm * cos);
            (c, c * place.pitch_mm * sin * inv_row)
        })
        .collect();
    let inv_steps = src.places.map(|pl| inverse_steps(&pl.along));
    let ctx = Sampler {
        src,
        x0: place.x0_mm,
        inv_row,
        grid,
        cols: &cols,
        places: src.places.zip(inv_steps.as_deref()),
        any_lost,
        inv_feather: 1.0 / feather_px.max(1e-9),
        last: ((rows - 1) as f64, (w - 1) as f64),
        avx2: instructions.avx2(),
    };
    // The rows in parts, one per core (each pixel is its own: the parts are the rows
    // resampled one after the other).
    let threads = std::thread::available_parallelism().map_or(1, |t| t.get());
    let part_rows = is.len().div_ceil(threads).max(MIN_PART_ROWS);
    let mut rest = Out {
        heights: &mut out.heights.data,
        period: &mut out.period_um.data,
        weight: &mut out.weight.data,
        variance: out.variance.as_mut().map(|v| &mut v.data[..]),
        lost: &mut out.lost,
    };
    std::thread::scope(|sc| {
        let mut i = is.start;
        while i < is.end {
            let n = part_rows.min(is.end - i);
            let (part, tail) = rest.split_at(n * js.len());
            rest = tail;
            let ctx = &ctx;
            let rows = i..i + n;
            if i + n < is.end {
                sc.spawn(move || ctx.rows(rows, part));
            } else {
                ctx.rows(rows, part);
            }
            i += n;
        }
    });
    out
}

/// Columns of a row whose camera rows are found together ([`Sampler::seen_at`]).
const RUN: usize = 64;

/// Fewest rows a thread of [`resample`] takes.
const MIN_PART_ROWS: usize = 32;

/// A layer's grids over some of its rows (row-major, whole rows of the window).
struct Out<'a> {
    heights: &'a mut [f32],
    period: &'a mut [f32],
    weight: &'a mut [f32],
    variance: Option<&'a mut [f32]>,
    /// Empty when the camera lost no row.
    lost: &'a mut [bool],
}

impl<'a> Out<'a> {
    /// The first `n` pixels, and the rest.
    fn split_at(self, n: usize) -> (Out<'a>, Out<'a>) {
        let (h0, h1) = self.heights.split_at_mut(n);
        let (p0, p1) = self.period.split_at_mut(n);
        let (w0, w1) = self.weight.split_at_mut(n);
        let (v0, v1) = match self.variance {
            Some(v) => {
                let (a, b) = v.split_at_mut(n);
                (Some(a), Some(b))
            }
            None => (None, None),
        };
        let (l0, l1) = self.lost.split_at_mut(n.min(self.lost.len()));
        (
            Out {
                heights: h0,
                period: p0,
                weight: w0,
                variance: v0,
                lost: l0,
            },
            Out {
                heights: h1,
                period: p1,
                weight: w1,
                variance: v1,
                lost: l1,
            },
        )
    }
}

/// One board pixel resampled.
enum Pixel {
    /// Outside the camera's rows at hand, or too few valid neighbours.
    Invalid,
    /// On a lost camera row.
    Lost,
    /// Height, variance (um^2), height per turn, blending weight.
    Valid(f32, f32, f32, f32),
}

/// What [`resample`] resamples every pixel with.
struct Sampler<'a> {
    src: &'a Source<'a>,
    /// The placement's `x0_mm` and `1 / row_mm`.
    x0: f64,
    inv_row: f64,
    grid: &'a BoardGrid,
    /// Per window column: the camera column and its share of the camera row.
    cols: &'a [(f64, f64)],
    /// The row places and their inverse steps ([`inverse_steps`]).
    places: Option<(&'a crate::places::RowPlaces, &'a [f64])>,
    any_lost: bool,
    inv_feather: f64,
    /// The last row at hand and the last column.
    last: (f64, f64),
    /// Whether to take [`avx2::run`] (detected).
    avx2: bool,
}

impl Sampler<'_> {
    /// Board rows `is` (whole rows of the window, from its row `is.start`) into `out`, every
    /// pixel written.
    fn rows(&self, is: Range<usize>, out: Out<'_>) {
        let lw = self.cols.len();
        let Out {
            heights,
            period,
            weight,
            mut variance,
            lost,
        } = out;
        let (mut bs, mut cs) = ([0.0f64; RUN], [0.0f64; RUN]);
        let src = self.src;
        let taps = Taps {
            hs: &src.heights.data,
            vs: src.variance.map(|v| &v.data[..]),
            period: src.period_um,
            lost_rows: src.lost_rows,
            w: src.heights.width,
            rows: src.heights.rows,
            row0: src.row0,
            row0_f: src.row0 as i64 as f64,
            last_b: self.last.0,
            last_c: self.last.1,
            inv_feather: self.inv_feather,
            any_lost: self.any_lost,
        };
        #[cfg(target_arch = "x86_64")]
        let avx2 = self.avx2 && avx2::takes(&taps);
        for (k, i) in is.enumerate() {
            let b_row =
                (self.grid.centre(i, 0).0 - self.x0) * self.inv_row - self.src.first_row as f64;
            // The row places' search starts from the nominal row, then from the last found.
            let mut hint = b_row.max(0.0) as usize;
            for (n, run) in self.cols.chunks(RUN).enumerate() {
                let (bs, cs) = (&mut bs[..run.len()], &mut cs[..run.len()]);
                self.seen_at(b_row, run, &mut hint, bs, cs);
                let at = k * lw + n * RUN;
                // The run's pixels left to `Taps::pixel`: all, or those AVX2 did not take.
                let mut left = u64::MAX >> (64 - run.len());
                #[cfg(target_arch = "x86_64")]
                if avx2 {
                    let end = at + run.len();
                    #[allow(unsafe_code)]
                    // SAFETY: `self.avx2` holds only where `Instructions::avx2`, and
                    // `avx2::takes(&taps)` was checked above.
                    unsafe {
                        left = avx2::run(
                            &taps,
                            bs,
                            cs,
                            &mut heights[at..end],
                            &mut period[at..end],
                            &mut weight[at..end],
                        );
                    }
                }
                while left != 0 {
                    let jj = left.trailing_zeros() as usize;
                    left &= left - 1;
                    let (b, c) = (bs[jj], cs[jj]);
                    let idx = at + jj;
                    let (h, v, t, wt) = match taps.pixel(b, c) {
                        Pixel::Valid(h, v, t, wt) => (h, v, t, wt),
                        Pixel::Invalid => (f32::NAN, f32::NAN, f32::NAN, 0.0),
                        Pixel::Lost => {
                            lost[idx] = true;
                            (f32::NAN, f32::NAN, f32::NAN, 0.0)
                        }
                    };
                    heights[idx] = h;
                    period[idx] = t;
                    weight[idx] = wt;
                    if let Some(vs) = variance.as_deref_mut() {
                        vs[idx] = v;
                    }
                }
            }
        }
    }

    /// Where the pixels of a run of window columns `run` of the board row at nominal camera
    /// row `b_row` were seen: camera rows `bs` (from the camera's row 0; NaN outside the row
    /// places) and columns `cs`.
    ///
    /// A run spans a small fraction of a camera row along the motion, so nearly always all its
    /// pixels fall between the same two row places: [`row_at`]'s search is made once for the
    /// run, and each pixel takes the same arithmetic [`row_at`] would (the same values).
    #[inline]
    fn seen_at(
        &self,
        b_row: f64,
        run: &[(f64, f64)],
        hint: &mut usize,
        bs: &mut [f64],
        cs: &mut [f64],
    ) {
        let Some((pl, inv)) = self.places else {
            for ((b, c), &(cc, along_c)) in bs.iter_mut().zip(cs.iter_mut()).zip(run) {
                (*b, *c) = (b_row - along_c, cc);
            }
            return;
        };
        let pos = &pl.along;
        let across = |b: f64, c: f64| {
            // `b >= 0` (a row of `along`): truncation is its floor. Through i64: the
            // saturating f64 -> u64 conversion is several instructions more on x86-64, and
            // `b` is far below 2^63.
            let i = b as i64;
            let f = b - i as f64;
            let i = i as usize;
            let a0 = pl.across.get(i).copied().unwrap_or(0.0);
            let a1 = pl.across.get(i + 1).copied().unwrap_or(a0);
            c - (a0 * (1.0 - f) + a1 * f)
        };
        // The nominal rows of the run's ends are its least and greatest (`along_c` is the
        // camera column times a constant, and the columns increase along the window).
        let (t0, t1) = (b_row - run[0].1, b_row - run[run.len() - 1].1);
        let (lo, hi) = (t0.min(t1), t0.max(t1));
        let one = match row_at(pos, inv, lo, hint) {
            Some(_) if hi.is_finite() && *hint + 1 < pos.len() && hi < pos[*hint + 1] => {
                Some(*hint)
            }
            _ => None,
        };
        match one {
            Some(s) => {
                // `pos[s] <= lo <= t <= hi < pos[s + 1]` for every pixel: `row_at` would find
                // row `s` for each.
                let (p, q) = (pos[s], inv[s]);
                let mut done = 0;
                #[cfg(target_arch = "x86_64")]
                if self.avx2 && s < pl.across.len() && pl.across.len() < i32::MAX as usize {
                    #[allow(unsafe_code)]
                    // SAFETY: `self.avx2` holds only where `Instructions::avx2`; `s` is a row of
                    // `across`, which has fewer than `i32::MAX`.
                    unsafe {
                        done = avx2::seen_in_one((s, p, q), b_row, run, &pl.across, bs, cs);
                    }
                }
                let s = s as i64 as f64;
                let (bs, cs, run) = (&mut bs[done..], &mut cs[done..], &run[done..]);
                for ((b, c), &(cc, along_c)) in bs.iter_mut().zip(cs.iter_mut()).zip(run) {
                    let t = b_row - along_c;
                    *b = s + (t - p) * q;
                    *c = across(*b, cc);
                }
            }
            None => {
                for ((b, c), &(cc, along_c)) in bs.iter_mut().zip(cs.iter_mut()).zip(run) {
                    match row_at(pos, inv, b_row - along_c, hint) {
                        Some(r) => (*b, *c) = (r, across(r, cc)),
                        None => (*b, *c) = (f64::NAN, cc),
                    }
                }
            }
        }
    }
}

/// What a pixel is interpolated from: the rows at hand of a camera ([`Sampler`]'s, copied
/// into locals for the loop).
#[derive(Clone, Copy)]
struct Taps<'a> {
    hs: &'a [f32],
    vs: Option<&'a [f32]>,
    period: &'a [f32],
    lost_rows: &'a [bool],
    w: usize,
    rows: usize,
    row0: usize,
    /// `row0` as f64.
    row0_f: f64,
    last_b: f64,
    last_c: f64,
    inv_feather: f64,
    any_lost: bool,
}

impl Taps<'_> {
    /// The pixel at camera row `b` (from the camera's row 0, where the row places put it;
    /// NaN: none) and column `c`.
    #[inline]
    fn pixel(&self, b: f64, c: f64) -> Pixel {
        let Taps {
            hs,
            vs,
            period,
            lost_rows,
            w,
            rows,
            row0,
            row0_f,
            last_b,
            last_c,
            inv_feather,
            any_lost,
        } = *self;
        // The row within the rows at hand.
        let b = b - row0_f;
        if !(b >= 0.0 && c >= 0.0 && b <= last_b && c <= last_c) {
            return Pixel::Invalid;
        }
        // Both non-negative here: truncation is the floor (no libm `floor` call in the
        // hot loop; the x86-64 baseline has no rounding instruction), and far below 2^63
        // (through i64, as above).
        let (b0, c0) = (b as i64, c as i64);
        let (fb, fc) = (b - b0 as f64, c - c0 as f64);
        let (b0, c0) = (b0 as usize, c0 as usize);
        let (b1, c1) = ((b0 + 1).min(rows - 1), (c0 + 1).min(w - 1));
        let lost = |r: usize| lost_rows.get(row0 + r).copied().unwrap_or(false);
        if any_lost && ((lost(b0) && fb < 1.0) || (lost(b1) && fb > 0.0)) {
            return Pixel::Lost;
        }
        let (r0, r1) = (b0 * w, b1 * w);
        let edge = c.min(last_c - c) + 0.5;
        let wt = (edge * inv_feather).clamp(1e-3, 1.0) as f32;
        let t = f64::from(period[c0]) * (1.0 - fc) + f64::from(period[c1]) * fc;
        if vs.is_none() {
            // Four valid neighbours (nearly every pixel): the bilinear value as two lerps
            // along the row, one across, with no division by the weights' sum (1 up to
            // rounding).
            let (h00, h01, h10, h11) = (hs[r0 + c0], hs[r0 + c1], hs[r1 + c0], hs[r1 + c1]);
            if (h00 + h01 + h10 + h11).is_finite() {
                let top = f64::from(h00) + fc * (f64::from(h01) - f64::from(h00));
                let bottom = f64::from(h10) + fc * (f64::from(h11) - f64::from(h10));
                return Pixel::Valid((top + fb * (bottom - top)) as f32, f32::NAN, t as f32, wt);
            }
        }
        let taps = [
            (r0 + c0, (1.0 - fb) * (1.0 - fc)),
            (r0 + c1, (1.0 - fb) * fc),
            (r1 + c0, fb * (1.0 - fc)),
            (r1 + c1, fb * fc),
        ];
        let (mut sum, mut wsum, mut vsum) = (0.0f64, 0.0f64, 0.0f64);
        // Without a branch per tap: a tap left out adds `0 x 0`, which leaves each sum the
        // same value (none of them is ever -0: it starts at +0 and `x + (-x)` is +0).
        for (k, wt) in taps {
            let h = hs[k];
            let take = h.is_finite() && wt > 0.0;
            let m = if take { wt } else { 0.0 };
            sum += m * if take { f64::from(h) } else { 0.0 };
            wsum += m;
            if let Some(v) = vs {
                vsum += m * m * if take { f64::from(v[k]) } else { 0.0 };
            }
        }
        if wsum < 0.5 {
            return Pixel::Invalid;
        }
        let var = match vs {
            Some(_) => (vsum / (wsum * wsum)) as f32,
            None => f32::NAN,
        };
        Pixel::Valid((sum / wsum) as f32, var, t as f32, wt)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rows seen off their nominal place: the inverse through `row_at` finds, for any nominal
    /// position, the fractional row whose interpolated position is that position.
    #[test]
    fn row_at_inverts_the_row_positions() {
        let pos: Vec<f64> = (0..50)
            .map(|i| i as f64 + [0.4, -0.45, 0.1, 0.0, -0.2][i / 8 % 5])
            .collect();
        for k in 0..400 {
            let t = pos[0] + k as f64 * (pos[49] - pos[0]) / 399.0;
            let mut hint = [0, t.max(0.0) as usize, 49, 1000][k % 4];
            let r = row_at(&pos, &inverse_steps(&pos), t, &mut hint).unwrap();
            let (i, f) = (r.floor() as usize, r - r.floor());
            let back = if i + 1 < pos.len() {
                pos[i] * (1.0 - f) + pos[i + 1] * f
            } else {
                pos[i]
            };
            assert!((back - t).abs() < 1e-9, "{t} -> {r} -> {back}");
        }
        let inv = inverse_steps(&pos);
        assert_eq!(row_at(&pos, &inv, pos[0] - 0.01, &mut 0), None);
        assert_eq!(row_at(&pos, &inv, pos[49] + 0.01, &mut 0), None);
        assert_eq!(row_at(&[], &[], 0.0, &mut 0), None);
    }

    /// A run of columns takes the rows the search would find for each of its pixels, the
    /// same values bit for bit, whether the run lies between two row places or crosses
    /// several (a steep slope across the run), and NaN where the search finds none.
    #[test]
    fn a_run_of_columns_sees_each_pixel_where_the_search_does() {
        let mut rng = crate::test_rng::Lcg(99);
        let mut rnd = || rng.next();
        let n = 200;
        let along: Vec<f64> = (0..n).map(|i| i as f64 + 0.9 * (rnd() - 0.5)).collect();
        let across: Vec<f64> = (0..n).map(|_| 0.6 * (rnd() - 0.5)).collect();
        let places = crate::places::RowPlaces {
            along,
            across,
            samples: Vec::new(),
        };
        let inv = inverse_steps(&places.along);
        let heights = Grid::invalid(4, 4);
        let src = Source {
            heights: &heights,
            row0: 0,
            variance: None,
            period_um: &[400.0; 4],
            first_row: 0,
            places: Some(&places),
            lost_rows: &[],
        };
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 4,
            width: 4,
        };
        let (mut crossed, mut nan) = (0, 0);
        // Rows per column along the motion: none, a small rotation either way, steep.
        // The baseline, and the AVX2 form where this processor has it.
        let avx2 = Instructions::best() == Instructions::Avx2;
        let forms = [
            (0.0, false),
            (0.0, avx2),
            (0.0017, avx2),
            (-0.0023, false),
            (-0.0023, avx2),
        ];
        let forms = forms
            .into_iter()
            .chain([0.0017, 0.04, -0.11].map(|s| (s, false)));
        let forms = forms.chain([0.04, -0.11].map(|s| (s, avx2)));
        for (slope, avx2) in forms {
            let cols: Vec<(f64, f64)> = (0..300)
                .map(|j| (j as f64 * 1.01, j as f64 * slope))
                .collect();
            let ctx = Sampler {
                src: &src,
                x0: 0.0,
                inv_row: 1.0,
                grid: &grid,
                cols: &cols,
                places: Some((&places, &inv)),
                any_lost: false,
                inv_feather: 0.1,
                last: (3.0, 3.0),
                avx2,
            };
            for k in 0..400 {
                let b_row = -15.0 + 230.0 * rnd();
                let mut hint = [0, 50, 199, 1000][k % 4];
                for run in cols.chunks(RUN) {
                    let (mut bs, mut cs) = (vec![0.0; run.len()], vec![0.0; run.len()]);
                    ctx.seen_at(b_row, run, &mut hint, &mut bs, &mut cs);
                    let mut segs = std::collections::BTreeSet::new();
                    for (jj, &(c, along_c)) in run.iter().enumerate() {
                        let mut h = 0;
                        let (b, c) = match row_at(&places.along, &inv, b_row - along_c, &mut h) {
                            Some(r) => {
                                segs.insert(h);
                                let i = r.floor() as usize;
                                let f = r - i as f64;
                                let a0 = places.across.get(i).copied().unwrap_or(0.0);
                                let a1 = places.across.get(i + 1).copied().unwrap_or(a0);
                                (r, c - (a0 * (1.0 - f) + a1 * f))
                            }
                            None => (f64::NAN, c),
                        };
                        if b.is_nan() {
                            nan += 1;
                            assert!(bs[jj].is_nan());
                        } else {
                            assert_eq!(bs[jj].to_bits(), b.to_bits(), "{slope} {b_row} {jj}");
                        }
                        assert_eq!(cs[jj].to_bits(), c.to_bits(), "{slope} {b_row} {jj}");
                    }
                    crossed += usize::from(segs.len() > 1);
                }
            }
        }
        assert!(crossed > 100 && nan > 100, "{crossed} {nan}");
    }

    /// The AVX2 form gives every pixel of a layer the baseline's bits: heights with invalid
    /// and infinite pixels, odd widths, a band of a camera's rows, rotations either way, row
    /// places, lost rows and a variance grid (the last two left to the baseline), the
    /// window's edges and the rows at hand's.
    #[test]
    fn every_instruction_set_resamples_the_same_bits() {
        let mut rng = crate::test_rng::Lcg(2026);
        let mut rnd = move || rng.next();
        let (mut cases, mut taken) = (0, 0);
        for case in 0..24 {
            let w = [1, 2, 3, 5, 37, 64, 65, 203][case % 8];
            let rows = [1, 2, 7, 60, 133][case % 5];
            let row0 = [0, 3, 40][case % 3];
            let mut cam = Grid::invalid(w, rows);
            for v in &mut cam.data {
                let u = rnd();
                *v = match u {
                    u if u < 0.06 => f32::NAN,
                    u if u < 0.07 => f32::INFINITY,
                    u if u < 0.08 => f32::NEG_INFINITY,
                    _ => (400.0 * rnd() - 200.0) as f32,
                };
            }
            let var = cam.data.iter().map(|_| rnd() as f32).collect::<Vec<_>>();
            let var = Grid {
                width: w,
                rows,
                data: var,
            };
            let period: Vec<f32> = (0..w).map(|_| (300.0 + 200.0 * rnd()) as f32).collect();
            let total = row0 + rows;
            let places = crate::places::RowPlaces {
                along: (0..total).map(|i| i as f64 + 0.8 * (rnd() - 0.5)).collect(),
                across: (0..total).map(|_| 0.7 * (rnd() - 0.5)).collect(),
                samples: Vec::new(),
            };
            let lost: Vec<bool> = (0..total).map(|_| rnd() < 0.05).collect();
            let (with_places, with_lost, with_var) = (case % 4 == 1, case % 6 == 5, case % 7 == 3);
            let src = Source {
                heights: &cam,
                row0,
                variance: with_var.then_some(&var),
                period_um: &period,
                first_row: 7,
                places: with_places.then_some(&places),
                lost_rows: if with_lost { &lost } else { &[] },
            };
            let p = CameraPlacement {
                x0_mm: 0.1,
                y0_mm: 0.2,
                row_mm: 0.03,
                pitch_mm: 0.0299 + 0.0003 * rnd(),
                rotation_rad: 0.02 * (rnd() - 0.5),
            };
            let grid = BoardGrid {
                x0_mm: 0.0,
                y0_mm: 0.0,
                pitch_mm: 0.03,
                rows: total + 20,
                width: w + 10,
            };
            let band = [0..grid.rows, 9..grid.rows / 2 + 9][case % 2].clone();
            // Weights clamped at 1 (narrow feathers) and at 1e-3 (a feather of 1000 columns).
            let feather = [1.0, 15.0, 80.0, 1000.0][(case / 3) % 4];
            let base = resample_on(
                Instructions::Baseline,
                &src,
                &p,
                &grid,
                band.clone(),
                feather,
            );
            let best = resample_on(Instructions::best(), &src, &p, &grid, band, feather);
            let bits = |g: &Grid| g.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(
                (base.rows.clone(), base.cols.clone()),
                (best.rows.clone(), best.cols.clone())
            );
            assert_eq!(bits(&base.heights), bits(&best.heights), "case {case}");
            assert_eq!(bits(&base.period_um), bits(&best.period_um), "case {case}");
            assert_eq!(bits(&base.weight), bits(&best.weight), "case {case}");
            assert_eq!(
                base.variance.as_ref().map(bits),
                best.variance.as_ref().map(bits)
            );
            assert_eq!(base.lost, best.lost, "case {case}");
            cases += 1;
            #[cfg(target_arch = "x86_64")]
            {
                let valid = base.heights.data.iter().filter(|h| h.is_finite()).count();
                taken += usize::from(!with_var && !with_lost && valid > 100);
            }
        }
        assert_eq!(cases, 24);
        // On x86-64 with AVX2 most cases took the vector form for some of their pixels.
        #[cfg(target_arch = "x86_64")]
        if Instructions::best() == Instructions::Avx2 {
            assert!(taken >= 8, "{taken}");
        }
    }

    #[test]
    fn placement_round_trips() {
        let p = CameraPlacement {
            x0_mm: 3.0,
            y0_mm: 50.0,
            row_mm: 0.0277,
            pitch_mm: 0.02755,
            rotation_rad: 0.003,
        };
        for &(b, c) in &[(0.0, 0.0), (1234.5, 17.25), (7000.0, 2047.0)] {
            let (x, y) = p.to_board(b, c);
            let (b2, c2) = p.to_camera(x, y);
            assert!((b - b2).abs() < 1e-9 && (c - c2).abs() < 1e-9);
        }
    }

    #[test]
    fn a_plane_resamples_exactly_and_the_footprint_is_where_the_placement_says() {
        // Heights a linear function of board (x, y): bilinear resampling reproduces it.
        let p = CameraPlacement {
            x0_mm: 0.0,
            y0_mm: 1.0,
            row_mm: 0.03,
            pitch_mm: 0.0301,
            rotation_rad: 0.004,
        };
        let (w, rows, first) = (100usize, 300usize, 10i64);
        let mut cam = Grid::invalid(w, rows);
        for r in 0..rows {
            for c in 0..w {
                let (x, y) = p.to_board((r as i64 + first) as f64, c as f64);
                *cam.at_mut(r, c) = (2.0 * x + 3.0 * y) as f32;
            }
        }
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 340,
            width: 140,
        };
        let src = Source {
            heights: &cam,
            variance: None,
            period_um: &vec![400.0; w],
            row0: 0,
            first_row: first,
            places: None,
            lost_rows: &[],
        };
        let l = resample(&src, &p, &grid, 0..grid.rows, 20.0);
        let mut seen = 0;
        for i in 0..grid.rows {
            for j in 0..grid.width {
                let h = l.height(i, j);
                let (x, y) = grid.centre(i, j);
                let (b, c) = p.to_camera(x, y);
                let inside = b >= first as f64
                    && b <= (first + rows as i64 - 1) as f64
                    && (0.0..=(w - 1) as f64).contains(&c);
                assert_eq!(h.is_finite(), inside, "({i}, {j})");
                if inside {
                    seen += 1;
                    assert!((f64::from(h) - (2.0 * x + 3.0 * y)).abs() < 1e-3);
                    assert_eq!(l.period(i, j), 400.0);
                    let wt = l.weight_at(i, j);
                    assert!(wt > 0.0 && wt <= 1.0);
                }
            }
        }
        assert!(seen > 20_000);
        // The window is the footprint, not the board: every finite pixel inside it, and it
        // is narrower than the board across.
        assert!(l.cols.len() < grid.width && l.heights.data.len() == l.rows.len() * l.cols.len());
        assert!(!l.height(grid.rows + 5, 0).is_finite() && l.weight_at(0, grid.width) == 0.0);
    }
}
