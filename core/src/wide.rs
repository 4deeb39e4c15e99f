//! The core's one 128-bit division, out of line.
//!
//! The once-per-frame arithmetic needs 128-bit quotients in three places: the window solve's
//! conditioning limit and its rounded `P` entries ([`crate::solve`]), and a frame's row offset
//! from its encoder latch ([`crate::frames::Config::offset`]). A 32-bit Arm target has no
//! library routine for a 128-bit division, so LLVM expands each `/` on `i128` or `u128` in
//! place, about 1 KB of code apiece. All four go through [`div`] instead, one copy, never
//! inlined: the firmware's flash went from 71,160 to 66,256 B (its budget is 64 KiB), for about
//! 700 more instructions per window solve (21,330 instead of 20,630, once per frame). The
//! callers handle signs and rounding themselves; their results are bit for bit those of the
//! `i128` expressions they replace (the tests below hold the old expressions as the reference).

/// `num / den`, rounded toward zero. A zero `den` (no caller passes one) gives `u128::MAX`
/// rather than a panic.
#[inline(never)]
pub(crate) fn div(num: u128, den: u128) -> u128 {
    num.checked_div(den).unwrap_or(u128::MAX)
}

/// `floor(num / den)` for `den > 0`, as `num.div_euclid(den)` (equal for a positive divisor).
pub(crate) fn div_floor(num: i128, den: u128) -> i128 {
    let q = div(num.unsigned_abs(), den);
    if num >= 0 {
        q as i128
    } else if q * den == num.unsigned_abs() {
        -(q as i128)
    } else {
        -(q as i128) - 1
    }
}

/// `num / den` rounded to nearest, halves away from zero, for `den > 0`.
#[inline(never)]
pub(crate) fn div_round(num: i128, den: u128) -> i128 {
    let q = div(num.unsigned_abs() + den / 2, den) as i128;
    if num >= 0 {
        q
    } else {
        -q
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The window solve's rounding before this module: i128 arithmetic, inline.
    fn old_round(num: i128, den: i128) -> i128 {
        if num >= 0 {
            (num + den / 2) / den
        } else {
            -((-num + den / 2) / den)
        }
    }

    #[test]
    fn edges() {
        assert_eq!(div(7, 0), u128::MAX);
        assert_eq!(div(u128::MAX, 1), u128::MAX);
        for (n, d) in [
            (7i128, 2u128),
            (-7, 2),
            (-6, 2),
            (6, 2),
            (0, 5),
            (-1, 1 << 100),
        ] {
            assert_eq!(div_floor(n, d), n.div_euclid(d as i128), "{n} / {d}");
            assert_eq!(div_round(n, d), old_round(n, d as i128), "{n} / {d}");
        }
        // Halves go away from zero, both ways.
        assert_eq!(div_round(5, 2), 3);
        assert_eq!(div_round(-5, 2), -3);
        assert_eq!(div_floor(i128::MIN, 2), i128::MIN / 2);
    }

    proptest! {
        /// The callers' ranges and beyond: numerators to 2^120 of either sign, divisors from 1
        /// to 2^100 (the solve's are above 2^42, the offset's below 2^33).
        #[test]
        fn equal_to_the_inline_i128_division(
            mag in 0u128..(1 << 120), neg: bool,
            den_bits in 0u32..100, den_low: u64,
        ) {
            let num = if neg { -(mag as i128) } else { mag as i128 };
            let den = ((1u128 << den_bits) | (den_low as u128 & ((1u128 << den_bits) - 1))).max(1);
            prop_assert_eq!(div(mag, den), mag / den);
            prop_assert_eq!(div_floor(num, den), num.div_euclid(den as i128));
            prop_assert_eq!(div_round(num, den), old_round(num, den as i128));
        }
    }
}
