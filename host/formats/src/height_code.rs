//! The 16-bit code of a height in the board map's `heights.png` and the line's kept maps:
//! `round(h / 0.25 um) + 32768`, the rounding half away from zero, 0 for an invalid height.
//!
//! A map is 48 M heights on the paper board, and the line codes one per board. Written as
//! `(f64::from(h) / 0.25).round()`, each height is a call of the C library's `round` (x86-64's
//! baseline has no rounding instruction), and the loop cannot run on vectors. [`steps`] gives
//! the same integer with additions, a comparison and the float's bits, which the compiler runs
//! four heights at a time (`heights.png` of the paper board, with the PNG's filter of the same
//! change: `timing.files_s` 0.34 - 0.38 s before, 0.25 - 0.32 s after; `docs/board.md`).
//! Tested against the `f64` rounding at every float near a half step and on random bit
//! patterns; before it went in, it was checked against it on all 2^32 `f32` bit patterns in a
//! throwaway program (none differed).

/// The code's height step, um.
pub const LSB_UM: f64 = 0.25;
/// The code of a height of zero (0 is invalid).
pub const ZERO: u16 = 32768;

/// Steps of the code are at most this far from zero before [`steps`] saturates (a height of
/// 16,384 um: twice what 16 bits hold).
pub const STEPS_MAX: i32 = 65536;

/// `round(h / LSB_UM)` half away from zero, saturated to `+-STEPS_MAX`, for a finite `h`; 0 for
/// a NaN (the callers test `h.is_finite()` for what a NaN codes to).
///
/// How: `x = 4 h` is exact in `f32`. Its magnitude `r` plus `2^23` rounds, in the float
/// addition, to the nearest integer with ties to even, and that integer is the sum's bits less
/// `2^23`'s bits (`r <= 2^16`, so the sum lies in `[2^23, 2^24)`, where the float's step is 1).
/// A tie rounded down to even (`even - r == -0.5`, exact in `f32`) gets its step back; the
/// sign goes back on last.
#[inline]
pub fn steps(h: f32) -> i32 {
    const TWO_23: f32 = 8_388_608.0;
    let x = (h * 4.0).clamp(-(STEPS_MAX as f32), STEPS_MAX as f32);
    let r = x.abs();
    let sum = r + TWO_23;
    let even = sum - TWO_23;
    let k = sum.to_bits().wrapping_sub(TWO_23.to_bits()) as i32 + i32::from(even - r == -0.5);
    if x < 0.0 {
        -k
    } else if x >= 0.0 {
        k
    } else {
        0
    }
}

/// `heights` (um, NaN invalid) coded into `out` as `heights.png` codes them: heights beyond the
/// 16 bits clamped to 1 or 65535 (the board map marks them nowhere else: its TIFF has the
/// heights themselves).
pub fn code_clamped(heights: &[f32], out: &mut [u16]) {
    for (o, &h) in out.iter_mut().zip(heights) {
        let q = (steps(h) + i32::from(ZERO)).clamp(1, 65535) as u16;
        *o = if h.is_finite() { q } else { 0 };
    }
}

