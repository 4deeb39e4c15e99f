//! Pads: the paste openings of a board, in the paste layer's own frame (mm).
//!
//! A pad is one connected paste opening. Its [`Outline`] is exact for the shapes stencils are
//! made of (circles, rectangles with rounded corners, obrounds) and a polygon with holes for
//! everything else (regions, macro outlines, strokes, unions, clear polarity). Every outline
//! answers the same questions: signed distance (negative inside), area, centroid, bounding box
//! and perimeter (for the stencil's area ratio). The same type is the opening the inspection
//! measures against and the footprint the simulator prints paste into.

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// A point in mm, `[x, y]`.
pub type Point = [f64; 2];

/// The shape of one paste opening, mm.
///
/// JSON: an object with `kind` (`circle`, `round_rect`, `polygon`) beside the variant's fields.
/// It is read through `OutlineRepr` rather than serde's internally tagged enum: that one
/// buffers numbers, and with serde_json's `arbitrary_precision` (which `defmt-decoder` turns on
/// in this workspace) a buffered number no longer reads as an `f64`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", try_from = "OutlineRepr")]
pub enum Outline {
    /// A disc.
    Circle {
        /// Centre, mm.
        centre: Point,
        /// Diameter, mm (positive in a sane outline).
        diameter: f64,
    },
    /// A `size[0]` x `size[1]` rectangle (before rotation) whose corners are rounded with
    /// `radius` (0 = sharp; `min(size) / 2` = obround), turned counter-clockwise by
    /// `rotation_deg` about its centre.
    RoundRect {
        /// Centre, mm.
        centre: Point,
        /// Width along the rectangle's own x and height along its y before the rotation, mm.
        size: [f64; 2],
        /// Corner radius, mm; clamped to `0 ..= min(size) / 2` in every computation.
        radius: f64,
        /// Counter-clockwise rotation about the centre, degrees.
        rotation_deg: f64,
    },
    /// An exterior ring and holes; rings are not closed (the last point joins the first) and
    /// may run either way round.
    Polygon {
        /// The outer ring, mm (at least 3 points in a sane outline).
        exterior: Vec<Point>,
        /// The holes' rings, mm, each inside the exterior.
        holes: Vec<Vec<Point>>,
    },
}

/// The JSON form of an [`Outline`] as read: `kind` and every variant's fields, optional.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct OutlineRepr {
    kind: String,
    centre: Option<Point>,
    diameter: Option<f64>,
    size: Option<[f64; 2]>,
    radius: Option<f64>,
    rotation_deg: Option<f64>,
    exterior: Option<Vec<Point>>,
    holes: Option<Vec<Vec<Point>>>,
}

impl TryFrom<OutlineRepr> for Outline {
    type Error = String;

    fn try_from(r: OutlineRepr) -> Result<Outline, String> {
        let need =
            |v: Option<f64>, name: &str| v.ok_or_else(|| format!("{} without `{name}`", r.kind));
        let extra = |present: bool, name: &str| {
            if present {
                Err(format!("`{name}` does not belong to a {}", r.kind))
            } else {
                Ok(())
            }
        };
        match r.kind.as_str() {
            "circle" => {
                extra(r.size.is_some(), "size")?;
                extra(r.radius.is_some(), "radius")?;
                extra(r.rotation_deg.is_some(), "rotation_deg")?;
                extra(r.exterior.is_some() || r.holes.is_some(), "exterior")?;
                Ok(Outline::Circle {
                    centre: r.centre.ok_or("circle without `centre`")?,
                    diameter: need(r.diameter, "diameter")?,
                })
            }
            "round_rect" => {
                extra(r.diameter.is_some(), "diameter")?;
                extra(r.exterior.is_some() || r.holes.is_some(), "exterior")?;
                Ok(Outline::RoundRect {
                    centre: r.centre.ok_or("round_rect without `centre`")?,
                    size: r.size.ok_or("round_rect without `size`")?,
                    radius: need(r.radius, "radius")?,
                    rotation_deg: need(r.rotation_deg, "rotation_deg")?,
                })
            }
            "polygon" => {
                extra(r.centre.is_some(), "centre")?;
                extra(r.diameter.is_some() || r.size.is_some(), "size")?;
                extra(r.radius.is_some() || r.rotation_deg.is_some(), "radius")?;
                Ok(Outline::Polygon {
                    exterior: r.exterior.ok_or("polygon without `exterior`")?,
                    holes: r.holes.ok_or("polygon without `holes`")?,
                })
            }
            k => Err(format!(
                "unknown outline kind {k:?}, expected circle, round_rect or polygon"
            )),
        }
    }
}

