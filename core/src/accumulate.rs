//! Accumulate: the raw samples of open board rows, and the per-pixel `v = P i` products.
//!
//! A board row needs `n` samples from `n` consecutive frames, but its window's `P` is only
//! known once the encoder latch of its last frame arrives. So the first `n - 1` samples of
//! every open row are kept raw in a pool of line slots ([`Pool`]: Mono12p for a 12-bit
//! configuration, u16 otherwise), and the `n`-th line is combined with them as it streams in.
//! Open rows entered in the last `n - 1` frames hold `1..n-1` lines each, so the pool needs at
//! most `max_step_rows * n (n - 1) / 2` lines: a triangle, not the `(n - 1)` full frames a
//! frame buffer would take.
//!
//! The kernels ([`block`] for u16 lines, [`block_packed`] for Mono12p) work on pairs of
//! neighbouring pixels with the M7's dual 16-bit instructions (`src/dsp.rs`); [`pixel_v`] is
//! their scalar definition, and [`crate::offload`] the seam where a front end can take the
//! stage over. On an x86-64 host with AVX2 the pipeline runs both kernels sixteen pixels at a
//! time in AVX2 ([`block_packed_with`], [`block_with`]: the same sums; about 6 times the
//! scalar loop's rate on Mono12p lines and 9 times on 16-bit lines, `cargo bench -p dpsa-core
//! --bench kernel -- accumulate`).

use crate::dsp::{pack_bottoms, pack_tops, pair, smlad, unpack12, uqsub16};
use crate::frames::mono12p;
use crate::lanes::Kernel;
use crate::solve::{Window, MAX_N};

/// `v_2`, `v_3` of one pixel in Q?.24 DN (i64), and whether a sample was saturated.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Acc {
    /// `v_2 = sum_j P_2j i_j = C cos Phi`, DN * 2^24.
    pub v2: i64,
    /// `v_3 = sum_j P_3j i_j = C sin Phi`, DN * 2^24.
    pub v3: i64,
    /// Some sample was `>= saturation`.
    pub saturated: bool,
}

/// `v_2`, `v_3` of a pixel in DN with a known number of fractional bits (`frac`), never
/// `i32::MIN`: the form the phase stage takes ([`crate::height::Gate`] holds the modulation
/// threshold in the same units). The pipeline's kernel gives `frac = Coef::frac` ([`block`]);
/// the i64 reference path [`Acc::reduce`] gives Q20.12 (`frac = 12`). [`SATURATED`] in `v_2`
/// marks a saturated pixel.
pub type V = [i32; 2];

/// `v_2` of a saturated pixel in a [`V`] (never a reduced value: those are clamped above it).
pub const SATURATED: i32 = i32::MIN;

impl Acc {
    /// The pixel in the phase stage's form: Q24 -> Q12 by an arithmetic shift, clamped.
    #[inline(always)]
    pub fn reduce(&self) -> V {
        if self.saturated {
            [SATURATED, 0]
        } else {
            [q12(self.v2), q12(self.v3)]
        }
    }
}

/// Q?.24 -> Q20.12, clamped to `+-(2^31 - 1)`.
///
/// On a 32-bit core the common case needs only the two words of `v`: when the high word
/// `h = v >> 32` lies in `(-2^11, 2^11)`, `v >> 12 = (h << 20) | (lo >> 12)` fits in i32 and
/// is above `i32::MIN`. Anything else takes the clamping path.
#[inline(always)]
fn q12(v: i64) -> i32 {
    let h = (v >> 32) as i32;
    if (h as u32).wrapping_add(0x7FF) < 0xFFF {
        ((h << 20) as u32 | (v as u32 >> 12)) as i32
    } else {
        q12_clamped(v)
    }
}

#[cold]
#[inline(never)]
fn q12_clamped(v: i64) -> i32 {
    (v >> 12).clamp(i32::MIN as i64 + 1, i32::MAX as i64) as i32
}

/// `v = P i` for one pixel from its `n` samples (u16 DN).
///
/// Formats: `P` Q7.24 (i32, `|P| < 2^30`), samples `< 2^16`, `n <= 8`, so
/// `|v| < 8 * 2^30 * 2^16 = 2^49` and the i64 sums cannot overflow.
#[inline(always)]
pub fn pixel(win: &Window, samples: &[u16], saturation: u16) -> Acc {
    let mut acc = Acc::default();
    for (j, &x) in samples.iter().enumerate().take(win.n.min(MAX_N)) {
        acc.v2 += win.p2[j] as i64 * x as i64;
        acc.v3 += win.p3[j] as i64 * x as i64;
        acc.saturated |= x >= saturation;
    }
    acc
}

/// The window's `P` in the form the per-pixel kernel multiplies: rows 2 and 3 of `P` with
/// `frac` fractional bits (`Q?.frac`, `frac <= 24`), as integers that fit in i16, summing to
/// exactly zero per row. Built once per window by [`Coef::of`].
///
/// Why these three properties:
/// - **sum zero**: the exact `P` rows sum to zero (the centred solve, `docs/model.md`), so the
///   background `B` cancels. Keeping that exact after rounding means
///   `sum_j q_j x_j = sum_j q_j (x_j - m)` for any offset `m`; with `m` half the saturation
///   level every non-saturated sample is within `half = ceil(saturation / 2)` of `m`, so
///   `|v| <= half * sum_j |q_j|`, which `frac` keeps below `2^31`: the per-pixel sums are
///   done in *wrapping* i32 arithmetic (`MLA`, no 64-bit product), intermediate wraps cancel,
///   and the final `v` is exact. (Saturated pixels may wrap; they are discarded.)
/// - **i16**: `|q_j| <= 32767`, so pairs of 16-bit samples can meet 16-bit coefficients in a
///   dual multiply-accumulate (`SMLAD`) on a core that has one.
/// - **largest `frac`** under both limits: the relative rounding of each coefficient is at
///   most `2^-16 / max_j |P_j|` (plus the zero-sum fix-up of at most `n/2` units on the
///   largest entry), which the tests bound against an f64 solve (see [`Coef::of`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Coef {
    /// Observations.
    pub n: usize,
    /// `P_2j * 2^frac`, rounded, row sum zero.
    pub q2: [i32; MAX_N],
    /// `P_3j * 2^frac`, rounded, row sum zero.
    pub q3: [i32; MAX_N],
    /// Fractional bits of `q2`, `q3` and of the reduced pixels `v` they give.
    pub frac: u32,
}

