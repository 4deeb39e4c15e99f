//! Phase as a wrapping binary angle, integer `atan2` and `sin`/`cos`.
//!
//! A phase is a `u32` *binary angle*: `2^32` is one turn (`2 pi`), so adding and subtracting
//! phases with `wrapping_add`/`wrapping_sub` wraps modulo `2 pi` for free, and reading the result
//! as `i32` maps it into `[-pi, pi)`.
//!
//! Binary angles (phases, shifts, `Config::fx`, the reference-phase table) stay plain `u32`
//! rather than `fixed`'s `U0F32` (turns): a binary angle is a wrapping `u32` by design, and
//! the phase arithmetic is integer wrapping arithmetic on it (sums and differences modulo a
//! turn, the difference read as a signed `i32`, `rows * fx` as a wrapping integer product, the
//! top bits indexing the `atan`/`sin` tables), none of which a `U0F32` would express more
//! clearly than the `u32` it would have to be converted back to.
//!
//! Error bounds (tested below on dense grids over the full circle and at small magnitudes):
//! - [`atan2`]: at most [`ATAN2_MAX_ERR_RAD`] from the exact angle for any input pair except
//!   `(0, 0)` (which returns 0 and is caught as zero modulation upstream).
//! - [`sincos`]: at most `4 * 2^-30` from the exact values.

/// `2^32 / (2 pi)`: binary-angle units per radian.
pub const UNITS_PER_RAD: f64 = 683_565_275.576_431_6;

/// One eighth of a turn (`pi / 4`).
const OCTANT: u32 = 1 << 29;
/// A quarter turn (`pi / 2`).
pub(crate) const QUARTER: u32 = 1 << 30;
/// Half a turn (`pi`).
pub(crate) const HALF: u32 = 1 << 31;

/// Tested worst-case error of [`atan2`] in radians.
pub const ATAN2_MAX_ERR_RAD: f64 = 2.0e-5;

include!(concat!(env!("OUT_DIR"), "/atan_table.rs"));

/// The `atan` table of [`atan2`] (`atan(i / 256)` in binary-angle units, `i = 0..=256`, and a
/// guard entry): a front end that computes the phase the same way loads the same table.
pub fn atan_table() -> &'static [u32] {
    &ATAN
}

/// Converts radians to a binary angle (host-side helper; rounds to nearest, wraps).
pub fn from_rad(rad: f64) -> u32 {
    let turns = rad / (2.0 * core::f64::consts::PI);
    let frac = turns - floor(turns);
    // frac in [0, 1]; 2^32 * frac rounded, with 2^32 wrapping to 0.
    let units = frac * 4_294_967_296.0 + 0.5;
    (units as u64 & 0xFFFF_FFFF) as u32
}

/// Converts a binary angle to radians in `[-pi, pi)`.
pub fn to_rad(a: u32) -> f64 {
    a as i32 as f64 / UNITS_PER_RAD
}

/// `floor` without std (exact for |x| < 2^52).
fn floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

/// Four-quadrant arctangent of `y / x` as a binary angle (`0` along `+x`, counter-clockwise).
///
/// Built for the per-pixel loop: one hardware `u32` division (`UDIV` on the Cortex-M7), one
/// table interpolation, no 64-bit arithmetic. Steps and formats:
/// 1. `hi = max(|x|, |y|)`, `lo = min(|x|, |y|)` (u32), both shifted left by `clz(hi)` so that
///    `hi` has its top bit set; nothing is lost.
/// 2. Divisor `d = hi >> 16` in `[2^15, 2^16)` (relative truncation `< 2^-15`), and the ratio
///    `t = lo / d` in Q16 (`t <= 2^16`, clamped).
/// 3. `atan(t)` from the 256-segment table `ATAN`, linear interpolation on the low 8 bits of
///    `t`: interpolation error `<= (1/256)^2 / 8 * max|atan''| = 1.3e-6 rad`.
/// 4. Octant, then quadrant folding by wrapping binary-angle arithmetic.
///
/// The divisor truncation and the Q16 ratio bound the error by [`ATAN2_MAX_ERR_RAD`]
/// (`2e-5` rad; the tested grid reaches 1.6e-5 rad max, 7e-6 rad rms); at 0.25 um per LSB
/// and 500 um per turn that is 0.0064 LSB.
#[inline(always)]
pub fn atan2(y: i32, x: i32) -> u32 {
    let ax = x.unsigned_abs();
    let ay = y.unsigned_abs();
    let (hi, lo, swap) = if ax >= ay {
        (ax, ay, false)
    } else {
        (ay, ax, true)
    };
    let s = hi.leading_zeros();
    // Top bit of `hi << s` is set, so `d >= 2^15`: the `| 0x8000` only tells the compiler.
    // `(0, 0)` needs no branch: `s = 32` wraps to a shift by 0, `lo = 0` gives `t = 0`, and
    // the angle is 0.
    let d = (hi.wrapping_shl(s) >> 16) | 0x8000;
    let t = (lo.wrapping_shl(s) / d).min(1 << 16);
    let i = (t >> 8) as usize;
    let f = t & 0xFF;
    let a = ATAN[i];
    let b = ATAN[i + 1];
    // Q32 binary angle within the first octant: a + (b - a) * f / 2^8, rounded.
    let oct = a + (((b - a) * f + (1 << 7)) >> 8);
    let mut ang = if swap { QUARTER - oct } else { oct };
    if x < 0 {
        ang = HALF.wrapping_sub(ang);
    }
    if y < 0 {
        ang = ang.wrapping_neg();
    }
    ang
}

