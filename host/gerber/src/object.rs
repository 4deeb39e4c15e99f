//! The layer's objects as the interpreter leaves them for the merging: compact, so that a
//! layer of [`MAX_OBJECTS`](super::MAX_OBJECTS) objects stays within the memory the reader
//! promises (`docs/inspection.md`, "At scale").
//!
//! A flash holds its aperture (shared) and where it was flashed, not a polygon: the polygon is
//! made when the merging needs it (two objects whose boxes meet, a group of several objects),
//! and a lone plain flash never needs it (its pad is the exact outline). Strokes and regions
//! hold their polygon, shared by the copies of a step and repeat. The flash transforms, the
//! step-and-repeat offsets and the X2 attributes (few distinct values in a layer) live in
//! tables of the [`Layer`], objects hold their index.

use super::shapes::{
    capsule, circle_points, map_multi, polygon, round_rect_points, swept_rect, Affine, Exact,
};
use crate::pads::{Outline, Point, Rigid};
use geo::{Coord, LineString, MultiPolygon, Polygon};
use std::borrow::Cow;
use std::sync::Arc;

/// An aperture ready to flash or draw, about its origin, mm. Standard apertures keep their
/// parameters (their polygon is made on use); a macro keeps its evaluated polygon.
#[derive(Debug)]
pub(super) enum ApertureShape {
    /// `C`: a disc of diameter `d` with an optional round hole (`hole` 0: none).
    Circle { d: f64, hole: f64 },
    /// `R` or `O`: a `w` x `h` rectangle (an obround: corners rounded by half the smaller
    /// side), with an optional round hole.
    Rect {
        w: f64,
        h: f64,
        obround: bool,
        hole: f64,
    },
    /// `P`: a regular polygon of `n` vertices on a circle of diameter `d`, the first at `rot`
    /// degrees, with an optional round hole.
    Regular { d: f64, n: u32, rot: f64, hole: f64 },
    /// An aperture macro, evaluated.
    Macro(Box<MacroShape>),
}

/// An evaluated aperture macro.
#[derive(Debug)]
pub(super) struct MacroShape {
    pub shape: MultiPolygon<f64>,
    /// The circle or rounded rectangle it draws, when recognised.
    pub exact: Option<Exact>,
    /// The macro's name, with the recognised size.
    pub class: String,
}

fn holes(hole: f64) -> Vec<Vec<Point>> {
    if hole > 0.0 {
        vec![circle_points([0.0, 0.0], hole)]
    } else {
        vec![]
    }
}

