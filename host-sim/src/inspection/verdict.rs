//! Verdicts: each pad's measurement against its windows, and the board's.
//!
//! A pad's call is the most severe of its findings: fail over warning over pass. Its class is
//! the first finding at that severity in this order, which is also the order an operator
//! reworks them in: not measurable, missing, bridge, offset, insufficient, excess, shape.
//! An offset deposit keeps its volume but lowers the height over the opening, and a bridge
//! adds volume, so offset and bridge come before insufficient and excess.
//! "Not measurable" (the opening off the map, too few valid pixels, no bare board around it)
//! is a failure of the inspection, never a pass.

use super::measure::PadMeasurement;
use super::program::{Upper, Window, Windows};
use serde::Serialize;

/// What is wrong with a pad.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Class {
    NotMeasurable,
    Missing,
    Bridge,
    Offset,
    Insufficient,
    Excess,
    Shape,
}

impl Class {
    pub const ALL: [Class; 7] = [
        Class::NotMeasurable,
        Class::Missing,
        Class::Bridge,
        Class::Offset,
        Class::Insufficient,
        Class::Excess,
        Class::Shape,
    ];

    pub fn name(self) -> &'static str {
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
    Pass,
    Warn,
    Fail,
}

impl Level {
    pub fn name(self) -> &'static str {
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

/// Judges one pad.
pub fn judge(m: &PadMeasurement, w: &Windows) -> Call {
    let mut f: Vec<(Level, Class)> = Vec::new();
    if m.unmeasurable.is_some() {
        f.push((Level::Fail, Class::NotMeasurable));
    } else {
        if m.volume_pct < w.missing_pct {
            f.push((Level::Fail, Class::Missing));
        }
        if !m.bridged_to.is_empty() {
            f.push((Level::Fail, Class::Bridge));
        }
        let missing = !f.is_empty() && f[0].1 == Class::Missing;
        if !missing {
            let off = upper(m.offset_pct, &w.offset_pct);
            if off != Level::Pass {
                f.push((off, Class::Offset));
            }
            for (v, win) in [
                (m.volume_pct, &w.volume_pct),
                (m.height_pct, &w.height_pct),
                (m.area_pct, &w.area_pct),
            ] {
                let (lv, side) = two_sided(v, win);
                if lv != Level::Pass {
                    f.push((
                        lv,
                        if side < 0 {
                            Class::Insufficient
                        } else {
                            Class::Excess
                        },
                    ));
                }
            }
            let sh = upper(m.shape_pct, &w.shape_pct);
            if sh != Level::Pass {
                f.push((sh, Class::Shape));
            }
        }
    }
    f.sort_by_key(|&(l, c)| (std::cmp::Reverse(l), c));
    f.dedup();
    let (level, class) = match f.first() {
        Some(&(l, c)) => (l, Some(c)),
        None => (Level::Pass, None),
    };
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
                Box::new(|m| {
                    m.unmeasurable = Some(super::super::measure::Unmeasurable::LowCoverage)
                }),
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
