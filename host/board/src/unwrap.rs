//! Wrapped heights into absolute heights, referenced to the smooth local board surface.
//!
//! A camera measures height modulo one fringe turn: `h = u T(c)` with `u` in `[-1/2, 1/2)`
//! turns and `T(c)` the height per turn of column `c` (non-telecentric optics: it varies
//! across the columns). The board's bow spans several turns; a paste deposit stays within
//! half a turn of the board surface around it. So the unwrapping never follows pixel to pixel
//! across a deposit's wall: it estimates the board surface first and then puts every pixel on
//! the turn nearest to it.
//!
//! 1. **Blocks.** The grid is cut into `block x block` pixel blocks. Each block's phase is the
//!    trimmed circular mean of its valid pixels (pixels more than 1/8 turn from the first mean
//!    are dropped, which removes most paste from a board block). Blocks with fewer than a
//!    quarter valid pixels have none.
//! 2. **Block unwrapping.** From the block with the most valid pixels, a quality-guided flood
//!    (8 neighbours, the smallest wrapped step first) puts each block on the turn nearest its
//!    already unwrapped neighbour: board blocks are reached along board paths before any step
//!    onto a deposit is taken. The bow changes far less than half a turn from one block
//!    to the next (1 mm over 110 mm is 0.25 um per 28 um pixel), so this is safe. Blocks it
//!    does not reach (no valid block path) take the surface of the nearest reached block.
//! 3. **Surface.** The block values, bilinear between block centres, are the first surface;
//!    every pixel goes on its nearest turn; each block's surface is then re-estimated as the
//!    30th percentile of its pixels (the board lies below the paste) and smoothed with the
//!    median of its 3 x 3 blocks.
//! 4. **Pixels.** Every valid pixel goes on the turn nearest the final surface.
//!
//! The result is relative: turn 0 is the seed block's. [`Unwrapped::shift`] moves it by
//! whole turns; the board map chooses the turn from the cameras' overlaps and the board's
//! clamped edges (`super::blend`).

use crate::Grid;
use dpsa_formats::instructions::Instructions;
use std::collections::{BinaryHeap, VecDeque};

/// Default block size, px.
pub const BLOCK: usize = 16;

/// A camera's heights on one consistent turn, um (see the module docs).
#[derive(Clone, Debug)]
pub struct Unwrapped {
    /// Heights, um; NaN where the input was invalid.
    pub heights: Grid,
    /// Height per turn of each column, um.
    pub period_um: Vec<f32>,
    /// Valid pixels whose block the flood did not reach (placed from an extrapolated surface).
    pub unreached: usize,
    /// Of them, per row.
    pub unreached_rows: Vec<u32>,
}

impl Unwrapped {
    /// Moves every height by `turns` whole turns (`turns x T(c)`).
    pub fn shift(&mut self, turns: i32) {
        shift_rows(&mut self.heights.data, &self.period_um, turns);
    }
}

/// Moves every height of the rows `heights` (of `period_um.len()` columns) by `turns` whole
/// turns of its column.
fn shift_rows(heights: &mut [f32], period_um: &[f32], turns: i32) {
    if turns == 0 {
        return;
    }
    for row in heights.chunks_exact_mut(period_um.len().max(1)) {
        for (h, &t) in row.iter_mut().zip(period_um) {
            *h += turns as f32 * t;
        }
    }
}

/// The buffers of an unwrapping, kept from chunk to chunk by an [`Unwrapper`] (a chunk's are
/// megabytes: allocated afresh, every page of them is faulted in and zeroed again).
#[derive(Clone, Debug, Default)]
struct Scratch {
    /// Turns per pixel.
    turns: Vec<f32>,
    /// The unwrapped heights, um (row-major, NaN where invalid).
    heights: Vec<f32>,
}

/// Steps of the circular mean's angle table per turn.
const MEAN_STEPS: usize = 4096;

/// The angle table's sines and cosines are integers in units of `2^-24`.
const MEAN_ONE: f64 = 16_777_216.0;

/// `(sin, cos)` of `k / MEAN_STEPS` turns, `k` in `0..MEAN_STEPS`, in units of `2^-24`
/// (rounded). Integers, so that a block's sums are exact and do not depend on their order:
/// the sums run as several independent chains (an `f64` sum is one chain of dependent
/// additions, four cycles each), and the mean is the same whatever the compiler makes of it.
fn angle_table() -> &'static [[i32; 2]] {
    static T: std::sync::OnceLock<Vec<[i32; 2]>> = std::sync::OnceLock::new();
    T.get_or_init(|| {
        (0..MEAN_STEPS)
            .map(|k| {
                let (s, c) = (std::f64::consts::TAU * k as f64 / MEAN_STEPS as f64).sin_cos();
                [(s * MEAN_ONE).round() as i32, (c * MEAN_ONE).round() as i32]
            })
            .collect()
    })
}

/// The angle table's index of a wrapped turn `u` (in `[-1/2, 1/2)`, finite): `u` to the
/// nearest 1/4096 turn, modulo a turn. `u x 4096` is exact (a power of two), its rounding
/// exact below `2^22` (`round_f32`), and the mask is the Euclidean remainder of a power of
/// two in two's complement.
#[inline]
fn angle_index(u: f32) -> u16 {
    ((round_f32(u * MEAN_STEPS as f32) as i32) & (MEAN_STEPS as i32 - 1)) as u16
}