impl ApertureShape {
    /// The polygon about the origin (none for a zero-size circle or rectangle).
    pub fn polygon(&self) -> Cow<'_, MultiPolygon<f64>> {
        match self {
            ApertureShape::Circle { d, hole } => Cow::Owned(if *d > 0.0 {
                MultiPolygon::new(vec![polygon(&circle_points([0.0, 0.0], *d), &holes(*hole))])
            } else {
                MultiPolygon::new(vec![])
            }),
            ApertureShape::Rect {
                w,
                h,
                obround,
                hole,
            } => Cow::Owned(if *w > 0.0 && *h > 0.0 {
                let r = if *obround { w.min(*h) / 2.0 } else { 0.0 };
                MultiPolygon::new(vec![polygon(
                    &round_rect_points([0.0, 0.0], *w, *h, r, 0.0),
                    &holes(*hole),
                )])
            } else {
                MultiPolygon::new(vec![])
            }),
            ApertureShape::Regular { d, n, rot, hole } => {
                let pts: Vec<Point> = (0..*n)
                    .map(|i| {
                        let a = (rot + 360.0 * f64::from(i) / f64::from(*n)).to_radians();
                        [d / 2.0 * a.cos(), d / 2.0 * a.sin()]
                    })
                    .collect();
                Cow::Owned(MultiPolygon::new(vec![polygon(&pts, &holes(*hole))]))
            }
            ApertureShape::Macro(m) => Cow::Borrowed(&m.shape),
        }
    }

    /// Whether a flash of it draws nothing.
    pub fn is_empty(&self) -> bool {
        match self {
            ApertureShape::Circle { d, .. } => *d <= 0.0,
            ApertureShape::Rect { w, h, .. } => !(*w > 0.0 && *h > 0.0),
            ApertureShape::Regular { .. } => false,
            ApertureShape::Macro(m) => m.shape.0.is_empty(),
        }
    }

    /// The exact outline about the origin: a plain circle or rounded rectangle (no hole).
    pub fn exact(&self) -> Option<Exact> {
        match *self {
            ApertureShape::Circle { d, hole } => {
                (d > 0.0 && hole == 0.0).then_some(Exact::Circle { d })
            }
            ApertureShape::Rect {
                w,
                h,
                obround,
                hole,
            } => (hole == 0.0 && w > 0.0 && h > 0.0).then_some(Exact::RoundRect {
                w,
                h,
                r: if obround { w.min(h) / 2.0 } else { 0.0 },
                rot: 0.0,
            }),
            ApertureShape::Regular { .. } => None,
            ApertureShape::Macro(ref m) => m.exact,
        }
    }

    /// The aperture class of its pads (`R 0.60x0.30`, `C 0.25`, `P 1 n6`, a macro's name).
    pub fn class(&self) -> String {
        match self {
            ApertureShape::Circle { d, .. } => format!("C {}", num(*d)),
            ApertureShape::Rect { w, h, obround, .. } => {
                format!(
                    "{} {}x{}",
                    if *obround { "O" } else { "R" },
                    num(*w),
                    num(*h)
                )
            }
            ApertureShape::Regular { d, n, .. } => format!("P {} n{n}", num(*d)),
            ApertureShape::Macro(m) => m.class.clone(),
        }
    }

    /// What it sweeps when drawn (D01).
    pub fn stroke(&self) -> Stroke {
        match *self {
            ApertureShape::Circle { d, .. } => Stroke::Circle(d),
            ApertureShape::Rect {
                w,
                h,
                obround: false,
                ..
            } => Stroke::Rect(w, h),
            _ => Stroke::None,
        }
    }
}

/// `R 0.60x0.30`-style number: at least 2 and at most 3 decimals.
pub(super) fn num(v: f64) -> String {
    let s = format!("{v:.3}");
    match s.strip_suffix('0') {
        Some(t) => t.to_string(),
        None => s,
    }
}

/// What an aperture sweeps when drawn.
#[derive(Clone, Copy, Debug)]
pub(super) enum Stroke {
    /// A circle of this diameter.
    Circle(f64),
    /// A rectangle of these sides.
    Rect(f64, f64),
    /// Not allowed for D01 by the specification (obround, polygon, macro).
    None,
}

/// What drew a stroke or region polygon (for the pad's class).
#[derive(Clone, Debug)]
pub(super) enum Class {
    Region,
    /// A stroke (D01) of this aperture.
    Stroke(Arc<ApertureShape>),
    /// A class given by name (tests).
    #[cfg(test)]
    Named(Arc<str>),
}

/// What an object draws.
#[derive(Clone, Debug)]
pub(super) enum Geom {
    /// A flash (D03) of `ap` at `at`, by the flash transform `linear` (an index into
    /// [`Layer::linears`]: mirroring, rotation, scaling).
    Flash {
        ap: Arc<ApertureShape>,
        at: Point,
        linear: u32,
    },
    /// A straight stroke (D01) of a circle or rectangle `ap` from `a` to `b`: its polygon
    /// (a capsule or the hull of the two rectangles) is made on use.
    Line {
        ap: Arc<ApertureShape>,
        a: Point,
        b: Point,
    },
    /// A stroke along an arc or a path, or a region: its polygon, mm (flat, shared by the
    /// copies of a step and repeat).
    Drawn { shape: Flat, class: Class },
    /// Made into its pad: the merging frees each object's geometry once its group's pads are
    /// made, so the objects and the pads are not both held whole.
    Done,
}

