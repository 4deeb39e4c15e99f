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
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Outline {
    /// A disc.
    Circle { centre: Point, diameter: f64 },
    /// A `size[0]` x `size[1]` rectangle (before rotation) whose corners are rounded with
    /// `radius` (0 = sharp; `min(size) / 2` = obround), turned counter-clockwise by
    /// `rotation_deg` about its centre.
    RoundRect {
        centre: Point,
        size: [f64; 2],
        radius: f64,
        rotation_deg: f64,
    },
    /// An exterior ring and holes; rings are not closed (the last point joins the first) and
    /// may run either way round.
    Polygon {
        exterior: Vec<Point>,
        holes: Vec<Vec<Point>>,
    },
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
    (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
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

impl Outline {
    /// Signed distance from `p` to the outline's edge, mm: negative inside, positive outside.
    pub fn signed_distance(&self, p: Point) -> f64 {
        match self {
            Outline::Circle { centre, diameter } => {
                (p[0] - centre[0]).hypot(p[1] - centre[1]) - diameter / 2.0
            }
            Outline::RoundRect {
                centre,
                size,
                radius,
                rotation_deg,
            } => {
                let (s, c) = rotation_deg.to_radians().sin_cos();
                let (dx, dy) = (p[0] - centre[0], p[1] - centre[1]);
                // Into the rectangle's own axes.
                let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
                let r = radius.clamp(0.0, size[0].min(size[1]) / 2.0);
                let qx = u.abs() - (size[0] / 2.0 - r);
                let qy = v.abs() - (size[1] / 2.0 - r);
                qx.max(0.0).hypot(qy.max(0.0)) + qx.max(qy).min(0.0) - r
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
    pub outline: Outline,
    /// Component reference (`%TO.C`, X2), e.g. `U3`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub component: Option<String>,
    /// Pin number or name (`%TO.P`, X2), e.g. `14`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pin: Option<String>,
    /// The aperture or object that drew it, e.g. `D12` or `region` (for pad classes).
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
    pub rotation_rad: f64,
    pub tx: f64,
    pub ty: f64,
}

impl Rigid {
    pub const IDENTITY: Rigid = Rigid {
        rotation_rad: 0.0,
        tx: 0.0,
        ty: 0.0,
    };

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