/// `heights` (um, NaN invalid) coded into `out` as a kept map codes them: heights beyond the
/// 16 bits are 0 (invalid), never the nearest value. Returns the counts of valid codes and of
/// heights that were finite but beyond the 16 bits.
pub fn code_or_clip(heights: &[f32], out: &mut [u16]) -> (u64, u64) {
    let (mut valid, mut clipped) = (0u64, 0u64);
    for (o, &h) in out.iter_mut().zip(heights) {
        let q = steps(h) + i32::from(ZERO);
        let finite = h.is_finite();
        let ok = finite & (1..=65535).contains(&q);
        *o = if ok { q as u16 } else { 0 };
        valid += u64::from(ok);
        clipped += u64::from(finite & !ok);
    }
    (valid, clipped)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The rounding in `f64`, as the maps were coded before [`steps`].
    fn reference(h: f32) -> f64 {
        (f64::from(h) / LSB_UM).round()
    }

    fn clamped_reference(h: f32) -> u16 {
        if h.is_finite() {
            (reference(h) + f64::from(ZERO)).clamp(1.0, 65535.0) as u16
        } else {
            0
        }
    }

    fn clip_reference(h: f32) -> (u16, bool, bool) {
        if !h.is_finite() {
            return (0, false, false);
        }
        let q = reference(h) + f64::from(ZERO);
        if (1.0..=65535.0).contains(&q) {
            (q as u16, true, false)
        } else {
            (0, false, true)
        }
    }

    fn check(h: f32) {
        let r = reference(h);
        if h.is_finite() && r.abs() <= f64::from(STEPS_MAX) {
            assert_eq!(f64::from(steps(h)), r, "h = {h:e} ({:#010x})", h.to_bits());
        }
        if h.is_nan() {
            assert_eq!(steps(h), 0);
        }
        let mut out = [7u16];
        code_clamped(&[h], &mut out);
        assert_eq!(out[0], clamped_reference(h), "clamped, h = {h:e}");
        let (valid, clipped) = code_or_clip(&[h], &mut out);
        let (code, v, c) = clip_reference(h);
        assert_eq!(
            (out[0], valid, clipped),
            (code, u64::from(v), u64::from(c)),
            "kept, h = {h:e}"
        );
    }

    /// Every float within 3 steps of each half step (`(k + 1/2) / 4` um) and of each whole
    /// step, across the whole code and past its ends: where a rounding goes wrong.
    #[test]
    fn near_every_half_step_it_is_the_f64_rounding() {
        for k in -(STEPS_MAX + 8)..(STEPS_MAX + 8) {
            for centre in [(k as f32 + 0.5) / 4.0, k as f32 / 4.0] {
                let b = centre.to_bits();
                for d in 0..=3u32 {
                    check(f32::from_bits(b.wrapping_add(d)));
                    check(f32::from_bits(b.wrapping_sub(d)));
                }
            }
        }
    }

    #[test]
    fn special_values_are_the_f64_rounding() {
        let tie_below_half = f32::from_bits(0.5f32.to_bits() - 1); // 0.49999997
        for h in [
            0.0,
            -0.0,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::from_bits(1),
            f32::from_bits(0x8000_0001),
            tie_below_half / 4.0,
            -tie_below_half / 4.0,
            0.125,
            -0.125,
            0.375,
            8191.75,
            8191.875,
            -8192.0,
            -8192.125,
            16384.0,
            16384.25,
            1e30,
            -1e30,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
        ] {
            check(h);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(20_000))]
        #[test]
        fn any_float_is_the_f64_rounding(bits in any::<u32>()) {
            check(f32::from_bits(bits));
        }

        #[test]
        fn a_height_in_the_code_is_the_f64_rounding(h in -8200.0f32..8200.0) {
            check(h);
        }
    }

    /// Rows code as their heights one by one (the loops' counts too).
    #[test]
    fn a_row_is_its_heights() {
        let row: Vec<f32> = (0..1000)
            .map(|i| match i % 7 {
                0 => f32::NAN,
                1 => 9000.0 * if i % 2 == 0 { 1.0 } else { -1.0 },
                _ => (i as f32 - 500.0) * 0.37,
            })
            .collect();
        let mut out = vec![0u16; row.len()];
        code_clamped(&row, &mut out);
        assert!(out
            .iter()
            .zip(&row)
            .all(|(&o, &h)| o == clamped_reference(h)));
        let (valid, clipped) = code_or_clip(&row, &mut out);
        let want: Vec<_> = row.iter().map(|&h| clip_reference(h)).collect();
        assert!(out.iter().zip(&want).all(|(&o, w)| o == w.0));
        assert_eq!(valid, want.iter().filter(|w| w.1).count() as u64);
        assert_eq!(clipped, want.iter().filter(|w| w.2).count() as u64);
        assert!(valid > 0 && clipped > 0);
    }
}
