//! Control charts: where a measure's points sit against the limits its own short-term spread
//! sets.
//!
//! - **I-MR** (one pad, one value a board): the individuals' centre is their mean and
//!   `sigma = MR / d2` with `MR` the mean moving range of successive boards; limits at
//!   `mean +- 3 sigma`. The moving-range chart has its centre at `MR` and its upper limit at
//!   `D4 MR` ([`crate::constants`]).
//! - **X-bar/S** (a component, a package family or the whole board: the board's pads of it
//!   are the subgroup): a point is a board's mean, `sigma` is the pooled standard deviation
//!   of the subgroups unbiased by `c4(dof + 1)`, and each board's limits are
//!   `mean +- 3 sigma / sqrt(n)` for its own subgroup size `n` (a pad not measured on a board
//!   makes that board's subgroup smaller, never a zero). The S chart's centre is
//!   `c4(n) sigma` with limits `+- 3 sigma sqrt(1 - c4(n)^2)`, the lower one at least 0.
//!   X-bar/S rather than X-bar/R: the subgroups are tens to thousands of pads, where the
//!   range wastes the data.
//!
//! **Baseline (phase I).** The centre and the limits come from the first boards of the chart,
//! its baseline, and every later board is judged against them: a change that lasts (a stencil
//! misaligned at a change-over, apertures clogging) would otherwise pull the centre towards
//! itself and hide, and make the boards before it look shifted the other way. Without a
//! baseline the limits come from every point (a retrospective chart). Capability (`Cp`, `Pk`
//! ...) always describes every point of the chart.
//!
//! Every point also has its `z`, its distance from the centre in its own sigmas, which the
//! run rules read ([`crate::rules`]).

use crate::capability::{indices, Indices, SpecLimits};
use crate::constants::{c4, d2_of_two, d4_of_two};
use std::fmt;

/// Why a chart cannot be drawn.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ChartError {
    /// Fewer points (or degrees of freedom) than the chart needs.
    TooFew {
        /// What there was.
        what: &'static str,
        /// How many.
        got: usize,
        /// How many are needed.
        need: usize,
    },
    /// A baseline of fewer than 2 points or subgroups, or more than there are.
    Baseline {
        /// The baseline asked for.
        baseline: usize,
        /// Points or subgroups there are.
        points: usize,
    },
    /// A value that is NaN or infinite (a measurement that could not be made must be left
    /// out before, not passed on as a number).
    NotFinite {
        /// Its index (subgroup, value).
        at: (usize, usize),
    },
}

impl fmt::Display for ChartError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ChartError::TooFew { what, got, need } => {
                write!(f, "{got} {what}: a chart needs at least {need}")
            }
            ChartError::Baseline { baseline, points } => write!(
                f,
                "a baseline of {baseline} of {points} points: it needs at least 2, at most all"
            ),
            ChartError::NotFinite { at } => {
                write!(
                    f,
                    "value {} of subgroup {} is not a finite number",
                    at.1, at.0
                )
            }
        }
    }
}

impl std::error::Error for ChartError {}

/// Which chart.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum Kind {
    /// Individuals and moving range.
    IndividualsMovingRange,
    /// Subgroup means and standard deviations.
    MeanDeviation,
}

/// Where the limits of a chart of subgroup means come from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MeanLimits {
    /// From the pooled within-subgroup sigma over `sqrt(n)` (Shewhart's X-bar chart): right
    /// when the subgroups differ by nothing but the within scatter.
    Within,
    /// From the moving ranges of the subgroup means (`MR-bar / d2(2)`, the same for every
    /// point), the S chart still from the within sigma: the three-way chart (Wheeler), right
    /// when every board has its own common-cause level (the paste roll, the squeegee
    /// stroke), which the within sigma of a board's thousands of pads does not see.
    Between,
}

/// The lower chart: moving ranges (I-MR) or subgroup deviations (X-bar/S). Per point; `None`
/// where there is none (the first board of an I-MR chart has no moving range, a subgroup of
/// one pad no deviation).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Dispersion {
    /// The plotted value.
    pub points: Vec<Option<f64>>,
    /// Centre line.
    pub centre: Vec<Option<f64>>,
    /// Lower control limit.
    pub lcl: Vec<Option<f64>>,
    /// Upper control limit.
    pub ucl: Vec<Option<f64>>,
}

