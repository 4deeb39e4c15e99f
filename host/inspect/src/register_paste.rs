//! Registration without fiducials: the design found on the board map by its paste pattern.
//!
//! A program without fiducials places the design by the conveyor datum only (the program's
//! `placement`: the board corner against the stop, the board turned as it lies). That nominal
//! place is good to a millimetre or so; the deposits themselves then say where the design
//! lies, in two steps:
//!
//! 1. **Search.** For a candidate correction (a shift within [`SEARCH_MM`] and a turn within
//!    [`SEARCH_DEG`] of the nominal place) every sample pad scores the mean height at a few
//!    points inside its opening less the mean height on a ring just outside it (away from
//!    every other opening): a deposit under the opening scores about the stencil height, bare
//!    board about 0, and a warped board cancels out locally. The sum over the pads, divided by
//!    the stencil and the pad count, is about 1 where the design meets its print. The search
//!    runs on a coarse grid ([`COARSE_MM`], [`COARSE_DEG`]), then on a fine one around the
//!    best. A board without a paste pattern (best score under [`MIN_SCORE`]) and a pattern
//!    that repeats within the search (another place, farther than two coarse steps, scoring
//!    [`AMBIGUOUS`] of the best or more) are refused: they cannot be told apart from a wrong
//!    placement.
//! 2. **Fit.** Each sample pad's deposit centre (the paste-weighted centroid of the board
//!    around its registered place above the plane through its ring points, weights rising
//!    from 0 at 20 % of the stencil to 1 at 50 %) is
//!    paired with the pad's design centre, and a rotation and shift is fitted by least
//!    squares (`register::fit_rigid`); pads whose deposits miss by more than three
//!    times the median miss (and 50 um) are left out (an offset or bridged print is a defect
//!    to find, not a placement) and the fit repeated. The residual is the rms of the kept
//!    pads' misses: part placement, part print offset; the report says how many pads it used.

use crate::map::BoardMap;
use crate::program::Program;
use crate::register::{fit_rigid, RegisterError, Registration};
use dpsa_gerber::pads::{Pad, Point, Rigid};

/// Largest departure from the nominal placement searched, mm (each way).
pub const SEARCH_MM: f64 = 2.0;
/// Largest turn from the nominal placement searched, degrees (each way).
pub const SEARCH_DEG: f64 = 0.5;
/// Coarse search step in shift, mm.
pub const COARSE_MM: f64 = 0.1;
/// Coarse search step in turn, degrees.
pub const COARSE_DEG: f64 = 0.25;
/// Fine search step in shift, mm.
pub const FINE_MM: f64 = 0.02;
/// Fine search step in turn, degrees.
pub const FINE_DEG: f64 = 0.05;
/// Lowest best score (about 1 for a good print in place) taken as the paste pattern.
pub const MIN_SCORE: f64 = 0.25;
/// A second place scoring this share of the best is an ambiguous pattern.
pub const AMBIGUOUS: f64 = 0.85;
/// Pads used: at least this size both ways, mm (smaller openings are a pixel or two).
pub const MIN_PAD_MM: f64 = 0.15;
/// Most pads sampled by the fit (evenly through the file order beyond it); the coarse
/// search takes at most 300 of them, the fine one at most 600.
pub const MAX_PADS: usize = 2000;
/// Fewest pads the fit needs.
pub const MIN_PADS: usize = 3;

/// One pad's sample points, design mm.
struct Sample {
    centre: Point,
    inside: Vec<Point>,
    ring: Vec<Point>,
    /// The window its deposit's centroid is taken in: half sizes around the centre, mm.
    reach: [f64; 2],
}

/// Height at board point `q`, um (None: off the map or invalid).
fn height(map: &BoardMap, q: Point) -> Option<f64> {
    let (i, j) = map.pixel_of(q);
    if i < 0 || j < 0 {
        return None;
    }
    let v = map.heights.at(i as usize, j as usize);
    v.is_finite().then_some(f64::from(v))
}