/// Signed area of a ring (positive counter-clockwise).
fn ring_area(r: &[Point]) -> f64 {
    let n = r.len();
    let mut a = 0.0;
    for i in 0..n {
        let (p, q) = (r[i], r[(i + 1) % n]);
        a += p[0] * q[1] - q[0] * p[1];
    }
    a / 2.0
}

/// Area-weighted centroid sums of a ring: `(signed area, sum_x, sum_y)` with
/// centroid = sum / (6 * area).
fn ring_moments(r: &[Point]) -> (f64, f64, f64) {
    let n = r.len();
    let (mut a, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for i in 0..n {
        let (p, q) = (r[i], r[(i + 1) % n]);
        let cross = p[0] * q[1] - q[0] * p[1];
        a += cross;
        sx += (p[0] + q[0]) * cross;
        sy += (p[1] + q[1]) * cross;
    }
    (a / 2.0, sx, sy)
}

fn ring_perimeter(r: &[Point]) -> f64 {
    let n = r.len();
    (0..n)
        .map(|i| {
            let (p, q) = (r[i], r[(i + 1) % n]);
            (q[0] - p[0]).hypot(q[1] - p[1])
        })
        .sum()
}

/// Distance from `p` to the segment `a..b`.
fn segment_distance(p: Point, a: Point, b: Point) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len2 = dx * dx + dy * dy;
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let (ex, ey) = (p[0] - a[0] - t * dx, p[1] - a[1] - t * dy);
    (ex * ex + ey * ey).sqrt()
}

/// `sqrt(x^2 + y^2)` without `hypot`'s care for overflow (mm-sized values), several times
/// faster in the inspection's inner loops.
#[inline]
pub fn norm(x: f64, y: f64) -> f64 {
    (x * x + y * y).sqrt()
}

/// Crossing-number test contribution of one ring (even-odd rule).
fn ring_crossings(r: &[Point], p: Point) -> bool {
    let n = r.len();
    let mut inside = false;
    let mut j = n.wrapping_sub(1);
    for i in 0..n {
        let (a, b) = (r[i], r[j]);
        if (a[1] > p[1]) != (b[1] > p[1]) {
            let x = a[0] + (p[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]);
            if p[0] < x {
                inside = !inside;
            }
        }
        j = i;
    }
    inside
}

/// Signed distance to a rounded rectangle turned by the angle whose sine and cosine are `s`, `c`.
#[inline]
fn round_rect_distance(
    p: Point,
    centre: Point,
    size: [f64; 2],
    radius: f64,
    s: f64,
    c: f64,
) -> f64 {
    let (dx, dy) = (p[0] - centre[0], p[1] - centre[1]);
    // Into the rectangle's own axes.
    let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
    let r = radius.clamp(0.0, size[0].min(size[1]) / 2.0);
    let qx = u.abs() - (size[0] / 2.0 - r);
    let qy = v.abs() - (size[1] / 2.0 - r);
    let (a, b) = (qx.max(0.0), qy.max(0.0));
    // Off a corner, the distance to it; beside a side (`a` or `b` zero, most points), the
    // other one, which is what `norm` gives there (`sqrt(x * x) == x` for `x >= 0` in binary
    // floating point without underflow, and these are differences of millimetre-sized
    // values): the square root only where it is needed, the same value (`+ 0.0` turns a
    // `-0` into the `+0` of the root).
    let out = if a > 0.0 && b > 0.0 {
        norm(a, b)
    } else {
        a + b + 0.0
    };
    out + qx.max(qy).min(0.0) - r
}

/// An outline with its rotation's sine and cosine worked out once: the same signed distance
/// as [`Outline::signed_distance`], for inner loops.
#[derive(Clone, Debug)]
pub struct Prepared {
    /// The outline.
    pub outline: Outline,
    sin_cos: (f64, f64),
}

