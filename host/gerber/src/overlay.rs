//! Unions and differences of the layer's polygons (geo's types), computed by `i_overlay` 9.
//!
//! Why not geo's `BooleanOps`: geo 0.32 and 0.33 pin `i_overlay` 4.x, whose segment splitting
//! is pathological on long edges that cross many short ones at shallow angles. A fuzz input of
//! 16 copies (a 4 x 4 step and repeat, 1 mm apart) of a 521 mm disc with a 530 mm line across
//! it took 11.1 s to unite through geo (i_overlay 4.0.7 and 4.5.2 alike) and 11 ms through
//! `i_overlay` 9.1 directly (`fuzz/README.md`, the `load_gerber` findings). The tests below
//! hold the results to geo's own overlay on random rectangles, discs and holes. The
//! conversion both ways is a few lines: rings lose their closing point on the way in, and the
//! shapes that come out (outer contour counter-clockwise, holes clockwise: the overlay's
//! default output direction, geo's default orientation) become polygons.
//!
//! The fill rule is non-zero throughout: the polygons handed in are oriented (exteriors
//! counter-clockwise, holes clockwise, as `shapes::polygon` and the overlay make them), so a
//! point is inside the union when it is inside any of them, and a self-overlapping contour
//! (which the specification does not allow, but a file may hold) is filled wherever it winds.

use geo::{Coord, LineString, MultiPolygon, Polygon};
use i_overlay::core::fill_rule::FillRule;
use i_overlay::core::overlay::ShapeType;
use i_overlay::core::overlay_rule::OverlayRule;
use i_overlay::float::overlay::FloatOverlay;
use i_overlay::i_float::adapter::FloatPointAdapter;
use i_overlay::i_float::float::rect::FloatRect;

/// The integer grid an overlay snaps points to, over a box that holds every point given to it.
///
/// Results computed separately and then combined must share one grid: the cascade of
/// `shapes::union_all` unites halves and then the halves, and a pad's evaluation alternates
/// unions and cuts. Each snapping to a grid of its own would move a shared edge by different
/// amounts on each side: a strip of 2,230 touching copies came apart at the halves' seam, 4 nm
/// wide, into two pads. Points on one grid snap to the same integers every time.
#[derive(Clone)]
pub(super) struct Grid(FloatPointAdapter<[f64; 2], i32>);

impl Grid {
    /// A grid over `b` (`[x0, y0, x1, y1]`, mm), widened by a margin; `None` when `b` is not a
    /// finite box.
    pub fn around(b: [f64; 4]) -> Option<Grid> {
        let pad = 1e-6 * (b[2] - b[0]).abs().max((b[3] - b[1]).abs()) + 1e-9;
        let rect = FloatRect::new(b[0] - pad, b[2] + pad, b[1] - pad, b[3] + pad).ok()?;
        Some(Grid(FloatPointAdapter::new_conservative(rect)))
    }

    /// A grid over the points of `polys` (`None` for no points, or points that are not
    /// finite).
    pub fn of<'a>(polys: impl IntoIterator<Item = &'a Polygon<f64>>) -> Option<Grid> {
        let mut b = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        for p in polys {
            for c in p.exterior().0.iter() {
                b = [b[0].min(c.x), b[1].min(c.y), b[2].max(c.x), b[3].max(c.y)];
            }
        }
        Grid::around(b)
    }

    /// Whether every point of `polys` is inside the grid's box.
    fn holds<'a>(&self, mut polys: impl Iterator<Item = &'a Polygon<f64>>) -> bool {
        let r = self.0.rect();
        polys.all(|p| {
            p.exterior()
                .0
                .iter()
                .all(|c| r.min_x <= c.x && c.x <= r.max_x && r.min_y <= c.y && c.y <= r.max_y)
        })
    }
}

/// One shape for the overlay: the exterior, then the holes, each without its closing point.
fn shape_of(p: &Polygon<f64>) -> Vec<Vec<[f64; 2]>> {
    std::iter::once(p.exterior())
        .chain(p.interiors())
        .map(|ring| {
            let c = &ring.0;
            let open = match (c.first(), c.last()) {
                (Some(a), Some(b)) if c.len() > 1 && a == b => &c[..c.len() - 1],
                _ => &c[..],
            };
            open.iter().map(|q| [q.x, q.y]).collect()
        })
        .collect()
}

fn polygons_of(shapes: Vec<Vec<Vec<[f64; 2]>>>) -> MultiPolygon<f64> {
    let ring = |c: Vec<[f64; 2]>| {
        LineString::from(
            c.into_iter()
                .map(|[x, y]| Coord { x, y })
                .collect::<Vec<_>>(),
        )
    };
    MultiPolygon::new(
        shapes
            .into_iter()
            .filter(|s| !s.is_empty())
            .map(|s| {
                let mut contours = s.into_iter();
                let exterior = contours
                    .next()
                    .map(ring)
                    .unwrap_or_else(|| LineString::new(vec![]));
                Polygon::new(exterior, contours.map(ring).collect())
            })
            .collect(),
    )
}

