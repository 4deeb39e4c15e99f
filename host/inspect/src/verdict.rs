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
}

impl Class {
    /// Every class, in the order of [`Class`]'s declaration.
    pub const ALL: [Class; 7] = [
        Class::NotMeasurable,
        Class::Missing,
        Class::Bridge,
        Class::Offset,
        Class::Insufficient,
        Class::Excess,
        Class::Shape,
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
        let (lv, side) = two_sided(m.volume_pct, &w.volume_pct);
        if lv != Level::Pass {
            f.push((lv, side_class(side)));
        }
        let off = upper(m.offset_pct, &w.offset_pct);
        if off != Level::Pass {
            f.push((off, Class::Offset));
        }
        for (v, win) in [(m.height_pct, &w.height_pct), (m.area_pct, &w.area_pct)] {
            let (lv, side) = two_sided(v, win);
            if lv != Level::Pass {
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