/// Circular mean of the turns whose angle-table indices are `ks` (kept where `keep` is true),
/// in `[-1/2, 1/2)`; `None` without samples (or when their sines and cosines cancel
/// exactly). Each sample's angle is taken to the nearest 1/4096 turn (a table, not two
/// transcendental calls per pixel): at most 0.8 mrad off, far below what a block's first
/// surface estimate needs (its pixels are placed on the nearest turn to it and the surface
/// is re-estimated from them, step 3). The table's rounding to `2^-24` moves the mean by
/// less than `1e-7` turns.
fn circular_mean(ks: &[u16], keep: impl Fn(usize) -> bool) -> Option<f32> {
    let table = angle_table();
    // Two chains per sum (at most 2^16 samples of at most 2^24 each: far inside i64).
    let (mut s, mut c, mut n) = ([0i64; 2], [0i64; 2], 0usize);
    for (i, pair) in ks.chunks(2).enumerate() {
        for (j, &k) in pair.iter().enumerate() {
            let take = keep(2 * i + j);
            let [sa, ca] = table[usize::from(k)];
            let m = i64::from(take);
            s[j] += m * i64::from(sa);
            c[j] += m * i64::from(ca);
            n += usize::from(take);
        }
    }
    let (s, c) = (s[0] + s[1], c[0] + c[1]);
    (n > 0 && (s != 0 || c != 0))
        .then(|| ((s as f64).atan2(c as f64) / std::f64::consts::TAU) as f32)
}

/// `u` moved by whole turns to lie within half a turn of `near` (exactly half a turn: to the
/// even number of turns).
fn nearest(u: f32, near: f32) -> f32 {
    u + round_f32(near - u)
}

/// `x` to the nearest integer, ties to even, by adding and taking away `1.5 x 2^23`: exact for
/// `|x| < 2^22` (turn counts are far smaller), NaN stays NaN. `f32::round` is a libm call on
/// the x86-64 baseline (no rounding instruction), 6 % of `dpsa board`'s time on the paper
/// board where this is two additions.
#[inline]
fn round_f32(x: f32) -> f32 {
    const M: f32 = 12_582_912.0;
    (x + M) - M
}

/// `x`'s place in `f32::total_cmp`'s order as an unsigned integer: `order_key(a) <
/// order_key(b)` exactly where `a.total_cmp(&b)` is `Less` (NaNs and signed zeros included),
/// and [`from_order_key`] gives back `x`'s bits. A non-negative value (sign bit clear) gets its
/// sign bit set, so it comes after every negative; a negative one has every bit flipped, so a
/// larger magnitude comes first.
#[inline]
fn order_key(x: f32) -> u32 {
    let b = x.to_bits();
    b ^ (((b as i32 >> 31) as u32) | 0x8000_0000)
}

/// The value whose [`order_key`] is `k`, to the bit.
#[inline]
fn from_order_key(k: u32) -> f32 {
    f32::from_bits(if k & 0x8000_0000 != 0 {
        k ^ 0x8000_0000
    } else {
        !k
    })
}

/// The finite values of `from` written into `to` from index `n` on (which has room for all
/// of `from` past `n`); returns the index past the last one written. Without a branch per
/// value: every value is written, and the next one overwrites it unless it is finite.
#[inline]
fn compact_finite(from: &[f32], to: &mut [f32], n: usize) -> usize {
    let to = &mut to[n..n + from.len()];
    let mut k = 0;
    for &u in from {
        to[k] = u;
        k += usize::from(u.is_finite());
    }
    n + k
}

/// Unwraps `wrapped` (heights in `[-T(c)/2, T(c)/2)`, NaN invalid) with `period_um[c]` per
/// column. `block` is the block size in pixels (at least 2).
pub fn unwrap(wrapped: &Grid, period_um: &[f32], block: usize) -> Unwrapped {
    unwrap_on(Instructions::best(), wrapped, period_um, block)
}

/// [`unwrap`] on `instructions` (the same heights on every set, to the bit:
/// [`Instructions`]).
pub fn unwrap_on(
    instructions: Instructions,
    wrapped: &Grid,
    period_um: &[f32],
    block: usize,
) -> Unwrapped {
    let (w, rows) = (wrapped.width, wrapped.rows);
    assert_eq!(period_um.len(), w, "one period per column");
    let mut s = Scratch::default();
    let unreached_rows = unwrap_rows(
        instructions,
        &wrapped.data[..w * rows],
        rows,
        period_um,
        block,
        &mut s,
    );
    Unwrapped {
        heights: Grid {
            width: w,
            rows,
            data: s.heights,
        },
        period_um: period_um.to_vec(),
        unreached: unreached_rows.iter().map(|&n| n as usize).sum(),
        unreached_rows,
    }
}

/// [`unwrap`] of the `rows` whole rows `wrapped` (of `period_um.len()` columns) into
/// `scratch.heights`, built for AVX2 where `instructions` asks for it and the processor has
/// it, else for the baseline; returns the unreached pixels per row
/// ([`Unwrapped::unreached_rows`]).
fn unwrap_rows(
    instructions: Instructions,
    wrapped: &[f32],
    rows: usize,
    period_um: &[f32],
    block: usize,
    scratch: &mut Scratch,
) -> Vec<u32> {
    #[cfg(target_arch = "x86_64")]
    if instructions.avx2() {
        /// [`unwrap_rows_in`] in AVX2.
        #[target_feature(enable = "avx2")]
        fn on_avx2(args: UnwrapArgs<'_>) -> Vec<u32> {
            unwrap_rows_in(args)
        }
        #[allow(unsafe_code)]
        // SAFETY: `Instructions::avx2` holds only where run-time detection found AVX2.
        return unsafe { on_avx2((wrapped, rows, period_um, block, scratch)) };
    }
    let _ = instructions;
    unwrap_rows_in((wrapped, rows, period_um, block, scratch))
}

/// [`unwrap_rows`]' arguments but the instruction set, as one (for its two builds).
type UnwrapArgs<'a> = (&'a [f32], usize, &'a [f32], usize, &'a mut Scratch);

