//! Process capability: how the spread and the centring of a measure compare with its
//! specification limits.
//!
//! With `sigma` the process's standard deviation, `mean` its centre and `LSL`, `USL` the
//! limits: `Cp = (USL - LSL) / 6 sigma`, `Cpu = (USL - mean) / 3 sigma`,
//! `Cpl = (mean - LSL) / 3 sigma`, `Cpk = min(Cpu, Cpl)`. With the *within* sigma (short-term:
//! moving ranges, or the pooled subgroup deviation) they are `Cp`/`Cpk`; with the *overall*
//! sample deviation (long-term, drift included) `Pp`/`Ppk`. A one-sided limit (the offsets have
//! an upper one only) gives `Cpk` from that side and no `Cp`. Zero sigma gives none: a measure
//! that never varies says nothing of capability.

/// A measure's specification limits (either may be absent).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SpecLimits {
    /// Lower specification limit.
    pub lsl: Option<f64>,
    /// Upper specification limit.
    pub usl: Option<f64>,
}

/// The four indices of one sigma: `Cp, Cpu, Cpl, Cpk` (or `Pp, Ppu, Ppl, Ppk`).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Indices {
    /// `(USL - LSL) / 6 sigma`; both limits needed.
    pub p: Option<f64>,
    /// `(USL - mean) / 3 sigma`.
    pub upper: Option<f64>,
    /// `(mean - LSL) / 3 sigma`.
    pub lower: Option<f64>,
    /// The smaller of `upper` and `lower` (the one there is, with one limit).
    pub k: Option<f64>,
}

/// The indices of `mean` and `sigma` against `limits`; all `None` unless `sigma` is finite and
/// positive and `mean` finite.
pub fn indices(mean: f64, sigma: f64, limits: SpecLimits) -> Indices {
    if !(sigma.is_finite() && sigma > 0.0 && mean.is_finite()) {
        return Indices::default();
    }
    let p = match (limits.lsl, limits.usl) {
        (Some(l), Some(u)) => Some((u - l) / (6.0 * sigma)),
        _ => None,
    };
    let upper = limits.usl.map(|u| (u - mean) / (3.0 * sigma));
    let lower = limits.lsl.map(|l| (mean - l) / (3.0 * sigma));
    let k = match (upper, lower) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    };
    Indices { p, upper, lower, k }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Montgomery's worked example (piston rings, 6.9): USL 74.05, LSL 73.95, mean 74.001,
    /// sigma 0.0099: Cp 1.68, Cpk = min(1.65, 1.72) = 1.65 (to the book's digits).
    #[test]
    fn a_textbook_example() {
        let limits = SpecLimits {
            lsl: Some(73.95),
            usl: Some(74.05),
        };
        let i = indices(74.001, 0.0099, limits);
        assert!((i.p.unwrap() - 1.68).abs() < 5e-3);
        assert!((i.upper.unwrap() - 1.65).abs() < 5e-3);
        assert!((i.lower.unwrap() - 1.72).abs() < 5e-3);
        assert_eq!(i.k, i.upper);
    }

    #[test]
    fn one_sided_limits_give_cpk_only() {
        let i = indices(
            10.0,
            2.0,
            SpecLimits {
                lsl: None,
                usl: Some(25.0),
            },
        );
        assert_eq!(i.p, None);
        assert_eq!(i.lower, None);
        assert_eq!(i.upper, Some(2.5));
        assert_eq!(i.k, Some(2.5));
        let none = indices(10.0, 2.0, SpecLimits::default());
        assert_eq!(none, Indices::default());
    }

    #[test]
    fn no_indices_without_a_spread() {
        let l = SpecLimits {
            lsl: Some(0.0),
            usl: Some(1.0),
        };
        for s in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert_eq!(indices(0.5, s, l), Indices::default(), "sigma {s}");
        }
        assert_eq!(indices(f64::NAN, 1.0, l), Indices::default());
    }

    /// A mean outside the limits gives a negative Cpk (a process that mostly fails), never a
    /// positive one.
    #[test]
    fn an_off_centre_process_has_a_negative_cpk() {
        let i = indices(
            2.0,
            0.1,
            SpecLimits {
                lsl: Some(0.0),
                usl: Some(1.0),
            },
        );
        assert!(i.k.unwrap() < 0.0);
        assert!(i.p.unwrap() > 1.0);
    }
}