/// The sample pads: inside points (centre and four around it), ring points (the box grown by
/// a gap, its corners and edge middles) that fall in no opening.
fn samples(pads: &[Pad]) -> Vec<Sample> {
    let size = |p: &Pad| {
        let b = p.outline.bbox();
        [b[2] - b[0], b[3] - b[1]]
    };
    let usable: Vec<&Pad> = pads
        .iter()
        .filter(|p| {
            let s = size(p);
            s[0] >= MIN_PAD_MM && s[1] >= MIN_PAD_MM
        })
        .collect();
    let stride = usable.len().div_ceil(MAX_PADS).max(1);
    // Openings, grown a little, to keep ring points off other deposits: the boxes, bucketed.
    let cell = 1.0;
    let mut buckets: std::collections::HashMap<(i64, i64), Vec<usize>> = Default::default();
    let boxes: Vec<[f64; 4]> = pads
        .iter()
        .map(|p| {
            let b = p.outline.bbox();
            [b[0] - 0.05, b[1] - 0.05, b[2] + 0.05, b[3] + 0.05]
        })
        .collect();
    for (k, b) in boxes.iter().enumerate() {
        for x in (b[0] / cell).floor() as i64..=(b[2] / cell).floor() as i64 {
            for y in (b[1] / cell).floor() as i64..=(b[3] / cell).floor() as i64 {
                buckets.entry((x, y)).or_default().push(k);
            }
        }
    }
    let in_opening = |q: Point| {
        let key = ((q[0] / cell).floor() as i64, (q[1] / cell).floor() as i64);
        buckets.get(&key).is_some_and(|ks| {
            ks.iter().any(|&k| {
                let b = boxes[k];
                q[0] >= b[0] && q[0] <= b[2] && q[1] >= b[1] && q[1] <= b[3]
            })
        })
    };
    usable
        .iter()
        .step_by(stride)
        .filter_map(|p| {
            let c = p.outline.centroid();
            let s = size(p);
            let inside: Vec<Point> = [[0.0, 0.0], [0.3, 0.0], [-0.3, 0.0], [0.0, 0.3], [0.0, -0.3]]
                .iter()
                .map(|f| [c[0] + f[0] * s[0], c[1] + f[1] * s[1]])
                .filter(|&q| p.outline.contains(q))
                .collect();
            let gap = (0.5 * s[0].min(s[1])).clamp(0.1, 0.3);
            let b = p.outline.bbox();
            let (x0, y0, x1, y1) = (b[0] - gap, b[1] - gap, b[2] + gap, b[3] + gap);
            let (xm, ym) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
            let ring: Vec<Point> = [
                [x0, y0],
                [xm, y0],
                [x1, y0],
                [x1, ym],
                [x1, y1],
                [xm, y1],
                [x0, y1],
                [x0, ym],
            ]
            .into_iter()
            .filter(|&q| !in_opening(q))
            .collect();
            (!inside.is_empty() && ring.len() >= 2).then(|| Sample {
                centre: c,
                inside,
                ring,
                reach: [s[0] / 2.0 + gap, s[1] / 2.0 + gap],
            })
        })
        .collect()
}

/// The correction `(dx, dy, turn)` about `pivot` (design mm) before the nominal placement.
fn candidate(nominal: &Rigid, pivot: Point, d: [f64; 3]) -> Rigid {
    let turn = Rigid {
        rotation_rad: d[2].to_radians(),
        tx: 0.0,
        ty: 0.0,
    };
    let r = turn.apply(pivot);
    let correction = Rigid {
        rotation_rad: d[2].to_radians(),
        tx: pivot[0] - r[0] + d[0],
        ty: pivot[1] - r[1] + d[1],
    };
    nominal.after(&correction)
}

/// Mean over the sample pads of (inside - ring) / stencil at transform `t`.
fn score(map: &BoardMap, samples: &[&Sample], t: &Rigid, stencil: f64) -> f64 {
    let (sn, cs) = t.rotation_rad.sin_cos();
    let apply = |p: Point| [cs * p[0] - sn * p[1] + t.tx, sn * p[0] + cs * p[1] + t.ty];
    let mean = |pts: &[Point]| -> Option<f64> {
        let (mut s, mut n) = (0.0, 0usize);
        for &p in pts {
            if let Some(h) = height(map, apply(p)) {
                s += h;
                n += 1;
            }
        }
        (n > 0).then(|| s / n as f64)
    };
    let mut total = 0.0;
    for s in samples {
        if let (Some(a), Some(b)) = (mean(&s.inside), mean(&s.ring)) {
            total += ((a - b) / stencil).clamp(-1.5, 1.5);
        }
    }
    total / samples.len().max(1) as f64
}