/// [`unwrap_rows`] in whichever build calls it.
#[inline(always)]
fn unwrap_rows_in((wrapped, rows, period_um, block, scratch): UnwrapArgs<'_>) -> Vec<u32> {
    let w = period_um.len();
    let block = block.max(2);
    // Turns per pixel (row by row: no division to find a pixel's column).
    let turns = &mut scratch.turns;
    turns.clear();
    for row in wrapped.chunks_exact(w.max(1)) {
        turns.extend(row.iter().zip(period_um).map(|(&h, &t)| {
            if h.is_finite() && t > 0.0 {
                h / t
            } else {
                f32::NAN
            }
        }));
    }
    let (bw, bh) = (w.div_ceil(block).max(1), rows.div_ceil(block).max(1));
    // The finite turns of block (br, bc) into `vals`; returns the block's pixel count.
    let block_turns = |br: usize, bc: usize, vals: &mut Vec<f32>| {
        let (r0, c0) = (br * block, bc * block);
        let (r1, c1) = ((r0 + block).min(rows), (c0 + block).min(w));
        let size = (r1 - r0) * (c1 - c0);
        vals.resize(size, 0.0);
        let mut n = 0;
        for r in r0..r1 {
            n = compact_finite(&turns[r * w + c0..r * w + c1], vals, n);
        }
        vals.truncate(n);
        size
    };

    // 1. Trimmed circular mean per block.
    let mut phase = vec![f32::NAN; bw * bh];
    let mut count = vec![0usize; bw * bh];
    let mut vals: Vec<f32> = Vec::with_capacity(block * block);
    let mut ks: Vec<u16> = Vec::with_capacity(block * block);
    for br in 0..bh {
        for bc in 0..bw {
            let size = block_turns(br, bc, &mut vals);
            if vals.len() * 4 < size || vals.is_empty() {
                continue;
            }
            ks.clear();
            ks.extend(vals.iter().map(|&u| angle_index(u)));
            let Some(m) = circular_mean(&ks, |_| true) else {
                continue;
            };
            let m2 = circular_mean(&ks, |i| (nearest(vals[i], m) - m).abs() < 0.125).unwrap_or(m);
            phase[br * bw + bc] = m2;
            count[br * bw + bc] = vals.len();
        }
    }

    // 2. Quality-guided flood over the blocks, smallest step first: board-to-board steps
    //    (the bow's slope) are taken before steps onto or off a deposit, so the board's
    //    blocks are placed along board paths and a deposit never passes a turn error on.
    //    A region the flood cannot reach (cut off by invalid blocks) starts from its block
    //    nearest the placed ones, on the turn of their extrapolated surface.
    let mut surf = vec![f32::NAN; bw * bh];
    let mut reached = vec![false; bw * bh];
    if let Some(s) = (0..bw * bh)
        .filter(|&i| phase[i].is_finite())
        .max_by_key(|&i| count[i])
    {
        surf[s] = phase[s];
        flood(&phase, &mut surf, s, bw, bh);
        reached
            .iter_mut()
            .zip(&surf)
            .for_each(|(r, v)| *r = v.is_finite());
        loop {
            let (fill, dist) = fill_nearest(&surf, bw, bh);
            let next = (0..bw * bh)
                .filter(|&i| phase[i].is_finite() && !surf[i].is_finite())
                .min_by_key(|&i| dist[i]);
            let Some(j) = next else { break };
            surf[j] = nearest(phase[j], fill[j]);
            flood(&phase, &mut surf, j, bw, bh);
        }
    }
    let (filled, _) = fill_nearest(&surf, bw, bh);
    surf = filled;

    // 3. Surface refinement: the 30th percentile of each block's pixels on their nearest
    //    turn, then a 3 x 3 median over the blocks.
    let mut bil = Bilinear::new(w, rows, bw, bh, block);
    let mut low = vec![f32::NAN; bw * bh];
    // A block's values as their order keys ([`order_key`]): integers, compared in one
    // instruction where `f32::total_cmp` reworks both sides of every comparison.
    let mut v: Vec<u32> = Vec::with_capacity(block * block);
    // The surface of a block row's pixel rows, row-major (`block x w`).
    let mut band: Vec<f32> = vec![f32::NAN; block * w];
    for br in 0..bh {
        let r0 = br * block;
        let r1 = (r0 + block).min(rows);
        for r in r0..r1 {
            bil.row(&surf, r, &mut band[(r - r0) * w..(r - r0 + 1) * w]);
        }
        for bc in 0..bw {
            let (c0, c1) = (bc * block, (bc * block + block).min(w));
            v.resize((r1 - r0) * (c1 - c0), 0);
            let mut n = 0;
            for r in r0..r1 {
                let (us, ss) = (&turns[r * w + c0..r * w + c1], &band[(r - r0) * w + c0..]);
                for (&u, &sv) in us.iter().zip(ss) {
                    // Without a branch: every value is written, and the next one overwrites
                    // it unless it is finite.
                    v[n] = order_key(nearest(u, sv));
                    n += usize::from(u.is_finite());
                }
            }
            v.truncate(n);
            if v.len() * 4 < (r1 - r0) * (c1 - c0) || v.is_empty() {
                continue;
            }
            let k = (v.len() * 3) / 10;
            low[br * bw + bc] = from_order_key(*v.select_nth_unstable(k).1);
        }
    }
    let (low, _) = fill_nearest(&low, bw, bh);
    if low.iter().all(|v| v.is_finite()) {
        surf = median3(&low, bw, bh);
    }

    // 4. Every pixel on the turn nearest the surface (each one written: the buffer holds the
    //    last chunk's).
    bil.forget();
    let heights = &mut scratch.heights;
    heights.truncate(w * rows);
    heights.resize(w * rows, f32::NAN);
    let mut unreached_rows = vec![0u32; rows];
    let mut srow = vec![f32::NAN; w];
    for (r, unreached) in unreached_rows.iter_mut().enumerate() {
        let row = r * w;
        let reached_row = &reached[(r / block) * bw..];
        bil.row(&surf, r, &mut srow);
        let out = &mut heights[row..row + w];
        for ((o, &u), (&s, &t)) in out
            .iter_mut()
            .zip(&turns[row..row + w])
            .zip(srow.iter().zip(period_um))
        {
            *o = if u.is_finite() && s.is_finite() {
                nearest(u, s) * t
            } else {
                f32::NAN
            };
        }
        // A height is finite exactly where its turn and its surface are.
        for (bc, part) in out.chunks(block).enumerate() {
            if !reached_row[bc] {
                *unreached += part.iter().filter(|h| h.is_finite()).count() as u32;
            }
        }
    }
    unreached_rows
}