impl Coef {
    /// The kernel form of `win` for samples below `saturation`.
    ///
    /// `frac` is the largest value in `0..=24` for which the rounded rows fit in i16 and
    /// `ceil(saturation / 2) * sum |q_j| < 2^31` (checked on the rounded values); a window so
    /// large that even `frac = 0` fails (impossible for `P` from [`Window::solve`] with a noise
    /// gain up to 8) gets `None`.
    pub fn of(win: &Window, saturation: u16) -> Option<Coef> {
        let n = win.n.min(MAX_N);
        let half = ((saturation as i64 + 1) / 2).max(1);
        let mut frac = crate::solve::P_FRAC;
        loop {
            let sh = crate::solve::P_FRAC - frac;
            let q2 = zero_sum(&win.p2[..n], sh);
            let q3 = zero_sum(&win.p3[..n], sh);
            let fits = |q: &[i32; MAX_N]| {
                let s: i64 = q.iter().map(|&x| (x as i64).abs()).sum();
                q.iter().all(|&x| (-32767..=32767).contains(&x)) && half * s < 1 << 31
            };
            if fits(&q2) && fits(&q3) {
                return Some(Coef { n, q2, q3, frac });
            }
            if frac == 0 {
                return None;
            }
            frac -= 1;
        }
    }
}

/// `p >> sh` rounded to nearest (halves up), then the row sum moved onto the entry of largest
/// magnitude so that the row sums to exactly zero.
fn zero_sum(p: &[i32], sh: u32) -> [i32; MAX_N] {
    let mut q = [0i32; MAX_N];
    let mut sum = 0i64;
    let mut big = 0;
    for (j, &x) in p.iter().enumerate() {
        q[j] = round_shift(x as i64, sh);
        sum += q[j] as i64;
        if q[j].unsigned_abs() > q[big].unsigned_abs() {
            big = j;
        }
    }
    q[big] = round_shift(q[big] as i64 - sum, 0);
    q
}

/// `x >> sh` rounded to nearest (halves up), clamped to `-(2^31 - 1)..=2^31 - 1`. Out of line:
/// [`zero_sum`] runs a few times per frame, and this body unrolled into it nine times over cost
/// the firmware 936 B of flash (the calls cost [`Coef::of`] about 950 instructions a frame).
#[inline(never)]
fn round_shift(x: i64, sh: u32) -> i32 {
    let r = if sh == 0 {
        x
    } else {
        (x + (1 << (sh - 1))) >> sh
    };
    r.clamp(i32::MIN as i64 + 1, i32::MAX as i64) as i32
}

/// `v = P i` of one pixel in the kernel's form: `[v_2, v_3]` with `coef.frac` fractional bits
/// (wrapping i32 sums, exact for non-saturated samples, see [`Coef`]), or
/// `[SATURATED, 0]` when a sample is `>= saturation`. The scalar definition [`block`] must
/// equal (tested).
#[inline(always)]
pub fn pixel_v(coef: &Coef, samples: &[u16], saturation: u16) -> V {
    let (mut v2, mut v3, mut sat) = (0i32, 0i32, false);
    for (j, &x) in samples.iter().enumerate().take(coef.n) {
        v2 = v2.wrapping_add(coef.q2[j].wrapping_mul(x as i32));
        v3 = v3.wrapping_add(coef.q3[j].wrapping_mul(x as i32));
        sat |= x >= saturation;
    }
    if sat {
        [SATURATED, 0]
    } else {
        [v2, v3]
    }
}

/// The accumulate stage over a run of columns of 16-bit lines: `out[k]` is pixel `c0 + k` of
/// the `n = lines.len()` lines (`3..=8`; other counts write nothing), [`pixel_v`] of its
/// samples. The pipeline runs it when the line pool is 16-bit (`saturation > 4095`, cameras
/// of more than 12 bits); 12-bit configurations keep Mono12p lines ([`block_packed`]).
///
/// Two neighbouring pixels at a time, as the M7's packed 16-bit instructions want them
/// (`crate::dsp`): each line is read as words (`c0` even and the lines 4-byte aligned, as
/// the pipeline's and the firmware's buffers are; otherwise [`pixel_v`] per pixel), a word
/// holding both pixels' samples; see `pair_step`. Lanes are read as i16: samples below
/// `2^15` as they are, and above a saturation level of `2^15` as `x - 2^15` (`x ^ 0x8000`),
/// which the zero row sums of [`Coef`] cancel. Either way the sums of every non-saturated
/// pixel are exact, the same values as [`pixel_v`]'s. An odd last column takes [`pixel_v`].
///
/// Never inlined: the pipeline and the firmware's stage benchmark run this one copy.
/// Every line must hold at least `c0 + out.len()` samples (the caller checks; a shorter line
/// would be a programming error and panics).
#[inline(never)]
pub fn block(coef: &Coef, lines: &[&[u16]], c0: usize, saturation: u16, out: &mut [V]) {
    let (n, len) = (lines.len(), out.len());
    if !kernel_applies(n, saturation, out) {
        return;
    }
    let even = len & !1;
    let mut words: [&[u32]; MAX_N] = [&[]; MAX_N];
    let mut aligned = true;
    for (w, l) in words.iter_mut().zip(lines) {
        match bytemuck::try_cast_slice::<u16, u32>(&l[c0..c0 + even]) {
            Ok(x) => *w = x,
            Err(_) => aligned = false,
        }
    }
    let (pairs, rest) = out.split_at_mut(even);
    if aligned {
        let k = Pairs::new(coef, n, saturation);
        let m = even / 2;
        let w: [&[u32]; MAX_N] = core::array::from_fn(|j| if j < n { &words[j][..m] } else { &[] });
        // Lanes flipped (`x ^ 0x8000`) only above a saturation level of 2^15, where samples
        // of 2^15 and more count; the flip is a constant of each loop.
        const FLIP: u32 = 0x8000_8000;
        match (saturation <= 0x8000, n == 4) {
            (true, true) => {
                for (i, o) in pairs.chunks_exact_mut(2).enumerate() {
                    pair_step::<4, 0>(&k, 4, |j| w[j][i], o);
                }
            }
            (true, false) => {
                for (i, o) in pairs.chunks_exact_mut(2).enumerate() {
                    pair_step::<MAX_N, 0>(&k, n, |j| w[j][i], o);
                }
            }
            (false, true) => {
                for (i, o) in pairs.chunks_exact_mut(2).enumerate() {
                    pair_step::<4, FLIP>(&k, 4, |j| w[j][i] ^ FLIP, o);
                }
            }
            (false, false) => {
                for (i, o) in pairs.chunks_exact_mut(2).enumerate() {
                    pair_step::<MAX_N, FLIP>(&k, n, |j| w[j][i] ^ FLIP, o);
                }
            }
        }
    } else {
        for (k, o) in pairs.iter_mut().enumerate() {
            *o = pixel_at(coef, n, |j| lines[j][c0 + k], saturation);
        }
    }
    if let Some(o) = rest.first_mut() {
        *o = pixel_at(coef, n, |j| lines[j][c0 + even], saturation);
    }
}

