//! Objects -> pads: a pad is one connected paste opening.
//!
//! Objects whose shapes intersect (overlap or touch) fall into one group; a clear object joins
//! the groups of the dark objects it touches. Each group is evaluated in file order (dark
//! objects add, a clear object removes what was drawn before it) and every connected polygon
//! of the result is one pad. A group of a single plain flash keeps its exact outline.

use super::object::{vertex_count, Geom, Layer};
use super::shapes::{outline_of, union_on};
use super::{GerberError, Limits};
use crate::pads::Pad;
use geo::{Intersects, MultiPolygon, Polygon};
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
/// The exact tests go piece by piece (the polygons of a macro's shape can lie far apart: only
/// pieces whose boxes meet are tested, [`pieces_meet`]) and cost the sum of the two pieces'
/// vertex counts plus the product of their edges near the other; the total is bounded by
/// [`MAX_PAIR_WORK`] (objects whose pieces' boxes meet but whose shapes do not, e.g. a step
/// and repeat of long diagonal lines 0.02 mm apart, are not joined by any earlier test, so
/// their count grows with the square of the copies): beyond it the layer is refused. Returns
/// the work done.
fn join_touching(
    layer: &Layer,
    rep: &[usize],
    groups: &mut Groups,
    budget: u64,
) -> Result<u64, GerberError> {
    use rstar::AABB;
    const EPS: f64 = 1e-9;
    let objects = &layer.objects;
    for (i, &r) in rep.iter().enumerate() {
        if r != i {
            groups.join(i, r);
        }
    }
    let tree = box_index(layer, (0..objects.len()).filter(|&i| rep[i] == i));
    let mut work = 0u64;
    for i in 0..objects.len() {
        let b = objects[i].bbox;
        if rep[i] != i || !finite_box(&b) {
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
                let pieces_i = shape_i.get_or_insert_with(|| Pieces::of(&layer.shape(i)));
                if pieces_i.meet(&Pieces::of(&layer.shape(j)), &mut work, budget)? {
                    groups.join(i, j);
                }
            }
        }
    }
    Ok(work)
}

/// The polygons of an object's shape with their boxes and vertex counts, for the exact test.
struct Pieces(Vec<(Polygon<f64>, [f64; 4], u64)>);

impl Pieces {
    fn of(shape: &MultiPolygon<f64>) -> Pieces {
        Pieces(
            shape
                .iter()
                .map(|p| {
                    let n = std::iter::once(p.exterior())
                        .chain(p.interiors())
                        .map(|r| r.0.len() as u64)
                        .sum();
                    (p.clone(), bbox(p), n)
                })
                .collect(),
        )
    }

    /// Whether any piece of `self` intersects (overlaps or touches) any piece of `other`
    /// ([`pieces_meet`] for each pair of pieces whose boxes meet), adding the tests' cost to
    /// `work`, refused beyond `budget`.
    fn meet(&self, other: &Pieces, work: &mut u64, budget: u64) -> Result<bool, GerberError> {
        for (a, ba, na) in &self.0 {
            for (b, bb, nb) in &other.0 {
                if boxes_meet(ba, bb) && pieces_meet((a, ba, *na), (b, bb, *nb), work, budget)? {
                    return Ok(true);
                }
            }
        }
        Ok(false)
    }
}

/// The rings of a polygon as segments.
fn edges(p: &Polygon<f64>) -> impl Iterator<Item = geo::Line<f64>> + '_ {
    std::iter::once(p.exterior())
        .chain(p.interiors())
        .flat_map(|r| r.lines())
}