/// Camera rows each chunk of an [`Unwrapper`] hands on.
pub const CHUNK_ROWS: usize = 512;

/// Rows of context a chunk of an [`Unwrapper`] unwraps on either side of the rows it hands on
/// (two blocks: the surface's 3 x 3 block median and the bilinear surface between block
/// centres reach one block past a block).
pub const MARGIN_ROWS: usize = 2 * BLOCK;

/// A camera's rows unwrapped as they arrive, chunk by chunk, with bounded memory: the chunk
/// of rows `[s, s + chunk)` is unwrapped ([`unwrap`]) together with `margin` rows on either
/// side once those have arrived (or the camera has ended), and handed on.
///
/// Each chunk is unwrapped on its own turn (its seed block's), so it is moved by the whole
/// number of turns that makes it agree with the chunk before: the median, over the leading
/// margin rows that both unwrapped, of the whole turns between the two. Where the two share
/// no valid pixel (a gap of invalid or lost rows longer than the margin across the whole
/// camera), each column's first valid height of the chunk is compared with the column's last
/// valid height handed on before; the board's bow changes by far less than half a turn over
/// such a gap (0.25 um per 28 um row at 1 mm over 110 mm).
///
/// The rows handed on are those of [`unwrap`] on the whole camera, up to a whole number of
/// turns per chunk that the alignment removes: the surface is estimated from the chunk and
/// its margins, and every pixel's turn is the one nearest it.
#[derive(Clone, Debug)]
pub struct Unwrapper {
    period_um: Vec<f32>,
    block: usize,
    chunk: usize,
    margin: usize,
    /// Wrapped rows held (row-major), camera row `held_from` first.
    wrapped: Vec<f32>,
    held_from: usize,
    /// Rows pushed, and handed on.
    pushed: usize,
    emitted: usize,
    /// The last `min(margin, emitted)` rows handed on, as handed on.
    tail: Vec<f32>,
    /// Each column's last valid height handed on, um (NaN: none yet).
    last: Vec<f32>,
    /// Valid pixels whose block the flood did not reach, over the rows handed on.
    pub unreached: usize,
    /// Chunks whose turn came from the columns' last valid heights (no shared margin pixel).
    pub gap_aligned: usize,
    /// The unwrapping's buffers, kept from chunk to chunk.
    scratch: Scratch,
    /// What the unwrapping runs on ([`Instructions::best`] unless [`Self::on`] says).
    instructions: Instructions,
}

impl Unwrapper {
    /// A camera of `period_um.len()` columns (height per turn of each, um), unwrapped in
    /// `block`-pixel blocks, `chunk` rows per chunk with `margin` rows of context (`chunk`
    /// at least 1; a `margin` of at least two blocks keeps the rows handed on those of a whole
    /// camera's unwrapping).
    pub fn new(period_um: Vec<f32>, block: usize, chunk: usize, margin: usize) -> Unwrapper {
        let w = period_um.len();
        Unwrapper {
            period_um,
            block,
            chunk: chunk.max(1),
            margin,
            wrapped: Vec::new(),
            held_from: 0,
            pushed: 0,
            emitted: 0,
            tail: Vec::new(),
            last: vec![f32::NAN; w],
            unreached: 0,
            gap_aligned: 0,
            scratch: Scratch::default(),
            instructions: Instructions::best(),
        }
    }

    /// The same unwrapper on `instructions` (the same rows on every set, to the bit).
    pub fn on(self, instructions: Instructions) -> Unwrapper {
        Unwrapper {
            instructions,
            ..self
        }
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.period_um.len()
    }

    /// Rows pushed so far.
    pub fn pushed(&self) -> usize {
        self.pushed
    }

    /// Rows handed on so far.
    pub fn emitted(&self) -> usize {
        self.emitted
    }

    /// The next rows of wrapped heights (whole rows of [`Self::width`], um, NaN invalid; the
    /// caller hands whole rows: a part row at the end is not taken).
    pub fn push(&mut self, rows: &[f32]) {
        let w = self.width().max(1);
        debug_assert_eq!(rows.len() % w, 0, "whole rows");
        let n = rows.len() / w;
        self.wrapped.extend_from_slice(&rows[..n * w]);
        self.pushed += n;
    }

    /// Whether [`Self::next`] has a chunk to hand on (`ended`: no more rows will come).
    pub fn ready(&self, ended: bool) -> bool {
        if ended {
            self.emitted < self.pushed
        } else {
            self.pushed >= self.emitted + self.chunk + self.margin
        }
    }

    /// The next chunk of unwrapped rows (camera rows from [`Self::emitted`] before the call),
    /// or `None` when [`Self::ready`] is false.
    pub fn next(&mut self, ended: bool) -> Option<Grid> {
        if !self.ready(ended) {
            return None;
        }
        let w = self.width();
        let s = self.emitted;
        let e = (s + self.chunk).min(self.pushed);
        let lo = s.saturating_sub(self.margin);
        let hi = (e + self.margin).min(self.pushed);
        let from = (lo - self.held_from) * w;
        let mut scratch = std::mem::take(&mut self.scratch);
        let unreached_rows = unwrap_rows(
            self.instructions,
            &self.wrapped[from..from + (hi - lo) * w],
            hi - lo,
            &self.period_um,
            self.block,
            &mut scratch,
        );
        let u = &mut scratch.heights;
        let turns = self.turns_to_previous(u, s - lo);
        shift_rows(u, &self.period_um, turns);
        let (a, b) = (s - lo, e - lo);
        self.unreached += unreached_rows[a..b]
            .iter()
            .map(|&n| n as usize)
            .sum::<usize>();
        let mut data = crate::pool::ROWS.take_empty((b - a) * w);
        data.extend_from_slice(&u[a * w..b * w]);
        let out = Grid {
            width: w,
            rows: e - s,
            data,
        };
        for row in out.data.chunks_exact(w.max(1)) {
            for (l, &h) in self.last.iter_mut().zip(row) {
                if h.is_finite() {
                    *l = h;
                }
            }
        }
        let t0 = e.saturating_sub(self.margin);
        self.tail.clear();
        self.tail.extend_from_slice(&u[(t0 - lo) * w..b * w]);
        self.scratch = scratch;
        // The next chunk's leading margin starts at `t0`.
        self.wrapped.drain(..(t0 - self.held_from) * w);
        self.held_from = t0;
        self.emitted = e;
        Some(out)
    }