/// Whether a kernel has work for `n` lines: `n` in `3..=8` (else nothing is written), and a
/// saturation level above 0 (at 0 every sample is saturated: `out` is marked so here).
#[inline(always)]
fn kernel_applies(n: usize, saturation: u16, out: &mut [V]) -> bool {
    if !(3..=MAX_N).contains(&n) {
        return false;
    }
    if saturation == 0 {
        out.fill([SATURATED, 0]);
        return false;
    }
    true
}

/// [`pixel_v`] of the samples `sample(j)`, `j < n`.
#[inline(always)]
fn pixel_at(coef: &Coef, n: usize, sample: impl Fn(usize) -> u16, saturation: u16) -> V {
    let mut s = [0u16; MAX_N];
    for (j, x) in s.iter_mut().enumerate().take(n) {
        *x = sample(j);
    }
    pixel_v(coef, &s[..n], saturation)
}

/// [`block`] for Mono12p lines ([`crate::frames::mono12p`]: the packed line pool of a 12-bit
/// configuration, and lines as a 12-bit camera sends them): `out[k]` is pixel `c0 + k`,
/// [`pixel_v`] of its samples. Each line holds at least [`mono12p::packed_len`]`(c0 +
/// out.len())` bytes. From a `c0` that is a multiple of 8, on word-aligned lines (the pool's
/// and the firmware's buffers are), eight pixels are three aligned words per line and one
/// `unpack12` per pair (`groups_packed`); the rest (a short last block, or any other
/// `c0` or alignment) sample by sample. Samples are below `2^15`: no lane flip.
/// `n = lines.len()` in `3..=8` (else nothing is written); `n = 4`, the paper's and the
/// default geometry's, has its own unrolled loop.
#[inline(never)]
pub fn block_packed(coef: &Coef, lines: &[&[u8]], c0: usize, saturation: u16, out: &mut [V]) {
    let (n, len) = (lines.len(), out.len());
    if !kernel_applies(n, saturation, out) {
        return;
    }
    // Groups of eight pixels (three aligned words per line) from `c0` (a multiple of 8,
    // lines 4-byte aligned: the pool's lines and the firmware's receive buffer are).
    let ng = if c0 % 8 == 0 { len / 8 } else { 0 };
    let at = 3 * c0 / 2;
    let mut groups: [&[[u32; 3]]; MAX_N] = [&[]; MAX_N];
    let mut fast = ng > 0;
    for (g, l) in groups.iter_mut().zip(lines) {
        match l
            .get(at..at + 12 * ng)
            .and_then(|b| bytemuck::try_cast_slice::<u8, [u32; 3]>(b).ok())
        {
            Some(x) => *g = x,
            None => fast = false,
        }
    }
    let done = if fast { 8 * ng } else { 0 };
    let (head, rest) = out.split_at_mut(done);
    if fast {
        let k = Pairs::new(coef, n, saturation);
        if n == 4 {
            groups_packed::<4>(&k, 4, &groups, head);
        } else {
            groups_packed::<MAX_N>(&k, n, &groups, head);
        }
    }
    for (i, o) in rest.iter_mut().enumerate() {
        let c = c0 + done + i;
        *o = pixel_at(coef, n, |j| mono12p::sample(lines[j], c), saturation);
    }
}

/// The coefficient pairs of the kernels (see [`pair_step`]) and the saturation test word,
/// made once per call.
struct Pairs {
    q2: [u32; MAX_N / 2],
    q3: [u32; MAX_N / 2],
    s1: u32,
}

impl Pairs {
    #[inline(always)]
    fn new(coef: &Coef, n: usize, saturation: u16) -> Pairs {
        let at = |q: &[i32; MAX_N], j: usize| if j < n { q[j] } else { 0 };
        Pairs {
            q2: core::array::from_fn(|p| pair(at(&coef.q2, 2 * p), at(&coef.q2, 2 * p + 1))),
            q3: core::array::from_fn(|p| pair(at(&coef.q3, 2 * p), at(&coef.q3, 2 * p + 1))),
            s1: (saturation as u32 - 1) * 0x0001_0001,
        }
    }
}

/// Two neighbouring pixels `o[0]`, `o[1]` of `n <= N` lines; `word(j)` is both pixels' samples
/// of line `j` as two i16 lanes (flipped by `FLIP`, which the saturation test undoes).
///
/// [`pack_bottoms`] / [`pack_tops`] pair line `2p`'s sample with line `2p + 1`'s for each
/// pixel, and one [`smlad`] per pair of lines and row of `P` multiplies them by the
/// coefficient pair `[q_2p, q_2p+1]` (an odd `n` pairs its last line with a zero
/// coefficient): `n` dual multiply-accumulates per pixel instead of `2 n` single ones, no
/// 64-bit arithmetic. The saturation test is one [`uqsub16`] and one or per line: a lane of
/// `x - (saturation - 1)`, floored at 0, is non-zero exactly when `x >= saturation`.
/// Saturated pixels are marked off the hot path ([`mark_saturated`]).
#[inline(always)]
fn pair_step<const N: usize, const FLIP: u32>(
    k: &Pairs,
    n: usize,
    word: impl Fn(usize) -> u32,
    o: &mut [V],
) {
    let (mut a2, mut a3, mut b2, mut b3) = (0i32, 0i32, 0i32, 0i32);
    let mut sat = 0u32;
    let mut p = 0;
    while 2 * p < N && 2 * p < n {
        let x0 = word(2 * p);
        sat |= uqsub16(x0 ^ FLIP, k.s1);
        let x1 = if 2 * p + 1 < n {
            let x1 = word(2 * p + 1);
            sat |= uqsub16(x1 ^ FLIP, k.s1);
            x1
        } else {
            0
        };
        let (lo, hi) = (pack_bottoms(x0, x1), pack_tops(x0, x1));
        a2 = smlad(lo, k.q2[p], a2);
        a3 = smlad(lo, k.q3[p], a3);
        b2 = smlad(hi, k.q2[p], b2);
        b3 = smlad(hi, k.q3[p], b3);
        p += 1;
    }
    o[0] = [a2, a3];
    o[1] = [b2, b3];
    if sat != 0 {
        mark_saturated(o, sat);
    }
}

