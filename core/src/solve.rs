//! Per-window least-squares solve: `P = (M^T M)^-1 M^T` from the window's phase shifts.
//!
//! `M` has rows `[1, cos theta_j, -sin theta_j]`. Only `v_2 = C cos Phi` and `v_3 = C sin Phi`
//! are needed, so the solve uses the centred form (identical algebra, see `docs/model.md`):
//!
//! ```text
//! u_j = cos theta_j - mean(cos),   w_j = -(sin theta_j - mean(sin))
//! A   = [[sum u^2, sum u w], [sum u w, sum w^2]]
//! [P_2j; P_3j] = A^-1 [u_j; w_j]
//! ```
//!
//! Everything is integer, so the host and the Cortex-M7 compute the same bits:
//! - `cos`, `sin`: Q1.30 from [`crate::phase::sincos`], rounded to Q1.24 (`c_j`, `s_j`).
//! - `U_j = n c_j - sum c`, `W_j = -(n s_j - sum s)`: `n * 2^24` times `u_j, w_j` (i64, `|.| < 2^28`).
//! - `S_uu, S_uw, S_ww`: sums of products, `n^2 2^48` times the entries of `A` (i64, `< 2^60`).
//! - Ill-conditioning test on `lambda_min(A)` without a square root (see [`Window::solve`]).
//! - `P_q = round(P * 2^24)` as i32 (Q7.24): `n 2^48 (S_ww U_j - S_uw W_j) / det` in i128.
//!
//! Error bound: the Q1.24 rounding of `cos`/`sin` perturbs `A` and `P` by about `2^-24`
//! relative; with `g <= 8` the entries of `P` are below 64, and the rounding of `P_q` adds at
//! most `2^-25` absolute per entry. The tests check `P_q` against an f64 solve to `3e-7`
//! times the noise gain for random non-uniform shift sets.

use crate::phase::sincos;
use crate::wide;
use fixed::types::U8F8;

/// Largest number of observations per board row.
pub const MAX_N: usize = 8;
/// Smallest number of observations per board row.
pub const MIN_N: usize = 3;
/// Fractional bits of the solve matrix entries `P_q` (Q7.24).
pub const P_FRAC: u32 = 24;

/// Why a window has no usable solution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SolveError {
    /// `n` outside `MIN_N..=MAX_N`.
    BadCount,
    /// Noise gain above the configured limit (includes singular windows).
    IllConditioned,
}

/// Rows 2 and 3 of `P` for one window, Q7.24.
///
/// The entries stay raw `i32` (Q7.24, [`P_FRAC`] fractional bits) rather than `fixed`'s
/// `I8F24`, because they are consumed as raw integers by the per-pixel multiply-accumulate
/// `v = P i` (`p as i64 * sample as i64`, an `SMLAL` on the Cortex-M7, in `crate::accumulate`),
/// the hot loop this type exists for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Window {
    /// Observations in the window.
    pub n: usize,
    /// `P_2j` (coefficients of `v_2 = C cos Phi`), Q7.24.
    pub p2: [i32; MAX_N],
    /// `P_3j` (coefficients of `v_3 = C sin Phi`), Q7.24.
    pub p3: [i32; MAX_N],
}