    /// The whole turns that bring `u` (the rows of a chunk unwrapped on its own turn, whose
    /// row `shared` is the first row not handed on before) onto the rows handed on before.
    fn turns_to_previous(&mut self, u: &[f32], shared: usize) -> i32 {
        let w = self.width();
        let rows = u.len() / w.max(1);
        let turns = |a: f32, b: f32, t: f32| round_f32((a - b) / t) as i32;
        let mut d: Vec<i32> = Vec::new();
        for (prev, cur) in self
            .tail
            .chunks_exact(w.max(1))
            .zip(u.chunks_exact(w.max(1)).take(shared))
        {
            for ((&a, &b), &t) in prev.iter().zip(cur).zip(&self.period_um) {
                if a.is_finite() && b.is_finite() && t > 0.0 {
                    d.push(turns(a, b, t));
                }
            }
        }
        if d.is_empty() && self.last.iter().any(|h| h.is_finite()) {
            self.gap_aligned += 1;
            for c in 0..w {
                let first = (shared..rows).map(|r| u[r * w + c]).find(|h| h.is_finite());
                let (a, t) = (self.last[c], self.period_um[c]);
                if let Some(b) = first {
                    if a.is_finite() && t > 0.0 {
                        d.push(turns(a, b, t));
                    }
                }
            }
        }
        if d.is_empty() {
            return 0;
        }
        let k = d.len() / 2;
        *d.select_nth_unstable(k).1
    }
}

/// Places every block reachable from `seed` (already placed) through finite-phase blocks, the
/// smallest wrapped step first (8 neighbours).
fn flood(phase: &[f32], surf: &mut [f32], seed: usize, bw: usize, bh: usize) {
    type Edge = (std::cmp::Reverse<u32>, usize, usize);
    let mut heap: BinaryHeap<Edge> = BinaryHeap::new();
    let push = |heap: &mut BinaryHeap<Edge>, surf: &[f32], i: usize| {
        let (br, bc) = (i / bw, i % bw);
        for dr in -1i64..=1 {
            for dc in -1i64..=1 {
                let (nr, nc) = (br as i64 + dr, bc as i64 + dc);
                if (dr, dc) == (0, 0) || nr < 0 || nc < 0 || nr >= bh as i64 || nc >= bw as i64 {
                    continue;
                }
                let j = nr as usize * bw + nc as usize;
                if phase[j].is_finite() && !surf[j].is_finite() {
                    let d = (nearest(phase[j], surf[i]) - surf[i]).abs();
                    heap.push((std::cmp::Reverse((d * 1e6) as u32), i, j));
                }
            }
        }
    };
    push(&mut heap, surf, seed);
    while let Some((_, i, j)) = heap.pop() {
        if surf[j].is_finite() {
            continue;
        }
        surf[j] = nearest(phase[j], surf[i]);
        push(&mut heap, surf, j);
    }
}

/// Every NaN block takes the value of the nearest finite block (breadth first, 8
/// neighbours); also returns each block's distance in blocks (`usize::MAX`: none finite).
fn fill_nearest(v: &[f32], bw: usize, bh: usize) -> (Vec<f32>, Vec<usize>) {
    let mut out = v.to_vec();
    let mut dist = vec![usize::MAX; v.len()];
    let mut queue: VecDeque<usize> = (0..bw * bh).filter(|&i| v[i].is_finite()).collect();
    for &i in &queue {
        dist[i] = 0;
    }
    while let Some(i) = queue.pop_front() {
        let (br, bc) = (i / bw, i % bw);
        for dr in -1i64..=1 {
            for dc in -1i64..=1 {
                let (nr, nc) = (br as i64 + dr, bc as i64 + dc);
                if nr < 0 || nc < 0 || nr >= bh as i64 || nc >= bw as i64 {
                    continue;
                }
                let j = nr as usize * bw + nc as usize;
                if dist[j] == usize::MAX {
                    out[j] = out[i];
                    dist[j] = dist[i] + 1;
                    queue.push_back(j);
                }
            }
        }
    }
    (out, dist)
}

/// The median of each block's 3 x 3 neighbourhood (clipped at the borders).
fn median3(v: &[f32], bw: usize, bh: usize) -> Vec<f32> {
    let mut out = vec![f32::NAN; v.len()];
    for br in 0..bh {
        for bc in 0..bw {
            let mut n: Vec<f32> = (br.saturating_sub(1)..(br + 2).min(bh))
                .flat_map(|r| (bc.saturating_sub(1)..(bc + 2).min(bw)).map(move |c| (r, c)))
                .map(|(r, c)| v[r * bw + c])
                .collect();
            n.sort_by(f32::total_cmp);
            out[br * bw + bc] = n[n.len() / 2];
        }
    }
    out
}

/// Bilinear interpolation of block values between block centres, with every row's and
/// column's blocks and weights computed once (`at` is the per-pixel part).
struct Bilinear {
    bw: usize,
    /// Per pixel row: block rows `i`, `i1` and the weight of `i1`.
    rows: Vec<(usize, usize, f32)>,
    /// Per pixel column: block columns `j`, `j1` and the weight of `j1`.
    cols: Vec<(usize, usize, f32)>,
    /// The block rows `(i, i1)` last asked for (since [`Self::forget`]), and their values
    /// interpolated across the columns, one per pixel column.
    across: Option<(usize, usize)>,
    across_i: Vec<f32>,
    across_i1: Vec<f32>,
}

