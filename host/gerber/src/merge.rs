//! Objects -> pads: a pad is one connected paste opening.
//!
//! Objects whose shapes intersect (overlap or touch) fall into one group; a clear object joins
//! the groups of the dark objects it touches. Each group is evaluated in file order (dark
//! objects add, a clear object removes what was drawn before it) and every connected polygon
//! of the result is one pad. A group of a single plain flash keeps its exact outline.

use super::object::{vertex_count, Geom, Layer};
use super::shapes::{outline_of, union_all};
use super::{GerberError, MAX_PAIR_WORK, MAX_VERTICES};
use crate::pads::Pad;
use geo::{BooleanOps, Intersects, MultiPolygon, Polygon};
use std::sync::Arc;

/// Smallest pad kept, mm^2: boolean slivers below it are dropped (with a warning).
const MIN_AREA_MM2: f64 = 1e-6;

/// Disjoint sets over object indices.
struct Groups {
    parent: Vec<usize>,
}

impl Groups {
    fn new(n: usize) -> Groups {
        Groups {
            parent: (0..n).collect(),
        }
    }

    fn find(&mut self, mut i: usize) -> usize {
        while self.parent[i] != i {
            self.parent[i] = self.parent[self.parent[i]];
            i = self.parent[i];
        }
        i
    }

    fn join(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            // The smaller index is the root: groups keep file order.
            let (lo, hi) = if ra < rb { (ra, rb) } else { (rb, ra) };
            self.parent[hi] = lo;
        }
    }
}

fn boxes_meet(a: &[f64; 4], b: &[f64; 4]) -> bool {
    const EPS: f64 = 1e-9;
    a[0] <= b[2] + EPS && b[0] <= a[2] + EPS && a[1] <= b[3] + EPS && b[1] <= a[3] + EPS
}

/// The value all of `values` agree on, if they do.
fn consensus<'a>(mut values: impl Iterator<Item = Option<&'a Arc<str>>>) -> Option<String> {
    let first = values.next()??;
    values.all(|v| v == Some(first)).then(|| first.to_string())
}

/// For each object, the first dark object of the file with the very same (non-empty) shape: copies
/// (10^5 flashes on one point) are grouped at once and evaluated once.
fn first_copies(layer: &Layer) -> Vec<usize> {
    use std::collections::HashMap;
    use std::hash::{Hash, Hasher};
    let objects = &layer.objects;
    let mut first: HashMap<u64, usize> = HashMap::new();
    let mut rep: Vec<usize> = (0..objects.len()).collect();
    for (i, o) in objects.iter().enumerate() {
        let shape = layer.shape(i);
        if shape.0.is_empty() {
            continue;
        }
        let mut h = std::collections::hash_map::DefaultHasher::new();
        for c in shape.0.iter().flat_map(|p| {
            std::iter::once(p.exterior())
                .chain(p.interiors())
                .flat_map(|r| {
                    r.0.iter().chain(std::iter::once(&geo::Coord {
                        x: f64::NAN,
                        y: 0.0,
                    }))
                })
        }) {
            (c.x.to_bits(), c.y.to_bits()).hash(&mut h);
        }
        // Only dark objects are firsts: whatever touches a copy touches its dark first, and
        // joins it as the pair test would (at least one of the two dark).
        match first.get(&h.finish()) {
            // A hash collision between different shapes only loses the shortcut.
            Some(&j) if *layer.shape(j) == *shape => rep[i] = j,
            Some(_) => {}
            None if o.dark => {
                first.insert(h.finish(), i);
            }
            None => {}
        }
    }
    rep
}

