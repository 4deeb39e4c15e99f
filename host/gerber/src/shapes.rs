//! Geometry of the layer's objects, mm: polygons for apertures, aperture macros, strokes,
//! arcs and regions, and the exact outline of plain flashes (circle, rounded rectangle).
//!
//! Curves become polygons whose chords stay within [`CHORD_MM`] of the true curve; unions and
//! differences go through `overlay` (i_overlay 9 on geo's polygon types).

use crate::overlay;
use crate::pads::{Outline, Point};
use geo::{Coord, LineString, MultiPolygon, Polygon};
use std::collections::HashMap;
use std::f64::consts::{PI, TAU};

/// Largest distance between a curve and the chords that replace it, mm (1 um).
pub(super) const CHORD_MM: f64 = 0.001;

/// Number of chords for an arc of `radius` (mm) through `sweep` (rad), so that no chord is
/// farther than [`CHORD_MM`] from the arc (at least 1; at most 4096 for a full turn).
pub(super) fn arc_segments(radius: f64, sweep: f64) -> usize {
    let sweep = sweep.abs();
    if radius.is_nan() || radius <= CHORD_MM || !sweep.is_finite() {
        return 1.max((sweep / (PI / 2.0)).ceil() as usize);
    }
    let step = 2.0 * (1.0 - CHORD_MM / radius).clamp(-1.0, 1.0).acos();
    let n = (sweep / step).ceil();
    (n as usize).clamp(1, 4096)
}

/// A polygon from point lists (rings not closed), oriented counter-clockwise outside.
pub(super) fn polygon(exterior: &[Point], holes: &[Vec<Point>]) -> Polygon<f64> {
    let ring = |r: &[Point]| -> LineString<f64> {
        LineString::from(
            r.iter()
                .map(|p| Coord { x: p[0], y: p[1] })
                .collect::<Vec<_>>(),
        )
    };
    oriented(Polygon::new(
        ring(exterior),
        holes.iter().map(|h| ring(h)).collect(),
    ))
}

/// `p` with its exterior counter-clockwise and its holes clockwise (geo's default
/// orientation), reversing rings in place: no copy when they already are.
pub(super) fn oriented(mut p: Polygon<f64>) -> Polygon<f64> {
    use geo::Winding;
    p.exterior_mut(|r| {
        if r.is_cw() {
            r.0.reverse();
        }
    });
    p.interiors_mut(|holes| {
        for r in holes {
            if r.is_ccw() {
                r.0.reverse();
            }
        }
    });
    p
}

/// Points of a circle of diameter `d` about `c`.
pub(super) fn circle_points(c: Point, d: f64) -> Vec<Point> {
    let r = d / 2.0;
    let n = arc_segments(r, TAU).max(8);
    (0..n)
        .map(|i| {
            let a = TAU * i as f64 / n as f64;
            [c[0] + r * a.cos(), c[1] + r * a.sin()]
        })
        .collect()
}

/// Corners of a `w` x `h` rectangle about `c` turned by `rot_deg`.
pub(super) fn rect_points(c: Point, w: f64, h: f64, rot_deg: f64) -> Vec<Point> {
    let (s, k) = rot_deg.to_radians().sin_cos();
    [[-w, -h], [w, -h], [w, h], [-w, h]]
        .iter()
        .map(|p| {
            let (x, y) = (p[0] / 2.0, p[1] / 2.0);
            [c[0] + k * x - s * y, c[1] + s * x + k * y]
        })
        .collect()
}

/// Points of a rounded rectangle (`Outline::RoundRect`) as a polygon.
pub(super) fn round_rect_points(c: Point, w: f64, h: f64, r: f64, rot_deg: f64) -> Vec<Point> {
    let r = r.clamp(0.0, w.min(h) / 2.0);
    if r <= 0.0 {
        return rect_points(c, w, h, rot_deg);
    }
    let (s, k) = rot_deg.to_radians().sin_cos();
    let (hx, hy) = (w / 2.0 - r, h / 2.0 - r);
    let n = arc_segments(r, PI / 2.0).max(2);
    let mut pts = Vec::with_capacity(4 * (n + 1));
    for (q, (cx, cy)) in [(hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)]
        .iter()
        .enumerate()
    {
        for i in 0..=n {
            let a = (q as f64 + i as f64 / n as f64) * PI / 2.0;
            let (x, y) = (cx + r * a.cos(), cy + r * a.sin());
            pts.push([c[0] + k * x - s * y, c[1] + s * x + k * y]);
        }
    }
    dedup(pts)
}

