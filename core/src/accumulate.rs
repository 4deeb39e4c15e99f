//! Accumulate: the raw samples of open board rows, and the per-pixel `v = P i` products.
//!
//! A board row needs `n` samples from `n` consecutive frames, but its window's `P` is only
//! known once the encoder latch of its last frame arrives. So the first `n - 1` samples of
//! every open row are kept raw (u16) in a pool of line slots, and the `n`-th line is combined
//! with them as it streams in. Open rows entered in the last `n - 1` frames hold `1..n-1`
//! lines each, so the pool needs at most `max_step * n (n - 1) / 2` lines: a triangle, not
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
        Some(Pool { width, lines, free, top: count })
    }

    /// Takes a slot and copies `line` into it; `None` when the pool is exhausted.
    pub fn store(&mut self, line: &[u16]) -> Option<u16> {
        if self.top == 0 {
            return None;
        }
        self.top -= 1;
        let slot = self.free[self.top];
        let w = self.width;
        let dst = self.lines.get_mut(slot as usize * w..slot as usize * w + w)?;
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
        self.lines.get(slot as usize * w..slot as usize * w + w).unwrap_or(&[])
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
        let bam: std::vec::Vec<u32> = th.iter().map(|&t| from_rad(t)).collect();
        let w = Window::solve(&bam, 2048).unwrap();
        let (b, c, phi) = (1800.0, 700.0, 0.9f64);
        let s: std::vec::Vec<u16> =
            th.iter().map(|t| (b + c * (phi + t).cos()).round() as u16).collect();
        let a = pixel(&w, &s, 4095);
        let q = (1u64 << 24) as f64;
        // Integer rounding of the samples (<= 0.5 DN) bounds the error.
        assert!((a.v2 as f64 / q - c * phi.cos()).abs() < 2.0);
        assert!((a.v3 as f64 / q - c * phi.sin()).abs() < 2.0);
        assert!(!a.saturated);
        assert!(pixel(&w, &[0, 0, 4095, 0, 0], 4095).saturated);
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
