//! The inspection's figures against the simulator's truth.
//!
//! The truth of a pad is measured with the inspection's own definitions ([`super::measure`]) on
//! the true paste surface instead of the map: the same cell (built from the true placement),
//! integrated on a 5 um grid of the true paste height above the board (no optics, no noise,
//! no warp, no registration error). The differences are therefore the gauge's error alone:
//! optics and pixels, noise, the local surface, the registration.

use super::measure::{cell_member, height_inset, per_pad, PadMeasurement, Placed, Reach};
use super::program::Program;
use super::verdict::{Call, Class, Level};
use dpsa_gerber::pads::{Pad, Point, Rigid};
use serde::Serialize;

/// Truth integration step, mm.
pub const STEP_MM: f64 = 0.005;

/// One pad's true figures (the inspection's definitions).
#[derive(Clone, Debug, Default, Serialize)]
pub struct PadTruth {
    /// True paste volume over the pad's cell, % of the opening volume (area x stencil).
    pub volume_pct: f64,
    /// True cell area with paste above `area_threshold_pct` of the stencil, % of the
    /// opening's.
    pub area_pct: f64,
    /// True mean paste height over the opening's interior (shrunk by the wall), um; NaN
    /// when no point lies there.
    pub height_um: f64,
    /// True deposit centre minus opening centre, design-frame axes, um (NaN: no paste
    /// above the area threshold).
    pub offset_um: [f64; 2],
}

/// True figures of every pad: `height(p)` is the true paste height above the board at board
/// point `p` (um), `t` the true design-to-board transform.
pub fn measure_truth(
    pads: &[Pad],
    t: &Rigid,
    program: &Program,
    height: &(dyn Fn(Point) -> f64 + Sync),
) -> Vec<PadTruth> {
    measure_truth_counted(pads, t, program, height, &indicatif::ProgressBar::hidden())
}

/// [`measure_truth`], counting every pad on `bar`.
pub fn measure_truth_counted(
    pads: &[Pad],
    t: &Rigid,
    program: &Program,
    height: &(dyn Fn(Point) -> f64 + Sync),
    bar: &indicatif::ProgressBar,
) -> Vec<PadTruth> {
    let placed = Placed::new(pads, t, &[], 1.0);
    per_pad(pads.len(), |k| {
        let r = one(pads, &placed, t, program, height, k);
        bar.inc(1);
        r
    })
}

fn one(
    pads: &[Pad],
    placed: &Placed,
    t: &Rigid,
    program: &Program,
    height: &(dyn Fn(Point) -> f64 + Sync),
    k: usize,
) -> PadTruth {
    let ms = placed.min_size[k];
    let reach = Reach::new(placed, k, program);
    let margin = reach.max;
    let inset = height_inset(program, ms);
    let bb = placed.bboxes[k];
    let near = placed.near(bb, 2.0 * margin, k);
    let o = &placed.outlines[k];
    let c = o.centroid();
    let thr = program.stencil_um * program.measure.area_threshold_pct / 100.0;
    let s = STEP_MM;
    let (mut vol, mut area, mut hs, mut hn, mut sw, mut sx, mut sy) =
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let rb = reach.bbox;
    let mut x = rb[0] + s / 2.0;
    while x < rb[2] {
        let mut y = rb[1] + s / 2.0;
        while y < rb[3] {
            let (inside, d) = cell_member(placed, k, &near, &reach, [x, y]);
            if inside {
                let h = height([x, y]);
                vol += h;
                if h > thr {
                    area += 1.0;
                    sw += h;
                    sx += h * x;
                    sy += h * y;
                }
                if d <= -inset {
                    hs += h;
                    hn += 1.0;
                }
            }
            y += s;
        }
        x += s;
    }
    let a = pads[k].outline.area();
    let mut offset = [f64::NAN; 2];
    if sw > 0.0 {
        let (dx, dy) = (sx / sw - c[0], sy / sw - c[1]);
        let (sn, cs) = t.rotation_rad.sin_cos();
        offset = [(cs * dx + sn * dy) * 1000.0, (-sn * dx + cs * dy) * 1000.0];
    }
    PadTruth {
        volume_pct: 100.0 * vol * s * s / (a * program.stencil_um),
        area_pct: 100.0 * area * s * s / a,
        height_um: if hn > 0.0 { hs / hn } else { f64::NAN },
        offset_um: offset,
    }
}

/// Mean and rms of a set of errors (None when empty).
#[derive(Clone, Debug, Serialize)]
pub struct ErrStats {
    /// Finite errors counted.
    pub n: usize,
    /// Mean error, in the errors' unit.
    pub bias: f64,
    /// Root mean square error (about zero, not the mean), in the errors' unit.
    pub rms: f64,
    /// Largest absolute error, in the errors' unit.
    pub max_abs: f64,
}

/// [`ErrStats`] of the finite values of `v`; `None` when none is finite.
pub fn stats(v: &[f64]) -> Option<ErrStats> {
    let v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    let n = v.len() as f64;
    Some(ErrStats {
        n: v.len(),
        bias: v.iter().sum::<f64>() / n,
        rms: (v.iter().map(|x| x * x).sum::<f64>() / n).sqrt(),
        max_abs: v.iter().fold(0.0, |a, x| a.max(x.abs())),
    })
}

