//! Verdicts: each pad's measurement against its windows, and the board's.
//!
//! A pad's call is the most severe of its findings: fail over warning over pass. Its class is
//! the first finding at that severity in this order: not measurable, missing, bridge,
//! insufficient or excess by volume, offset, insufficient or excess by height or area, shape.
//! A bridge adds volume, so it comes first; an offset deposit keeps its volume in its cell but
//! lowers the height over the opening, so the volume decides before the offset and the
//! height after it.
//! "Not measurable" (the opening off the map, too few valid pixels, no bare board around it)
//! is a failure of the inspection, never a pass.

use crate::measure::PadMeasurement;
use crate::program::{Upper, Window, Windows};
use serde::Serialize;

/// What is wrong with a pad.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Class {
    /// The pad could not be measured ([`crate::measure::Unmeasurable`]).
    NotMeasurable,
    /// Volume below the windows' `missing_pct`.
    Missing,
    /// Paste joins the opening to another one.
    Bridge,
    /// The deposit's centre off the opening's beyond `offset_pct`.
    Offset,
    /// Volume, height or area below its window.
    Insufficient,
    /// Volume, height or area above its window.
    Excess,
    /// Paste outside the grown opening beyond `shape_pct` (smear, misshapen deposit).
    Shape,
    /// The volume or height lies so near a failure limit that its uncertainty interval
    /// (`guard_band_k` standard uncertainties each way) straddles it: neither a pass nor a
    /// fail can be backed (always a warning).
    Uncertain,
}

impl Class {
    /// Every class, in the order of [`Class`]'s declaration.
    pub const ALL: [Class; 8] = [
        Class::NotMeasurable,
        Class::Missing,
        Class::Bridge,
        Class::Offset,
        Class::Insufficient,
        Class::Excess,
        Class::Shape,
        Class::Uncertain,
    ];

    /// The class as the reports write it (snake case, as serialized).
    pub const fn name(self) -> &'static str {
        match self {
            Class::NotMeasurable => "not_measurable",
            Class::Missing => "missing",
            Class::Bridge => "bridge",
            Class::Offset => "offset",
            Class::Insufficient => "insufficient",
            Class::Excess => "excess",
            Class::Shape => "shape",
            Class::Uncertain => "uncertain",
        }
    }
}

/// Pass, warning or failure.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Level {
    /// Inside every window.
    Pass,
    /// Outside a warning window, inside every failure window.
    Warn,
    /// Outside a failure window, or not measurable.
    Fail,
}

impl Level {
    /// The level as the reports write it (`pass`, `warn`, `fail`).
    pub const fn name(self) -> &'static str {
        match self {
            Level::Pass => "pass",
            Level::Warn => "warn",
            Level::Fail => "fail",
        }
    }
}

/// A pad's verdict.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Call {
    /// The most severe finding's level (pass without findings).
    pub level: Level,
    /// The deciding class (None for a pass).
    pub class: Option<Class>,
    /// Every finding, `(level, class)`, in the order above.
    pub findings: Vec<(Level, Class)>,
}

fn two_sided(v: f64, w: &Window) -> (Level, i8) {
    if !v.is_finite() {
        return (Level::Fail, -1);
    }
    if v < w.fail[0] {
        (Level::Fail, -1)
    } else if v > w.fail[1] {
        (Level::Fail, 1)
    } else if v < w.warn[0] {
        (Level::Warn, -1)
    } else if v > w.warn[1] {
        (Level::Warn, 1)
    } else {
        (Level::Pass, 0)
    }
}

/// Whether `v +- k u` straddles a failure limit of `w` (never without a finite `u` or with
/// `k` 0).
fn straddles(v: f64, u: f64, k: f64, w: &Window) -> bool {
    if !(k > 0.0 && u.is_finite() && u > 0.0 && v.is_finite()) {
        return false;
    }
    let (lo, hi) = (v - k * u, v + k * u);
    w.fail.iter().any(|&limit| lo < limit && limit < hi)
}

fn upper(v: f64, u: &Upper) -> Level {
    if v > u.fail {
        Level::Fail
    } else if v > u.warn {
        Level::Warn
    } else {
        Level::Pass
    }
}