/// Whether two polygons (closed: boundary included) whose boxes meet intersect. Exact: they
/// do if and only if an edge of one meets an edge of the other or, failing that, the exterior
/// of one lies inside the other (the boundary of the intersection is then made of whole rings,
/// and a hole of one inside the other without its exterior would leave them apart), and then
/// every vertex of that exterior is inside: the first test takes the vertex of each nearest
/// the other's box centre, which also ends most overlapping pairs at once. Only edges whose
/// boxes meet the common part of the two polygons' boxes can meet the other polygon, so only
/// those are paired: two discs whose boxes merely overlap at a corner compare a few edges,
/// not all 276 x 276.
///
/// Cost added to `work`: the two vertex counts (the vertex tests and the filters), then the
/// product of the edges kept; refused beyond `budget`.
fn pieces_meet(
    (a, ba, na): (&Polygon<f64>, &[f64; 4], u64),
    (b, bb, nb): (&Polygon<f64>, &[f64; 4], u64),
    work: &mut u64,
    budget: u64,
) -> Result<bool, GerberError> {
    const EPS: f64 = 1e-9;
    let over = |w: &mut u64, add: u64| {
        *w = w.saturating_add(add);
        if *w > budget {
            Err(GerberError::TooEntangled { limit: budget })
        } else {
            Ok(())
        }
    };
    over(work, na.saturating_add(nb))?;
    // The vertex of each nearest the other's box centre, in the other: overlapping pieces,
    // the usual case, end here (two overlapping discs always do).
    let nearest_inside = |p: &Polygon<f64>, q: &Polygon<f64>, qb: &[f64; 4]| {
        let (cx, cy) = ((qb[0] + qb[2]) / 2.0, (qb[1] + qb[3]) / 2.0);
        p.exterior()
            .0
            .iter()
            .min_by(|u, v| {
                let du = (u.x - cx).powi(2) + (u.y - cy).powi(2);
                let dv = (v.x - cx).powi(2) + (v.y - cy).powi(2);
                du.total_cmp(&dv)
            })
            .is_some_and(|c| q.intersects(c))
    };
    if nearest_inside(a, b, bb) || nearest_inside(b, a, ba) {
        return Ok(true);
    }
    let common = [
        ba[0].max(bb[0]) - EPS,
        ba[1].max(bb[1]) - EPS,
        ba[2].min(bb[2]) + EPS,
        ba[3].min(bb[3]) + EPS,
    ];
    // The edges near the common box, each with its own box: a pair whose boxes do not meet
    // is settled without the robust predicates.
    let near = |p: &Polygon<f64>| -> Vec<(geo::Line<f64>, [f64; 4])> {
        edges(p)
            .map(|l| {
                let b = [
                    l.start.x.min(l.end.x),
                    l.start.y.min(l.end.y),
                    l.start.x.max(l.end.x),
                    l.start.y.max(l.end.y),
                ];
                (l, b)
            })
            .filter(|(_, b)| boxes_meet(b, &common))
            .collect()
    };
    let (ea, eb) = (near(a), near(b));
    over(work, (ea.len() as u64).saturating_mul(eb.len() as u64))?;
    Ok(ea.iter().any(|(u, ub)| {
        eb.iter()
            .any(|(v, vb)| boxes_meet(ub, vb) && u.intersects(v))
    }))
}

/// The pads of a layer's objects, in the order of the file. Errors when the merged pads'
/// outlines need more than [`MAX_VERTICES`] vertices. The layer's geometry is freed as its
/// pads are made.
pub(super) fn pads(
    mut layer: Layer,
    warnings: &mut Vec<String>,
    limits: &Limits,
) -> Result<Vec<Pad>, GerberError> {
    let n = layer.objects.len();
    let rep = first_copies(&layer);
    let mut groups = Groups::new(n);
    join_touching(&layer, &rep, &mut groups, limits.pair_work)?;
    pads_of_groups(&mut layer, &rep, groups, warnings, limits.vertices)
}

