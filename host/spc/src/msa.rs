//! The measurement system: a gauge R&R study by the ANOVA method (AIAG MSA, 4th edition),
//! crossed parts x appraisers x trials.
//!
//! For an SPI machine the parts are the board's pads (each pad a different printed deposit),
//! the appraisers are set-ups of the machine (a calibration and the board's placement on the
//! conveyor), and the trials are repeated measurements under one set-up. With `P` parts, `A`
//! appraisers, `r` trials and `x[p][a][t]`:
//!
//! | source | SS | df |
//! | --- | --- | --- |
//! | part | `A r sum_p (mean_p - mean)^2` | `P - 1` |
//! | appraiser | `P r sum_a (mean_a - mean)^2` | `A - 1` |
//! | interaction | `r sum_pa (mean_pa - mean_p - mean_a + mean)^2` | `(P - 1)(A - 1)` |
//! | repeatability | `sum (x - mean_pa)^2` | `P A (r - 1)` |
//!
//! `MS = SS / df`; the variance components are `EV^2 = MS_e`, `interaction^2 = (MS_pa -
//! MS_e) / r`, `appraiser^2 = (MS_a - MS_pa) / (P r)`, `PV^2 = (MS_p - MS_pa) / (A r)` (each
//! 0 where negative); `AV^2 = appraiser^2 + interaction^2`, `GRR^2 = EV^2 + AV^2`, `TV^2 =
//! GRR^2 + PV^2`. `%GRR` against the tolerance is `6 GRR / (USL - LSL) x 100` (AIAG's 6 sigma
//! spread), against the total variation `GRR / TV x 100`; the number of distinct categories
//! `ndc = floor(1.41 PV / GRR)`. The interaction is always kept (not pooled into the error
//! whatever its significance): with thousands of pads it is estimated well. Checked against
//! the numpy reference (`tests/REFERENCE.md`, "msa").

use serde::Serialize;

/// Why a study cannot be analysed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MsaError {
    /// Fewer than 2 parts, appraisers or trials.
    TooFew {
        /// Which.
        what: &'static str,
        /// How many.
        got: usize,
    },
    /// The values are not `parts x appraisers x trials`.
    Shape {
        /// Values given.
        got: usize,
        /// Values the study needs.
        need: usize,
    },
    /// A value that is NaN or infinite, at this index.
    NotFinite(usize),
}

impl std::fmt::Display for MsaError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MsaError::TooFew { what, got } => {
                write!(f, "a gauge study needs at least 2 {what}, got {got}")
            }
            MsaError::Shape { got, need } => write!(
                f,
                "{got} values for a study of {need} (parts x appraisers x trials)"
            ),
            MsaError::NotFinite(i) => write!(f, "value {i} is not a finite number"),
        }
    }
}

impl std::error::Error for MsaError {}

/// A gauge study's result, in the values' units.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Gauge {
    /// Parts, appraisers and trials.
    pub parts: usize,
    /// Appraisers.
    pub appraisers: usize,
    /// Trials per part and appraiser.
    pub trials: usize,
    /// Degrees of freedom: part, appraiser, interaction, repeatability.
    pub df: [f64; 4],
    /// Mean squares, in the same order.
    pub ms: [f64; 4],
    /// Repeatability, the equipment variation EV (a standard deviation).
    pub repeatability: f64,
    /// Reproducibility AV: the appraiser and interaction components together.
    pub reproducibility: f64,
    /// Of it, the appraisers'.
    pub appraiser: f64,
    /// Of it, the part-appraiser interaction's.
    pub interaction: f64,
    /// The gauge: `sqrt(EV^2 + AV^2)`.
    pub grr: f64,
    /// The parts' own variation PV.
    pub part: f64,
    /// The total TV: `sqrt(GRR^2 + PV^2)`.
    pub total: f64,
    /// `6 GRR / tolerance x 100` (None without a tolerance).
    pub pct_tolerance: Option<f64>,
    /// `GRR / TV x 100` (None when TV is 0).
    pub pct_total: Option<f64>,
    /// Number of distinct categories, `floor(1.41 PV / GRR)` (None when GRR is 0).
    pub ndc: Option<u64>,
}