/// Judges one pad's measurement against its windows. A non-finite volume, height or area
/// fails as insufficient.
pub fn judge(m: &PadMeasurement, w: &Windows) -> Call {
    // Findings in the order that decides the class at a level: a volume outside its window
    // decides before an offset (an offset deposit keeps its volume in its cell), the height and
    // area after it (an offset deposit lowers the height over its opening).
    let mut f: Vec<(Level, Class)> = Vec::new();
    if m.unmeasurable.is_some() {
        f.push((Level::Fail, Class::NotMeasurable));
    } else if m.volume_pct < w.missing_pct {
        f.push((Level::Fail, Class::Missing));
    } else {
        if !m.bridged_to.is_empty() {
            f.push((Level::Fail, Class::Bridge));
        }
        let side_class = |side: i8| {
            if side < 0 {
                Class::Insufficient
            } else {
                Class::Excess
            }
        };
        let k = w.guard_band_k;
        let (lv, side) = two_sided(m.volume_pct, &w.volume_pct);
        if straddles(m.volume_pct, m.volume_u_pct, k, &w.volume_pct) {
            f.push((Level::Warn, Class::Uncertain));
        } else if lv != Level::Pass {
            f.push((lv, side_class(side)));
        }
        let off = upper(m.offset_pct, &w.offset_pct);
        if off != Level::Pass {
            f.push((off, Class::Offset));
        }
        for (v, u, win) in [
            (m.height_pct, m.height_u_pct, &w.height_pct),
            (m.area_pct, f64::NAN, &w.area_pct),
        ] {
            let (lv, side) = two_sided(v, win);
            if straddles(v, u, k, win) {
                f.push((Level::Warn, Class::Uncertain));
            } else if lv != Level::Pass {
                f.push((lv, side_class(side)));
            }
        }
        let sh = upper(m.shape_pct, &w.shape_pct);
        if sh != Level::Pass {
            f.push((sh, Class::Shape));
        }
    }
    let level = f.iter().map(|x| x.0).max().unwrap_or(Level::Pass);
    let class = f.iter().find(|x| x.0 == level).map(|x| x.1);
    let mut seen = Vec::new();
    f.retain(|x| {
        let new = !seen.contains(x);
        seen.push(*x);
        new
    });
    Call {
        level,
        class,
        findings: f,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn good() -> PadMeasurement {
        PadMeasurement {
            coverage: 1.0,
            volume_pct: 95.0,
            area_pct: 105.0,
            height_pct: 92.0,
            offset_pct: 5.0,
            shape_pct: 1.0,
            ..Default::default()
        }
    }

    /// A value whose `+- k u` interval holds a failure limit is "warn: uncertain" whichever
    /// side it lies on; clear of the limit, or with the guard band off or no uncertainty,
    /// the windows decide as without it.
    #[test]
    fn guard_band_marks_what_the_uncertainty_cannot_decide() {
        let call = |volume: f64, u: f64, height: f64, hu: f64, k: f64| {
            let mut m = good();
            (m.volume_pct, m.volume_u_pct, m.height_pct, m.height_u_pct) = (volume, u, height, hu);
            let w = Windows {
                guard_band_k: k,
                ..Windows::default()
            };
            let c = judge(&m, &w);
            (c.level, c.class)
        };
        let uncertain = (Level::Warn, Some(Class::Uncertain));
        // The default volume window fails below 55 and above 145; k = 2.
        assert_eq!(
            call(56.0, 1.0, 92.0, 0.5, 2.0),
            uncertain,
            "a pass it cannot back"
        );
        assert_eq!(
            call(54.0, 1.0, 92.0, 0.5, 2.0),
            uncertain,
            "a fail it cannot back"
        );
        assert_eq!(
            call(146.0, 1.0, 92.0, 0.5, 2.0),
            uncertain,
            "the upper limit too"
        );
        assert_eq!(
            call(58.0, 1.0, 92.0, 0.5, 2.0),
            (Level::Warn, Some(Class::Insufficient)),
            "[56, 60] is clear of 55"
        );
        assert_eq!(
            call(52.0, 1.0, 92.0, 0.5, 2.0),
            (Level::Fail, Some(Class::Insufficient)),
            "[50, 54] is a sure fail"
        );
        assert_eq!(
            call(54.0, 1.0, 92.0, 0.5, 0.0),
            (Level::Fail, Some(Class::Insufficient)),
            "guard band off"
        );
        assert_eq!(
            call(54.0, f64::NAN, 92.0, 0.5, 2.0),
            (Level::Fail, Some(Class::Insufficient)),
            "no uncertainty: the value alone"
        );
        // The height (fail below 40 %): the same.
        assert_eq!(call(95.0, 1.0, 41.0, 1.0, 2.0), uncertain);
        assert_eq!(
            call(95.0, 1.0, 43.0, 1.0, 2.0),
            (Level::Warn, Some(Class::Insufficient))
        );
        // A sure failure elsewhere still fails the pad.
        let mut m = good();
        (m.volume_pct, m.volume_u_pct, m.offset_pct) = (56.0, 1.0, 40.0);
        let c = judge(&m, &Windows::default());
        assert_eq!((c.level, c.class), (Level::Fail, Some(Class::Offset)));
        assert!(c.findings.contains(&(Level::Warn, Class::Uncertain)));
    }

    #[test]
    fn classes_follow_the_windows() {
        let w = Windows::default();
        assert_eq!(judge(&good(), &w).level, Level::Pass);
        type Case = (Box<dyn Fn(&mut PadMeasurement)>, Level, Class);
        let cases: Vec<Case> = vec![
            (
                Box::new(|m| m.volume_pct = 3.0),
                Level::Fail,
                Class::Missing,
            ),
            (
                Box::new(|m| {
                    m.volume_pct = 40.0;
                    m.height_pct = 40.0;
                }),
                Level::Fail,
                Class::Insufficient,
            ),
            (
                Box::new(|m| m.volume_pct = 60.0),
                Level::Warn,
                Class::Insufficient,
            ),
            (
                Box::new(|m| m.volume_pct = 170.0),
                Level::Fail,
                Class::Excess,
            ),
            (
                Box::new(|m| {
                    m.offset_pct = 40.0;
                    m.height_pct = 50.0;
                }),
                Level::Fail,
                Class::Offset,
            ),
            (
                Box::new(|m| {
                    m.bridged_to = vec![3];
                    m.volume_pct = 160.0;
                }),
                Level::Fail,
                Class::Bridge,
            ),
            (Box::new(|m| m.shape_pct = 50.0), Level::Fail, Class::Shape),
            (
                Box::new(|m| m.unmeasurable = Some(crate::measure::Unmeasurable::LowCoverage)),
                Level::Fail,
                Class::NotMeasurable,
            ),
            (
                Box::new(|m| m.height_pct = f64::NAN),
                Level::Fail,
                Class::Insufficient,
            ),
        ];
        for (i, (f, l, c)) in cases.into_iter().enumerate() {
            let mut m = good();
            f(&mut m);
            let call = judge(&m, &w);
            assert_eq!((call.level, call.class), (l, Some(c)), "case {i}: {call:?}");
        }
    }
}