/// Every other question (area, centroid, box) goes to the outline.
impl std::ops::Deref for Prepared {
    type Target = Outline;
    fn deref(&self) -> &Outline {
        &self.outline
    }
}

impl Prepared {
    /// Works out the rotation of `outline` (a rounded rectangle's; none for the others).
    pub fn new(outline: Outline) -> Prepared {
        let sin_cos = match &outline {
            Outline::RoundRect { rotation_deg, .. } => rotation_deg.to_radians().sin_cos(),
            _ => (0.0, 1.0),
        };
        Prepared { outline, sin_cos }
    }

    /// [`Outline::signed_distance`] of the outline, mm (negative inside), without a sine and
    /// cosine per call.
    #[inline]
    pub fn signed_distance(&self, p: Point) -> f64 {
        match &self.outline {
            Outline::RoundRect {
                centre,
                size,
                radius,
                ..
            } => round_rect_distance(p, *centre, *size, *radius, self.sin_cos.0, self.sin_cos.1),
            o => o.signed_distance(p),
        }
    }

    /// [`Prepared::signed_distance`] of the points `(x, ys[b])` into `out[b]` (as many as the
    /// shorter of the two): the same values, one loop per kind of outline, so that a rounded
    /// rectangle's or a disc's points (a map row's pixels) are worked out several at a time.
    pub fn signed_distances(&self, x: f64, ys: &[f64], out: &mut [f64]) {
        let pairs = out.iter_mut().zip(ys);
        match &self.outline {
            Outline::RoundRect {
                centre,
                size,
                radius,
                ..
            } => {
                let (s, c) = self.sin_cos;
                for (o, &y) in pairs {
                    *o = round_rect_distance([x, y], *centre, *size, *radius, s, c);
                }
            }
            Outline::Circle { centre, diameter } => {
                for (o, &y) in pairs {
                    *o = norm(x - centre[0], y - centre[1]) - diameter / 2.0;
                }
            }
            o => {
                for (out, &y) in pairs {
                    *out = o.signed_distance([x, y]);
                }
            }
        }
    }
}

impl Outline {
    /// Signed distance from `p` to the outline's edge, mm: negative inside, positive outside.
    pub fn signed_distance(&self, p: Point) -> f64 {
        match self {
            Outline::Circle { centre, diameter } => {
                norm(p[0] - centre[0], p[1] - centre[1]) - diameter / 2.0
            }
            Outline::RoundRect {
                centre,
                size,
                radius,
                rotation_deg,
            } => {
                let (s, c) = rotation_deg.to_radians().sin_cos();
                round_rect_distance(p, *centre, *size, *radius, s, c)
            }
            Outline::Polygon { exterior, holes } => {
                let mut d = f64::INFINITY;
                let mut inside = false;
                for ring in std::iter::once(exterior).chain(holes.iter()) {
                    let n = ring.len();
                    for i in 0..n {
                        d = d.min(segment_distance(p, ring[i], ring[(i + 1) % n]));
                    }
                    if ring_crossings(ring, p) {
                        inside = !inside;
                    }
                }
                if inside {
                    -d
                } else {
                    d
                }
            }
        }
    }

    /// Whether `p` lies inside (or on) the outline.
    pub fn contains(&self, p: Point) -> bool {
        self.signed_distance(p) <= 0.0
    }

    /// Area, mm^2.
    pub fn area(&self) -> f64 {
        match self {
            Outline::Circle { diameter, .. } => PI * diameter * diameter / 4.0,
            Outline::RoundRect { size, radius, .. } => {
                let r = radius.clamp(0.0, size[0].min(size[1]) / 2.0);
                size[0] * size[1] - (4.0 - PI) * r * r
            }
            Outline::Polygon { exterior, holes } => {
                ring_area(exterior).abs() - holes.iter().map(|h| ring_area(h).abs()).sum::<f64>()
            }
        }
    }

    /// Perimeter, mm (outer and hole edges): the stencil wall the paste must leave.
    pub fn perimeter(&self) -> f64 {
        match self {
            Outline::Circle { diameter, .. } => PI * diameter,
            Outline::RoundRect { size, radius, .. } => {
                let r = radius.clamp(0.0, size[0].min(size[1]) / 2.0);
                2.0 * (size[0] + size[1]) - (8.0 - 2.0 * PI) * r
            }
            Outline::Polygon { exterior, holes } => {
                ring_perimeter(exterior) + holes.iter().map(|h| ring_perimeter(h)).sum::<f64>()
            }
        }
    }