/// Joins the groups of every two objects that intersect (overlap or touch), at least one of
/// them dark. Copies join their first copy (identical non-empty shapes intersect); the other
/// objects are found through an R-tree of their boxes, so a layer costs n log n plus the
/// pairs whose boxes meet, not n^2 for objects sharing an x range.
///
/// The exact tests cost about the product of the two polygons' vertex counts each; their sum
/// is bounded by [`MAX_PAIR_WORK`] (objects whose boxes meet but whose shapes do not, e.g. a
/// step and repeat of long diagonal lines 0.02 mm apart, are not joined by any earlier test,
/// so their count grows with the square of the copies): beyond it the layer is refused.
fn join_touching(
    layer: &Layer,
    rep: &[usize],
    groups: &mut Groups,
    budget: u64,
) -> Result<(), GerberError> {
    use rstar::primitives::{GeomWithData, Rectangle};
    use rstar::{RTree, AABB};
    const EPS: f64 = 1e-9;
    let objects = &layer.objects;
    let finite = |b: &[f64; 4]| b.iter().all(|v| v.is_finite()) && b[0] <= b[2] && b[1] <= b[3];
    let mut leaves = Vec::new();
    for (i, o) in objects.iter().enumerate() {
        if rep[i] != i {
            groups.join(i, rep[i]);
        } else if finite(&o.bbox) {
            let b = o.bbox;
            leaves.push(GeomWithData::new(
                Rectangle::from_corners([b[0], b[1]], [b[2], b[3]]),
                i,
            ));
        }
    }
    let tree = RTree::bulk_load(leaves);
    let mut work = 0u64;
    for i in 0..objects.len() {
        let b = objects[i].bbox;
        if rep[i] != i || !finite(&b) {
            continue;
        }
        let query = AABB::from_corners([b[0] - EPS, b[1] - EPS], [b[2] + EPS, b[3] + EPS]);
        // The polygon of `i`, made once and only if a box meets its box.
        let mut shape_i = None;
        for leaf in tree.locate_in_envelope_intersecting(&query) {
            let j = leaf.data;
            if j <= i || !(objects[i].dark || objects[j].dark) {
                continue;
            }
            if boxes_meet(&b, &objects[j].bbox) && groups.find(i) != groups.find(j) {
                let (si, ni) = shape_i.get_or_insert_with(|| {
                    let s = layer.shape(i);
                    let n = vertex_count(&s) as u64;
                    (s, n)
                });
                let sj = layer.shape(j);
                work = work.saturating_add(*ni * vertex_count(&sj) as u64);
                if work > budget {
                    return Err(GerberError::TooEntangled { limit: budget });
                }
                if si.intersects(&*sj) {
                    groups.join(i, j);
                }
            }
        }
    }
    Ok(())
}

/// The pads of a layer's objects, in the order of the file. Errors when the merged pads'
/// outlines need more than [`MAX_VERTICES`] vertices. The layer's geometry is freed as its
/// pads are made.
pub(super) fn pads(mut layer: Layer, warnings: &mut Vec<String>) -> Result<Vec<Pad>, GerberError> {
    let n = layer.objects.len();
    let rep = first_copies(&layer);
    let mut groups = Groups::new(n);
    join_touching(&layer, &rep, &mut groups, MAX_PAIR_WORK)?;
    pads_of_groups(&mut layer, &rep, groups, warnings)
}

fn pads_of_groups(
    layer: &mut Layer,
    rep: &[usize],
    mut groups: Groups,
    warnings: &mut Vec<String>,
) -> Result<Vec<Pad>, GerberError> {
    let n = layer.objects.len();
    // The members of every group, in file order, groups in the order of their first member
    // (a group's root is its first member): (root, member) pairs sorted.
    let mut members: Vec<(usize, usize)> = (0..n).map(|i| (groups.find(i), i)).collect();
    drop(groups);
    members.sort_unstable();
    let mut pads = Vec::with_capacity(members.iter().filter(|m| m.0 == m.1).count());
    let mut slivers = 0usize;
    let mut vertices = 0usize;
    for run in members.chunk_by(|a, b| a.0 == b.0) {
        let group: Vec<usize> = run.iter().map(|m| m.1).collect();
        group_pads(layer, rep, &group, &mut pads, &mut slivers, &mut vertices)?;
        for &i in &group {
            layer.objects[i].geom = Geom::Done;
        }
    }
    if slivers > 0 {
        warnings.push(format!(
            "{slivers} sliver(s) under {MIN_AREA_MM2} mm^2 left by clear objects dropped"
        ));
    }
    for (i, p) in pads.iter_mut().enumerate() {
        p.index = i;
    }
    Ok(pads)
}

