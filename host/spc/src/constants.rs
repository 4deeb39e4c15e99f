//! The bias constants of the control charts, computed rather than read from a table.
//!
//! A standard deviation of `m` normal values is biased low: `E[s] = c4(m) sigma`, with
//! `c4(m) = sqrt(2 / (m - 1)) Gamma(m / 2) / Gamma((m - 1) / 2)` (through `ln Gamma` up to
//! `m = 200`, through the ratio's asymptotic series above, so that it holds to 1e-14 for the
//! hundreds of thousands of values a study pools). The range of two values has
//! `E[R] = d2 sigma` and `sd[R] = d3 sigma` with `d2 = 2 / sqrt(pi)` and
//! `d3 = sqrt(2 - 4 / pi)` exactly (the range of two is `sqrt(2) |Z|`); the moving-range chart
//! needs no other. Published tables give these to 3 or 4 digits (1.128, 0.853, 3.267 for
//! `D4`): the tests compare with them, and the statistics use the exact values, as Minitab
//! does.

/// `c4(m)` for a standard deviation of `m >= 2` values; `None` below.
pub fn c4(m: u64) -> Option<f64> {
    if m < 2 {
        return None;
    }
    let m = m as f64;
    let x = (m - 1.0) / 2.0;
    if x >= 100.0 {
        // c4 = Gamma(x + 1/2) / (sqrt(x) Gamma(x)): its asymptotic series, whose next term is
        // below 1e-15 here, where the difference of two ln Gamma near x ln x would lose
        // digits (1e-10 at a million values).
        let r = 1.0 / x;
        return Some(
            1.0 - r / 8.0 + r * r / 128.0 + 5.0 * r.powi(3) / 1024.0
                - 21.0 * r.powi(4) / 32768.0
                - 399.0 * r.powi(5) / 262_144.0,
        );
    }
    let ln_ratio = libm::lgamma(m / 2.0) - libm::lgamma(x);
    Some((2.0 / (m - 1.0)).sqrt() * ln_ratio.exp())
}

/// `d2` for ranges of two: `2 / sqrt(pi)`.
pub fn d2_of_two() -> f64 {
    2.0 / std::f64::consts::PI.sqrt()
}

/// `d3` for ranges of two: `sqrt(2 - 4 / pi)`.
pub fn d3_of_two() -> f64 {
    (2.0 - 4.0 / std::f64::consts::PI).sqrt()
}

/// The moving-range chart's upper limit factor: `D4 = 1 + 3 d3 / d2`.
pub fn d4_of_two() -> f64 {
    1.0 + 3.0 * d3_of_two() / d2_of_two()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Published values (ASTM E2587 / Montgomery, appendix VI), to the digits printed.
    #[test]
    fn the_constants_agree_with_the_published_tables() {
        let c4_table = [
            (2, 0.7979),
            (3, 0.8862),
            (4, 0.9213),
            (5, 0.9400),
            (6, 0.9515),
            (10, 0.9727),
            (25, 0.9896),
        ];
        for (m, want) in c4_table {
            let got = c4(m).unwrap();
            assert!((got - want).abs() < 5e-5, "c4({m}) = {got}, table {want}");
        }
        assert!((d2_of_two() - 1.128).abs() < 5e-4);
        assert!((d3_of_two() - 0.853).abs() < 5e-4);
        assert!((d4_of_two() - 3.267).abs() < 5e-4);
        assert_eq!(c4(1), None);
        assert_eq!(c4(0), None);
    }

    /// `c4` tends to 1 as `1 - 1 / (4 m) - 7 / (32 m^2)`; the two ways of computing it meet
    /// where they hand over.
    #[test]
    fn c4_approaches_one_for_large_subgroups() {
        for m in [1_000u64, 6_000, 1_000_000, 1 << 40] {
            let got = c4(m).unwrap();
            let m = m as f64;
            let approx = 1.0 - 1.0 / (4.0 * m) - 7.0 / (32.0 * m * m);
            assert!(
                (got - approx).abs() < 10.0 / (m * m * m) + 1e-16,
                "c4({m}) = {got}"
            );
        }
        // Past the hand-over (m = 201) the series is the ln Gamma form to within the latter's own
        // rounding (ln Gamma near 500 carries about 1e-13).
        for m in [201u64, 250, 400] {
            let mf = m as f64;
            let by_gamma = (2.0 / (mf - 1.0)).sqrt()
                * (libm::lgamma(mf / 2.0) - libm::lgamma((mf - 1.0) / 2.0)).exp();
            assert!((c4(m).unwrap() - by_gamma).abs() < 2e-13, "m {m}");
        }
    }

    /// Monte Carlo free check of `c4`: the exact ratio for `m = 3` is `sqrt(pi) / 2`.
    #[test]
    fn c4_of_three_is_exact() {
        let want = std::f64::consts::PI.sqrt() / 2.0;
        assert!((c4(3).unwrap() - want).abs() < 1e-14);
        // And m = 2: sqrt(2 / pi).
        assert!((c4(2).unwrap() - (2.0 / std::f64::consts::PI).sqrt()).abs() < 1e-14);
    }
}