/// Removes consecutive duplicates (and a last point equal to the first).
pub(super) fn dedup(mut pts: Vec<Point>) -> Vec<Point> {
    pts.dedup_by(|a, b| (a[0] - b[0]).abs() < 1e-12 && (a[1] - b[1]).abs() < 1e-12);
    while pts.len() > 1 {
        let (f, l) = (pts[0], pts[pts.len() - 1]);
        if (f[0] - l[0]).abs() < 1e-12 && (f[1] - l[1]).abs() < 1e-12 {
            pts.pop();
        } else {
            break;
        }
    }
    pts
}

/// Convex hull (Andrew's monotone chain), counter-clockwise.
pub(super) fn convex_hull(mut pts: Vec<Point>) -> Vec<Point> {
    pts.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    pts.dedup();
    if pts.len() < 3 {
        return pts;
    }
    let cross = |o: Point, a: Point, b: Point| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let half = |seq: &mut dyn Iterator<Item = &Point>| -> Vec<Point> {
        let mut h: Vec<Point> = Vec::new();
        for &p in seq {
            while h.len() >= 2 && cross(h[h.len() - 2], h[h.len() - 1], p) <= 0.0 {
                h.pop();
            }
            h.push(p);
        }
        h.pop(); // it starts the other half
        h
    };
    let mut hull = half(&mut pts.iter());
    hull.extend(half(&mut pts.iter().rev()));
    hull
}

/// A stroke of a circular aperture of diameter `d` from `a` to `b`: a capsule, its two caps
/// half circles about the ends (symmetric, so its centroid is the segment's middle).
pub(super) fn capsule(a: Point, b: Point, d: f64) -> Vec<Point> {
    let r = d / 2.0;
    if (b[0] - a[0]).hypot(b[1] - a[1]) < 1e-12 {
        return circle_points(a, d);
    }
    let theta = (b[1] - a[1]).atan2(b[0] - a[0]);
    let n = arc_segments(r, PI).max(4);
    let mut pts = Vec::with_capacity(2 * (n + 1));
    for (c, start) in [(b, theta - PI / 2.0), (a, theta + PI / 2.0)] {
        for i in 0..=n {
            let t = start + PI * i as f64 / n as f64;
            pts.push([c[0] + r * t.cos(), c[1] + r * t.sin()]);
        }
    }
    pts
}

/// A stroke of a `w` x `h` rectangular aperture from `a` to `b`: the hull of both rectangles.
pub(super) fn swept_rect(a: Point, b: Point, w: f64, h: f64) -> Vec<Point> {
    let mut pts = rect_points(a, w, h, 0.0);
    pts.extend(rect_points(b, w, h, 0.0));
    convex_hull(pts)
}

/// An arc's start angle about `centre` and its sweep (rad, `0..=2 pi`), turning clockwise or
/// not; a full turn when `start == end`.
fn arc_sweep(start: Point, end: Point, centre: Point, clockwise: bool) -> (f64, f64) {
    let a0 = (start[1] - centre[1]).atan2(start[0] - centre[0]);
    let a1 = (end[1] - centre[1]).atan2(end[0] - centre[0]);
    let mut sweep = if clockwise { a0 - a1 } else { a1 - a0 };
    sweep = sweep.rem_euclid(TAU);
    let same = (start[0] - end[0]).abs() < 1e-9 && (start[1] - end[1]).abs() < 1e-9;
    if same || sweep < 1e-12 {
        sweep = if same { TAU } else { 0.0 };
    }
    (a0, sweep)
}