impl Window {
    /// Solves a window from its phase shifts `theta_j` (binary angles).
    ///
    /// `max_gain` is the largest accepted noise gain `g` (Q8.8, clamped to `1..=8`).
    /// `g = sqrt(n / (2 lambda_min(A)))` is the worst-case amplification of phase noise
    /// relative to an ideal equally spaced `n`-step set (`g = 1`).
    /// `lambda_min(A) >= L` is tested as `A - L I` positive semi-definite:
    /// `a - L >= 0`, `d - L >= 0`, `(a - L)(d - L) >= b^2`, in i128.
    pub fn solve(shifts: &[u32], max_gain: U8F8) -> Result<Window, SolveError> {
        let n = shifts.len();
        if !(MIN_N..=MAX_N).contains(&n) {
            return Err(SolveError::BadCount);
        }
        // g_q8: the Q8.8 bits of the limit.
        let g = max_gain.to_bits().clamp(256, 2048) as i128;
        // cos, sin in Q1.24.
        let mut c = [0i64; MAX_N];
        let mut s = [0i64; MAX_N];
        let (mut sc, mut ss) = (0i64, 0i64);
        for (j, &t) in shifts.iter().enumerate() {
            let (sn, cs) = sincos(t);
            c[j] = ((cs as i64) + (1 << 5)) >> 6;
            s[j] = ((sn as i64) + (1 << 5)) >> 6;
            sc += c[j];
            ss += s[j];
        }
        let nn = n as i64;
        let mut u = [0i64; MAX_N];
        let mut w = [0i64; MAX_N];
        let (mut suu, mut suw, mut sww) = (0i64, 0i64, 0i64);
        for j in 0..n {
            u[j] = nn * c[j] - sc;
            w[j] = -(nn * s[j] - ss);
            suu += u[j] * u[j];
            suw += u[j] * w[j];
            sww += w[j] * w[j];
        }
        // L = n / (2 g^2) on A; on the scaled sums (n^2 2^48 A) with g = g_q8 / 256:
        // Lq = n^3 2^48 2^16 / (2 g_q8^2) = n^3 2^63 / g_q8^2.
        let n3 = (nn * nn * nn) as i128;
        let lq = wide::div((n3 << 63) as u128, (g * g) as u128) as i128;
        let (a, b, d) = (suu as i128, suw as i128, sww as i128);
        if a < lq || d < lq || (a - lq) * (d - lq) < b * b {
            return Err(SolveError::IllConditioned);
        }
        // Both eigenvalues >= Lq > 2^45, so det >= Lq^2 > 2^90: the division keeps > 40 bits.
        let det = a * d - b * b;
        if det <= 0 {
            return Err(SolveError::IllConditioned);
        }
        let mut win = Window {
            n,
            p2: [0; MAX_N],
            p3: [0; MAX_N],
        };
        // P_q = n 2^48 num / det; num < 2^90, so scale det down by 2^48 instead of num up.
        // det >> 48 > 2^42 keeps the quotient exact to about 2^-42 relative.
        let dq = det >> 48;
        for j in 0..n {
            let (uj, wj) = (u[j] as i128, w[j] as i128);
            let num2 = (d * uj - b * wj) * nn as i128;
            let num3 = (a * wj - b * uj) * nn as i128;
            win.p2[j] =
                to_i32(wide::div_round(num2, dq as u128)).ok_or(SolveError::IllConditioned)?;
            win.p3[j] =
                to_i32(wide::div_round(num3, dq as u128)).ok_or(SolveError::IllConditioned)?;
        }
        Ok(win)
    }
}