/// Analyses `x` (index `(p * appraisers + a) * trials + t`) of a crossed study, against a
/// tolerance `usl - lsl` when given.
pub fn gauge_rr(
    x: &[f64],
    parts: usize,
    appraisers: usize,
    trials: usize,
    tolerance: Option<f64>,
) -> Result<Gauge, MsaError> {
    for (what, got) in [
        ("parts", parts),
        ("appraisers", appraisers),
        ("trials", trials),
    ] {
        if got < 2 {
            return Err(MsaError::TooFew { what, got });
        }
    }
    let need = parts
        .checked_mul(appraisers)
        .and_then(|v| v.checked_mul(trials))
        .unwrap_or(usize::MAX);
    if x.len() != need {
        return Err(MsaError::Shape { got: x.len(), need });
    }
    if let Some(i) = x.iter().position(|v| !v.is_finite()) {
        return Err(MsaError::NotFinite(i));
    }
    let (pn, an, rn) = (parts as f64, appraisers as f64, trials as f64);
    let at = |p: usize, a: usize| &x[(p * appraisers + a) * trials..][..trials];
    let cell: Vec<f64> = (0..parts)
        .flat_map(|p| (0..appraisers).map(move |a| (p, a)))
        .map(|(p, a)| at(p, a).iter().sum::<f64>() / rn)
        .collect();
    let grand = cell.iter().sum::<f64>() / (pn * an);
    let part_mean: Vec<f64> = (0..parts)
        .map(|p| cell[p * appraisers..][..appraisers].iter().sum::<f64>() / an)
        .collect();
    let app_mean: Vec<f64> = (0..appraisers)
        .map(|a| (0..parts).map(|p| cell[p * appraisers + a]).sum::<f64>() / pn)
        .collect();
    let ss_p = an * rn * part_mean.iter().map(|m| (m - grand).powi(2)).sum::<f64>();
    let ss_a = pn * rn * app_mean.iter().map(|m| (m - grand).powi(2)).sum::<f64>();
    let mut ss_pa = 0.0;
    let mut ss_e = 0.0;
    for p in 0..parts {
        for a in 0..appraisers {
            let c = cell[p * appraisers + a];
            ss_pa += (c - part_mean[p] - app_mean[a] + grand).powi(2);
            ss_e += at(p, a).iter().map(|v| (v - c).powi(2)).sum::<f64>();
        }
    }
    ss_pa *= rn;
    let df = [
        pn - 1.0,
        an - 1.0,
        (pn - 1.0) * (an - 1.0),
        pn * an * (rn - 1.0),
    ];
    let ms = [ss_p / df[0], ss_a / df[1], ss_pa / df[2], ss_e / df[3]];
    let ev2 = ms[3];
    let inter2 = ((ms[2] - ms[3]) / rn).max(0.0);
    let app2 = ((ms[1] - ms[2]) / (pn * rn)).max(0.0);
    let pv2 = ((ms[0] - ms[2]) / (an * rn)).max(0.0);
    let av2 = app2 + inter2;
    let grr2 = ev2 + av2;
    let tv2 = grr2 + pv2;
    let grr = grr2.sqrt();
    Ok(Gauge {
        parts,
        appraisers,
        trials,
        df,
        ms,
        repeatability: ev2.sqrt(),
        reproducibility: av2.sqrt(),
        appraiser: app2.sqrt(),
        interaction: inter2.sqrt(),
        grr,
        part: pv2.sqrt(),
        total: tv2.sqrt(),
        pct_tolerance: tolerance
            .filter(|t| *t > 0.0 && t.is_finite())
            .map(|t| 600.0 * grr / t),
        pct_total: (tv2 > 0.0).then(|| 100.0 * grr / tv2.sqrt()),
        ndc: (grr > 0.0).then(|| (1.41 * pv2.sqrt() / grr).floor() as u64),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Parts at 10, 20, ... with an appraiser offset and no noise: all variation is parts
    /// and appraisers, none repeatability or interaction.
    #[test]
    fn components_of_a_constructed_study() {
        let (p, a, r) = (5, 3, 2);
        let mut x = Vec::new();
        for pi in 0..p {
            for ai in 0..a {
                for _ in 0..r {
                    x.push(10.0 * (pi + 1) as f64 + [0.0, 1.0, -1.0][ai]);
                }
            }
        }
        let g = gauge_rr(&x, p, a, r, Some(60.0)).unwrap();
        assert_eq!(g.repeatability, 0.0);
        assert_eq!(g.interaction, 0.0);
        // Appraiser variance: the offsets' sample variance (1) ...
        assert!((g.appraiser - 1.0).abs() < 1e-12, "{g:?}");
        // ... part variance: the part means' sample variance (250).
        assert!((g.part - 250f64.sqrt()).abs() < 1e-9, "{g:?}");
        assert!((g.pct_tolerance.unwrap() - 10.0).abs() < 1e-12);
        assert_eq!(g.ndc, Some((1.41 * 250f64.sqrt()).floor() as u64));
    }

    #[test]
    fn bad_studies_are_refused() {
        assert_eq!(
            gauge_rr(&[1.0; 8], 1, 2, 4, None),
            Err(MsaError::TooFew {
                what: "parts",
                got: 1
            })
        );
        assert_eq!(
            gauge_rr(&[1.0; 7], 2, 2, 2, None),
            Err(MsaError::Shape { got: 7, need: 8 })
        );
        let mut x = [1.0; 8];
        x[5] = f64::NAN;
        assert_eq!(gauge_rr(&x, 2, 2, 2, None), Err(MsaError::NotFinite(5)));
        assert_eq!(
            gauge_rr(&[1.0; 8], 2, 2, 2, None).unwrap().ndc,
            None,
            "no spread: no categories"
        );
    }
}