impl Bilinear {
    fn new(w: usize, rows: usize, bw: usize, bh: usize, block: usize) -> Bilinear {
        let axis = |p: usize, n: usize| {
            if n <= 1 {
                return (0, 0, 0.0);
            }
            let x = (p as f32 + 0.5) / block as f32 - 0.5;
            let x = x.clamp(0.0, (n - 1) as f32);
            let i = (x.floor() as usize).min(n - 2);
            (i, (i + 1).min(n - 1), (x - i as f32).clamp(0.0, 1.0))
        };
        Bilinear {
            bw,
            rows: (0..rows).map(|r| axis(r, bh)).collect(),
            cols: (0..w).map(|c| axis(c, bw)).collect(),
            across: None,
            across_i: vec![0.0; w],
            across_i1: vec![0.0; w],
        }
    }

    /// The interpolated block values of pixel row `r` into `out` (one per column): for each
    /// pixel `a (1 - fy) + b fy` with `a`, `b` the block rows' values interpolated across
    /// (`v[.., j] (1 - fx) + v[.., j1] fx`), the same arithmetic in the same order for every
    /// pixel as a pixel at a time. The values across are kept while the block rows are the
    /// same (a block's rows): call [`Self::forget`] when `v` changes.
    fn row(&mut self, v: &[f32], r: usize, out: &mut [f32]) {
        let (i, i1, fy) = self.rows[r];
        let bw = self.bw;
        let key = (i, i1);
        if self.across != Some(key) {
            for ((a, b), &(j, j1, fx)) in self
                .across_i
                .iter_mut()
                .zip(self.across_i1.iter_mut())
                .zip(&self.cols)
            {
                *a = v[i * bw + j] * (1.0 - fx) + v[i * bw + j1] * fx;
                *b = v[i1 * bw + j] * (1.0 - fx) + v[i1 * bw + j1] * fx;
            }
            self.across = Some(key);
        }
        for ((o, &a), &b) in out.iter_mut().zip(&self.across_i).zip(&self.across_i1) {
            *o = a * (1.0 - fy) + b * fy;
        }
    }