/// `rule` over `subject` and `clip` on `grid`, or on a grid of their own points when `grid` is
/// `None` or does not hold them all (holes lie inside their exteriors: exteriors are enough).
fn run(
    subject: &[&Polygon<f64>],
    clip: &[&Polygon<f64>],
    rule: OverlayRule,
    grid: Option<&Grid>,
) -> MultiPolygon<f64> {
    let all = || subject.iter().chain(clip).copied();
    let own;
    let grid = match grid {
        Some(g) if g.holds(all()) => g,
        _ => match Grid::of(all()) {
            Some(g) => {
                own = g;
                &own
            }
            None => return MultiPolygon::new(vec![]),
        },
    };
    let subject: Vec<_> = subject.iter().map(|p| shape_of(p)).collect();
    let clip: Vec<_> = clip.iter().map(|p| shape_of(p)).collect();
    let capacity = subject.iter().chain(&clip).flatten().map(Vec::len).sum();
    polygons_of(
        FloatOverlay::with_adapter(grid.0.clone(), capacity)
            .unsafe_add_source(&subject, ShapeType::Subject)
            .unsafe_add_source(&clip, ShapeType::Clip)
            .overlay(rule, FillRule::NonZero),
    )
}

/// The union of `polys` (one overlay) on `grid`. A single polygon goes through it too: a
/// contour that touches itself (a cut-in) comes out as an outline with a hole.
pub(super) fn union<'a>(
    polys: impl IntoIterator<Item = &'a Polygon<f64>>,
    grid: Option<&Grid>,
) -> MultiPolygon<f64> {
    let subject: Vec<&Polygon<f64>> = polys.into_iter().collect();
    if subject.is_empty() {
        return MultiPolygon::new(vec![]);
    }
    run(&subject, &[], OverlayRule::Subject, grid)
}

/// `a` without `b`, on `grid`.
pub(super) fn difference(
    a: &MultiPolygon<f64>,
    b: &MultiPolygon<f64>,
    grid: Option<&Grid>,
) -> MultiPolygon<f64> {
    if a.0.is_empty() {
        return MultiPolygon::new(vec![]);
    }
    let subject: Vec<&Polygon<f64>> = a.iter().collect();
    let clip: Vec<&Polygon<f64>> = b.iter().collect();
    run(&subject, &clip, OverlayRule::Difference, grid)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shapes::{area, circle_points, polygon, rect_points};
    // The reference: geo's overlay (i_overlay 4, through geo's own conversions).
    use geo::BooleanOps;
    use proptest::prelude::*;

    /// A rectangle, a disc, or a rectangle with a round hole, from four numbers in 0..1.
    fn piece(kind: u8, v: [f64; 4]) -> Polygon<f64> {
        let c = [v[0] * 4.0, v[1] * 4.0];
        let (w, h) = (0.2 + v[2] * 2.0, 0.2 + v[3] * 2.0);
        match kind % 3 {
            0 => polygon(&rect_points(c, w, h, v[3] * 90.0), &[]),
            1 => polygon(&circle_points(c, w), &[]),
            _ => polygon(
                &rect_points(c, w, h, 0.0),
                &[circle_points(c, w.min(h) * 0.5)],
            ),
        }
    }

    fn pieces() -> impl Strategy<Value = Vec<Polygon<f64>>> {
        prop::collection::vec((any::<u8>(), prop::array::uniform4(0.0..1.0f64)), 1..8)
            .prop_map(|v| v.into_iter().map(|(k, a)| piece(k, a)).collect())
    }

    /// Area of the symmetric difference, against the larger of the two results' areas and
    /// the area of the input `scale`. Both overlays snap the points to an integer grid over
    /// the inputs' extent, each its own way, so the results differ by slivers along the
    /// outlines whose area follows the inputs, not the result: a difference that leaves a
    /// sliver of a disc differed by 2.8e-6 of its own area (CI, stop 38) but by far less of
    /// the disc's (4e-10). Against the inputs the results differ by up to a few 1e-8 (seen up to
    /// 5e-8 in a few thousand cases); the bound is 1e-6.
    fn mismatch(ours: &MultiPolygon<f64>, theirs: &MultiPolygon<f64>, scale: f64) -> f64 {
        area(&ours.xor(theirs)) / area(ours).max(area(theirs)).max(scale).max(1e-12)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]

        #[test]
        fn union_is_geos_union(polys in pieces()) {
            let ours = union(&polys, None);
            let theirs = geo::unary_union(&polys);
            let m = mismatch(&ours, &theirs, 0.0);
            prop_assert!(m < 1e-6, "mismatch {}", m);
            // Exteriors counter-clockwise, holes clockwise (geo's default orientation).
            use geo::Winding;
            for p in &ours {
                prop_assert!(p.exterior().is_ccw());
                prop_assert!(p.interiors().iter().all(|r| r.is_cw()));
            }
        }

        #[test]
        fn difference_is_geos_difference(a in pieces(), b in pieces()) {
            let (a, b) = (union(&a, None), union(&b, None));
            let ours = difference(&a, &b, None);
            let theirs = a.difference(&b);
            let m = mismatch(&ours, &theirs, area(&a));
            prop_assert!(m < 1e-6, "mismatch {}", m);
            prop_assert!(difference(&MultiPolygon::new(vec![]), &b, None).0.is_empty());
        }
    }

    /// A contour that touches itself (a cut-in to a hole, as regions draw them) becomes an
    /// outline with a hole.
    #[test]
    fn a_cut_in_becomes_a_hole() {
        let ring = [
            [0.0, 0.0],
            [4.0, 0.0],
            [4.0, 4.0],
            [2.0, 4.0],
            [2.0, 3.0],
            [3.0, 3.0],
            [3.0, 1.0],
            [1.0, 1.0],
            [1.0, 3.0],
            [2.0, 3.0],
            [2.0, 4.0],
            [0.0, 4.0],
        ];
        let out = union(&[polygon(&ring, &[])], None);
        assert_eq!(out.0.len(), 1);
        assert_eq!(out.0[0].interiors().len(), 1);
        assert!((area(&out) - 12.0).abs() < 1e-9, "{}", area(&out));
    }
}