/// One graphical object of the layer.
#[derive(Clone, Debug)]
pub(super) struct Object {
    pub geom: Geom,
    /// Bounding box `[xmin, ymin, xmax, ymax]`, mm (of the copy).
    pub bbox: [f64; 4],
    /// Dark (adds paste) or clear (removes what was drawn before it).
    pub dark: bool,
    /// Index into [`Layer::attributes`].
    pub attributes: u32,
    /// A step-and-repeat copy: index into [`Layer::shifts`] (0: the object as drawn).
    pub copy: u32,
}

/// The X2 object attributes of an object: component (`%TO.C`) and pin (`%TO.P`).
pub(super) type Attributes = (Option<Arc<str>>, Option<Arc<str>>);

/// The objects of a layer and the tables they index.
#[derive(Debug)]
pub(super) struct Layer {
    pub objects: Vec<Object>,
    /// Flash transforms (the linear part `[a, b, c, d]` of an [`Affine`]); 0 is the identity.
    pub linears: Vec<[f64; 4]>,
    /// Step-and-repeat offsets, mm; 0 is no offset (an object as drawn).
    pub shifts: Vec<Point>,
    /// `(component, pin)` X2 attributes; 0 is none.
    pub attributes: Vec<Attributes>,
}

impl Default for Layer {
    fn default() -> Layer {
        Layer {
            objects: Vec::new(),
            linears: vec![[1.0, 0.0, 0.0, 1.0]],
            shifts: vec![[0.0, 0.0]],
            attributes: vec![(None, None)],
        }
    }
}

impl Layer {
    fn shift(&self, o: &Object) -> Option<Point> {
        (o.copy != 0).then(|| self.shifts[o.copy as usize])
    }

    /// The polygon of object `i`, mm, rings oriented counter-clockwise outside.
    pub fn shape(&self, i: usize) -> Cow<'_, MultiPolygon<f64>> {
        let o = &self.objects[i];
        let placed: Cow<'_, MultiPolygon<f64>> = match &o.geom {
            Geom::Flash { ap, at, linear } => {
                let f = Affine {
                    m: self.linears[*linear as usize],
                    t: *at,
                };
                Cow::Owned(map_multi(&ap.polygon(), &f))
            }
            Geom::Line { ap, a, b } => Cow::Owned(line_shape(ap, *a, *b)),
            Geom::Drawn { shape, .. } => Cow::Owned(shape.to_multi()),
            Geom::Done => Cow::Owned(MultiPolygon::new(vec![])),
        };
        match self.shift(o) {
            None => placed,
            Some(t) => Cow::Owned(map_multi(
                &placed,
                &Affine {
                    m: [1.0, 0.0, 0.0, 1.0],
                    t,
                },
            )),
        }
    }

    /// The exact outline of object `i`, when it is a plain flash (circle, rounded rectangle).
    pub fn exact(&self, i: usize) -> Option<Outline> {
        let o = &self.objects[i];
        let Geom::Flash { ap, at, linear } = &o.geom else {
            return None;
        };
        let f = Affine {
            m: self.linears[*linear as usize],
            t: *at,
        };
        let placed = ap.exact()?.placed(*at, &f);
        Some(match self.shift(o) {
            None => placed,
            Some(t) => placed.transformed(&Rigid {
                rotation_rad: 0.0,
                tx: t[0],
                ty: t[1],
            }),
        })
    }

    /// The aperture class of object `i` (`R 0.60x0.30`, `stroke C 0.10`, `region`, a macro).
    pub fn class(&self, i: usize) -> String {
        match &self.objects[i].geom {
            Geom::Flash { ap, .. } => ap.class(),
            Geom::Line { ap, .. } => format!("stroke {}", ap.class()),
            Geom::Drawn { class, .. } => match class {
                Class::Region => "region".into(),
                Class::Stroke(ap) => format!("stroke {}", ap.class()),
                #[cfg(test)]
                Class::Named(n) => n.to_string(),
            },
            Geom::Done => String::new(),
        }
    }

    /// The component (`%TO.C`) of object `i`.
    pub fn component(&self, i: usize) -> Option<&Arc<str>> {
        self.attributes[self.objects[i].attributes as usize]
            .0
            .as_ref()
    }

    /// The pin (`%TO.P`) of object `i`.
    pub fn pin(&self, i: usize) -> Option<&Arc<str>> {
        self.attributes[self.objects[i].attributes as usize]
            .1
            .as_ref()
    }
}

