//! Run rules: patterns of points that a process in control rarely makes.
//!
//! A rule *fires at* point `i` when the window of points ending at `i` has its pattern; a
//! window needs as many points as it is long, so no rule fires before its window is full. The
//! zones are read on each point's `z` (its distance from the centre in its own sigmas,
//! [`crate::chart::Chart::z`]), always with strict comparisons; a chart whose `z` are unknown
//! (no spread) fires nothing. The trend and alternation rules read the points themselves.
//!
//! | rule | pattern over the window ending at `i` |
//! |---|---|
//! | WE1, N1 | the point beyond 3 sigma |
//! | WE2, N5 | 2 of 3 beyond 2 sigma on the same side |
//! | WE3, N6 | 4 of 5 beyond 1 sigma on the same side |
//! | WE4 | 8 in a row on the same side of the centre |
//! | N2 | 9 in a row on the same side of the centre |
//! | N3 | 6 in a row strictly increasing, or strictly decreasing |
//! | N4 | 14 in a row alternating up and down |
//! | N7 | 15 in a row within 1 sigma (stratification: too little spread) |
//! | N8 | 8 in a row beyond 1 sigma, on both sides (mixture) |
//!
//! Western Electric's four rules (Statistical Quality Control Handbook, 1956) and Nelson's
//! eight (J. Quality Technology 16, 1984) overlap: WE1-3 are N1, N5 and N6; WE4 is the
//! 8-point form of N2.

/// A run rule (serialised by its short name, [`Rule::id`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Rule {
    /// Western Electric 1: beyond 3 sigma.
    We1,
    /// Western Electric 2: 2 of 3 beyond 2 sigma, same side.
    We2,
    /// Western Electric 3: 4 of 5 beyond 1 sigma, same side.
    We3,
    /// Western Electric 4: 8 in a row on one side.
    We4,
    /// Nelson 1: beyond 3 sigma.
    N1,
    /// Nelson 2: 9 in a row on one side.
    N2,
    /// Nelson 3: 6 in a row increasing or decreasing.
    N3,
    /// Nelson 4: 14 in a row alternating.
    N4,
    /// Nelson 5: 2 of 3 beyond 2 sigma, same side.
    N5,
    /// Nelson 6: 4 of 5 beyond 1 sigma, same side.
    N6,
    /// Nelson 7: 15 in a row within 1 sigma.
    N7,
    /// Nelson 8: 8 in a row beyond 1 sigma, both sides.
    N8,
}

impl Rule {
    /// Every rule, Western Electric's first.
    pub const ALL: [Rule; 12] = [
        Rule::We1,
        Rule::We2,
        Rule::We3,
        Rule::We4,
        Rule::N1,
        Rule::N2,
        Rule::N3,
        Rule::N4,
        Rule::N5,
        Rule::N6,
        Rule::N7,
        Rule::N8,
    ];

    /// Nelson's eight.
    pub const NELSON: [Rule; 8] = [
        Rule::N1,
        Rule::N2,
        Rule::N3,
        Rule::N4,
        Rule::N5,
        Rule::N6,
        Rule::N7,
        Rule::N8,
    ];

    /// Western Electric's four.
    pub const WESTERN_ELECTRIC: [Rule; 4] = [Rule::We1, Rule::We2, Rule::We3, Rule::We4];