/// A control chart of one measure, with the capability its sigmas give.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Chart {
    /// Which chart.
    pub kind: Kind,
    /// Values in all (pads over boards).
    pub n: usize,
    /// Points (from the first) the centre and limits come from.
    pub baseline: usize,
    /// The centre line: the mean of the baseline's values.
    pub centre: f64,
    /// The sigma the limits are set with: the baseline's within sigma (I-MR and X-bar/S
    /// from within, a point's is this over `sqrt(size)`), or the baseline means' sigma from
    /// their moving ranges (X-bar/S from between, a point's whatever its size).
    pub sigma_limits: f64,
    /// For subgroup means: where the limits come from (`None` for I-MR).
    pub mean_limits: Option<MeanLimits>,
    /// The mean of every value.
    pub mean: f64,
    /// Short-term sigma (moving ranges, or pooled within subgroups).
    pub sigma_within: f64,
    /// The sample standard deviation of every value together.
    pub sigma_overall: f64,
    /// The plotted points: the values (I-MR) or the subgroup means (X-bar/S).
    pub points: Vec<f64>,
    /// Values behind each point (1 for I-MR).
    pub sizes: Vec<usize>,
    /// Lower control limit at each point.
    pub lcl: Vec<f64>,
    /// Upper control limit at each point.
    pub ucl: Vec<f64>,
    /// Each point's distance from the centre in its own sigmas; `None` throughout when
    /// `sigma_limits` is 0 (a measure that never moved: no rule can be read).
    pub z: Vec<Option<f64>>,
    /// The lower chart.
    pub dispersion: Dispersion,
    /// `Cp, Cpu, Cpl, Cpk` (within sigma).
    pub cp: Indices,
    /// `Pp, Ppu, Ppl, Ppk` (overall sigma).
    pub pp: Indices,
}

/// Sample standard deviation (`n - 1`) and mean of `v`, by Welford's update (no cancellation
/// on values far from 0).
fn mean_sd(v: impl Iterator<Item = f64>) -> (usize, f64, f64) {
    let (mut n, mut mean, mut m2) = (0usize, 0.0f64, 0.0f64);
    for x in v {
        n += 1;
        let d = x - mean;
        mean += d / n as f64;
        m2 += d * (x - mean);
    }
    let sd = if n >= 2 {
        (m2 / (n - 1) as f64).sqrt()
    } else {
        f64::NAN
    };
    (n, mean, sd)
}

fn check_finite(groups: &[&[f64]]) -> Result<(), ChartError> {
    for (g, v) in groups.iter().enumerate() {
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(ChartError::NotFinite { at: (g, i) });
        }
    }
    Ok(())
}

/// [`ChartError::TooFew`] unless `got >= need`.
fn at_least(what: &'static str, got: usize, need: usize) -> Result<(), ChartError> {
    if got < need {
        return Err(ChartError::TooFew { what, got, need });
    }
    Ok(())
}

/// The baseline's length: `baseline` (all when `None`), checked against `points`.
fn baseline_of(baseline: Option<usize>, points: usize) -> Result<usize, ChartError> {
    let b = baseline.unwrap_or(points);
    if b < 2 || b > points {
        return Err(ChartError::Baseline {
            baseline: b,
            points,
        });
    }
    Ok(b)
}

/// The mean moving range of `x`.
fn mean_moving_range(x: &[f64]) -> f64 {
    x.windows(2).map(|w| (w[1] - w[0]).abs()).sum::<f64>() / (x.len() - 1) as f64
}