fn to_i32(x: i128) -> Option<i32> {
    i32::try_from(x).ok()
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::phase::{from_rad, UNITS_PER_RAD};
    use proptest::prelude::*;
    use std::f64::consts::PI;
    use std::vec::Vec;

    /// Independent f64 solve of the full 3x3 normal equations (Gauss-Jordan).
    fn p_f64(th: &[f64]) -> Option<(Vec<f64>, Vec<f64>, f64)> {
        let n = th.len();
        let m: Vec<[f64; 3]> = th.iter().map(|t| [1.0, t.cos(), -t.sin()]).collect();
        let mut a = [[0f64; 6]; 3];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] = m.iter().map(|r| r[i] * r[j]).sum();
            }
            a[i][3 + i] = 1.0;
        }
        for col in 0..3 {
            let piv = (col..3).max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs()))?;
            a.swap(col, piv);
            let p = a[col][col];
            if p.abs() < 1e-12 {
                return None;
            }
            for x in a[col].iter_mut() {
                *x /= p;
            }
            let pivot = a[col];
            for (r, row) in a.iter_mut().enumerate() {
                if r != col {
                    let f = row[col];
                    for (x, q) in row.iter_mut().zip(pivot) {
                        *x -= f * q;
                    }
                }
            }
        }
        let inv = |i: usize, j: usize| a[i][3 + j];
        let p = |row: usize| -> Vec<f64> {
            (0..n)
                .map(|k| (0..3).map(|j| inv(row, j) * m[k][j]).sum())
                .collect()
        };
        // Noise gain from the centred 2x2 block.
        let cm = th.iter().map(|t| t.cos()).sum::<f64>() / n as f64;
        let sm = th.iter().map(|t| t.sin()).sum::<f64>() / n as f64;
        let (mut aa, mut bb, mut dd) = (0.0, 0.0, 0.0);
        for t in th {
            let (u, w) = (t.cos() - cm, -(t.sin() - sm));
            aa += u * u;
            bb += u * w;
            dd += w * w;
        }
        let lmin = 0.5 * (aa + dd - ((aa - dd).powi(2) + 4.0 * bb * bb).sqrt());
        let g = (n as f64 / (2.0 * lmin)).sqrt();
        Some((p(1), p(2), g))
    }

    fn shifts_bam(th: &[f64]) -> Vec<u32> {
        th.iter().map(|&t| from_rad(t)).collect()
    }

    #[test]
    fn uniform_four_step_is_exact() {
        let th = [0.0, -PI / 2.0, -PI, -1.5 * PI];
        let w = Window::solve(&shifts_bam(&th), U8F8::ONE).unwrap();
        // Orthogonal set: P_2 = (2/n) cos theta, P_3 = -(2/n) sin theta, sin theta = 0,-1,0,1.
        let half = 1i32 << 23;
        assert_eq!(&w.p2[..4], &[half, 0, -half, 0]);
        assert_eq!(&w.p3[..4], &[0, half, 0, -half]);
    }

    #[test]
    fn stalled_and_two_phase_windows_are_ill_conditioned() {
        let stalled = [0u32; 4];
        assert_eq!(
            Window::solve(&stalled, U8F8::from_num(8)),
            Err(SolveError::IllConditioned)
        );
        let full_period = [0u32, 0, 0, 0, 0];
        assert_eq!(
            Window::solve(&full_period, U8F8::from_num(2)),
            Err(SolveError::IllConditioned)
        );
        let two = [0u32, 1 << 31, 0, 1 << 31];
        assert_eq!(
            Window::solve(&two, U8F8::from_num(8)),
            Err(SolveError::IllConditioned)
        );
        assert_eq!(
            Window::solve(&[0, 1], U8F8::from_num(2)),
            Err(SolveError::BadCount)
        );
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]
        /// Random non-uniform shift sets: P_q matches the f64 normal-equation solve, and the
        /// accept/reject decision matches the f64 noise gain (away from the threshold).
        #[test]
        fn p_matches_f64(n in 3usize..=8, raw in proptest::collection::vec(0.0f64..1.0, 8),
                         gain in 256u16..=2048) {
            let th: Vec<f64> = raw[..n].iter().map(|x| -2.0 * PI * x).collect();
            let gmax = gain as f64 / 256.0;
            let res = Window::solve(&shifts_bam(&th), U8F8::from_bits(gain));
            match p_f64(&th) {
                Some((p2, p3, g)) if g.is_finite() && g < gmax * (1.0 - 1e-6) => {
                    let w = res.expect("well-conditioned window rejected");
                    let q = (1u64 << P_FRAC) as f64;
                    for j in 0..n {
                        let tol = 3e-7 * g * g + 1.0 / q;
                        prop_assert!((w.p2[j] as f64 / q - p2[j]).abs() <= tol,
                            "p2[{}] {} vs {}", j, w.p2[j] as f64 / q, p2[j]);
                        prop_assert!((w.p3[j] as f64 / q - p3[j]).abs() <= tol,
                            "p3[{}] {} vs {}", j, w.p3[j] as f64 / q, p3[j]);
                    }
                }
                Some((_, _, g)) if g > gmax * (1.0 + 1e-6) => {
                    prop_assert_eq!(res, Err(SolveError::IllConditioned));
                }
                None => prop_assert_eq!(res, Err(SolveError::IllConditioned)),
                _ => {} // within 1e-6 of the threshold: either answer is right
            }
        }

        /// Shifts as produced by the conveyor: integer row offsets times the fringe frequency.
        #[test]
        fn p_matches_f64_for_row_offsets(steps in proptest::collection::vec(5u32..12, 7),
                                         period in 8.0f64..64.0, n in 3usize..=8) {
            let fx = (4_294_967_296.0 / period).round() as u32;
            let mut off = 0u32;
            let mut bam = Vec::new();
            let mut th = Vec::new();
            for j in 0..n {
                if j > 0 { off += steps[j - 1]; }
                let b = off.wrapping_mul(fx).wrapping_neg();
                bam.push(b);
                th.push(b as i32 as f64 / UNITS_PER_RAD);
            }
            if let (Ok(w), Some((p2, p3, g))) =
                (Window::solve(&bam, U8F8::from_num(8)), p_f64(&th))
            {
                let q = (1u64 << P_FRAC) as f64;
                for j in 0..n {
                    prop_assert!((w.p2[j] as f64 / q - p2[j]).abs() <= 3e-7 * g * g + 1.0 / q);
                    prop_assert!((w.p3[j] as f64 / q - p3[j]).abs() <= 3e-7 * g * g + 1.0 / q);
                }
            }
        }
    }
}