    /// Its short name: `WE1` ... `N8`.
    pub fn id(self) -> &'static str {
        match self {
            Rule::We1 => "WE1",
            Rule::We2 => "WE2",
            Rule::We3 => "WE3",
            Rule::We4 => "WE4",
            Rule::N1 => "N1",
            Rule::N2 => "N2",
            Rule::N3 => "N3",
            Rule::N4 => "N4",
            Rule::N5 => "N5",
            Rule::N6 => "N6",
            Rule::N7 => "N7",
            Rule::N8 => "N8",
        }
    }

    /// The rule by its short name (any case).
    pub fn from_id(id: &str) -> Option<Rule> {
        Rule::ALL
            .into_iter()
            .find(|r| r.id().eq_ignore_ascii_case(id))
    }

    /// What it means, for a person.
    pub fn text(self) -> &'static str {
        match self {
            Rule::We1 | Rule::N1 => "a point beyond 3 sigma",
            Rule::We2 | Rule::N5 => "2 of 3 points beyond 2 sigma on one side",
            Rule::We3 | Rule::N6 => "4 of 5 points beyond 1 sigma on one side",
            Rule::We4 => "8 points in a row on one side of the centre",
            Rule::N2 => "9 points in a row on one side of the centre",
            Rule::N3 => "6 points in a row steadily increasing or decreasing",
            Rule::N4 => "14 points in a row alternating up and down",
            Rule::N7 => "15 points in a row within 1 sigma",
            Rule::N8 => "8 points in a row beyond 1 sigma on both sides",
        }
    }

    /// Points in its window.
    pub fn window(self) -> usize {
        match self {
            Rule::We1 | Rule::N1 => 1,
            Rule::We2 | Rule::N5 => 3,
            Rule::We3 | Rule::N6 => 5,
            Rule::We4 | Rule::N8 => 8,
            Rule::N2 => 9,
            Rule::N3 => 6,
            Rule::N4 => 14,
            Rule::N7 => 15,
        }
    }
}

impl serde::Serialize for Rule {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.id())
    }
}

impl std::fmt::Display for Rule {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.id())
    }
}

/// At least `k` of `z` beyond `limit` on one side.
fn k_beyond(z: &[f64], k: usize, limit: f64) -> bool {
    let above = z.iter().filter(|&&v| v > limit).count();
    let below = z.iter().filter(|&&v| v < -limit).count();
    above >= k || below >= k
}

/// Whether `rule`'s pattern holds over a window of points `p` with their `z` (the window's
/// length is the rule's).
fn holds(rule: Rule, p: &[f64], z: &[f64]) -> bool {
    match rule {
        Rule::We1 | Rule::N1 => z[0].abs() > 3.0,
        Rule::We2 | Rule::N5 => k_beyond(z, 2, 2.0),
        Rule::We3 | Rule::N6 => k_beyond(z, 4, 1.0),
        Rule::We4 | Rule::N2 => z.iter().all(|&v| v > 0.0) || z.iter().all(|&v| v < 0.0),
        Rule::N3 => p.windows(2).all(|w| w[1] > w[0]) || p.windows(2).all(|w| w[1] < w[0]),
        Rule::N4 => {
            let d: Vec<f64> = p.windows(2).map(|w| w[1] - w[0]).collect();
            d.iter().all(|&v| v != 0.0) && d.windows(2).all(|w| (w[0] > 0.0) != (w[1] > 0.0))
        }
        Rule::N7 => z.iter().all(|&v| v.abs() < 1.0),
        Rule::N8 => {
            z.iter().all(|&v| v.abs() > 1.0)
                && z.iter().any(|&v| v > 1.0)
                && z.iter().any(|&v| v < -1.0)
        }
    }
}

/// The points at which `rule` fires over `points` with their `z` (same length; a `z` of
/// `None` anywhere: the chart has no spread, and nothing fires).
pub fn fires(rule: Rule, points: &[f64], z: &[Option<f64>]) -> Vec<usize> {
    let Some(z) = z.iter().copied().collect::<Option<Vec<f64>>>() else {
        return Vec::new();
    };
    let n = points.len().min(z.len());
    let w = rule.window();
    (w.saturating_sub(1)..n)
        .filter(|&i| holds(rule, &points[i + 1 - w..=i], &z[i + 1 - w..=i]))
        .collect()
}

/// One rule's firings, and the episodes they make.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Firings {
    /// The rule.
    pub rule: Rule,
    /// The points it fires at.
    pub at: Vec<usize>,
}

/// A run of firings of one rule: from the first point of the first window that fired to the
/// last point that fired, with no point between where it did not.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Episode {
    /// The rule.
    pub rule: Rule,
    /// The first point of the pattern (the start of the first firing window).
    pub since: usize,
    /// The first point at which the rule fired.
    pub first_fired: usize,
    /// The last point at which it fired.
    pub last_fired: usize,
}