/// The pads of one group (its members in file order).
fn group_pads(
    layer: &Layer,
    rep: &[usize],
    group: &[usize],
    pads: &mut Vec<Pad>,
    slivers: &mut usize,
    vertices: &mut usize,
) -> Result<(), GerberError> {
    let objects = &layer.objects;
    let any_clear = group.iter().any(|&i| !objects[i].dark);
    let darks: Vec<usize> = group.iter().copied().filter(|&i| objects[i].dark).collect();
    if darks.is_empty() {
        return Ok(());
    }
    if let ([only], false) = (darks.as_slice(), any_clear) {
        if let Some(exact) = layer.exact(*only) {
            pads.push(pad(exact, &[*only], layer));
            return Ok(());
        }
    }
    let result = evaluate(group, layer, rep)?;
    *vertices = vertices.saturating_add(vertex_count(&result));
    if *vertices > MAX_VERTICES {
        return Err(GerberError::TooComplex {
            line: 0,
            limit: MAX_VERTICES,
        });
    }
    // One piece and nothing clear: every dark object is in it (no test needed; a step and
    // repeat of 220 overlapping copies would test each against the union's long outline).
    // Otherwise each piece tests only the objects whose boxes meet its box, once per set of
    // coinciding copies (`rep`): a group of n objects in m pieces costs about
    // (n + m) log n, not n x m.
    let single = result.0.len() == 1 && !any_clear;
    let index = (!single).then(|| ContributorIndex::new(layer, rep, &darks));
    for poly in result.iter() {
        let area = super::shapes::area(&MultiPolygon::new(vec![poly.clone()]));
        if area < MIN_AREA_MM2 {
            *slivers += 1;
            continue;
        }
        let contributors: Vec<usize> = match &index {
            None => darks.clone(),
            Some(index) => index.meeting(layer, poly),
        };
        let contributors = if contributors.is_empty() {
            darks.clone()
        } else {
            contributors
        };
        let outline = match (layer.exact(contributors[0]), contributors.len(), any_clear) {
            (Some(e), 1, false) => e,
            _ => outline_of(poly),
        };
        pads.push(pad(outline, &contributors, layer));
    }
    Ok(())
}

/// The dark objects of a group by the box of their first copy, to find the objects of a piece.
struct ContributorIndex {
    tree: rstar::RTree<
        rstar::primitives::GeomWithData<rstar::primitives::Rectangle<[f64; 2]>, usize>,
    >,
    /// The group's dark objects per first copy: `(rep, object)` sorted.
    members: Vec<(usize, usize)>,
}

impl ContributorIndex {
    fn new(layer: &Layer, rep: &[usize], darks: &[usize]) -> ContributorIndex {
        use rstar::primitives::{GeomWithData, Rectangle};
        let mut members: Vec<(usize, usize)> = darks.iter().map(|&i| (rep[i], i)).collect();
        members.sort_unstable();
        let mut leaves = Vec::new();
        for run in members.chunk_by(|a, b| a.0 == b.0) {
            let r = run[0].0;
            let b = layer.objects[r].bbox;
            if b.iter().all(|v| v.is_finite()) && b[0] <= b[2] && b[1] <= b[3] {
                leaves.push(GeomWithData::new(
                    Rectangle::from_corners([b[0], b[1]], [b[2], b[3]]),
                    r,
                ));
            }
        }
        ContributorIndex {
            tree: rstar::RTree::bulk_load(leaves),
            members,
        }
    }

    /// The objects whose shapes meet `poly`, in file order.
    fn meeting(&self, layer: &Layer, poly: &Polygon<f64>) -> Vec<usize> {
        const EPS: f64 = 1e-9;
        let pb = bbox(poly);
        let query =
            rstar::AABB::from_corners([pb[0] - EPS, pb[1] - EPS], [pb[2] + EPS, pb[3] + EPS]);
        let mut out = Vec::new();
        for leaf in self.tree.locate_in_envelope_intersecting(&query) {
            let r = leaf.data;
            if boxes_meet(&layer.objects[r].bbox, &pb) && layer.shape(r).intersects(poly) {
                let from = self.members.partition_point(|m| m.0 < r);
                out.extend(
                    self.members[from..]
                        .iter()
                        .take_while(|m| m.0 == r)
                        .map(|m| m.1),
                );
            }
        }
        out.sort_unstable();
        out
    }
}

fn bbox(p: &Polygon<f64>) -> [f64; 4] {
    let mut b = [
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    ];
    for c in p.exterior().coords() {
        b = [b[0].min(c.x), b[1].min(c.y), b[2].max(c.x), b[3].max(c.y)];
    }
    b
}

fn pad(outline: crate::pads::Outline, contributors: &[usize], layer: &Layer) -> Pad {
    let class = {
        let mut classes = contributors.iter().map(|&i| layer.class(i));
        let first = classes.next().unwrap_or_default();
        if classes.all(|c| c == first) {
            first
        } else {
            "merged".into()
        }
    };
    Pad {
        index: 0,
        outline,
        component: consensus(contributors.iter().map(|&i| layer.component(i))),
        pin: consensus(contributors.iter().map(|&i| layer.pin(i))),
        aperture: Some(class),
    }
}