/// Points along an arc from `start` (excluded) to `end` (included) about `centre`, turning
/// clockwise or not; a full turn when `start == end`. The radius goes linearly from the
/// start's to the end's (files round them differently).
pub(super) fn arc_points(start: Point, end: Point, centre: Point, clockwise: bool) -> Vec<Point> {
    let (r0, r1) = (
        (start[0] - centre[0]).hypot(start[1] - centre[1]),
        (end[0] - centre[0]).hypot(end[1] - centre[1]),
    );
    let (a0, sweep) = arc_sweep(start, end, centre, clockwise);
    let n = arc_segments(r0.max(r1), sweep);
    let dir = if clockwise { -1.0 } else { 1.0 };
    let mut pts = Vec::with_capacity(n);
    for i in 1..=n {
        let t = i as f64 / n as f64;
        if i == n {
            pts.push(end);
        } else {
            let a = a0 + dir * sweep * t;
            let r = r0 + (r1 - r0) * t;
            pts.push([centre[0] + r * a.cos(), centre[1] + r * a.sin()]);
        }
    }
    pts
}

/// What a disc of diameter `d` sweeps along an arc from `start` to `end` about `centre`
/// (as [`arc_points`] turns): the annular sector between the radii `R - d/2` and `R + d/2`
/// and the discs at both ends (a full turn: the annulus alone), each curve within
/// [`CHORD_MM`]. Three polygons to unite instead of a capsule per chord: a stroke along a
/// long arc costs what its outline has, not chords x disc. `None` when the band has no hole
/// side (the disc reaches the centre) or the radius changes along the arc by more than a
/// tenth of the disc (a spiral): the caller unites the chords' capsules then.
pub(super) fn arc_band(
    start: Point,
    end: Point,
    centre: Point,
    clockwise: bool,
    d: f64,
) -> Option<Vec<Polygon<f64>>> {
    let r = d / 2.0;
    let (r0, r1) = (
        (start[0] - centre[0]).hypot(start[1] - centre[1]),
        (end[0] - centre[0]).hypot(end[1] - centre[1]),
    );
    let inner = r0.min(r1) - r;
    if inner.is_nan() || inner <= CHORD_MM || (r1 - r0).abs() > 0.1 * d {
        return None;
    }
    let (a0, sweep) = arc_sweep(start, end, centre, clockwise);
    let dir = if clockwise { -1.0 } else { 1.0 };
    let n = arc_segments(r0.max(r1) + r, sweep).max(1);
    let at = |t: f64, off: f64| -> Point {
        let a = a0 + dir * sweep * t;
        let rr = r0 + (r1 - r0) * t + off;
        [centre[0] + rr * a.cos(), centre[1] + rr * a.sin()]
    };
    if sweep >= TAU {
        let outer: Vec<Point> = (0..n).map(|i| at(i as f64 / n as f64, r)).collect();
        let inner: Vec<Point> = (0..n).map(|i| at(i as f64 / n as f64, -r)).collect();
        return Some(vec![polygon(&outer, &[inner])]);
    }
    if sweep == 0.0 {
        return None;
    }
    let mut band: Vec<Point> = (0..=n).map(|i| at(i as f64 / n as f64, r)).collect();
    band.extend((0..=n).rev().map(|i| at(i as f64 / n as f64, -r)));
    Some(vec![
        polygon(&band, &[]),
        polygon(&circle_points(start, d), &[]),
        polygon(&circle_points(end, d), &[]),
    ])
}

/// Polygons united in one overlay at most; more are united in halves, then the halves.
const CASCADE: usize = 32;

/// Union of polygons. Up to [`CASCADE`] in one overlay; more in a balanced cascade (each half
/// united, then the two): one overlay of many polygons whose edges overlap along their length
/// (a step and repeat of a long line, 0.02 mm apart) costs the square of their count, while
/// the halves' unions stay as small as the result (880 such copies: 3.5 s in one overlay).
pub(super) fn union_all(polys: &[Polygon<f64>]) -> MultiPolygon<f64> {
    union_on(polys, overlay::Grid::of(polys).as_ref())
}