/// The episodes of `rule` firing at `at` (increasing).
pub fn episodes(rule: Rule, at: &[usize]) -> Vec<Episode> {
    let mut out: Vec<Episode> = Vec::new();
    for &i in at {
        match out.last_mut() {
            Some(e) if e.last_fired + 1 == i => e.last_fired = i,
            _ => out.push(Episode {
                rule,
                since: i + 1 - rule.window(),
                first_fired: i,
                last_fired: i,
            }),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn z_of(z: &[f64]) -> Vec<Option<f64>> {
        z.iter().map(|&v| Some(v)).collect()
    }

    #[test]
    fn each_rule_fires_where_its_pattern_completes() {
        // Points equal to their z (centre 0, sigma 1).
        let cases: &[(Rule, &[f64], &[usize])] = &[
            (Rule::N1, &[0.0, 3.5, -3.01, 3.0], &[1, 2]),
            (Rule::N5, &[2.5, 0.0, 2.1, 0.0, -2.2, -2.3], &[2, 5]),
            (Rule::N6, &[1.5, 1.2, 0.0, 1.1, 1.3, -0.5], &[4]),
            (Rule::We4, &[0.1; 8], &[7]),
            (Rule::N2, &[0.1; 8], &[]),
            (Rule::N2, &[-0.1; 10], &[8, 9]),
            (Rule::N3, &[0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.5], &[5]),
            (Rule::N7, &[0.5; 15], &[14]),
            (
                Rule::N8,
                &[1.5, -1.5, 1.5, -1.5, 1.5, -1.5, 1.5, -1.5],
                &[7],
            ),
            (Rule::N8, &[1.5; 8], &[]),
        ];
        for &(rule, p, want) in cases {
            assert_eq!(fires(rule, p, &z_of(p)), want, "{rule} on {p:?}");
        }
        let alt: Vec<f64> = (0..14)
            .map(|i| if i % 2 == 0 { 0.5 } else { -0.5 })
            .collect();
        assert_eq!(fires(Rule::N4, &alt, &z_of(&alt)), vec![13]);
        let mut broken = alt.clone();
        broken[6] = broken[5];
        assert!(fires(Rule::N4, &broken, &z_of(&broken)).is_empty());
    }

    /// Boundaries are strict: exactly 3 sigma, exactly on the centre, equal neighbours.
    #[test]
    fn the_boundaries_do_not_fire() {
        let p = [3.0, -3.0, 0.0];
        assert!(fires(Rule::N1, &p, &z_of(&p)).is_empty());
        let side = [0.1, 0.1, 0.1, 0.0, 0.1, 0.1, 0.1, 0.1, 0.1];
        assert!(fires(Rule::N2, &side, &z_of(&side)).is_empty());
        let flat = [1.0, 2.0, 3.0, 3.0, 4.0, 5.0, 6.0];
        assert!(fires(Rule::N3, &flat, &z_of(&flat)).is_empty());
        let two = [2.0, 2.0, 2.0];
        assert!(fires(Rule::N5, &two, &z_of(&two)).is_empty());
    }

    #[test]
    fn no_spread_fires_nothing() {
        let p = [1.0; 20];
        let z = vec![None; 20];
        for r in Rule::ALL {
            assert!(fires(r, &p, &z).is_empty());
        }
    }

    #[test]
    fn episodes_join_consecutive_firings() {
        let e = episodes(Rule::N2, &[8, 9, 10, 15]);
        assert_eq!(e.len(), 2);
        assert_eq!((e[0].since, e[0].first_fired, e[0].last_fired), (0, 8, 10));
        assert_eq!((e[1].since, e[1].last_fired), (7, 15));
    }

    #[test]
    fn ids_round_trip() {
        for r in Rule::ALL {
            assert_eq!(Rule::from_id(r.id()), Some(r));
            assert_eq!(Rule::from_id(&r.id().to_lowercase()), Some(r));
            assert!(!r.text().is_empty());
        }
        assert_eq!(Rule::from_id("N9"), None);
    }
}