/// The best of a grid of corrections around `around`: `(score, correction)`, and the best
/// score farther than `apart` mm from it.
#[allow(clippy::too_many_arguments)]
fn search(
    map: &BoardMap,
    samples: &[&Sample],
    nominal: &Rigid,
    pivot: Point,
    stencil: f64,
    around: [f64; 3],
    (reach_mm, step_mm, reach_deg, step_deg): (f64, f64, f64, f64),
    apart: f64,
) -> ((f64, [f64; 3]), f64) {
    let n = (reach_mm / step_mm).round() as i64;
    let m = (reach_deg / step_deg).round() as i64;
    let mut all: Vec<(f64, [f64; 3])> = Vec::new();
    for a in -m..=m {
        for i in -n..=n {
            for j in -n..=n {
                let d = [
                    around[0] + i as f64 * step_mm,
                    around[1] + j as f64 * step_mm,
                    around[2] + a as f64 * step_deg,
                ];
                let t = candidate(nominal, pivot, d);
                all.push((score(map, samples, &t, stencil), d));
            }
        }
    }
    let best = all
        .iter()
        .copied()
        .max_by(|x, y| x.0.total_cmp(&y.0))
        .unwrap_or((f64::NEG_INFINITY, around));
    let second = all
        .iter()
        .filter(|(_, d)| (d[0] - best.1[0]).hypot(d[1] - best.1[1]) > apart)
        .map(|x| x.0)
        .fold(f64::NEG_INFINITY, f64::max);
    (best, second)
}

/// Where pad `s`'s deposit is on the board at transform `t`: the paste-weighted centroid
/// around its place (None: no paste there). The bare board around it is the plane through
/// its ring points (a warped board tilts by a few um over a pad); paste counts from 20 % of
/// the stencil above it, fully from 50 %.
fn deposit_centre(map: &BoardMap, s: &Sample, t: &Rigid, stencil: f64) -> Option<Point> {
    let ring: Vec<[f64; 3]> = s
        .ring
        .iter()
        .filter_map(|&p| {
            let q = t.apply(p);
            height(map, q).map(|h| [q[0], q[1], h])
        })
        .collect();
    if ring.len() < 3 {
        return None;
    }
    let plane = plane_through(&ring)?;
    let c = t.apply(s.centre);
    let reach = s.reach[0].max(s.reach[1]);
    let (ri, rj) = map.window([c[0] - reach, c[1] - reach, c[0] + reach, c[1] + reach]);
    let inv = t.inverse();
    let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for i in ri {
        for j in rj.clone() {
            let h = map.heights.at(i, j);
            if !h.is_finite() {
                continue;
            }
            let q = map.grid.centre(i, j);
            let q = [q.0, q.1];
            // Only the pad's own window (in the design frame), not a neighbour's deposit.
            let d = inv.apply(q);
            if (d[0] - s.centre[0]).abs() > s.reach[0] || (d[1] - s.centre[1]).abs() > s.reach[1] {
                continue;
            }
            let above = f64::from(h) - (plane[0] + plane[1] * q[0] + plane[2] * q[1]);
            let w = ((above - 0.2 * stencil) / (0.3 * stencil)).clamp(0.0, 1.0);
            sw += w;
            sx += w * q[0];
            sy += w * q[1];
        }
    }
    let px = map.grid.pitch_mm * map.grid.pitch_mm;
    // At least a quarter of a (0.15 mm)^2 opening's worth of paste.
    (sw * px >= 0.25 * MIN_PAD_MM * MIN_PAD_MM).then(|| [sx / sw, sy / sw])
}