/// [`union_all`] on `grid` (every level of the cascade on the same one: the halves meet on it).
pub(super) fn union_on(polys: &[Polygon<f64>], grid: Option<&overlay::Grid>) -> MultiPolygon<f64> {
    if polys.len() <= CASCADE {
        // A single polygon goes through the overlay too: resolves self-touching contours
        // (cut-ins) into holes.
        return overlay::union(polys, grid);
    }
    let (a, b) = polys.split_at(polys.len() / 2);
    overlay::union(
        union_on(a, grid).iter().chain(union_on(b, grid).iter()),
        grid,
    )
}

/// An affine map of the plane: `p -> [a p.x + b p.y + tx, c p.x + d p.y + ty]`.
#[derive(Clone, Copy, Debug)]
pub(super) struct Affine {
    pub m: [f64; 4],
    pub t: [f64; 2],
}

impl Affine {
    pub fn apply(&self, p: Point) -> Point {
        [
            self.m[0] * p[0] + self.m[1] * p[1] + self.t[0],
            self.m[2] * p[0] + self.m[3] * p[1] + self.t[1],
        ]
    }
}

/// `mp` mapped by `f`. The polygons of the layer are oriented (exteriors counter-clockwise,
/// holes clockwise: `polygon`, and the overlay's output): a map that keeps orientation keeps
/// theirs, a mirroring reverses every ring, and only a degenerate map is re-oriented ring by
/// ring (flashes are mapped each time their shape is needed: no winding sums on that path).
pub(super) fn map_multi(mp: &MultiPolygon<f64>, f: &Affine) -> MultiPolygon<f64> {
    let det = f.m[0] * f.m[3] - f.m[1] * f.m[2];
    let ring = |ls: &LineString<f64>| -> LineString<f64> {
        let mut r: LineString<f64> = ls
            .coords()
            .map(|c| {
                let q = f.apply([c.x, c.y]);
                Coord { x: q[0], y: q[1] }
            })
            .collect();
        if det < 0.0 {
            r.0.reverse();
        }
        r
    };
    MultiPolygon::new(
        mp.iter()
            .map(|p| {
                let q = Polygon::new(ring(p.exterior()), p.interiors().iter().map(ring).collect());
                if det.is_normal() {
                    q
                } else {
                    oriented(q)
                }
            })
            .collect(),
    )
}

/// A polygon of geo as an [`Outline::Polygon`] (rings not closed).
pub(super) fn outline_of(p: &Polygon<f64>) -> Outline {
    let ring = |ls: &LineString<f64>| -> Vec<Point> {
        let mut v: Vec<Point> = ls.coords().map(|c| [c.x, c.y]).collect();
        if v.len() > 1 && v.first() == v.last() {
            v.pop();
        }
        v
    };
    Outline::Polygon {
        exterior: ring(p.exterior()),
        holes: p.interiors().iter().map(ring).collect(),
    }
}