    /// Forgets the values across kept by [`Self::row`] (the block values changed).
    fn forget(&mut self) {
        self.across = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bowed board with paste boxes, noise and dead pixels, wrapped with a period that
    /// varies across the columns.
    fn board(w: usize, rows: usize, bow_um: f32, t0: f32) -> (Grid, Grid, Vec<f32>) {
        tilted_board(w, rows, bow_um, t0, 0.0)
    }

    /// [`board`] tilted by `tilt_um` per row along the rows (the board's leading edge lower
    /// than its trailing edge: no corner of a chunk lies on turn 0).
    fn tilted_board(
        w: usize,
        rows: usize,
        bow_um: f32,
        t0: f32,
        tilt_um: f32,
    ) -> (Grid, Grid, Vec<f32>) {
        let period: Vec<f32> = (0..w)
            .map(|c| t0 * (1.0 + 0.02 * (c as f32 / w as f32 - 0.5)))
            .collect();
        let mut truth = Grid::invalid(w, rows);
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 33) as f32 / (1u64 << 31) as f32) - 0.5
        };
        for r in 0..rows {
            for c in 0..w {
                let (x, y) = (
                    2.0 * r as f32 / rows as f32 - 1.0,
                    2.0 * c as f32 / w as f32 - 1.0,
                );
                let mut h = bow_um * (1.0 - x * x) * (1.0 - y * y) + tilt_um * r as f32;
                // 150 um paste boxes of 12 x 20 px on a 40 px pitch.
                if r % 40 < 12 && c % 40 < 20 {
                    h += 150.0;
                }
                h += 2.0 * rnd();
                *truth.at_mut(r, c) = h;
            }
        }
        let mut wrapped = truth.clone();
        for (i, h) in wrapped.data.iter_mut().enumerate() {
            let t = period[i % w];
            *h -= t * (*h / t + 0.5).floor();
            if i % 97 == 0 {
                *h = f32::NAN; // dead pixels
            }
        }
        (truth, wrapped, period)
    }

    /// Pixels whose unwrapped height differs from the truth by another number of turns than
    /// the most common one (the relative result may sit any whole number of turns off).
    fn wrong_turns(u: &Unwrapped, truth: &Grid) -> usize {
        let w = truth.width;
        let k: Vec<i64> = u
            .heights
            .data
            .iter()
            .enumerate()
            .filter(|(_, h)| h.is_finite())
            .map(|(i, h)| ((truth.data[i] - h) / u.period_um[i % w]).round() as i64)
            .collect();
        let mut counts = std::collections::HashMap::new();
        for &x in &k {
            *counts.entry(x).or_insert(0usize) += 1;
        }
        let best = counts.values().copied().max().unwrap_or(0);
        k.len() - best
    }

    #[test]
    fn a_bow_of_several_turns_with_paste_unwraps_without_a_wrong_turn() {
        // 1 mm bow, 400 um per turn: 2.5 turns; paste 150 um (0.375 turn) above the board.
        // The grid is small, so the bow is 20 times steeper than on a real board (up to
        // 10 um per pixel where a 220 mm board bowed by 1 mm has 0.5): blocks of 6 px keep
        // the change between neighbouring blocks below a sixth of a turn.
        let (truth, wrapped, period) = board(400, 600, 1000.0, 400.0);
        let u = unwrap(&wrapped, &period, 6);
        assert_eq!(u.heights.valid(), wrapped.valid());
        assert_eq!(wrong_turns(&u, &truth), 0);
        // Negative bow too.
        let (truth, wrapped, period) = board(300, 500, -1000.0, 400.0);
        let u = unwrap(&wrapped, &period, 6);
        assert_eq!(wrong_turns(&u, &truth), 0);
    }

    #[test]
    fn shifting_moves_by_whole_turns_of_each_column() {
        let (_, wrapped, period) = board(64, 64, 500.0, 400.0);
        let u0 = unwrap(&wrapped, &period, BLOCK);
        let mut u1 = u0.clone();
        u1.shift(2);
        for (i, (a, b)) in u0.heights.data.iter().zip(&u1.heights.data).enumerate() {
            if a.is_finite() {
                assert!((b - a - 2.0 * period[i % 64]).abs() < 1e-3);
            }
        }
    }

    #[test]
    fn empty_and_tiny_grids() {
        let g = Grid::invalid(5, 3);
        let u = unwrap(&g, &[400.0; 5], BLOCK);
        assert_eq!(u.heights.valid(), 0);
        let g = Grid {
            width: 1,
            rows: 1,
            data: vec![100.0],
        };
        let u = unwrap(&g, &[400.0], BLOCK);
        assert_eq!(u.heights.data, vec![100.0]);
    }

    #[test]
    fn a_region_cut_off_by_invalid_pixels_still_lands_on_the_surface() {
        // An invalid band splits the board; the far side follows the extrapolated surface.
        let (truth, mut wrapped, period) = board(300, 600, 400.0, 400.0);
        for r in 290..320 {
            for c in 0..300 {
                *wrapped.at_mut(r, c) = f32::NAN;
            }
        }
        let u = unwrap(&wrapped, &period, 6);
        assert!(u.unreached > 0);
        assert_eq!(wrong_turns(&u, &truth), 0);
    }

    /// Pushes `wrapped` into an unwrapper `pieces` rows at a time and collects every chunk.
    fn chunked(
        wrapped: &Grid,
        period: &[f32],
        chunk: usize,
        margin: usize,
        pieces: usize,
    ) -> (Unwrapped, Unwrapper) {
        let w = wrapped.width;
        let mut un = Unwrapper::new(period.to_vec(), 6, chunk, margin);
        let mut out = Vec::new();
        for piece in wrapped.data.chunks(pieces * w) {
            un.push(piece);
            while let Some(g) = un.next(false) {
                out.extend(g.data);
            }
        }
        while let Some(g) = un.next(true) {
            out.extend(g.data);
        }
        assert_eq!(un.emitted(), wrapped.rows);
        let u = Unwrapped {
            heights: Grid {
                width: w,
                rows: wrapped.rows,
                data: out,
            },
            period_um: period.to_vec(),
            unreached: un.unreached,
            unreached_rows: Vec::new(),
        };
        (u, un)
    }

    #[test]
    fn chunk_by_chunk_is_the_whole_camera_up_to_a_turn() {
        // 1 mm bow and 1.8 mm of tilt along the rows: every chunk's seed block on another turn.
        let (truth, wrapped, period) = tilted_board(400, 900, 1000.0, 400.0, 2.0);
        let whole = unwrap(&wrapped, &period, 6);
        for (chunk, margin, pieces) in [(100, 12, 7), (64, 24, 1000), (250, 12, 33), (2000, 12, 50)]
        {
            let (u, _) = chunked(&wrapped, &period, chunk, margin, pieces);
            assert_eq!(u.heights.valid(), whole.heights.valid());
            assert_eq!(wrong_turns(&u, &truth), 0, "chunk {chunk}");
            // Every pixel on the whole camera's turn, up to one turn for all.
            let k = (0..u.heights.data.len())
                .find(|&i| u.heights.data[i].is_finite())
                .map(|i| ((u.heights.data[i] - whole.heights.data[i]) / period[i % 400]).round())
                .unwrap();
            for (i, (a, b)) in u.heights.data.iter().zip(&whole.heights.data).enumerate() {
                if a.is_finite() {
                    assert!((a - b - k * period[i % 400]).abs() < 1e-2, "{i}: {a} {b}");
                }
            }
        }
        // One chunk over the whole camera is the whole camera's unwrapping, bit for bit.
        let (u, _) = chunked(&wrapped, &period, 5000, 12, 900);
        assert_eq!(
            u.heights
                .data
                .iter()
                .map(|h| h.to_bits())
                .collect::<Vec<_>>(),
            whole
                .heights
                .data
                .iter()
                .map(|h| h.to_bits())
                .collect::<Vec<_>>()
        );
        assert_eq!(u.unreached, whole.unreached);
    }

    /// The baseline's build unwraps the same bits as the best this processor runs (AVX2
    /// where it has it), whole and chunk by chunk, over widths that leave a part vector.
    #[test]
    fn every_instruction_set_unwraps_the_same_bits() {
        let bits = |d: &[f32]| d.iter().map(|h| h.to_bits()).collect::<Vec<_>>();
        for w in [397, 400] {
            let (_, wrapped, period) = tilted_board(w, 300, 1000.0, 400.0, 2.0);
            let best = unwrap_on(Instructions::best(), &wrapped, &period, 6);
            let base = unwrap_on(Instructions::Baseline, &wrapped, &period, 6);
            assert_eq!(
                bits(&base.heights.data),
                bits(&best.heights.data),
                "width {w}"
            );
            assert_eq!(base.unreached_rows, best.unreached_rows);
            let chunks = |instructions: Instructions| {
                let mut un = Unwrapper::new(period.clone(), 6, 100, 12).on(instructions);
                un.push(&wrapped.data);
                let mut out = Vec::new();
                while let Some(g) = un.next(true) {
                    out.extend(g.data);
                }
                (out, un.unreached)
            };
            let (a, b) = (chunks(Instructions::Baseline), chunks(Instructions::best()));
            assert_eq!(bits(&a.0), bits(&b.0), "width {w}, chunks");
            assert_eq!(a.1, b.1);
        }
    }

    #[test]
    fn a_gap_longer_than_the_margin_keeps_the_turn() {
        // 80 invalid rows across the whole camera, longer than the 12-row margin: the chunk
        // after the gap is aligned on the columns' last valid heights.
        let (truth, mut wrapped, period) = tilted_board(300, 800, 800.0, 400.0, 1.5);
        for r in 330..410 {
            for c in 0..300 {
                *wrapped.at_mut(r, c) = f32::NAN;
            }
        }
        let (u, un) = chunked(&wrapped, &period, 100, 12, 64);
        assert!(un.gap_aligned > 0);
        assert_eq!(wrong_turns(&u, &truth), 0);
        assert_eq!(u.heights.valid(), wrapped.valid());
    }

    #[test]
    fn the_fast_rounding_is_round_but_for_ties() {
        let mut rng = crate::test_rng::Lcg(0x9e37_79b9_7f4a_7c15);
        for _ in 0..100_000 {
            let v = (rng.next() - 0.5) * 4000.0;
            let f = v as f32;
            if (f - f.trunc()).abs() != 0.5 {
                assert_eq!(round_f32(f), f.round(), "{f}");
            }
        }
        assert_eq!(round_f32(2.5), 2.0);
        assert_eq!(round_f32(-3.5), -4.0);
        assert!(round_f32(f32::NAN).is_nan());
    }

    #[test]
    fn the_angle_index_is_the_nearest_step_modulo_a_turn() {
        let mut rng = crate::test_rng::Lcg(0x1234_5678_9abc_def1);
        let steps = MEAN_STEPS as f64;
        let mut us: Vec<f32> = (0..50_000).map(|_| (rng.next() - 0.5) as f32).collect();
        // Every half step (the ties) and the ends of the wrapped range.
        us.extend((-2 * MEAN_STEPS as i32..2 * MEAN_STEPS as i32).map(|k| k as f32 / 8192.0));
        us.extend([-0.5, 0.5 - f32::EPSILON / 4.0, 0.0, -0.0]);
        for u in us {
            let k = (f64::from(u) * steps).round_ties_even().rem_euclid(steps) as u16;
            assert_eq!(angle_index(u), k, "{u}");
        }
    }

    #[test]
    fn the_circular_mean_is_the_table_angles_mean() {
        // Against the mean of the same quantised angles in f64 with libm's sines: the integer
        // table's rounding (2^-24) moves it by far less than 1e-6 turns.
        let mut rng = crate::test_rng::Lcg(0x0bad_5eed_dead_beef);
        for trial in 0..400 {
            let n = 1 + (rng.next() * 300.0) as usize;
            let centre = rng.next() - 0.5;
            let spread = if trial % 2 == 0 { 0.05 } else { 0.4 };
            let us: Vec<f32> = (0..n)
                .map(|_| {
                    let u = centre + (rng.next() - 0.5) * spread;
                    (u - u.round()) as f32
                })
                .map(|u| if u >= 0.5 { -0.5 } else { u })
                .collect();
            let ks: Vec<u16> = us.iter().map(|&u| angle_index(u)).collect();
            let keep = |i: usize| i % 3 != 1;
            for (all, m) in [
                (true, circular_mean(&ks, |_| true)),
                (false, circular_mean(&ks, keep)),
            ] {
                let (mut s, mut c, mut cnt) = (0.0f64, 0.0f64, 0);
                for (i, &k) in ks.iter().enumerate() {
                    if all || keep(i) {
                        let a = std::f64::consts::TAU * f64::from(k) / MEAN_STEPS as f64;
                        s += a.sin();
                        c += a.cos();
                        cnt += 1;
                    }
                }
                let want = (s.atan2(c) / std::f64::consts::TAU) as f32;
                let m = m.expect("samples");
                assert!(cnt > 0);
                let d = (m - want) - (m - want).round();
                assert!(d.abs() < 1e-6, "{m} {want}");
                assert!((-0.5..=0.5).contains(&m));
            }
        }
        assert_eq!(circular_mean(&[], |_| true), None);
        // Opposite angles cancel exactly.
        assert_eq!(circular_mean(&[0, 2048], |_| true), None);
        assert_eq!(circular_mean(&[5, 7], |i| i > 5), None);
    }

    /// The order keys sort as `f32::total_cmp` does, pair by pair and as a whole (NaNs of
    /// either sign, both zeros, the infinities, subnormals), and give back every value's bits;
    /// a selection over them picks what `select_nth_unstable_by(total_cmp)` picks.
    #[test]
    fn order_keys_are_the_total_order() {
        let mut rng = crate::test_rng::Lcg(99);
        let mut bits = || (rng.next() * 4_294_967_296.0) as u32;
        let mut xs: Vec<f32> = [
            0.0,
            -0.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x8000_0001),
            f32::MAX,
            f32::MIN,
            1.0,
            -1.0,
        ]
        .to_vec();
        xs.extend((0..2000).map(|_| f32::from_bits(bits())));
        // Turns as step 3 sees them: near each other.
        xs.extend((0..2000).map(|i| (i as f32 - 1000.0) * 1e-3 + (bits() % 7) as f32 * 0.25));
        for &a in &xs {
            assert_eq!(from_order_key(order_key(a)).to_bits(), a.to_bits());
        }
        for (a, b) in xs.iter().zip(xs.iter().skip(1).chain(xs.iter().rev())) {
            assert_eq!(order_key(*a).cmp(&order_key(*b)), a.total_cmp(b), "{a} {b}");
        }
        for (len, k) in [(1, 0), (7, 2), (256, 76), (4014, 1204)] {
            let mut f = xs[xs.len() - len..].to_vec();
            let mut keys: Vec<u32> = f.iter().map(|&x| order_key(x)).collect();
            let want = *f.select_nth_unstable_by(k, f32::total_cmp).1;
            let got = from_order_key(*keys.select_nth_unstable(k).1);
            assert_eq!(got.to_bits(), want.to_bits(), "len {len}");
        }
    }

    #[test]
    fn compacting_keeps_the_finite_values_in_order() {
        let mut rng = crate::test_rng::Lcg(0x5851_f42d_4c95_7f2d);
        for len in [0usize, 1, 2, 7, 16, 33] {
            for nan_share in [0.0, 0.3, 1.0] {
                let from: Vec<f32> = (0..len)
                    .map(|_| {
                        let x = rng.next();
                        if rng.next() < nan_share {
                            [f32::NAN, f32::INFINITY, f32::NEG_INFINITY][(x * 3.0) as usize % 3]
                        } else {
                            (x - 0.5) as f32
                        }
                    })
                    .collect();
                let mut to = vec![7.0f32; 5 + len];
                let n = compact_finite(&from, &mut to, 5);
                let want: Vec<f32> = from.iter().copied().filter(|u| u.is_finite()).collect();
                assert_eq!(n, 5 + want.len());
                assert_eq!(&to[5..n], &want[..]);
                assert_eq!(&to[..5], &[7.0; 5]);
            }
        }
    }
}