    /// Centroid of the area, mm.
    pub fn centroid(&self) -> Point {
        match self {
            Outline::Circle { centre, .. } | Outline::RoundRect { centre, .. } => *centre,
            Outline::Polygon { exterior, holes } => {
                let sign = |r: &[Point]| ring_area(r).signum();
                let (a, sx, sy) = ring_moments(exterior);
                let s = sign(exterior);
                let (mut area, mut mx, mut my) = (a * s, sx * s, sy * s);
                for h in holes {
                    let (a, sx, sy) = ring_moments(h);
                    let s = sign(h);
                    area -= a * s;
                    mx -= sx * s;
                    my -= sy * s;
                }
                if area.abs() > 0.0 {
                    [mx / (6.0 * area), my / (6.0 * area)]
                } else {
                    exterior.first().copied().unwrap_or([0.0, 0.0])
                }
            }
        }
    }

    /// Bounding box `[xmin, ymin, xmax, ymax]`, mm.
    pub fn bbox(&self) -> [f64; 4] {
        match self {
            Outline::Circle { centre, diameter } => {
                let r = diameter / 2.0;
                [centre[0] - r, centre[1] - r, centre[0] + r, centre[1] + r]
            }
            Outline::RoundRect {
                centre,
                size,
                radius,
                rotation_deg,
            } => {
                let (s, c) = rotation_deg.to_radians().sin_cos();
                let r = radius.clamp(0.0, size[0].min(size[1]) / 2.0);
                let (hu, hv) = (size[0] / 2.0 - r, size[1] / 2.0 - r);
                let ex = (c * hu).abs() + (s * hv).abs() + r;
                let ey = (s * hu).abs() + (c * hv).abs() + r;
                [
                    centre[0] - ex,
                    centre[1] - ey,
                    centre[0] + ex,
                    centre[1] + ey,
                ]
            }
            Outline::Polygon { exterior, .. } => {
                let mut b = [
                    f64::INFINITY,
                    f64::INFINITY,
                    f64::NEG_INFINITY,
                    f64::NEG_INFINITY,
                ];
                for p in exterior {
                    b = [
                        b[0].min(p[0]),
                        b[1].min(p[1]),
                        b[2].max(p[0]),
                        b[3].max(p[1]),
                    ];
                }
                b
            }
        }
    }

    /// The outline moved by the rigid transform `t`.
    pub fn transformed(&self, t: &Rigid) -> Outline {
        match self {
            Outline::Circle { centre, diameter } => Outline::Circle {
                centre: t.apply(*centre),
                diameter: *diameter,
            },
            Outline::RoundRect {
                centre,
                size,
                radius,
                rotation_deg,
            } => Outline::RoundRect {
                centre: t.apply(*centre),
                size: *size,
                radius: *radius,
                rotation_deg: rotation_deg + t.rotation_rad.to_degrees(),
            },
            Outline::Polygon { exterior, holes } => Outline::Polygon {
                exterior: exterior.iter().map(|&p| t.apply(p)).collect(),
                holes: holes
                    .iter()
                    .map(|h| h.iter().map(|&p| t.apply(p)).collect())
                    .collect(),
            },
        }
    }

    /// The outline grown outwards by `d` mm (shrunk for `d < 0`), exactly: a disc's diameter
    /// grows by `2 d`, a rounded rectangle's size by `2 d` and its corner radius by `d`
    /// (clamped at 0 when shrinking). `None` for a polygon (its offset is not a polygon).
    pub fn offset(&self, d: f64) -> Option<Outline> {
        match self {
            Outline::Circle { centre, diameter } => Some(Outline::Circle {
                centre: *centre,
                diameter: (diameter + 2.0 * d).max(0.0),
            }),
            Outline::RoundRect {
                centre,
                size,
                radius,
                rotation_deg,
            } => {
                let r = radius.clamp(0.0, size[0].min(size[1]) / 2.0);
                Some(Outline::RoundRect {
                    centre: *centre,
                    size: [(size[0] + 2.0 * d).max(0.0), (size[1] + 2.0 * d).max(0.0)],
                    radius: (r + d).max(0.0),
                    rotation_deg: *rotation_deg,
                })
            }
            Outline::Polygon { .. } => None,
        }
    }