/// Evaluates an aperture-macro arithmetic expression: decimals, `$n` variables, `+ - x X /`,
/// unary minus and brackets, with the usual precedence. Undefined variables are 0 (Gerber
/// spec 4.5.4.2: missing parameters are 0).
pub(super) fn eval_expr(text: &str, vars: &HashMap<u32, f64>) -> Result<f64, String> {
    struct P<'a> {
        s: &'a [u8],
        i: usize,
        vars: &'a HashMap<u32, f64>,
        depth: usize,
    }
    impl P<'_> {
        fn peek(&mut self) -> Option<u8> {
            while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
                self.i += 1;
            }
            self.s.get(self.i).copied()
        }
        fn expr(&mut self) -> Result<f64, String> {
            let mut v = self.term()?;
            while let Some(c) = self.peek() {
                match c {
                    b'+' => {
                        self.i += 1;
                        v += self.term()?;
                    }
                    b'-' => {
                        self.i += 1;
                        v -= self.term()?;
                    }
                    _ => break,
                }
            }
            Ok(v)
        }
        fn term(&mut self) -> Result<f64, String> {
            let mut v = self.factor()?;
            while let Some(c) = self.peek() {
                match c {
                    b'x' | b'X' => {
                        self.i += 1;
                        v *= self.factor()?;
                    }
                    b'/' => {
                        self.i += 1;
                        v /= self.factor()?;
                    }
                    _ => break,
                }
            }
            Ok(v)
        }
        fn factor(&mut self) -> Result<f64, String> {
            self.depth += 1;
            if self.depth > 64 {
                return Err("expression nested too deeply".into());
            }
            let r = match self.peek() {
                Some(b'-') => {
                    self.i += 1;
                    self.factor().map(|v| -v)
                }
                Some(b'+') => {
                    self.i += 1;
                    self.factor()
                }
                Some(b'(') => {
                    self.i += 1;
                    let v = self.expr()?;
                    if self.peek() != Some(b')') {
                        return Err("missing ')'".into());
                    }
                    self.i += 1;
                    Ok(v)
                }
                Some(b'$') => {
                    self.i += 1;
                    let start = self.i;
                    while self.i < self.s.len() && self.s[self.i].is_ascii_digit() {
                        self.i += 1;
                    }
                    let n: u32 = std::str::from_utf8(&self.s[start..self.i])
                        .ok()
                        .and_then(|t| t.parse().ok())
                        .ok_or("'$' without a variable number")?;
                    Ok(self.vars.get(&n).copied().unwrap_or(0.0))
                }
                Some(c) if c.is_ascii_digit() || c == b'.' => {
                    let start = self.i;
                    while self.i < self.s.len()
                        && (self.s[self.i].is_ascii_digit() || self.s[self.i] == b'.')
                    {
                        self.i += 1;
                    }
                    std::str::from_utf8(&self.s[start..self.i])
                        .ok()
                        .and_then(|t| t.parse::<f64>().ok())
                        .ok_or_else(|| "bad number".to_string())
                }
                Some(c) => Err(format!("unexpected {:?}", c as char)),
                None => Err("unexpected end".into()),
            };
            self.depth -= 1;
            r
        }
    }
    let mut p = P {
        s: text.as_bytes(),
        i: 0,
        vars,
        depth: 0,
    };
    let v = p.expr()?;
    if p.peek().is_some() {
        return Err(format!("unexpected text after {:?}", &text[..p.i]));
    }
    Ok(v)
}

/// The exact shape of a plain flash, relative to the flash point, mm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Exact {
    Circle { d: f64 },
    RoundRect { w: f64, h: f64, r: f64, rot: f64 },
}

impl Exact {
    /// The outline at `at` after the flash transform `f` (rotation, mirroring, scaling; its
    /// translation is ignored).
    pub fn placed(&self, at: Point, f: &Affine) -> Outline {
        let scale = (f.m[0] * f.m[3] - f.m[1] * f.m[2]).abs().sqrt();
        match *self {
            Exact::Circle { d } => Outline::Circle {
                centre: at,
                diameter: d * scale,
            },
            Exact::RoundRect { w, h, r, rot } => {
                // The image of the rectangle's first axis gives the new rotation.
                let u = rot.to_radians();
                let (ux, uy) = (u.cos(), u.sin());
                let ax = [f.m[0] * ux + f.m[1] * uy, f.m[2] * ux + f.m[3] * uy];
                let rotation_deg = normalise_deg(ax[1].atan2(ax[0]).to_degrees());
                Outline::RoundRect {
                    centre: at,
                    size: [w * scale, h * scale],
                    radius: r * scale,
                    rotation_deg,
                }
            }
        }
    }
}

/// An angle in degrees into (-180, 180]; values within 1e-9 of a whole degree are snapped.
pub(super) fn normalise_deg(a: f64) -> f64 {
    let mut a = a.rem_euclid(360.0);
    if a > 180.0 {
        a -= 360.0;
    }
    let r = a.round();
    if (a - r).abs() < 1e-9 {
        a = r;
    }
    if a == -180.0 {
        180.0
    } else if a == 0.0 {
        0.0 // no -0
    } else {
        a
    }
}