/// Accuracy of one size group of defect-free pads.
#[derive(Clone, Debug, Serialize)]
pub struct Accuracy {
    /// Measured minus true volume, percentage points of the opening volume.
    pub volume_err_pct: Option<ErrStats>,
    /// Measured minus true mean interior height, um.
    pub height_err_um: Option<ErrStats>,
    /// Length of the offset error vector, um (bias: its mean).
    pub offset_err_um: Option<ErrStats>,
    /// Measured minus true paste area, percentage points of the opening area.
    pub area_err_pct: Option<ErrStats>,
}

/// Accuracy of the pads `sel`: measurements `m` minus truths `t`, pads the inspection
/// could not measure left out.
pub fn accuracy(sel: &[usize], m: &[PadMeasurement], t: &[PadTruth]) -> Accuracy {
    let mut v = Vec::new();
    let mut h = Vec::new();
    let mut o = Vec::new();
    let mut a = Vec::new();
    for &k in sel {
        if m[k].unmeasurable.is_some() {
            continue;
        }
        v.push(m[k].volume_pct - t[k].volume_pct);
        h.push(m[k].height_um - t[k].height_um);
        a.push(m[k].area_pct - t[k].area_pct);
        let e =
            (m[k].offset_um[0] - t[k].offset_um[0]).hypot(m[k].offset_um[1] - t[k].offset_um[1]);
        o.push(e);
    }
    Accuracy {
        volume_err_pct: stats(&v),
        height_err_um: stats(&h),
        offset_err_um: stats(&o),
        area_err_pct: stats(&a),
    }
}

/// The injected defect classes the inspection must find, as its own classes. Smears are
/// judged as shape; they are reported apart (thin smears on small openings are below what
/// the map resolves).
pub fn expected_class(defect: &str) -> Option<Class> {
    match defect {
        "missing" => Some(Class::Missing),
        "insufficient" => Some(Class::Insufficient),
        "excess" => Some(Class::Excess),
        "offset" => Some(Class::Offset),
        "bridge" => Some(Class::Bridge),
        "smear" => Some(Class::Shape),
        _ => None,
    }
}

/// Detection figures.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Detection {
    /// Pads with an injected missing, insufficient, excess, offset or bridge defect.
    pub injected: usize,
    /// ... called fail.
    pub detected: usize,
    /// ... not called fail.
    pub missed: usize,
    /// ... called fail with another class.
    pub wrong_class: usize,
    /// Defect-free pads called fail.
    pub false_fail: usize,
    /// Of which within 1 mm of a pad with an injected defect (its paste: a smear or an
    /// offset deposit reaching the neighbour); a defect-free board has none of these.
    pub false_fail_next_to_defect: usize,
    /// Defect-free pads called warning.
    pub false_warn: usize,
    /// Pads with no injected defect.
    pub defect_free: usize,
    /// Smears (judged as shape): injected, failed with class shape, failed otherwise.
    pub smear_injected: usize,
    /// Smears called fail with class shape.
    pub smear_detected: usize,
    /// Smears called fail with another class.
    pub smear_other_class: usize,
    /// Per injected class: `[injected, detected with the right class]`.
    pub per_class: std::collections::BTreeMap<String, [usize; 2]>,
    /// The misses and wrong classes, `pad name: injected -> called`.
    pub errors: Vec<String>,
}

/// Scores the inspection's `calls` against the injected `defects` (per pad, `None`
/// for a good print).
pub fn detection(pads: &[Pad], defects: &[Option<String>], calls: &[Call]) -> Detection {
    let mut d = Detection::default();
    for (k, call) in calls.iter().enumerate() {
        let defect = defects.get(k).cloned().flatten();
        let called = match call.class {
            Some(c) if call.level == Level::Fail => Some(c),
            _ => None,
        };
        match defect.as_deref().and_then(expected_class) {
            None => {
                d.defect_free += 1;
                match call.level {
                    Level::Fail => {
                        d.false_fail += 1;
                        let c = pads[k].outline.centroid();
                        let next = defects.iter().enumerate().any(|(j, dj)| {
                            dj.is_some() && j != k && pads[j].outline.signed_distance(c) <= 1.0
                        });
                        if next {
                            d.false_fail_next_to_defect += 1;
                        }
                        d.errors.push(format!(
                            "{}: none -> {}",
                            pads[k].name(),
                            call.class.map(Class::name).unwrap_or("?")
                        ));
                    }
                    Level::Warn => d.false_warn += 1,
                    Level::Pass => {}
                }
            }
            Some(Class::Shape) => {
                d.smear_injected += 1;
                match called {
                    Some(Class::Shape) => d.smear_detected += 1,
                    Some(_) => d.smear_other_class += 1,
                    None => {}
                }
            }
            Some(want) => {
                d.injected += 1;
                let e = d.per_class.entry(want.name().to_string()).or_insert([0, 0]);
                e[0] += 1;
                match called {
                    Some(c) if c == want => {
                        d.detected += 1;
                        e[1] += 1;
                    }
                    Some(c) => {
                        d.detected += 1;
                        d.wrong_class += 1;
                        d.errors.push(format!(
                            "{}: {} -> {}",
                            pads[k].name(),
                            want.name(),
                            c.name()
                        ));
                    }
                    None => {
                        d.missed += 1;
                        d.errors.push(format!(
                            "{}: {} -> {}",
                            pads[k].name(),
                            want.name(),
                            call.level.name()
                        ));
                    }
                }
            }
        }
    }
    d
}