    /// The outline moved by `[dx, dy]` mm.
    pub fn shifted(&self, d: Point) -> Outline {
        self.transformed(&Rigid {
            rotation_rad: 0.0,
            tx: d[0],
            ty: d[1],
        })
    }

    /// Whether every number of the outline is finite and its size positive.
    pub fn is_sane(&self) -> bool {
        let fin = |p: &Point| p[0].is_finite() && p[1].is_finite();
        match self {
            Outline::Circle { centre, diameter } => {
                fin(centre) && diameter.is_finite() && *diameter > 0.0
            }
            Outline::RoundRect {
                centre,
                size,
                radius,
                rotation_deg,
            } => {
                fin(centre)
                    && fin(size)
                    && size[0] > 0.0
                    && size[1] > 0.0
                    && radius.is_finite()
                    && *radius >= 0.0
                    && rotation_deg.is_finite()
            }
            Outline::Polygon { exterior, holes } => {
                exterior.len() >= 3
                    && exterior.iter().all(fin)
                    && holes.iter().all(|h| h.len() >= 3 && h.iter().all(fin))
                    && self.area() > 0.0
            }
        }
    }
}

/// One paste opening of the layer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pad {
    /// Index in the layer (0-based, the order of the file).
    pub index: usize,
    /// The opening's shape, mm, in the layer's frame.
    pub outline: Outline,
    /// Component reference (`%TO.C`, X2), e.g. `U3`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub component: Option<String>,
    /// Pin number or name (`%TO.P`, X2), e.g. `14`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pin: Option<String>,
    /// The class of what drew it, for pad classes: an aperture (`C 0.25`, `R 0.60x0.30`,
    /// `O 1.20x0.60`, `P 1 n6`, a macro's name), `stroke` and an aperture, `region`, or
    /// `merged` when objects of several classes make the pad.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub aperture: Option<String>,
}

impl Pad {
    /// `component-pin` when both are known, else `#index`.
    pub fn name(&self) -> String {
        match (&self.component, &self.pin) {
            (Some(c), Some(p)) => format!("{c}-{p}"),
            (Some(c), None) => format!("{c}#{}", self.index),
            _ => format!("#{}", self.index),
        }
    }
}

/// A rigid transform of the plane: rotate counter-clockwise by `rotation_rad` about the origin,
/// then translate by `[tx, ty]` (mm).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rigid {
    /// Counter-clockwise rotation about the origin, radians.
    pub rotation_rad: f64,
    /// Translation along x after the rotation, mm.
    pub tx: f64,
    /// Translation along y after the rotation, mm.
    pub ty: f64,
}

impl Rigid {
    /// The transform that moves nothing.
    pub const IDENTITY: Rigid = Rigid {
        rotation_rad: 0.0,
        tx: 0.0,
        ty: 0.0,
    };

    /// The image of the point `p`, mm.
    pub fn apply(&self, p: Point) -> Point {
        let (s, c) = self.rotation_rad.sin_cos();
        [c * p[0] - s * p[1] + self.tx, s * p[0] + c * p[1] + self.ty]
    }

    /// The transform that undoes this one.
    pub fn inverse(&self) -> Rigid {
        let (s, c) = self.rotation_rad.sin_cos();
        Rigid {
            rotation_rad: -self.rotation_rad,
            tx: -(c * self.tx + s * self.ty),
            ty: -(-s * self.tx + c * self.ty),
        }
    }