/// One evaluated macro primitive, mm, with the macro's rotation applied.
#[derive(Clone, Debug)]
pub(super) enum Prim {
    Circle {
        c: Point,
        d: f64,
    },
    /// A rectangle (vector line, centre line, 4-point outline that is a rectangle).
    Rect {
        c: Point,
        w: f64,
        h: f64,
        rot: f64,
    },
    /// Anything else.
    Poly(Vec<Point>),
}

impl Prim {
    pub fn points(&self) -> Vec<Point> {
        match *self {
            Prim::Circle { c, d } => circle_points(c, d),
            Prim::Rect { c, w, h, rot } => rect_points(c, w, h, rot),
            Prim::Poly(ref p) => p.clone(),
        }
    }
}

/// Recognises a flash of an aperture macro made of primitives (all exposure on) as a circle
/// or a rounded rectangle: a single circle or rectangle; or four equal circles on the corners
/// of a rectangle with only rectangles or polygons between them (KiCad's `RoundRect`,
/// Altium's rounded rectangles), provided the union's area is that of the rounded rectangle
/// (within 0.2 %, the polygons' chords). `union_area` is the area of the evaluated union.
pub(super) fn recognise(prims: &[Prim], union_area: f64) -> Option<Exact> {
    let rot_of = |rot: f64| normalise_deg(rot);
    if let [one] = prims {
        return match *one {
            Prim::Circle { c, d } if c[0].abs() < 1e-9 && c[1].abs() < 1e-9 => {
                Some(Exact::Circle { d })
            }
            // An offset shape: exact about its own centre but not about the flash point;
            // leave it to the polygon path.
            Prim::Rect { c, w, h, rot } if c[0].abs() < 1e-9 && c[1].abs() < 1e-9 => {
                Some(Exact::RoundRect {
                    w,
                    h,
                    r: 0.0,
                    rot: rot_of(rot),
                })
            }
            _ => None,
        };
    }
    let circles: Vec<(Point, f64)> = prims
        .iter()
        .filter_map(|p| match *p {
            Prim::Circle { c, d } => Some((c, d)),
            _ => None,
        })
        .collect();
    if circles.len() != 4 {
        return None;
    }
    let d = circles[0].1;
    if d <= 0.0
        || circles
            .iter()
            .any(|&(_, e)| (e - d).abs() > 1e-9 * d.max(1.0))
    {
        return None;
    }
    let centre = [
        circles.iter().map(|c| c.0[0]).sum::<f64>() / 4.0,
        circles.iter().map(|c| c.0[1]).sum::<f64>() / 4.0,
    ];
    if centre[0].abs() > 1e-9 || centre[1].abs() > 1e-9 {
        return None;
    }
    // Order the corners by angle about the centre and check the right angles.
    let mut pts: Vec<Point> = circles.iter().map(|c| c.0).collect();
    pts.sort_by(|a, b| a[1].atan2(a[0]).total_cmp(&b[1].atan2(b[0])));
    let edge = |i: usize| {
        let (a, b) = (pts[i], pts[(i + 1) % 4]);
        [b[0] - a[0], b[1] - a[1]]
    };
    let (e0, e1) = (edge(0), edge(1));
    let (l0, l1) = (e0[0].hypot(e0[1]), e1[0].hypot(e1[1]));
    let tol = 1e-6;
    let rect_ok = (0..4).all(|i| {
        let (a, b) = (edge(i), edge((i + 1) % 4));
        (a[0] * b[0] + a[1] * b[1]).abs() <= tol * (1.0 + l0 * l1)
    }) && (edge(2)[0] + e0[0]).abs() < tol
        && (edge(2)[1] + e0[1]).abs() < tol;
    if !rect_ok {
        return None;
    }
    let r = d / 2.0;
    let rot = if l0 > 0.0 {
        e0[1].atan2(e0[0]).to_degrees()
    } else {
        0.0
    };
    let exact = Exact::RoundRect {
        w: l0 + d,
        h: l1 + d,
        r,
        rot: rot_of(rot),
    };
    // Everything else must lie inside it, and together they must fill it.
    let outline = exact.placed([0.0, 0.0], &IDENTITY);
    let inside = prims.iter().all(|p| match p {
        Prim::Circle { .. } => true,
        _ => p
            .points()
            .iter()
            .all(|&q| outline.signed_distance(q) <= 1e-6),
    });
    let area = outline.area();
    // The union's circles are chords within 1 um: on small radii that loses more than the
    // tolerance, so compare with the same chords as well.
    let pts = round_rect_points([0.0, 0.0], l0 + d, l1 + d, r, rot_of(rot));
    let n = pts.len();
    let chord_area = (0..n)
        .map(|i| {
            let (p, q) = (pts[i], pts[(i + 1) % n]);
            p[0] * q[1] - q[0] * p[1]
        })
        .sum::<f64>()
        .abs()
        / 2.0;
    let close = |a: f64| (union_area - a).abs() <= 2e-3 * area;
    if inside && (close(area) || close(chord_area)) {
        Some(exact)
    } else {
        None
    }
}

