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

/// `v_2`, `v_3` of a pixel reduced to DN in Q20.12 (`v >> 12`, clamped to `+-(2^31 - 1)`),
/// the form the phase stage takes. [`SATURATED`] in `v_2` marks a saturated pixel.
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

/// The accumulate stage over a run of columns: `out[k]` is pixel `c0 + k` of the `N` lines,
/// `v = P i` (as [`pixel`]) reduced to [`V`]. `N` is the window's `n` as a constant, so the
/// sample loop unrolls into `2 N` 32x32 -> 64 multiply-accumulates (`SMLAL` on the M7).
///
/// Every line must hold at least `c0 + out.len()` samples (the caller checks; a shorter line
/// would be a programming error and panics).
#[inline(always)]
pub fn block<const N: usize>(
    win: &Window,
    lines: &[&[u16]; N],
    c0: usize,
    saturation: u16,
    out: &mut [V],
) {
    let len = out.len();
    let p2: [i32; N] = core::array::from_fn(|j| win.p2[j]);
    let p3: [i32; N] = core::array::from_fn(|j| win.p3[j]);
    let ls: [&[u16]; N] = core::array::from_fn(|j| &lines[j][c0..c0 + len]);
    for (k, o) in out.iter_mut().enumerate() {
        let (mut v2, mut v3, mut top) = (0i64, 0i64, 0u16);
        for j in 0..N {
            let x = ls[j][k];
            v2 += p2[j] as i64 * x as i64;
            v3 += p3[j] as i64 * x as i64;
            top = top.max(x);
        }
        *o = if top >= saturation {
            [SATURATED, 0]
        } else {
            [q12(v2), q12(v3)]
        };
    }
}

/// [`block`] with `n = lines.len()` chosen at run time, as its own (never inlined) function:
/// what a caller outside the pipeline (the firmware's stage benchmark) runs to time the
/// accumulate stage alone. `lines` holds `n` lines (`3..=8`, else nothing is written).
#[inline(never)]
pub fn row(win: &Window, lines: &[&[u16]], c0: usize, saturation: u16, out: &mut [V]) {
    fn go<const N: usize>(win: &Window, lines: &[&[u16]], c0: usize, sat: u16, out: &mut [V]) {
        let l: [&[u16]; N] = core::array::from_fn(|j| lines[j]);
        block::<N>(win, &l, c0, sat, out);
    }
    match lines.len() {
        3 => go::<3>(win, lines, c0, saturation, out),
        4 => go::<4>(win, lines, c0, saturation, out),
        5 => go::<5>(win, lines, c0, saturation, out),
        6 => go::<6>(win, lines, c0, saturation, out),
        7 => go::<7>(win, lines, c0, saturation, out),
        8 => go::<8>(win, lines, c0, saturation, out),
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

    #[test]
    fn block_is_pixel_reduced() {
        let bam: vec::Vec<u32> = [0.0f64, -1.9, -3.7, -5.8]
            .iter()
            .map(|&t| from_rad(t))
            .collect();
        let w = Window::solve(&bam, fixed::types::U8F8::from_num(8)).unwrap();
        let l: vec::Vec<vec::Vec<u16>> = (0..4u32)
            .map(|j| {
                (0..37u32)
                    .map(|c| ((c * 977 + j * 3331) % 4200) as u16)
                    .collect()
            })
            .collect();
        let lines: [&[u16]; 4] = core::array::from_fn(|j| &l[j][..]);
        let mut out = [[0i32; 2]; 30];
        block(&w, &lines, 5, 4095, &mut out);
        for (k, o) in out.iter().enumerate() {
            let s: vec::Vec<u16> = (0..4).map(|j| l[j][5 + k]).collect();
            assert_eq!(*o, pixel(&w, &s, 4095).reduce(), "column {}", 5 + k);
        }
        assert!(out.iter().any(|o| o[0] == SATURATED) && out.iter().any(|o| o[0] != SATURATED));
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