/// The least-squares plane `z = a + b x + c y` through points (None: they are on a line).
fn plane_through(p: &[[f64; 3]]) -> Option<[f64; 3]> {
    let n = p.len() as f64;
    let m = p.iter().fold([0.0; 3], |a, q| {
        [a[0] + q[0] / n, a[1] + q[1] / n, a[2] + q[2] / n]
    });
    let (mut sxx, mut sxy, mut syy, mut sxz, mut syz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for q in p {
        let (x, y, z) = (q[0] - m[0], q[1] - m[1], q[2] - m[2]);
        sxx += x * x;
        sxy += x * y;
        syy += y * y;
        sxz += x * z;
        syz += y * z;
    }
    let det = sxx * syy - sxy * sxy;
    if det.abs() < 1e-12 {
        return None;
    }
    let b = (sxz * syy - syz * sxy) / det;
    let c = (syz * sxx - sxz * sxy) / det;
    Some([m[2] - b * m[0] - c * m[1], b, c])
}

/// Registers the design on the map by its paste pattern (see the module docs).
pub fn register_paste(
    map: &BoardMap,
    pads: &[Pad],
    program: &Program,
) -> Result<Registration, RegisterError> {
    let samples = samples(pads);
    if samples.len() < MIN_PADS {
        return Err(RegisterError::NoPattern {
            why: format!(
                "the layer has {} openings of at least {MIN_PAD_MM} mm both ways with bare board \
                 around them (need {MIN_PADS})",
                samples.len()
            ),
        });
    }
    let stencil = program.stencil_um;
    let nominal = program.placement.nominal();
    let n = samples.len() as f64;
    let pivot = samples.iter().fold([0.0, 0.0], |a, s| {
        [a[0] + s.centre[0] / n, a[1] + s.centre[1] / n]
    });
    // The searches take up to 300 and 600 pads spread over the file (the fit takes all).
    let spread = |k: usize| -> Vec<&Sample> {
        samples
            .iter()
            .step_by(samples.len().div_ceil(k).max(1))
            .collect()
    };
    let (coarse, fine) = (spread(300), spread(600));
    let ((best, d0), second) = search(
        map,
        &coarse,
        &nominal,
        pivot,
        stencil,
        [0.0, 0.0, 0.0],
        (SEARCH_MM, COARSE_MM, SEARCH_DEG, COARSE_DEG),
        2.0 * COARSE_MM,
    );
    if best.is_nan() || best < MIN_SCORE {
        return Err(RegisterError::NoPattern {
            why: format!(
                "the paste pattern was not found within {SEARCH_MM} mm and {SEARCH_DEG} deg of \
                 the nominal placement (best match {best:.2}, a good print in place scores \
                 about 1; below {MIN_SCORE} is no pattern): is the board printed, and the \
                 program's placement right?"
            ),
        });
    }
    if second >= AMBIGUOUS * best {
        return Err(RegisterError::NoPattern {
            why: format!(
                "the paste pattern repeats within the search: the best place scores {best:.2}, \
                 another {second:.2} at least {:.1} mm away; give the program fiducials",
                2.0 * COARSE_MM
            ),
        });
    }
    let ((_, d1), _) = search(
        map,
        &fine,
        &nominal,
        pivot,
        stencil,
        d0,
        (COARSE_MM, FINE_MM, COARSE_DEG, FINE_DEG),
        f64::INFINITY,
    );
    let mut t = candidate(&nominal, pivot, d1);
    // Fit to the deposits' centres, leaving out the pads that miss by far.
    let mut used = 0;
    let mut residual = 0.0;
    for _ in 0..3 {
        let pairs: Vec<(Point, Point)> = samples
            .iter()
            .filter_map(|s| deposit_centre(map, s, &t, stencil).map(|b| (s.centre, b)))
            .collect();
        let misses: Vec<f64> = pairs
            .iter()
            .map(|(d, b)| {
                let p = t.apply(*d);
                (p[0] - b[0]).hypot(p[1] - b[1])
            })
            .collect();
        let mut sorted = misses.clone();
        sorted.sort_by(f64::total_cmp);
        let median = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
        let cut = (3.0 * median).max(0.05);
        let kept: Vec<(Point, Point)> = pairs
            .iter()
            .zip(&misses)
            .filter(|(_, &m)| m <= cut)
            .map(|(p, _)| *p)
            .collect();
        if kept.len() < MIN_PADS {
            return Err(RegisterError::NoPattern {
                why: format!(
                    "only {} deposits were found where the pattern put their pads (need \
                     {MIN_PADS})",
                    kept.len()
                ),
            });
        }
        let (ds, bs): (Vec<Point>, Vec<Point>) = kept.iter().copied().unzip();
        t = fit_rigid(&ds, &bs);
        let ss: f64 = kept
            .iter()
            .map(|(d, b)| {
                let p = t.apply(*d);
                (p[0] - b[0]).powi(2) + (p[1] - b[1]).powi(2)
            })
            .sum();
        residual = (ss / kept.len() as f64).sqrt() * 1000.0;
        used = kept.len();
    }
    let delta = t.after(&nominal.inverse());
    Ok(Registration {
        method: "paste pattern",
        transform: t,
        shift_mm: [delta.tx, delta.ty],
        rotation_deg: delta.rotation_rad.to_degrees(),
        fiducials: Vec::new(),
        residual_um: residual,
        pads_used: Some(used),
    })
}