/// The group's area in file order: runs of dark objects are unioned at once, a clear object
/// is subtracted from everything before it.
/// A copy of a dark object already in the run adds nothing (union is idempotent) and is skipped.
/// Errors when the run to union holds more than [`MAX_VERTICES`] vertices.
fn evaluate(
    group: &[usize],
    layer: &Layer,
    rep: &[usize],
) -> Result<MultiPolygon<f64>, GerberError> {
    let mut acc = MultiPolygon::<f64>::new(vec![]);
    let mut run: Vec<Polygon<f64>> = Vec::new();
    let mut run_vertices = 0usize;
    let mut in_run = std::collections::HashSet::new();
    for &i in group {
        let o = &layer.objects[i];
        if o.dark {
            if in_run.insert(rep[i]) {
                let shape = layer.shape(i).into_owned();
                run_vertices = run_vertices.saturating_add(vertex_count(&shape));
                if run_vertices > MAX_VERTICES {
                    return Err(GerberError::TooComplex {
                        line: 0,
                        limit: MAX_VERTICES,
                    });
                }
                run.extend(shape.0);
            }
        } else {
            in_run.clear();
            if !run.is_empty() {
                run.append(&mut acc.0);
                acc = union_all(&run);
                run.clear();
                run_vertices = 0;
            }
            acc = acc.difference(&*layer.shape(i));
        }
    }
    if !run.is_empty() {
        run.append(&mut acc.0);
        acc = union_all(&run);
    }
    Ok(acc)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::object::{Class, Flat, Geom, Object};
    use geo::{Coord, LineString};

    /// The reference: every pair of objects tested, no copies shortcut, no index.
    fn brute_groups(layer: &Layer) -> Groups {
        let objects = &layer.objects;
        let mut groups = Groups::new(objects.len());
        for i in 0..objects.len() {
            for j in 0..i {
                if (objects[i].dark || objects[j].dark)
                    && layer.shape(i).intersects(&*layer.shape(j))
                {
                    groups.join(i, j);
                }
            }
        }
        groups
    }

    fn partition(mut g: Groups) -> Vec<usize> {
        (0..g.parent.len()).map(|i| g.find(i)).collect()
    }

    /// A small deterministic generator (splitmix64).
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }
    }

    fn object(dark: bool, ring: Vec<[f64; 2]>, class: &str) -> Object {
        let mut b = [
            f64::INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NEG_INFINITY,
        ];
        for p in &ring {
            b = [
                b[0].min(p[0]),
                b[1].min(p[1]),
                b[2].max(p[0]),
                b[3].max(p[1]),
            ];
        }
        let ls = LineString::new(ring.iter().map(|p| Coord { x: p[0], y: p[1] }).collect());
        Object {
            geom: Geom::Drawn {
                shape: Flat::new(&MultiPolygon::new(vec![Polygon::new(ls, vec![])])),
                class: Class::Named(class.into()),
            },
            bbox: b,
            dark,
            attributes: 0,
            copy: 0,
        }
    }

    /// Rectangles and octagons on a 0.25 mm grid (so edges and corners touch exactly), with
    /// copies of earlier objects, some of them clear.
    fn layout(rng: &mut Rng, n: usize) -> Layer {
        let mut objects: Vec<Object> = Vec::new();
        for _ in 0..n {
            let dark = rng.below(5) != 0;
            if !objects.is_empty() && rng.below(4) == 0 {
                let k = rng.below(objects.len() as u64) as usize;
                let mut copy = objects[k].clone();
                copy.dark = dark;
                objects.push(copy);
                continue;
            }
            let x = rng.below(24) as f64 * 0.25;
            let y = rng.below(24) as f64 * 0.25;
            let w = (1 + rng.below(6)) as f64 * 0.25;
            let h = (1 + rng.below(6)) as f64 * 0.25;
            let ring = if rng.below(3) == 0 {
                // An octagon inscribed in the w x w box.
                let (c, r) = ([x + w / 2.0, y + w / 2.0], w / 2.0);
                (0..8)
                    .map(|k| {
                        let a = std::f64::consts::PI / 4.0 * k as f64 + std::f64::consts::PI / 8.0;
                        [c[0] + r * a.cos(), c[1] + r * a.sin()]
                    })
                    .collect()
            } else {
                vec![[x, y], [x + w, y], [x + w, y + h], [x, y + h], [x, y]]
            };
            objects.push(object(dark, ring, if dark { "D10" } else { "clear" }));
        }
        Layer {
            objects,
            ..Layer::default()
        }
    }

    /// The indexed grouping (R-tree + copies) equals testing every pair, and so do the pads, on
    /// random layouts of touching, overlapping, identical and disjoint shapes.
    #[test]
    fn index_groups_like_every_pair() {
        let mut rng = Rng(20);
        let mut pads_seen = 0;
        for round in 0..300 {
            let n = 1 + rng.below(if round % 10 == 0 { 120 } else { 30 }) as usize;
            let objects = layout(&mut rng, n);
            let rep = first_copies(&objects);
            let mut fast = Groups::new(n);
            join_touching(&objects, &rep, &mut fast, MAX_PAIR_WORK).expect("within the limits");
            let slow = brute_groups(&objects);
            assert_eq!(partition(fast), partition(slow), "round {round}");

            let mut w1 = Vec::new();
            let mut w2 = Vec::new();
            let brute = brute_groups(&objects);
            let mut copy = Layer {
                objects: objects.objects.clone(),
                ..Layer::default()
            };
            let got = pads(objects, &mut w1).expect("within the limits");
            let identity: Vec<usize> = (0..n).collect();
            let want =
                pads_of_groups(&mut copy, &identity, brute, &mut w2).expect("within the limits");
            assert_eq!(got.len(), want.len(), "round {round}");
            assert_eq!(w1, w2, "round {round}");
            for (a, b) in got.iter().zip(&want) {
                assert_eq!(
                    (&a.aperture, a.index),
                    (&b.aperture, b.index),
                    "round {round}"
                );
                assert!(
                    (a.outline.area() - b.outline.area()).abs() < 1e-9,
                    "round {round}"
                );
                let (ba, bb) = (a.outline.bbox(), b.outline.bbox());
                assert!(
                    ba.iter().zip(bb).all(|(p, q)| (p - q).abs() < 1e-9),
                    "round {round}"
                );
            }
            pads_seen += got.len();
        }
        assert!(pads_seen > 1000, "{pads_seen}");
    }

    /// 10^4 copies of one flash on one point make ONE pad (the copies shortcut: without it the
    /// pair test and the union are quadratic).
    #[test]
    fn copies_on_one_point_are_one_pad() {
        let square = vec![[0.0, 0.0], [0.5, 0.0], [0.5, 0.5], [0.0, 0.5], [0.0, 0.0]];
        let objects = Layer {
            objects: (0..10_000)
                .map(|_| object(true, square.clone(), "R 0.50x0.50"))
                .collect(),
            ..Layer::default()
        };
        let mut w = Vec::new();
        let got = pads(objects, &mut w).expect("within the limits");
        assert_eq!(got.len(), 1);
        assert!((got[0].outline.area() - 0.25).abs() < 1e-12);
        assert_eq!(got[0].aperture.as_deref(), Some("R 0.50x0.50"));
    }

    /// Parallel diagonal strips whose boxes all meet but whose shapes do not: the exact tests
    /// are counted, and a layer over the budget is refused, not tested pair by pair for
    /// minutes; under it they stay separate pads.
    #[test]
    fn entangled_objects_are_refused_beyond_the_work_budget() {
        let strips: Vec<Object> = (0..40)
            .map(|k| {
                let d = 0.05 * k as f64;
                object(
                    true,
                    vec![
                        [d, 0.0],
                        [d + 0.02, 0.0],
                        [d + 10.02, 10.0],
                        [d + 10.0, 10.0],
                        [d, 0.0],
                    ],
                    "strip",
                )
            })
            .collect();
        let layer = Layer {
            objects: strips,
            ..Layer::default()
        };
        let rep = first_copies(&layer);
        // 780 pairs of 5 x 5 vertices.
        let mut g = Groups::new(40);
        assert!(matches!(
            join_touching(&layer, &rep, &mut g, 10_000),
            Err(GerberError::TooEntangled { limit: 10_000 })
        ));
        let mut g = Groups::new(40);
        join_touching(&layer, &rep, &mut g, 780 * 25).expect("within the budget");
        assert_eq!(partition(g), (0..40).collect::<Vec<_>>());
    }
}