/// `(sin a, cos a)` of a binary angle, both in Q1.30 (`2^30` = 1.0).
///
/// The angle is folded into the first octant `x in [0, pi/4]` (Q2.30 radians), where Taylor
/// series of 5 (sin) and 6 (cos) terms in Horner form have truncation error `< 2e-9`; each
/// Horner step rounds at Q30. Used once per window in `crate::solve`, never per pixel.
pub fn sincos(a: u32) -> (i32, i32) {
    // pi/2 in Q30.
    const HALF_PI_Q30: u64 = 1_686_629_713;
    let quadrant = a >> 30;
    let r = a & (QUARTER - 1);
    // Fold to [0, pi/4]: beyond the octant use the complement and swap sin/cos.
    let (r, swap) = if r > OCTANT {
        (QUARTER - r, true)
    } else {
        (r, false)
    };
    // x = r * (pi/2) / 2^30, in Q30 radians (<= 0.786 * 2^30).
    let x = ((r as u64 * HALF_PI_Q30 + (1 << 29)) >> 30) as i64;
    let x2 = mul_q30(x, x);
    // sin x = x (1 - x^2/6 (1 - x^2/20 (1 - x^2/42 (1 - x^2/72))))
    let one = 1i64 << 30;
    let mut s = one - mul_q30(x2, one) / 72;
    s = one - mul_q30(x2, s) / 42;
    s = one - mul_q30(x2, s) / 20;
    s = one - mul_q30(x2, s) / 6;
    let s = mul_q30(x, s);
    // cos x = 1 - x^2/2 (1 - x^2/12 (1 - x^2/30 (1 - x^2/56 (1 - x^2/90))))
    let mut c = one - mul_q30(x2, one) / 90;
    c = one - mul_q30(x2, c) / 56;
    c = one - mul_q30(x2, c) / 30;
    c = one - mul_q30(x2, c) / 12;
    c = one - mul_q30(x2, c) / 2;
    let (s, c) = if swap { (c, s) } else { (s, c) };
    let (s, c) = match quadrant {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    };
    (s as i32, c as i32)
}

/// Q30 x Q30 -> Q30 with rounding.
fn mul_q30(a: i64, b: i64) -> i64 {
    (a * b + (1 << 29)) >> 30
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::f64::consts::PI;

    fn ang_err(a: u32, exact_rad: f64) -> f64 {
        // Difference folded to [-pi, pi).
        let d = to_rad(a) - exact_rad;
        (d + PI).rem_euclid(2.0 * PI) - PI
    }

    #[test]
    fn atan2_full_circle_grid() {
        let mut max = 0f64;
        let mut sum2 = 0f64;
        let mut count = 0u64;
        let steps = 200_000;
        for &r in &[1.0e3, 6.1e4, 3.3e7, 2.1e9] {
            for k in 0..steps {
                let th = 2.0 * PI * (k as f64 + 0.37) / steps as f64;
                let x = (r * th.cos()).round();
                let y = (r * th.sin()).round();
                let e = ang_err(atan2(y as i32, x as i32), y.atan2(x)).abs();
                max = max.max(e);
                sum2 += e * e;
                count += 1;
            }
        }
        let rms = (sum2 / count as f64).sqrt();
        std::println!("atan2 grid: max {max:e} rad, rms {rms:e} rad");
        assert!(max <= ATAN2_MAX_ERR_RAD, "max {max:e}");
        assert!(rms <= 0.5 * ATAN2_MAX_ERR_RAD, "rms {rms:e}");
    }

    #[test]
    fn atan2_small_magnitudes_exhaustive() {
        // Every integer pair in a small box: normalisation by left shift must be exact.
        let mut max = 0f64;
        for y in -64i32..=64 {
            for x in -64i32..=64 {
                if x == 0 && y == 0 {
                    continue;
                }
                let e = ang_err(atan2(y, x), (y as f64).atan2(x as f64)).abs();
                max = max.max(e);
            }
        }
        assert!(max <= ATAN2_MAX_ERR_RAD, "max {max:e}");
    }

    #[test]
    fn atan2_axes_and_extremes() {
        assert_eq!(atan2(0, 5), 0);
        assert_eq!(atan2(5, 0), QUARTER);
        assert_eq!(atan2(0, -5), HALF);
        assert_eq!(atan2(-5, 0), 3 * QUARTER);
        assert_eq!(atan2(7, 7), OCTANT);
        // Extremes must not overflow.
        for &(y, x) in &[
            (i32::MIN, i32::MIN),
            (i32::MAX, i32::MIN),
            (i32::MIN, 1),
            (1, i32::MAX),
            (i32::MAX, i32::MAX - 1),
        ] {
            let e = ang_err(atan2(y, x), (y as f64).atan2(x as f64)).abs();
            assert!(e <= ATAN2_MAX_ERR_RAD, "({y},{x}) err {e:e}");
        }
    }

    #[test]
    fn sincos_grid() {
        let mut max = 0f64;
        for k in 0..(1u64 << 20) {
            let a = (k << 12) as u32 ^ 0x5A5;
            let th = a as f64 / UNITS_PER_RAD;
            let (s, c) = sincos(a);
            let q = (1u64 << 30) as f64;
            max = max.max((s as f64 / q - th.sin()).abs());
            max = max.max((c as f64 / q - th.cos()).abs());
        }
        assert!(max <= 4.0 / (1u64 << 30) as f64, "max {max:e}");
    }

    #[test]
    fn rad_round_trip() {
        for k in -100..100 {
            let r = k as f64 * 0.0731;
            let e = ang_err(from_rad(r), r).abs();
            assert!(e <= 0.5 / UNITS_PER_RAD + 1e-15, "{r}: {e:e}");
        }
    }
}