/// The identity map.
pub(super) const IDENTITY: Affine = Affine {
    m: [1.0, 0.0, 0.0, 1.0],
    t: [0.0, 0.0],
};

/// Area of a multipolygon, mm^2.
pub(super) fn area(mp: &MultiPolygon<f64>) -> f64 {
    use geo::Area;
    mp.unsigned_area()
}

#[cfg(test)]
mod tests {
    use super::*;
    // geo's own overlay (i_overlay 4) as the reference for the symmetric differences.
    use geo::BooleanOps;

    #[test]
    fn chords_stay_within_a_micron() {
        for r in [0.05, 0.3, 1.0, 10.0] {
            let n = arc_segments(r, TAU);
            let sagitta = r * (1.0 - (PI / n as f64).cos());
            assert!(
                sagitta <= CHORD_MM + 1e-12,
                "r {r}: n {n} sagitta {sagitta}"
            );
        }
    }

    #[test]
    fn expressions_follow_precedence() {
        let vars = HashMap::from([(1, 2.0), (2, 0.5)]);
        let e = |s| eval_expr(s, &vars).expect(s);
        assert_eq!(e("$1+$1"), 4.0);
        assert_eq!(e("1+2x3"), 7.0);
        assert_eq!(e("(1+2)x3"), 9.0);
        assert_eq!(e("-$1x2/4"), -1.0);
        assert_eq!(e("$1-$2-$2"), 1.0);
        assert_eq!(e("$9"), 0.0);
        assert!(eval_expr("1+", &vars).is_err());
        assert!(eval_expr("(1", &vars).is_err());
        assert!(eval_expr("1$", &vars).is_err());
        let deep = "(".repeat(200) + "1" + &")".repeat(200);
        assert!(eval_expr(&deep, &vars).is_err());
    }

    #[test]
    fn convex_hull_keeps_the_corners() {
        let mut pts = rect_points([0.0, 0.0], 0.2, 0.4, 0.0);
        pts.extend(rect_points([1.0, 0.0], 0.2, 0.4, 0.0));
        pts.push([0.5, 0.0]); // inside
        let h = convex_hull(pts);
        assert_eq!(h.len(), 4, "{h:?}");
        let a = area(&MultiPolygon::new(vec![polygon(&h, &[])]));
        assert!((a - 1.2 * 0.4).abs() < 1e-12, "{a}");
    }

    #[test]
    fn arcs_run_the_right_way() {
        // Quarter turn counter-clockwise from (1,0) to (0,1) about the origin.
        let p = arc_points([1.0, 0.0], [0.0, 1.0], [0.0, 0.0], false);
        assert!(p.iter().all(|q| q[0] >= -1e-12 && q[1] >= -1e-12));
        // The same ends clockwise go the long way round.
        let p = arc_points([1.0, 0.0], [0.0, 1.0], [0.0, 0.0], true);
        assert!(p.iter().any(|q| q[0] < -0.5));
        // Same start and end: a full circle.
        let p = arc_points([1.0, 0.0], [1.0, 0.0], [0.0, 0.0], true);
        assert_eq!(p.len(), arc_segments(1.0, TAU));
        assert!(p.iter().all(|q| (q[0].hypot(q[1]) - 1.0).abs() < 1e-12));
    }