/// The I-MR chart of `x` (one value per board, oldest first) against `limits`, its limits from
/// the first `baseline` values (all when `None`).
pub fn individuals(
    x: &[f64],
    limits: SpecLimits,
    baseline: Option<usize>,
) -> Result<Chart, ChartError> {
    check_finite(&[x])?;
    at_least("values", x.len(), 2)?;
    let b = baseline_of(baseline, x.len())?;
    let (n, mean, sigma_overall) = mean_sd(x.iter().copied());
    let sigma = mean_moving_range(x) / d2_of_two();
    let (_, centre, _) = mean_sd(x[..b].iter().copied());
    let mr_b = mean_moving_range(&x[..b]);
    let sigma_limits = mr_b / d2_of_two();
    let z = x
        .iter()
        .map(|&v| (sigma_limits > 0.0).then(|| (v - centre) / sigma_limits))
        .collect();
    let m = x.len() - 1;
    let dispersion = Dispersion {
        points: x.windows(2).map(|w| Some((w[1] - w[0]).abs())).collect(),
        centre: vec![Some(mr_b); m],
        lcl: vec![Some(0.0); m],
        ucl: vec![Some(d4_of_two() * mr_b); m],
    };
    Ok(Chart {
        kind: Kind::IndividualsMovingRange,
        n,
        baseline: b,
        centre,
        sigma_limits,
        mean_limits: None,
        mean,
        sigma_within: sigma,
        sigma_overall,
        points: x.to_vec(),
        sizes: vec![1; x.len()],
        lcl: vec![centre - 3.0 * sigma_limits; x.len()],
        ucl: vec![centre + 3.0 * sigma_limits; x.len()],
        z,
        dispersion,
        cp: indices(mean, sigma, limits),
        pp: indices(mean, sigma_overall, limits),
    })
}

/// The pooled within sigma of subgroups `(size, mean, sd)`, unbiased by `c4(dof + 1)`;
/// `None` without a degree of freedom.
fn pooled(stats: &[(usize, f64, f64)]) -> Option<f64> {
    let dof: usize = stats.iter().map(|s| s.0 - 1).sum();
    if dof == 0 {
        return None;
    }
    let ss: f64 = stats
        .iter()
        .filter(|s| s.0 >= 2)
        .map(|s| (s.0 - 1) as f64 * s.2 * s.2)
        .sum();
    Some((ss / dof as f64).sqrt() / c4(dof as u64 + 1).unwrap_or(1.0))
}