    /// `self` after `first`: `p -> self(first(p))`.
    pub fn after(&self, first: &Rigid) -> Rigid {
        let t = self.apply([first.tx, first.ty]);
        Rigid {
            rotation_rad: self.rotation_rad + first.rotation_rad,
            tx: t[0],
            ty: t[1],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Area and centroid by sampling on a fine grid (independent of the closed forms).
    fn sampled(o: &Outline, step: f64) -> (f64, Point) {
        let b = o.bbox();
        let (mut n, mut sx, mut sy) = (0.0, 0.0, 0.0);
        let mut x = b[0] + step / 2.0;
        while x < b[2] {
            let mut y = b[1] + step / 2.0;
            while y < b[3] {
                if o.contains([x, y]) {
                    n += 1.0;
                    sx += x;
                    sy += y;
                }
                y += step;
            }
            x += step;
        }
        (n * step * step, [sx / n, sy / n])
    }

    fn shapes() -> Vec<Outline> {
        vec![
            Outline::Circle {
                centre: [1.0, 2.0],
                diameter: 0.6,
            },
            Outline::RoundRect {
                centre: [-3.0, 0.5],
                size: [1.2, 0.5],
                radius: 0.1,
                rotation_deg: 30.0,
            },
            Outline::RoundRect {
                centre: [0.0, 0.0],
                size: [0.3, 0.9],
                radius: 0.15,
                rotation_deg: -90.0,
            },
            // A 2 x 1 rectangle with a 0.5 x 0.5 hole, clockwise exterior.
            Outline::Polygon {
                exterior: vec![[0.0, 0.0], [0.0, 1.0], [2.0, 1.0], [2.0, 0.0]],
                holes: vec![vec![[0.25, 0.25], [0.75, 0.25], [0.75, 0.75], [0.25, 0.75]]],
            },
        ]
    }

    #[test]
    fn area_and_centroid_match_sampling() {
        for o in shapes() {
            let (a, c) = sampled(&o, 0.002);
            assert!(
                (a - o.area()).abs() < 2e-3 * o.area(),
                "{o:?}: {a} vs {}",
                o.area()
            );
            let cc = o.centroid();
            assert!(
                (c[0] - cc[0]).abs() < 2e-3 && (c[1] - cc[1]).abs() < 2e-3,
                "{o:?}"
            );
            let b = o.bbox();
            // Nothing inside lies outside the box; the box is tight to a sample step.
            assert!(o.contains(cc) || matches!(o, Outline::Polygon { .. }));
            assert!(b[0] < b[2] && b[1] < b[3]);
        }
    }

    #[test]
    fn signed_distance_is_a_distance() {
        // Inside negative, outside positive; stepping along the gradient by d reaches the edge.
        for o in shapes() {
            let b = o.bbox();
            for i in 0..40 {
                for j in 0..40 {
                    let p = [
                        b[0] - 0.3 + (b[2] - b[0] + 0.6) * f64::from(i) / 39.0,
                        b[1] - 0.3 + (b[3] - b[1] + 0.6) * f64::from(j) / 39.0,
                    ];
                    let d = o.signed_distance(p);
                    // Lipschitz 1 in each direction.
                    let q = [p[0] + 0.01, p[1]];
                    assert!((o.signed_distance(q) - d).abs() <= 0.01 + 1e-12);
                    if d.abs() > 1e-3 {
                        // No point within |d| of p is on the other side.
                        for k in 0..16 {
                            let a = f64::from(k) * std::f64::consts::TAU / 16.0;
                            let r = d.abs() * 0.99;
                            let q = [p[0] + r * a.cos(), p[1] + r * a.sin()];
                            assert_eq!(o.signed_distance(q) > 0.0, d > 0.0, "{o:?} {p:?}");
                        }
                    }
                }
            }
        }
    }

    /// A row's distances are the point-by-point ones, to the bit, for every kind of outline
    /// (turned or not), inside, on and beyond the edges.
    #[test]
    fn a_rows_distances_are_the_points() {
        let mut turned = shapes();
        turned.push(Outline::RoundRect {
            centre: [3.0, -1.0],
            size: [0.8, 0.3],
            radius: 0.05,
            rotation_deg: 27.0,
        });
        for o in turned {
            let p = Prepared::new(o.clone());
            let b = o.bbox();
            let ys: Vec<f64> = (0..157)
                .map(|j| b[1] - 0.4 + (b[3] - b[1] + 0.8) * f64::from(j) / 156.0)
                .collect();
            for i in 0..41 {
                let x = b[0] - 0.4 + (b[2] - b[0] + 0.8) * f64::from(i) / 40.0;
                let mut row = vec![f64::NAN; ys.len()];
                p.signed_distances(x, &ys, &mut row);
                for (&y, d) in ys.iter().zip(&row) {
                    assert_eq!(d.to_bits(), p.signed_distance([x, y]).to_bits(), "{o:?}");
                    assert_eq!(d.to_bits(), o.signed_distance([x, y]).to_bits(), "{o:?}");
                }
            }
        }
    }

    /// The square root only off the corners: the same bits as taking it everywhere, at
    /// random points around random rounded rectangles (and on their axes and edges).
    #[test]
    fn round_rect_distance_is_the_norm_everywhere() {
        let mut seed = 7u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut corner, mut side) = (0, 0);
        for _ in 0..200 {
            let centre = [200.0 * rnd(), 150.0 * rnd()];
            let size = [0.1 + 3.0 * rnd(), 0.1 + 3.0 * rnd()];
            let radius = [0.0, 0.05 * rnd(), 10.0][(rnd() * 3.0) as usize];
            let (s, c) = [0.0, 90.0, 33.0 * rnd()][(rnd() * 3.0) as usize]
                .to_radians()
                .sin_cos();
            for k in 0..500 {
                let p = match k % 5 {
                    // On an axis or on an edge of the unturned rectangle.
                    0 => [centre[0], centre[1] + 4.0 * (rnd() - 0.5)],
                    1 => [centre[0] + size[0] / 2.0, centre[1] + 4.0 * (rnd() - 0.5)],
                    _ => [
                        centre[0] + 4.0 * (rnd() - 0.5),
                        centre[1] + 4.0 * (rnd() - 0.5),
                    ],
                };
                let (dx, dy) = (p[0] - centre[0], p[1] - centre[1]);
                let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
                let r = radius.clamp(0.0, size[0].min(size[1]) / 2.0);
                let qx = u.abs() - (size[0] / 2.0 - r);
                let qy = v.abs() - (size[1] / 2.0 - r);
                let full = norm(qx.max(0.0), qy.max(0.0)) + qx.max(qy).min(0.0) - r;
                let d = round_rect_distance(p, centre, size, radius, s, c);
                assert_eq!(d.to_bits(), full.to_bits(), "{p:?} {centre:?} {size:?}");
                if qx > 0.0 && qy > 0.0 {
                    corner += 1;
                } else {
                    side += 1;
                }
            }
        }
        assert!(corner > 10_000 && side > 10_000, "{corner} {side}");
    }

    #[test]
    fn outlines_and_pads_round_trip_through_json() {
        for o in shapes() {
            let json = serde_json::to_string(&o).unwrap();
            assert!(json.contains("\"kind\""), "{json}");
            let back: Outline = serde_json::from_str(&json).unwrap();
            assert_eq!(back, o);
            let pad = Pad {
                index: 3,
                outline: o,
                component: Some("U1".into()),
                pin: Some("7".into()),
                aperture: None,
            };
            let back: Pad = serde_json::from_str(&serde_json::to_string(&pad).unwrap()).unwrap();
            assert_eq!(back, pad);
        }
        for bad in [
            r#"{"kind":"circle","centre":[0,0]}"#,
            r#"{"kind":"circle","centre":[0,0],"diameter":1,"size":[1,1]}"#,
            r#"{"kind":"hexagon","centre":[0,0]}"#,
        ] {
            assert!(serde_json::from_str::<Outline>(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn rigid_transforms_compose_and_invert() {
        let t = Rigid {
            rotation_rad: 0.3,
            tx: 5.0,
            ty: -2.0,
        };
        let u = Rigid {
            rotation_rad: -1.1,
            tx: 0.5,
            ty: 7.0,
        };
        let p = [1.5, -0.25];
        let q = t.inverse().apply(t.apply(p));
        assert!((q[0] - p[0]).abs() < 1e-12 && (q[1] - p[1]).abs() < 1e-12);
        let a = u.after(&t).apply(p);
        let b = u.apply(t.apply(p));
        assert!((a[0] - b[0]).abs() < 1e-12 && (a[1] - b[1]).abs() < 1e-12);
        for o in shapes() {
            let m = o.transformed(&t);
            assert!((m.area() - o.area()).abs() < 1e-9);
            let (c, cm) = (t.apply(o.centroid()), m.centroid());
            assert!((c[0] - cm[0]).abs() < 1e-9 && (c[1] - cm[1]).abs() < 1e-9);
            let p = [o.centroid()[0] + 0.1, o.centroid()[1] - 0.05];
            assert!((o.signed_distance(p) - m.signed_distance(t.apply(p))).abs() < 1e-9);
        }
    }
}