/// The Mono12p loop: eight pixels (four pairs, twelve bytes, three aligned words per line) at
/// a time. Pair `r` of a group is bytes `3r .. 3r + 3` of the line's three words `w`:
/// `w0`, `w0 >> 24 | w1 << 8`, `w1 >> 16 | w2 << 16`, `w2 >> 8` (the top byte is ignored by
/// [`unpack12`]). (One pass per pair of lines, which keeps fewer values live, measured
/// slower on the target: 46 against 38.5 instructions per pixel.)
#[inline(always)]
fn groups_packed<const N: usize>(
    k: &Pairs,
    n: usize,
    groups: &[&[[u32; 3]]; MAX_N],
    out: &mut [V],
) {
    for (g, o) in out.chunks_exact_mut(8).enumerate() {
        let w = |j: usize| &groups[j][g];
        pair_step::<N, 0>(k, n, |j| unpack12(w(j)[0]), &mut o[0..2]);
        pair_step::<N, 0>(
            k,
            n,
            |j| unpack12(w(j)[0] >> 24 | w(j)[1] << 8),
            &mut o[2..4],
        );
        pair_step::<N, 0>(
            k,
            n,
            |j| unpack12(w(j)[1] >> 16 | w(j)[2] << 16),
            &mut o[4..6],
        );
        pair_step::<N, 0>(k, n, |j| unpack12(w(j)[2] >> 8), &mut o[6..8]);
    }
}

/// Marks the saturated pixels of a pair: lane 0 of `sat` for `o[0]`, lane 1 for `o[1]`.
#[cold]
#[inline(never)]
fn mark_saturated(o: &mut [V], sat: u32) {
    if sat & 0xFFFF != 0 {
        o[0] = [SATURATED, 0];
    }
    if sat >> 16 != 0 {
        o[1] = [SATURATED, 0];
    }
}

/// Pool of line slots with a free-list, in caller-supplied memory. A slot holds one line's raw
/// samples either as `W` u16 or, when the pool is *packed*, as Mono12p bytes
/// ([`crate::frames::mono12p`], [`crate::frames::mono12p::stored_len`] bytes: the layout's
/// [`crate::pipeline::Layout::pool_line_units`] u16 units per slot).
pub struct Pool<'a> {
    width: usize,
    /// u16 units per slot.
    stride: usize,
    packed: bool,
    lines: &'a mut [u16],
    free: &'a mut [u16],
    top: usize,
}

impl<'a> Pool<'a> {
    /// `lines` holds `free.len()` slots of `stride` u16 units each (`stride >= width` for a
    /// 16-bit pool; `2 stride >=` [`crate::frames::mono12p::stored_len`]`(width)` for a packed
    /// one).
    pub fn new(
        width: usize,
        stride: usize,
        packed: bool,
        lines: &'a mut [u16],
        free: &'a mut [u16],
    ) -> Option<Self> {
        let count = free.len();
        let fits = if packed {
            2 * stride >= mono12p::stored_len(width)
        } else {
            stride >= width
        };
        if width == 0 || !fits || count > u16::MAX as usize || lines.len() < count * stride {
            return None;
        }
        for (i, f) in free.iter_mut().enumerate() {
            // Pop order is ascending (slot 0 first): free[top-1] is taken first.
            *f = (count - 1 - i) as u16;
        }
        Some(Pool {
            width,
            stride,
            packed,
            lines,
            free,
            top: count,
        })
    }

    /// Whether slots hold Mono12p lines.
    pub fn packed(&self) -> bool {
        self.packed
    }

    fn take(&mut self) -> Option<(u16, &mut [u16])> {
        if self.top == 0 {
            return None;
        }
        self.top -= 1;
        let slot = self.free[self.top];
        let s = self.stride;
        let dst = self
            .lines
            .get_mut(slot as usize * s..slot as usize * s + s)?;
        Some((slot, dst))
    }

    /// Takes a slot without writing it: the line lives elsewhere (a front end's own pool,
    /// [`crate::offload::FrontEnd::keep`]); `None` when the pool is exhausted.
    pub fn take_slot(&mut self) -> Option<u16> {
        self.take().map(|(slot, _)| slot)
    }

    /// Takes a slot and stores `line` (`W` samples) in it, packed (each sample clamped to
    /// 4095) in a packed pool; `None` when the pool is exhausted.
    pub fn store(&mut self, line: &[u16]) -> Option<u16> {
        let (packed, w) = (self.packed, self.width);
        let (slot, dst) = self.take()?;
        let n = w.min(line.len());
        if packed {
            mono12p::pack(&line[..n], bytemuck::cast_slice_mut(dst));
        } else {
            dst[..n].copy_from_slice(&line[..n]);
        }
        Some(slot)
    }

    /// Takes a slot of a packed pool and copies the Mono12p line `b`
    /// ([`crate::frames::mono12p::packed_len`]`(W)` bytes) into it; `None` when the pool is
    /// exhausted or not packed.
    pub fn store_packed(&mut self, b: &[u8]) -> Option<u16> {
        if !self.packed {
            return None;
        }
        let len = mono12p::packed_len(self.width).min(b.len());
        let (slot, dst) = self.take()?;
        let dst: &mut [u8] = bytemuck::cast_slice_mut(dst);
        dst[..len].copy_from_slice(&b[..len]);
        Some(slot)
    }

    /// Returns a slot to the pool.
    pub fn release(&mut self, slot: u16) {
        if self.top < self.free.len() {
            self.free[self.top] = slot;
            self.top += 1;
        }
    }

    /// The samples of a slot of a 16-bit pool (empty for a packed pool).
    pub fn line(&self, slot: u16) -> &[u16] {
        if self.packed {
            return &[];
        }
        let (s, w) = (self.stride, self.width);
        self.lines
            .get(slot as usize * s..slot as usize * s + w)
            .unwrap_or(&[])
    }