fn pads_of_groups(
    layer: &mut Layer,
    rep: &[usize],
    mut groups: Groups,
    warnings: &mut Vec<String>,
    max_vertices: usize,
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
        group_pads(
            layer,
            rep,
            &group,
            &mut pads,
            &mut slivers,
            &mut vertices,
            max_vertices,
        )?;
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
    max_vertices: usize,
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
    let result = evaluate(group, layer, rep, max_vertices)?;
    *vertices = vertices.saturating_add(vertex_count(&result));
    if *vertices > max_vertices {
        return Err(GerberError::TooComplex {
            line: 0,
            limit: max_vertices,
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

/// An R-tree of objects' boxes, each leaf holding its object's index.
type BoxIndex =
    rstar::RTree<rstar::primitives::GeomWithData<rstar::primitives::Rectangle<[f64; 2]>, usize>>;

/// Whether `b` is a box (finite, not inverted): only those go into a [`BoxIndex`].
fn finite_box(b: &[f64; 4]) -> bool {
    b.iter().all(|v| v.is_finite()) && b[0] <= b[2] && b[1] <= b[3]
}

/// The index of the boxes of `objects` (those with a [`finite_box`]).
fn box_index(layer: &Layer, objects: impl Iterator<Item = usize>) -> BoxIndex {
    use rstar::primitives::{GeomWithData, Rectangle};
    let leaves = objects
        .filter(|&i| finite_box(&layer.objects[i].bbox))
        .map(|i| {
            let b = layer.objects[i].bbox;
            GeomWithData::new(Rectangle::from_corners([b[0], b[1]], [b[2], b[3]]), i)
        })
        .collect();
    rstar::RTree::bulk_load(leaves)
}

/// The dark objects of a group by the box of their first copy, to find the objects of a piece.
struct ContributorIndex {
    tree: BoxIndex,
    /// The group's dark objects per first copy: `(rep, object)` sorted.
    members: Vec<(usize, usize)>,
}

impl ContributorIndex {
    fn new(layer: &Layer, rep: &[usize], darks: &[usize]) -> ContributorIndex {
        let mut members: Vec<(usize, usize)> = darks.iter().map(|&i| (rep[i], i)).collect();
        members.sort_unstable();
        let firsts = members.chunk_by(|a, b| a.0 == b.0).map(|run| run[0].0);
        ContributorIndex {
            tree: box_index(layer, firsts),
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
    max_vertices: usize,
) -> Result<MultiPolygon<f64>, GerberError> {
    // One grid for the whole group, over its objects' boxes: the unions and cuts meet on it.
    let mut b = [
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    ];
    for &i in group {
        let o = layer.objects[i].bbox;
        b = [
            b[0].min(o[0]),
            b[1].min(o[1]),
            b[2].max(o[2]),
            b[3].max(o[3]),
        ];
    }
    let grid = crate::overlay::Grid::around(b);
    let grid = grid.as_ref();
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
                if run_vertices > max_vertices {
                    return Err(GerberError::TooComplex {
                        line: 0,
                        limit: max_vertices,
                    });
                }
                run.extend(shape.0);
            }
        } else {
            in_run.clear();
            if !run.is_empty() {
                run.append(&mut acc.0);
                acc = union_on(&run, grid);
                run.clear();
                run_vertices = 0;
            }
            acc = crate::overlay::difference(&acc, &layer.shape(i), grid);
        }
    }
    if !run.is_empty() {
        run.append(&mut acc.0);
        acc = union_on(&run, grid);
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
            join_touching(&objects, &rep, &mut fast, Limits::READER.pair_work)
                .expect("within the limits");
            let slow = brute_groups(&objects);
            assert_eq!(partition(fast), partition(slow), "round {round}");

            let mut w1 = Vec::new();
            let mut w2 = Vec::new();
            let brute = brute_groups(&objects);
            let mut copy = Layer {
                objects: objects.objects.clone(),
                ..Layer::default()
            };
            let got = pads(objects, &mut w1, &Limits::READER).expect("within the limits");
            let identity: Vec<usize> = (0..n).collect();
            let want = pads_of_groups(
                &mut copy,
                &identity,
                brute,
                &mut w2,
                Limits::READER.vertices,
            )
            .expect("within the limits");
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
        let got = pads(objects, &mut w, &Limits::READER).expect("within the limits");
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
        // 780 pairs of 5-vertex rings (closed): each costs 5 + 5 (the filters and the vertex
        // tests) and at most 4 x 4 (their edges): the work done is counted, and one unit less
        // than it is refused.
        let mut g = Groups::new(40);
        let need = join_touching(&layer, &rep, &mut g, u64::MAX).expect("no budget");
        assert!((780 * 10..=780 * (10 + 16)).contains(&need), "{need}");
        let mut g = Groups::new(40);
        assert!(matches!(
            join_touching(&layer, &rep, &mut g, need - 1),
            Err(GerberError::TooEntangled { limit }) if limit == need - 1
        ));
        let mut g = Groups::new(40);
        join_touching(&layer, &rep, &mut g, need).expect("within the budget");
        assert_eq!(partition(g), (0..40).collect::<Vec<_>>());
    }

    /// The exact test of two pieces against geo's `Intersects` (all edge pairs, its own point
    /// in polygon), on random rectangles, discs, rings and thin strips, and on the cases the
    /// shortcuts could miss: shared edges, a touching corner, a piece in another's hole.
    mod exact {
        use super::super::*;
        use crate::shapes::{circle_points, polygon, rect_points};
        use proptest::prelude::*;

        fn piece(kind: u8, v: [f64; 5]) -> Polygon<f64> {
            let c = [v[0] * 6.0, v[1] * 6.0];
            let (w, h) = (0.05 + v[2] * 3.0, 0.05 + v[3] * 3.0);
            match kind % 4 {
                0 => polygon(&rect_points(c, w, h, v[4] * 180.0), &[]),
                1 => polygon(&circle_points(c, w), &[]),
                2 => polygon(&circle_points(c, w + h), &[circle_points(c, w)]),
                _ => polygon(&rect_points(c, 8.0 * w, 0.02, v[4] * 180.0), &[]),
            }
        }

        fn ours(a: &Polygon<f64>, b: &Polygon<f64>) -> bool {
            let (ba, bb) = (bbox(a), bbox(b));
            let n = |p: &Polygon<f64>| vertex_count(&MultiPolygon::new(vec![p.clone()])) as u64;
            let mut work = 0;
            boxes_meet(&ba, &bb)
                && pieces_meet((a, &ba, n(a)), (b, &bb, n(b)), &mut work, u64::MAX).unwrap()
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(2000))]
            #[test]
            fn pieces_meet_as_geo_says(
                ka in any::<u8>(), va in prop::array::uniform5(0.0..1.0f64),
                kb in any::<u8>(), vb in prop::array::uniform5(0.0..1.0f64),
            ) {
                let (a, b) = (piece(ka, va), piece(kb, vb));
                prop_assert_eq!(ours(&a, &b), a.intersects(&b));
                prop_assert_eq!(ours(&b, &a), a.intersects(&b));
            }
        }

        #[test]
        fn touching_and_nested_cases() {
            let sq = |x: f64, y: f64, s: f64| polygon(&rect_points([x, y], s, s, 0.0), &[]);
            // A shared edge, a shared corner, a gap of 1 um.
            assert!(ours(&sq(0.0, 0.0, 1.0), &sq(1.0, 0.0, 1.0)));
            assert!(ours(&sq(0.0, 0.0, 1.0), &sq(1.0, 1.0, 1.0)));
            assert!(!ours(&sq(0.0, 0.0, 1.0), &sq(1.001, 0.0, 1.0)));
            // A disc in a ring's hole does not meet it; one across the hole's edge does; a
            // ring around a whole square does not meet it, a disc over all of it does.
            let ring = polygon(
                &circle_points([0.0, 0.0], 4.0),
                &[circle_points([0.0, 0.0], 2.0)],
            );
            assert!(!ours(&ring, &polygon(&circle_points([0.0, 0.0], 1.0), &[])));
            assert!(ours(&ring, &polygon(&circle_points([0.9, 0.0], 1.0), &[])));
            assert!(ours(
                &polygon(&circle_points([0.0, 0.0], 10.0), &[]),
                &sq(0.0, 0.0, 1.0)
            ));
            assert!(ours(
                &sq(0.0, 0.0, 1.0),
                &polygon(&circle_points([0.0, 0.0], 10.0), &[])
            ));
        }
    }
}
