//! Accumulate: the raw samples of open board rows, and the per-pixel `v = P i` products.
//!
//! A board row needs `n` samples from `n` consecutive frames, but its window's `P` is only
//! known once the encoder latch of its last frame arrives. So the first `n - 1` samples of
//! every open row are kept raw (u16) in a pool of line slots, and the `n`-th line is combined
//! with them as it streams in. Open rows entered in the last `n - 1` frames hold `1..n-1`
//! lines each, so the pool needs at most `max_step_rows * n (n - 1) / 2` lines: a triangle, not
//! the `(n - 1)` full frames a frame buffer would take.

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
        let r = if sh == 0 {
            x as i64
        } else {
            (x as i64 + (1 << (sh - 1))) >> sh
        };
        q[j] = r.clamp(i32::MIN as i64 + 1, i32::MAX as i64) as i32;
        sum += q[j] as i64;
        if q[j].unsigned_abs() > q[big].unsigned_abs() {
            big = j;
        }
    }
    q[big] = (q[big] as i64 - sum).clamp(i32::MIN as i64 + 1, i32::MAX as i64) as i32;
    q
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

/// The accumulate stage over a run of columns: `out[k]` is pixel `c0 + k` of the `N` lines,
/// [`pixel_v`] of its samples. `N` is the window's `n` as a constant, so the sample loop
/// unrolls into `2 N` 32-bit multiply-accumulates (`MLA` on the M7; no 64-bit arithmetic).
///
/// The saturation test is one add and one or per sample: with `K = 2^16 - saturation`,
/// `x + K >= 2^16` exactly when `x >= saturation`, and the or of values below `2^16` stays
/// below `2^16` (all `x + K < 2^17`).
///
/// Every line must hold at least `c0 + out.len()` samples (the caller checks; a shorter line
/// would be a programming error and panics).
#[inline(always)]
pub fn block<const N: usize>(
    coef: &Coef,
    lines: &[&[u16]; N],
    c0: usize,
    saturation: u16,
    out: &mut [V],
) {
    if saturation <= 0x8000 {
        kernel::<N, false>(coef, lines, c0, saturation, out);
    } else {
        kernel::<N, true>(coef, lines, c0, saturation, out);
    }
}

/// [`block`] for one centring mode. The samples are read as i16 (`x as i16`): exact for every
/// sample below `2^15`, so when `saturation <= 2^15` every non-saturated pixel is exact
/// without centring (`CENTRE = false`; saturated pixels are discarded whatever their sums).
/// Above that, `CENTRE` reads `x - 2^15` (`x ^ 0x8000` as i16), which the zero row sums
/// cancel.
#[inline(always)]
fn kernel<const N: usize, const CENTRE: bool>(
    coef: &Coef,
    lines: &[&[u16]; N],
    c0: usize,
    saturation: u16,
    out: &mut [V],
) {
    let len = out.len();
    // Both rows' coefficients of sample j in one word: q2 in the bottom half, q3 in the top
    // (the operand form of the M7's 16 x 16 multiply-accumulates, `SMLABB` / `SMLATB`).
    let qp: [u32; N] =
        core::array::from_fn(|j| (coef.q2[j] as u16 as u32) | ((coef.q3[j] as u32) << 16));
    let ls: [&[u16]; N] = core::array::from_fn(|j| &lines[j][c0..c0 + len]);
    let sat = saturation as u32;
    for (i, o) in out.iter_mut().enumerate() {
        let (mut v2, mut v3, mut low) = (0i32, 0i32, u32::MAX);
        for j in 0..N {
            let x = ls[j][i];
            let xc = if CENTRE { x ^ 0x8000 } else { x } as i16 as i32;
            v2 = v2.wrapping_add((qp[j] as i16 as i32).wrapping_mul(xc));
            v3 = v3.wrapping_add(((qp[j] as i32) >> 16).wrapping_mul(xc));
            // Bit 31 stays set while every sample is below the saturation level.
            low &= (x as u32).wrapping_sub(sat);
        }
        *o = if low >> 31 == 0 {
            [SATURATED, 0]
        } else {
            [v2, v3]
        };
    }
}

/// [`block`] with `n = lines.len()` chosen at run time, as its own (never inlined) function:
/// what a caller outside the pipeline (the firmware's stage benchmark) runs to time the
/// accumulate stage alone. `lines` holds `n` lines (`3..=8`, else nothing is written).
#[inline(never)]
pub fn row(coef: &Coef, lines: &[&[u16]], c0: usize, saturation: u16, out: &mut [V]) {
    fn go<const N: usize>(coef: &Coef, lines: &[&[u16]], c0: usize, sat: u16, out: &mut [V]) {
        let l: [&[u16]; N] = core::array::from_fn(|j| lines[j]);
        block::<N>(coef, &l, c0, sat, out);
    }
    match lines.len() {
        3 => go::<3>(coef, lines, c0, saturation, out),
        4 => go::<4>(coef, lines, c0, saturation, out),
        5 => go::<5>(coef, lines, c0, saturation, out),
        6 => go::<6>(coef, lines, c0, saturation, out),
        7 => go::<7>(coef, lines, c0, saturation, out),
        8 => go::<8>(coef, lines, c0, saturation, out),
        _ => {}
    }
}

/// Pool of `W`-wide line slots with a free-list, in caller-supplied memory.
pub struct Pool<'a> {
    width: usize,
    lines: &'a mut [u16],
    free: &'a mut [u16],
    top: usize,
}

impl<'a> Pool<'a> {
    /// `lines` holds `free.len()` slots of `width` samples each.
    pub fn new(width: usize, lines: &'a mut [u16], free: &'a mut [u16]) -> Option<Self> {
        let count = free.len();
        if width == 0 || count > u16::MAX as usize || lines.len() < count * width {
            return None;
        }
        for (i, f) in free.iter_mut().enumerate() {
            // Pop order is ascending (slot 0 first): free[top-1] is taken first.
            *f = (count - 1 - i) as u16;
        }
        Some(Pool {
            width,
            lines,
            free,
            top: count,
        })
    }

    /// Takes a slot and copies `line` into it; `None` when the pool is exhausted.
    pub fn store(&mut self, line: &[u16]) -> Option<u16> {
        if self.top == 0 {
            return None;
        }
        self.top -= 1;
        let slot = self.free[self.top];
        let w = self.width;
        let dst = self
            .lines
            .get_mut(slot as usize * w..slot as usize * w + w)?;
        let n = w.min(line.len());
        dst[..n].copy_from_slice(&line[..n]);
        Some(slot)
    }

    /// Returns a slot to the pool.
    pub fn release(&mut self, slot: u16) {
        if self.top < self.free.len() {
            self.free[self.top] = slot;
            self.top += 1;
        }
    }

    /// The samples of a slot.
    pub fn line(&self, slot: u16) -> &[u16] {
        let w = self.width;
        self.lines
            .get(slot as usize * w..slot as usize * w + w)
            .unwrap_or(&[])
    }

    /// Slots in use.
    pub fn used(&self) -> usize {
        self.free.len() - self.top
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
        let mut p = Pool::new(4, &mut lines, &mut free).unwrap();
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