    /// The bytes of a slot of a packed pool: the Mono12p line, rounded up to whole words
    /// ([`crate::frames::mono12p::stored_len`]; empty for a 16-bit pool).
    pub fn packed_line(&self, slot: u16) -> &[u8] {
        if !self.packed {
            return &[];
        }
        let s = self.stride;
        let b: &[u8] = self
            .lines
            .get(slot as usize * s..slot as usize * s + s)
            .map_or(&[], bytemuck::cast_slice);
        &b[..mono12p::stored_len(self.width).min(b.len())]
    }

    /// Slots in use.
    pub fn used(&self) -> usize {
        self.free.len() - self.top
    }
}

/// [`block`] with the pipeline's [`Kernel`]: its AVX2 build ([`Kernel::Avx2`]) takes sixteen
/// pixels at a time; every other kernel runs [`block`]. The same results (tested:
/// `block_equals_pixel_v` through every kernel).
#[inline(always)]
pub fn block_with(
    kernel: Kernel,
    coef: &Coef,
    lines: &[&[u16]],
    c0: usize,
    saturation: u16,
    out: &mut [V],
) {
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2(proof) => x86::block(proof, coef, lines, c0, saturation, out),
        _ => block(coef, lines, c0, saturation, out),
    }
}

/// [`block_packed`] with the pipeline's [`Kernel`]: its AVX2 build ([`Kernel::Avx2`], x86-64
/// with AVX2 detected at run time) takes sixteen pixels at a time; every other kernel (the
/// firmware's scalar loop among them) runs [`block_packed`]. The results are the same
/// (tested: `block_equals_pixel_v` through every kernel, and the pipeline's rows).
#[inline(always)]
pub fn block_packed_with(
    kernel: Kernel,
    coef: &Coef,
    lines: &[&[u8]],
    c0: usize,
    saturation: u16,
    out: &mut [V],
) {
    match kernel {
        #[cfg(target_arch = "x86_64")]
        Kernel::Avx2(proof) => x86::block_packed(proof, coef, lines, c0, saturation, out),
        _ => block_packed(coef, lines, c0, saturation, out),
    }
}