/// The X-bar/S chart of `groups` (a board's values each, oldest first; sizes may differ, none
/// empty) against `limits`, its limits from the first `baseline` subgroups (all when `None`).
pub fn means_and_deviations(
    groups: &[&[f64]],
    limits: SpecLimits,
    baseline: Option<usize>,
    mean_limits: MeanLimits,
) -> Result<Chart, ChartError> {
    check_finite(groups)?;
    if let Some(g) = groups.iter().position(|g| g.is_empty()) {
        return Err(ChartError::TooFew {
            what: "values in a subgroup",
            got: g,
            need: 1,
        });
    }
    at_least("subgroups", groups.len(), 2)?;
    let b = baseline_of(baseline, groups.len())?;
    let stats: Vec<(usize, f64, f64)> = groups.iter().map(|g| mean_sd(g.iter().copied())).collect();
    let no_dof = ChartError::TooFew {
        what: "degrees of freedom within the subgroups",
        got: 0,
        need: 1,
    };
    let sigma = pooled(&stats).ok_or(no_dof.clone())?;
    // The S chart's sigma: the baseline's within.
    let sigma_s = pooled(&stats[..b]).ok_or(no_dof)?;
    let sigma_limits = match mean_limits {
        MeanLimits::Within => sigma_s,
        MeanLimits::Between => {
            let mr: f64 = stats[..b]
                .windows(2)
                .map(|w| (w[1].1 - w[0].1).abs())
                .sum::<f64>()
                / (b - 1) as f64;
            mr / d2_of_two()
        }
    };
    let (_, centre, _) = mean_sd(groups[..b].iter().flat_map(|g| g.iter().copied()));
    let (n, mean, sigma_overall) = mean_sd(groups.iter().flat_map(|g| g.iter().copied()));
    let mut chart = Chart {
        kind: Kind::MeanDeviation,
        n,
        baseline: b,
        centre,
        sigma_limits,
        mean_limits: Some(mean_limits),
        mean,
        sigma_within: sigma,
        sigma_overall,
        points: Vec::with_capacity(groups.len()),
        sizes: Vec::with_capacity(groups.len()),
        lcl: Vec::with_capacity(groups.len()),
        ucl: Vec::with_capacity(groups.len()),
        z: Vec::with_capacity(groups.len()),
        dispersion: Dispersion::default(),
        cp: indices(mean, sigma, limits),
        pp: indices(mean, sigma_overall, limits),
    };
    for &(m, xbar, s) in &stats {
        let se = match mean_limits {
            MeanLimits::Within => sigma_limits / (m as f64).sqrt(),
            MeanLimits::Between => sigma_limits,
        };
        chart.points.push(xbar);
        chart.sizes.push(m);
        chart.lcl.push(centre - 3.0 * se);
        chart.ucl.push(centre + 3.0 * se);
        chart
            .z
            .push((sigma_limits > 0.0).then(|| (xbar - centre) / se));
        let d = &mut chart.dispersion;
        match c4(m as u64) {
            Some(c) => {
                let (mid, half) = (c * sigma_s, 3.0 * sigma_s * (1.0 - c * c).sqrt());
                d.points.push(Some(s));
                d.centre.push(Some(mid));
                d.lcl.push(Some((mid - half).max(0.0)));
                d.ucl.push(Some(mid + half));
            }
            None => {
                d.points.push(None);
                d.centre.push(None);
                d.lcl.push(None);
                d.ucl.push(None);
            }
        }
    }
    Ok(chart)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Montgomery's example 6.5 style check by construction: for the I chart the limits are
    /// `mean +- 2.66 MR` (`3 / d2`, the published factor).
    #[test]
    fn individuals_limits_are_the_published_factor_of_the_moving_range() {
        let x = [10.0, 12.0, 11.0, 13.0, 12.5, 11.5];
        let c = individuals(&x, SpecLimits::default(), None).unwrap();
        let mr = (2.0 + 1.0 + 2.0 + 0.5 + 1.0) / 5.0;
        assert!((c.ucl[0] - (c.mean + 2.66 * mr)).abs() < 2e-3 * mr);
        assert_eq!(
            (c.centre, c.sigma_limits, c.baseline),
            (c.mean, c.sigma_within, 6)
        );
        assert!((c.dispersion.ucl[0].unwrap() - 3.267 * mr).abs() < 1e-3 * mr);
        assert_eq!(c.dispersion.points.len(), 5);
        assert_eq!(c.points.len(), 6);
    }

    /// With equal subgroups of 5 the mean chart's limits are `mean +- A3 S`, `A3(5) = 1.427`,
    /// and the S chart's `B3 S, B4 S` with `B3(5) = 0, B4(5) = 2.089` (published table), where
    /// `S` is the mean deviation: the pooled deviation differs from it, so the check is made on
    /// groups of equal deviation.
    #[test]
    fn equal_subgroups_give_the_published_a3_b4() {
        // Each group is a shifted copy of the same five values: equal deviations.
        let base = [0.0, 1.0, 3.0, 4.0, 7.0];
        let groups: Vec<Vec<f64>> = (0..6)
            .map(|k| base.iter().map(|v| v + k as f64 * 0.3).collect())
            .collect();
        let refs: Vec<&[f64]> = groups.iter().map(|g| &g[..]).collect();
        let c =
            means_and_deviations(&refs, SpecLimits::default(), None, MeanLimits::Within).unwrap();
        let (_, _, s) = mean_sd(base.iter().copied());
        // sigma = pooled / c4(dof + 1) with pooled = s; the table's A3 uses S / c4(5).
        let sigma_table = s / c4(5).unwrap();
        let ratio = c.sigma_within / sigma_table;
        assert!((ratio - c4(5).unwrap() / c4(25).unwrap()).abs() < 1e-12);
        let a3 = (c.ucl[0] - c.mean) / s * (sigma_table / c.sigma_within);
        assert!((a3 - 1.427).abs() < 5e-4, "A3 {a3}");
        let b4 = c.dispersion.ucl[0].unwrap() / s * (sigma_table / c.sigma_within);
        assert!((b4 - 2.089).abs() < 5e-4, "B4 {b4}");
        assert_eq!(c.dispersion.lcl[0], Some(0.0));
    }

    #[test]
    fn unequal_subgroups_have_their_own_limits() {
        let g: [&[f64]; 3] = [&[1.0, 2.0, 3.0], &[2.0], &[1.0, 3.0, 2.0, 2.5, 1.5]];
        let c = means_and_deviations(&g, SpecLimits::default(), None, MeanLimits::Within).unwrap();
        assert!(c.ucl[1] - c.mean > c.ucl[0] - c.mean);
        assert!(c.ucl[0] - c.mean > c.ucl[2] - c.mean);
        assert_eq!(c.dispersion.points[1], None);
        assert_eq!(c.sizes, vec![3, 1, 5]);
        assert_eq!(c.n, 9);
    }

    /// A step after the baseline stays out of the limits: the centre is the baseline's, the
    /// later points sit beyond them; without a baseline the step pulls the centre halfway.
    #[test]
    fn a_baseline_keeps_a_later_step_out_of_the_limits() {
        let x: Vec<f64> = (0..40)
            .map(|i| 100.0 + ((i * 7) % 5) as f64 - 2.0 - if i >= 30 { 12.0 } else { 0.0 })
            .collect();
        let l = SpecLimits::default();
        let with = individuals(&x, l, Some(25)).unwrap();
        assert!((with.centre - 100.0).abs() < 0.5, "{}", with.centre);
        assert!(with.z[35].unwrap() < -3.0);
        assert!(with.z[..30].iter().all(|z| z.unwrap().abs() < 3.0));
        let all = individuals(&x, l, None).unwrap();
        assert!(all.centre < 98.0);
        assert_eq!(with.mean, all.mean);
        assert_eq!(with.sigma_within, all.sigma_within);
        for b in [0, 1, 41] {
            assert!(matches!(
                individuals(&x, l, Some(b)),
                Err(ChartError::Baseline { .. })
            ));
        }
        let g: Vec<Vec<f64>> = x.chunks(4).map(|c| c.to_vec()).collect();
        let refs: Vec<&[f64]> = g.iter().map(|v| &v[..]).collect();
        let m = means_and_deviations(&refs, l, Some(5), MeanLimits::Within).unwrap();
        assert!(m.z[9].unwrap() < -3.0 && m.z[..5].iter().all(|z| z.unwrap().abs() < 3.0));
        let singles: Vec<&[f64]> = x.iter().map(std::slice::from_ref).collect();
        let mut mixed = singles.clone();
        mixed.push(&[1.0, 2.0]);
        assert!(matches!(
            means_and_deviations(&mixed, l, Some(3), MeanLimits::Within),
            Err(ChartError::TooFew { .. })
        ));
    }

    #[test]
    fn bad_input_is_an_error_not_a_chart() {
        let l = SpecLimits::default();
        assert!(matches!(
            individuals(&[1.0], l, None),
            Err(ChartError::TooFew { .. })
        ));
        assert_eq!(
            individuals(&[1.0, f64::NAN, 2.0], l, None),
            Err(ChartError::NotFinite { at: (0, 1) })
        );
        let one: [&[f64]; 1] = [&[1.0, 2.0]];
        assert!(matches!(
            means_and_deviations(&one, l, None, MeanLimits::Within),
            Err(ChartError::TooFew { .. })
        ));
        let singles: [&[f64]; 3] = [&[1.0], &[2.0], &[3.0]];
        assert!(matches!(
            means_and_deviations(&singles, l, None, MeanLimits::Within),
            Err(ChartError::TooFew { .. })
        ));
        let empty: [&[f64]; 2] = [&[1.0, 2.0], &[]];
        assert!(matches!(
            means_and_deviations(&empty, l, None, MeanLimits::Within),
            Err(ChartError::TooFew { .. })
        ));
        let inf: [&[f64]; 2] = [&[1.0, 2.0], &[f64::INFINITY]];
        assert_eq!(
            means_and_deviations(&inf, l, None, MeanLimits::Within),
            Err(ChartError::NotFinite { at: (1, 0) })
        );
        for e in [
            ChartError::NotFinite { at: (1, 0) },
            ChartError::TooFew {
                what: "values",
                got: 1,
                need: 2,
            },
        ] {
            assert!(!e.to_string().is_empty());
        }
    }

    #[test]
    fn a_constant_measure_has_no_z_and_no_indices() {
        let c = individuals(
            &[5.0; 10],
            SpecLimits {
                lsl: Some(0.0),
                usl: Some(10.0),
            },
            None,
        )
        .unwrap();
        assert_eq!(c.sigma_within, 0.0);
        assert!(c.z.iter().all(Option::is_none));
        assert_eq!(c.cp, Indices::default());
    }

    /// Welford's mean and deviation hold on values far from zero where the naive sum of
    /// squares loses every digit.
    #[test]
    fn the_deviation_survives_a_large_offset() {
        let x: Vec<f64> = (0..1000).map(|i| 1e9 + (i % 7) as f64).collect();
        let (_, _, sd) = mean_sd(x.iter().copied());
        let (_, _, sd0) = mean_sd(x.iter().map(|v| v - 1e9));
        assert!((sd - sd0).abs() < 1e-9 * sd0);
    }
}