    #[test]
    fn round_rect_points_match_the_outline_area() {
        let pts = round_rect_points([1.0, 2.0], 1.2, 0.6, 0.1, 30.0);
        let poly = polygon(&pts, &[]);
        let exact = Outline::RoundRect {
            centre: [1.0, 2.0],
            size: [1.2, 0.6],
            radius: 0.1,
            rotation_deg: 30.0,
        };
        let a = area(&MultiPolygon::new(vec![poly]));
        // Chords within 1 um inside the corners: at most arc length x 1 um less.
        assert!(
            a < exact.area() && exact.area() - a < 2.0 * PI * 0.1 * CHORD_MM,
            "{a}"
        );
    }

    /// The swept band of a disc along an arc is the union of the chords' capsules (the
    /// definition it replaces), within the chord tolerance: their symmetric difference is
    /// under 2 um times the band's outline, over arcs short and long, both ways, and a full
    /// turn.
    #[test]
    fn arc_band_is_the_union_of_the_chords_capsules() {
        let cases = [
            ([1.0, 0.0], [0.0, 1.0], [0.0, 0.0], false, 0.2),
            ([1.0, 0.0], [0.0, -1.0], [0.0, 0.0], false, 0.3),
            ([2.0, 1.0], [2.0, 1.0], [1.0, 1.0], true, 0.25),
            ([5.0, 0.0], [-5.0, 0.0], [0.0, 0.0], true, 1.0),
            ([0.5, 0.0], [0.4, 0.3], [0.0, 0.0], false, 0.4),
        ];
        for (start, end, centre, cw, d) in cases {
            let band = union_all(&arc_band(start, end, centre, cw, d).expect("a band"));
            let path = arc_points(start, end, centre, cw);
            let mut a = start;
            let caps: Vec<Polygon<f64>> = path
                .iter()
                .map(|&b| {
                    let p = polygon(&capsule(a, b, d), &[]);
                    a = b;
                    p
                })
                .collect();
            let caps = union_all(&caps);
            let diff = area(&band.xor(&caps));
            let r = (start[0] - centre[0]).hypot(start[1] - centre[1]);
            let outline = 2.0 * (r + d) * TAU + PI * d;
            assert!(
                diff < 2.0 * CHORD_MM * outline,
                "{start:?} -> {end:?}: {diff} mm^2 apart (outline {outline} mm)"
            );
            assert!(area(&band) > 0.9 * area(&caps));
        }
        // A disc that covers the centre, a spiral: the caller's capsules.
        assert!(arc_band([0.1, 0.0], [0.0, 0.1], [0.0, 0.0], false, 0.3).is_none());
        assert!(arc_band([1.0, 0.0], [0.0, 2.0], [0.0, 0.0], false, 0.3).is_none());
    }

    /// Mapped shapes keep geo's default orientation under rotations, mirrorings and scalings.
    #[test]
    fn mapped_shapes_stay_oriented() {
        use geo::Winding;
        let ring = MultiPolygon::new(vec![polygon(
            &round_rect_points([0.3, 0.1], 2.0, 1.0, 0.2, 0.0),
            &[circle_points([0.3, 0.1], 0.5)],
        )]);
        for m in [
            [1.0, 0.0, 0.0, 1.0],
            [-1.0, 0.0, 0.0, 1.0],
            [1.0, 0.0, 0.0, -1.0],
            [0.0, -1.0, 1.0, 0.0],
            [0.0, 1.0, 1.0, 0.0],
            [2.0, 0.3, -0.1, 0.5],
        ] {
            let out = map_multi(&ring, &Affine { m, t: [5.0, -2.0] });
            for p in &out {
                assert!(p.exterior().is_ccw(), "{m:?}");
                assert!(p.interiors().iter().all(|r| r.is_cw()), "{m:?}");
            }
            assert!((area(&out) - area(&ring) * (m[0] * m[3] - m[1] * m[2]).abs()).abs() < 1e-9);
        }
    }
}