/// The accumulate stage in AVX2: sixteen pixels a step (32 bytes of each 16-bit line, 24 of
/// each Mono12p line), the same sums as [`pair_step`] in the same wrapping i32 arithmetic.
///
/// - **Unpack.** Each 128-bit half takes twelve bytes (eight pixels) of a line; one byte
///   shuffle puts bytes `3i, 3i + 1` into the 16-bit lane of pixel `2i` and `3i + 1, 3i + 2`
///   into that of `2i + 1`; the even lanes keep their low twelve bits, the odd lanes shift
///   right by four: [`mono12p::sample`] of every pixel, as [`unpack12`] gives.
/// - **Multiply-accumulate.** `_mm256_madd_epi16` on the interleaved lanes of lines `2p` and
///   `2p + 1` against the broadcast coefficient pair `[q_2p, q_2p+1]` is [`smlad`] in eight
///   lanes: two exact i16 products added in i32. Its one overflowing case, both products
///   `(-2^15)^2`, cannot occur (samples are below 2^12, and `|q| <= 32767`). The sums over the
///   pairs of lines are wrapping 32-bit adds, as [`smlad`]'s.
/// - **16-bit lines** are read as they are, their lanes flipped (`x ^ 0x8000`) above a
///   saturation level of 2^15 as [`block`] flips them; `madd`'s overflowing case needs a
///   coefficient of `-2^15`, which [`Coef`] never has.
/// - **Saturation.** `_mm256_subs_epu16` is [`uqsub16`]: a lane of `x - (saturation - 1)`
///   floored at 0 is non-zero exactly when `x >= saturation`; such pixels are marked
///   `[SATURATED, 0]` afterwards, off the hot path.
///
/// A Mono12p step runs where both sixteen-byte loads (bytes `0..16` and `12..28` of the step)
/// lie inside every line; the rest of the columns (fewer than sixteen, or a line that ends
/// within four bytes) go through [`block_packed`], as do a `c0` that is not a multiple of 8
/// and line counts outside `3..=8`; the last columns of 16-bit lines (fewer than sixteen) go
/// through [`block`].
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod x86 {
    use super::*;
    use crate::lanes::Avx2;
    use core::arch::x86_64::*;

    /// Pixels per step.
    const STEP: usize = 16;

    pub(super) fn block_packed(
        proof: Avx2,
        coef: &Coef,
        lines: &[&[u8]],
        c0: usize,
        saturation: u16,
        out: &mut [V],
    ) {
        let _ = proof;
        let n = lines.len();
        if !(3..=MAX_N).contains(&n) || saturation == 0 || c0 % 8 != 0 {
            super::block_packed(coef, lines, c0, saturation, out);
            return;
        }
        let at = 3 * c0 / 2;
        // Steps whose loads (up to byte 12 * 2 + 16 = 28 of the step) lie inside every line.
        let shortest = lines.iter().map(|l| l.len()).min().unwrap_or(0);
        let room = shortest.saturating_sub(at + 4) / 24;
        let steps = (out.len() / STEP).min(room);
        let done = steps * STEP;
        let (head, rest) = out.split_at_mut(done);
        if steps > 0 {
            // SAFETY: a `proof` (`Avx2`) is made only after run-time detection found AVX2
            // (`Kernel::avx2`); `steps` keeps every load inside its line (checked again by
            // the slices the loads take).
            unsafe { steps_avx2(coef, lines, at, saturation, head) };
        }
        if !rest.is_empty() {
            super::block_packed(coef, lines, c0 + done, saturation, rest);
        }
    }

    pub(super) fn block(
        proof: Avx2,
        coef: &Coef,
        lines: &[&[u16]],
        c0: usize,
        saturation: u16,
        out: &mut [V],
    ) {
        let _ = proof;
        let n = lines.len();
        if !(3..=MAX_N).contains(&n) || saturation == 0 {
            super::block(coef, lines, c0, saturation, out);
            return;
        }
        let done = out.len() / STEP * STEP;
        let (head, rest) = out.split_at_mut(done);
        if done > 0 {
            // SAFETY: as in `block_packed`; every line holds `c0 + out.len()` samples (the
            // caller's contract, checked again by the slices the loads take).
            unsafe { steps_wide_avx2(coef, lines, c0, saturation, head) };
        }
        if !rest.is_empty() {
            super::block(coef, lines, c0 + done, saturation, rest);
        }
    }

    /// Sixteen samples of a 16-bit line from column `at`, flipped by `flip`.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn wide(line: &[u16], at: usize, flip: __m256i) -> (__m256i, __m256i) {
        let s: &[u16; STEP] = line[at..at + STEP].try_into().expect("16 samples");
        // SAFETY: `s` is 32 readable bytes; the load has no alignment requirement.
        let raw = unsafe { _mm256_loadu_si256(s.as_ptr().cast()) };
        (raw, _mm256_xor_si256(raw, flip))
    }

    #[target_feature(enable = "avx2")]
    fn steps_wide_avx2(coef: &Coef, lines: &[&[u16]], c0: usize, saturation: u16, out: &mut [V]) {
        let n = lines.len();
        let k = Pairs::new(coef, n, saturation);
        let flip = _mm256_set1_epi16(if saturation <= 0x8000 { 0 } else { i16::MIN });
        let s1 = _mm256_set1_epi16((saturation - 1) as i16);
        let q2: [__m256i; MAX_N / 2] = core::array::from_fn(|p| _mm256_set1_epi32(k.q2[p] as i32));
        let q3: [__m256i; MAX_N / 2] = core::array::from_fn(|p| _mm256_set1_epi32(k.q3[p] as i32));
        for (s, o) in out.chunks_exact_mut(STEP).enumerate() {
            let at = c0 + STEP * s;
            accumulate_step(n, &q2, &q3, s1, |j| wide(lines[j], at, flip), o);
        }
    }

    /// Sixteen bytes of `line` from `at` (a bounds-checked slice, then an unaligned load).
    #[target_feature(enable = "avx2")]
    #[inline]
    fn load16(line: &[u8], at: usize) -> __m128i {
        let b: &[u8; 16] = line[at..at + 16].try_into().expect("16 bytes");
        // SAFETY: `b` is sixteen readable bytes; the load has no alignment requirement.
        unsafe { _mm_loadu_si128(b.as_ptr().cast()) }
    }

    /// Pixels `16 s .. 16 s + 16` of a line from byte `at`: sixteen samples in 16-bit lanes,
    /// in column order.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn samples(line: &[u8], at: usize, shuffle: __m256i) -> __m256i {
        let both = _mm256_inserti128_si256::<1>(
            _mm256_castsi128_si256(load16(line, at)),
            load16(line, at + 12),
        );
        let w = _mm256_shuffle_epi8(both, shuffle);
        let even = _mm256_and_si256(w, _mm256_set1_epi16(0x0FFF));
        let odd = _mm256_srli_epi16::<4>(w);
        _mm256_blend_epi16::<0b1010_1010>(even, odd)
    }

    #[target_feature(enable = "avx2")]
    fn steps_avx2(coef: &Coef, lines: &[&[u8]], at: usize, saturation: u16, out: &mut [V]) {
        let n = lines.len();
        let k = Pairs::new(coef, n, saturation);
        // Bytes of each pixel's 16-bit lane, per 128-bit half (eight pixels in twelve bytes).
        let shuffle = _mm256_broadcastsi128_si256(_mm_setr_epi8(
            0, 1, 1, 2, 3, 4, 4, 5, 6, 7, 7, 8, 9, 10, 10, 11,
        ));
        let s1 = _mm256_set1_epi16((saturation - 1) as i16);
        let q2: [__m256i; MAX_N / 2] = core::array::from_fn(|p| _mm256_set1_epi32(k.q2[p] as i32));
        let q3: [__m256i; MAX_N / 2] = core::array::from_fn(|p| _mm256_set1_epi32(k.q3[p] as i32));
        for (s, o) in out.chunks_exact_mut(STEP).enumerate() {
            let b = at + 24 * s;
            accumulate_step(
                n,
                &q2,
                &q3,
                s1,
                |j| {
                    let x = samples(lines[j], b, shuffle);
                    (x, x)
                },
                o,
            );
        }
    }

    /// One step of sixteen pixels `o` of `n` lines: `line(j)` gives line `j`'s samples as
    /// they are (for the saturation test) and as the products take them (flipped or not).
    #[target_feature(enable = "avx2")]
    #[inline]
    fn accumulate_step(
        n: usize,
        q2: &[__m256i; MAX_N / 2],
        q3: &[__m256i; MAX_N / 2],
        s1: __m256i,
        line: impl Fn(usize) -> (__m256i, __m256i),
        o: &mut [V],
    ) {
        let zero = _mm256_setzero_si256();
        let (mut a2lo, mut a3lo, mut a2hi, mut a3hi) = (zero, zero, zero, zero);
        let mut sat = zero;
        for p in 0..n.div_ceil(2) {
            let (r0, x0) = line(2 * p);
            sat = _mm256_or_si256(sat, _mm256_subs_epu16(r0, s1));
            let x1 = if 2 * p + 1 < n {
                let (r1, x1) = line(2 * p + 1);
                sat = _mm256_or_si256(sat, _mm256_subs_epu16(r1, s1));
                x1
            } else {
                zero
            };
            // Per 128-bit half: pixels 0-3 (8-11) in `lo`, 4-7 (12-15) in `hi`.
            let lo = _mm256_unpacklo_epi16(x0, x1);
            let hi = _mm256_unpackhi_epi16(x0, x1);
            a2lo = _mm256_add_epi32(a2lo, _mm256_madd_epi16(lo, q2[p]));
            a3lo = _mm256_add_epi32(a3lo, _mm256_madd_epi16(lo, q3[p]));
            a2hi = _mm256_add_epi32(a2hi, _mm256_madd_epi16(hi, q2[p]));
            a3hi = _mm256_add_epi32(a3hi, _mm256_madd_epi16(hi, q3[p]));
        }
        // `[v_2, v_3]` per pixel, back in column order.
        let (l0, l1) = (
            _mm256_unpacklo_epi32(a2lo, a3lo),
            _mm256_unpackhi_epi32(a2lo, a3lo),
        );
        let (h0, h1) = (
            _mm256_unpacklo_epi32(a2hi, a3hi),
            _mm256_unpackhi_epi32(a2hi, a3hi),
        );
        let quarters = [
            _mm256_permute2x128_si256::<0x20>(l0, l1),
            _mm256_permute2x128_si256::<0x20>(h0, h1),
            _mm256_permute2x128_si256::<0x31>(l0, l1),
            _mm256_permute2x128_si256::<0x31>(h0, h1),
        ];
        for (q, dst) in quarters.iter().zip(o.chunks_exact_mut(4)) {
            let d: &mut [i32] = bytemuck::cast_slice_mut(dst);
            let d: &mut [i32; 8] = d.try_into().expect("four pixels");
            // SAFETY: `d` is 32 writable bytes; the store has no alignment requirement.
            unsafe { _mm256_storeu_si256(d.as_mut_ptr().cast(), *q) };
        }
        if _mm256_testz_si256(sat, sat) == 0 {
            mark(o, sat);
        }
    }

    /// Marks the saturated pixels of a step (a non-zero 16-bit lane of `sat`).
    #[cold]
    #[inline(never)]
    #[target_feature(enable = "avx2")]
    fn mark(o: &mut [V], sat: __m256i) {
        let mut lanes = [0u16; STEP];
        // SAFETY: `lanes` is 32 writable bytes; the store has no alignment requirement.
        unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast(), sat) };
        for (v, l) in o.iter_mut().zip(lanes) {
            if l != 0 {
                *v = [SATURATED, 0];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::phase::from_rad;
    use std::vec;

    #[test]
    fn pixel_recovers_cos_and_sin() {
        // Noiseless samples B + C cos(Phi + theta_j) with non-uniform shifts.
        let th = [0.0f64, -1.4, -3.3, -4.6, -6.0];
        let bam: vec::Vec<u32> = th.iter().map(|&t| from_rad(t)).collect();
        let w = Window::solve(&bam, fixed::types::U8F8::from_num(8)).unwrap();
        let (b, c, phi) = (1800.0, 700.0, 0.9f64);
        let s: vec::Vec<u16> = th
            .iter()
            .map(|t| (b + c * (phi + t).cos()).round() as u16)
            .collect();
        let a = pixel(&w, &s, 4095);
        let q = (1u64 << 24) as f64;
        // Integer rounding of the samples (<= 0.5 DN) bounds the error.
        assert!((a.v2 as f64 / q - c * phi.cos()).abs() < 2.0);
        assert!((a.v3 as f64 / q - c * phi.sin()).abs() < 2.0);
        assert!(!a.saturated);
        assert!(pixel(&w, &[0, 0, 4095, 0, 0], 4095).saturated);
    }

    fn lines4() -> vec::Vec<vec::Vec<u16>> {
        (0..4u32)
            .map(|j| {
                (0..37u32)
                    .map(|c| ((c * 977 + j * 3331) % 4200) as u16)
                    .collect()
            })
            .collect()
    }

    #[test]
    fn block_is_pixel_v() {
        let bam: vec::Vec<u32> = [0.0f64, -1.9, -3.7, -5.8]
            .iter()
            .map(|&t| from_rad(t))
            .collect();
        let w = Window::solve(&bam, fixed::types::U8F8::from_num(8)).unwrap();
        let coef = Coef::of(&w, 4095).unwrap();
        let l = lines4();
        let lines: [&[u16]; 4] = core::array::from_fn(|j| &l[j][..]);
        let mut out = [[0i32; 2]; 30];
        block(&coef, &lines, 5, 4095, &mut out);
        for (k, o) in out.iter().enumerate() {
            let s: vec::Vec<u16> = (0..4).map(|j| l[j][5 + k]).collect();
            assert_eq!(*o, pixel_v(&coef, &s, 4095), "column {}", 5 + k);
            // Non-saturated: the exact (i64) sum, no wrap.
            if o[0] != SATURATED {
                let exact = |q: &[i32]| -> i64 { (0..4).map(|j| q[j] as i64 * s[j] as i64).sum() };
                assert_eq!(
                    (o[0] as i64, o[1] as i64),
                    (exact(&coef.q2), exact(&coef.q3))
                );
            }
        }
        assert!(out.iter().any(|o| o[0] == SATURATED) && out.iter().any(|o| o[0] != SATURATED));
        // Saturation 0 marks everything, 65535 only 65535.
        let mut all = [[0i32; 2]; 30];
        block(&coef, &lines, 5, 0, &mut all);
        assert!(all.iter().all(|o| o[0] == SATURATED));
        let c16 = Coef::of(&w, 65535).unwrap();
        let hi = [[65534u16, 65534], [0, 0], [65535, 1], [1, 65534]];
        let hl: [&[u16]; 4] = core::array::from_fn(|j| &hi[j][..]);
        let mut o = [[0i32; 2]; 2];
        block(&c16, &hl, 0, 65535, &mut o);
        assert_eq!(o[0], pixel_v(&c16, &[65534, 0, 65535, 1], 65535));
        assert_eq!(o[0][0], SATURATED);
        assert_ne!(o[1][0], SATURATED);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(600))]

        /// The paired kernel (and its fallbacks: odd `c0`, misaligned lines, an odd last
        /// column) equals [`pixel_v`] for every `n`, at every saturation class (8, 12 and 16
        /// bits, the flip boundary `2^15` and its neighbours, 1 and 0), on samples drawn
        /// from the classes that matter (0, just below / at / above the level, `2^15 +- 1`,
        /// 65535) and uniformly.
        #[test]
        fn block_equals_pixel_v(
            n in 3usize..=8,
            th in proptest::collection::vec(0u32..u32::MAX, 8),
            sat_class in 0usize..9,
            c0 in 0usize..20,
            len in 0usize..100,
            shift in 0usize..2,
            samples in proptest::collection::vec((0u8..8, 0u16..=u16::MAX), 8 * 48),
        ) {
            let sat = [255u16, 4095, 65535, 0x8000, 0x7FFF, 0x8001, 1, 0, 3000][sat_class];
            let Ok(w) = Window::solve(&th[..n], fixed::types::U8F8::from_num(8)) else {
                return Ok(());
            };
            let Some(coef) = Coef::of(&w, sat) else { return Ok(()) };
            let width = c0 + len;
            // `shift` starts every line one sample into its buffer: misaligned words.
            let data: vec::Vec<vec::Vec<u16>> = (0..n)
                .map(|j| {
                    (0..width + shift)
                        .map(|c| {
                            let (class, u) = samples[(j * 48 + c) % samples.len()];
                            match class {
                                0 => 0,
                                1 => sat.saturating_sub(1),
                                2 => sat,
                                3 => sat.saturating_add(1),
                                4 => 0x7FFF,
                                5 => 0x8000,
                                6 => 65535,
                                _ => u,
                            }
                        })
                        .collect()
                })
                .collect();
            let lines: vec::Vec<&[u16]> = data.iter().map(|l| &l[shift..]).collect();
            let mut out = vec![[7i32, 7]; len];
            block(&coef, &lines, c0, sat, &mut out);
            for (k, o) in out.iter().enumerate() {
                let s: vec::Vec<u16> = lines.iter().map(|l| l[c0 + k]).collect();
                proptest::prop_assert_eq!(*o, pixel_v(&coef, &s, sat), "column {}", c0 + k);
            }
            for kernel in Kernel::all() {
                let mut outk = vec![[7i32, 7]; len];
                block_with(kernel, &coef, &lines, c0, sat, &mut outk);
                proptest::prop_assert_eq!(&outk, &out, "16-bit, {}", kernel.name());
            }
            // Mono12p lines (a packed pool: saturation <= 4095), with and without spare bytes
            // (the AVX2 build's last loads reach four bytes past a step), through every
            // kernel's build, give the same pixels: samples above 4095 are stored as 4095,
            // still saturated.
            if sat <= mono12p::MAX {
                for slack in [0usize, 1, 3, 4, 5] {
                    let packed: vec::Vec<vec::Vec<u8>> = lines
                        .iter()
                        .map(|l| {
                            let mut b = vec![0u8; mono12p::packed_len(width) + slack];
                            mono12p::pack(l, &mut b);
                            b
                        })
                        .collect();
                    let pl: vec::Vec<&[u8]> = packed.iter().map(|b| &b[..]).collect();
                    let mut outp = vec![[7i32, 7]; len];
                    block_packed(&coef, &pl, c0, sat, &mut outp);
                    proptest::prop_assert_eq!(&outp, &out, "packed, slack {}", slack);
                    for kernel in Kernel::all() {
                        let mut outk = vec![[7i32, 7]; len];
                        block_packed_with(kernel, &coef, &pl, c0, sat, &mut outk);
                        proptest::prop_assert_eq!(
                            &outk, &out, "packed, slack {}, {}", slack, kernel.name()
                        );
                    }
                }
            }
        }
    }

    /// The kernel's coefficients: i16, zero row sums, no overflow at any non-saturated sample
    /// set (checked at the extremes), and close to the Q7.24 `P` (relative to the row's
    /// largest entry, at most `2^-15` plus the fix-up).
    #[test]
    fn coef_bounds_over_random_windows() {
        let mut seed = 0x2545_F491_4F6C_DD1Du64;
        let mut rnd = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        let mut tested = 0;
        // Smallest largest-entry seen: the resolution of the coefficients.
        let mut least = [i32::MAX; 2];
        for _ in 0..4000 {
            let n = 3 + (rnd() % 6) as usize;
            let bam: vec::Vec<u32> = (0..n).map(|_| rnd() as u32).collect();
            let Ok(w) = Window::solve(&bam, fixed::types::U8F8::from_num(8)) else {
                continue;
            };
            for sat in [255u16, 4095, 65535] {
                let c = Coef::of(&w, sat).unwrap();
                tested += 1;
                // One `frac` for both rows (atan2 needs one scale): the larger row's largest entry.
                let big = c.q2[..n]
                    .iter()
                    .chain(&c.q3[..n])
                    .map(|x| x.abs())
                    .max()
                    .unwrap();
                let key = (sat == 65535) as usize;
                least[key] = least[key].min(big);
                for (q, p) in [(&c.q2, &w.p2), (&c.q3, &w.p3)] {
                    assert_eq!(q[..n].iter().map(|&x| x as i64).sum::<i64>(), 0);
                    assert!(q[..n].iter().all(|x| x.abs() <= 32767));
                    // Rounding (1/2) plus the zero-sum fix-up (n/2) per entry, in units of q.
                    for j in 0..n {
                        let want = p[j] as f64 / (1u64 << (24 - c.frac)) as f64;
                        assert!((q[j] as f64 - want).abs() <= 0.5 + n as f64 / 2.0);
                    }
                    // Worst case for the sum: samples at 0 or sat - 1 by the sign of q.
                    for sign in [1i64, -1] {
                        let v: i64 = (0..n)
                            .map(|j| {
                                let x = if (q[j] as i64) * sign > 0 {
                                    sat as i64 - 1
                                } else {
                                    0
                                };
                                q[j] as i64 * x
                            })
                            .sum();
                        assert!(v.abs() < 1 << 31, "v {v}");
                    }
                }
            }
        }
        assert!(tested > 3000, "{tested}");
        std::println!("smallest max |q|: {least:?}");
        // 12-bit and 8-bit samples: the largest entry has at least 14 bits; 16-bit: 12 bits.
        assert!(least[0] >= 1 << 14 && least[1] >= 1 << 12, "{least:?}");
    }

    #[test]
    fn reduce_clamps() {
        // Clamping keeps reduced values off the saturation marker; both paths agree with
        // the plain shift-and-clamp at and around every boundary.
        let big = Acc {
            v2: i64::MIN >> 1,
            v3: i64::MAX >> 1,
            saturated: false,
        };
        assert_eq!(big.reduce(), [i32::MIN + 1, i32::MAX]);
        let plain = |v: i64| (v >> 12).clamp(i32::MIN as i64 + 1, i32::MAX as i64) as i32;
        for edge in [
            0i64,
            1 << 43,
            -(1 << 43),
            (1 << 43) - (1 << 32),
            -(1 << 43) + (1 << 32),
            1 << 32,
            -(1 << 32),
        ] {
            for d in -5000i64..5000 {
                let v = edge.wrapping_add(d);
                assert_eq!(q12(v), plain(v), "v = {v}");
            }
        }
        for v in [i64::MIN, i64::MAX, i64::MIN + 1, -1] {
            assert_eq!(q12(v), plain(v), "v = {v}");
        }
    }

    #[test]
    fn pool_exhaustion_and_reuse() {
        let mut lines = vec![0u16; 3 * 4];
        let mut free = vec![0u16; 3];
        let mut p = Pool::new(4, 4, false, &mut lines, &mut free).unwrap();
        let a = p.store(&[1, 2, 3, 4]).unwrap();
        let b = p.store(&[5, 6, 7, 8]).unwrap();
        let c = p.store(&[9, 9, 9, 9]).unwrap();
        assert_eq!(p.store(&[0; 4]), None);
        assert_eq!(p.line(b), &[5, 6, 7, 8]);
        p.release(a);
        let d = p.store(&[4, 3, 2, 1]).unwrap();
        assert_eq!(d, a);
        assert_eq!(p.line(d), &[4, 3, 2, 1]);
        assert_eq!(p.line(c), &[9, 9, 9, 9]);
        assert_eq!(p.used(), 3);
    }
}