/// Polygon vertices of a multipolygon.
pub(super) fn vertex_count(mp: &MultiPolygon<f64>) -> usize {
    mp.iter()
        .map(|p| p.exterior().0.len() + p.interiors().iter().map(|r| r.0.len()).sum::<usize>())
        .sum()
}

/// The polygon of a straight stroke of a circle (a capsule) or a rectangle (the hull of the
/// rectangles at both ends); none for another aperture or a zero-size circle (the
/// interpreter refuses or skips those before making a [`Geom::Line`]).
pub(super) fn line_shape(ap: &ApertureShape, a: Point, b: Point) -> MultiPolygon<f64> {
    let pts = match ap.stroke() {
        Stroke::Circle(d) if d > 0.0 => capsule(a, b, d),
        Stroke::Rect(w, h) => swept_rect(a, b, w, h),
        _ => return MultiPolygon::new(vec![]),
    };
    MultiPolygon::new(vec![polygon(&pts, &[])])
}

/// A multipolygon in one allocation: for each polygon its ring count, then for each ring its
/// point count and coordinates (`x, y`, the closing point included). A layer of 10^6 regions
/// holds one allocation per region instead of four; [`Flat::to_multi`] gives back exactly
/// the multipolygon it was made from.
#[derive(Clone, Debug)]
pub(super) struct Flat(Arc<[f64]>);

impl Flat {
    pub fn new(mp: &MultiPolygon<f64>) -> Flat {
        let mut v = Vec::with_capacity(1 + 2 * vertex_count(mp) + 4 * mp.0.len());
        for p in mp.iter() {
            v.push((1 + p.interiors().len()) as f64);
            for ring in std::iter::once(p.exterior()).chain(p.interiors()) {
                v.push(ring.0.len() as f64);
                for c in &ring.0 {
                    v.push(c.x);
                    v.push(c.y);
                }
            }
        }
        Flat(Arc::from(v))
    }

    pub fn to_multi(&self) -> MultiPolygon<f64> {
        let v = &self.0;
        let mut at = 0;
        let mut polys = Vec::new();
        while at < v.len() {
            let rings = v[at] as usize;
            at += 1;
            let mut rs: Vec<LineString<f64>> = Vec::with_capacity(rings);
            for _ in 0..rings {
                let k = v[at] as usize;
                at += 1;
                let coords: Vec<Coord<f64>> = v[at..at + 2 * k]
                    .chunks_exact(2)
                    .map(|p| Coord { x: p[0], y: p[1] })
                    .collect();
                at += 2 * k;
                rs.push(LineString::new(coords));
            }
            let mut rs = rs.into_iter();
            let exterior = rs.next().unwrap_or_else(|| LineString::new(vec![]));
            polys.push(Polygon::new(exterior, rs.collect()));
        }
        MultiPolygon::new(polys)
    }

    /// Polygon vertices it holds.
    pub fn vertices(&self) -> usize {
        (self.0.len() - self.rings()) / 2
    }

    /// Ring and polygon count words.
    fn rings(&self) -> usize {
        let v = &self.0;
        let (mut at, mut words) = (0, 0);
        while at < v.len() {
            let rings = v[at] as usize;
            at += 1;
            words += 1;
            for _ in 0..rings {
                let k = v[at] as usize;
                at += 1 + 2 * k;
                words += 1;
            }
        }
        words
    }

    /// `[xmin, ymin, xmax, ymax]` of its exteriors.
    pub fn bbox(&self) -> [f64; 4] {
        let v = &self.0;
        let mut b = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut at = 0;
        while at < v.len() {
            let rings = v[at] as usize;
            at += 1;
            for r in 0..rings {
                let k = v[at] as usize;
                at += 1;
                if r == 0 {
                    for p in v[at..at + 2 * k].chunks_exact(2) {
                        b = [
                            b[0].min(p[0]),
                            b[1].min(p[1]),
                            b[2].max(p[0]),
                            b[3].max(p[1]),
                        ];
                    }
                }
                at += 2 * k;
            }
        }
        b
    }
}
