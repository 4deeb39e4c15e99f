//! Objects -> pads: a pad is one connected paste opening.
//!
//! Objects whose shapes intersect (overlap or touch) fall into one group; a clear object joins
//! the groups of the dark objects it touches. Each group is evaluated in file order (dark
//! objects add, a clear object removes what was drawn before it) and every connected polygon
//! of the result is one pad. A group of a single plain flash keeps its exact outline.

use super::interp::Object;
use super::shapes::{outline_of, union_all};
use crate::inspection::pads::Pad;
use geo::{BooleanOps, Intersects, MultiPolygon, Polygon};

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
fn consensus<'a>(mut values: impl Iterator<Item = Option<&'a String>>) -> Option<String> {
    let first = values.next()??;
    values.all(|v| v == Some(first)).then(|| first.clone())
}

/// For each object, the first dark object of the file with the very same (non-empty) shape: copies
/// (10^5 flashes on one point) are grouped at once and evaluated once.
fn first_copies(objects: &[Object]) -> Vec<usize> {
    use std::collections::HashMap;
    use std::hash::{Hash, Hasher};
    let mut first: HashMap<u64, usize> = HashMap::new();
    let mut rep: Vec<usize> = (0..objects.len()).collect();
    for (i, o) in objects.iter().enumerate() {
        if o.shape.0.is_empty() {
            continue;
        }
        let mut h = std::collections::hash_map::DefaultHasher::new();
        for c in o.shape.0.iter().flat_map(|p| {
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
            Some(&j) if objects[j].shape == o.shape => rep[i] = j,
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
fn join_touching(objects: &[Object], rep: &[usize], groups: &mut Groups) {
    use rstar::primitives::{GeomWithData, Rectangle};
    use rstar::{RTree, AABB};
    const EPS: f64 = 1e-9;
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
    for i in 0..objects.len() {
        let b = objects[i].bbox;
        if rep[i] != i || !finite(&b) {
            continue;
        }
        let query = AABB::from_corners([b[0] - EPS, b[1] - EPS], [b[2] + EPS, b[3] + EPS]);
        for leaf in tree.locate_in_envelope_intersecting(&query) {
            let j = leaf.data;
            if j <= i || !(objects[i].dark || objects[j].dark) {
                continue;
            }
            if boxes_meet(&b, &objects[j].bbox)
                && groups.find(i) != groups.find(j)
                && objects[i].shape.intersects(&objects[j].shape)
            {
                groups.join(i, j);
            }
        }
    }
}

/// The pads of a layer's objects, in the order of the file.
pub(super) fn pads(objects: &[Object], warnings: &mut Vec<String>) -> Vec<Pad> {
    let n = objects.len();
    let rep = first_copies(objects);
    let mut groups = Groups::new(n);
    join_touching(objects, &rep, &mut groups);
    pads_of_groups(objects, &rep, groups, warnings)
}

fn pads_of_groups(
    objects: &[Object],
    rep: &[usize],
    mut groups: Groups,
    warnings: &mut Vec<String>,
) -> Vec<Pad> {
    let n = objects.len();
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); n];
    for i in 0..n {
        let r = groups.find(i);
        members[r].push(i);
    }
    let mut pads = Vec::new();
    let mut slivers = 0usize;
    for group in members.iter().filter(|g| !g.is_empty()) {
        let any_clear = group.iter().any(|&i| !objects[i].dark);
        let darks: Vec<usize> = group.iter().copied().filter(|&i| objects[i].dark).collect();
        if darks.is_empty() {
            continue;
        }
        if let ([only], false) = (darks.as_slice(), any_clear) {
            let o = &objects[*only];
            if let Some(exact) = &o.exact {
                pads.push(pad(exact.clone(), &[*only], objects));
                continue;
            }
        }
        let result = evaluate(group, objects, rep);
        for poly in result.iter() {
            let area = super::shapes::area(&MultiPolygon::new(vec![poly.clone()]));
            if area < MIN_AREA_MM2 {
                slivers += 1;
                continue;
            }
            let pb = bbox(poly);
            let mut meets: std::collections::HashMap<usize, bool> = Default::default();
            let contributors: Vec<usize> = darks
                .iter()
                .copied()
                .filter(|&i| {
                    *meets.entry(rep[i]).or_insert_with(|| {
                        let o = &objects[rep[i]];
                        boxes_meet(&o.bbox, &pb) && o.shape.intersects(poly)
                    })
                })
                .collect();
            let contributors = if contributors.is_empty() {
                darks.clone()
            } else {
                contributors
            };
            let first = &objects[contributors[0]];
            let outline = match (&first.exact, contributors.len(), any_clear) {
                (Some(e), 1, false) => e.clone(),
                _ => outline_of(poly),
            };
            pads.push(pad(outline, &contributors, objects));
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
    pads
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

fn pad(
    outline: crate::inspection::pads::Outline,
    contributors: &[usize],
    objects: &[Object],
) -> Pad {
    let of = || contributors.iter().map(|&i| &objects[i]);
    let class = consensus(of().map(|o| Some(&o.class))).unwrap_or_else(|| "merged".into());
    Pad {
        index: 0,
        outline,
        component: consensus(of().map(|o| o.component.as_ref())),
        pin: consensus(of().map(|o| o.pin.as_ref())),
        aperture: Some(class),
    }
}

/// The group's area in file order: runs of dark objects are unioned at once, a clear object
/// is subtracted from everything before it.
/// A copy of a dark object already in the run adds nothing (union is idempotent) and is skipped.
fn evaluate(group: &[usize], objects: &[Object], rep: &[usize]) -> MultiPolygon<f64> {
    let mut acc = MultiPolygon::<f64>::new(vec![]);
    let mut run: Vec<Polygon<f64>> = Vec::new();
    let mut in_run = std::collections::HashSet::new();
    for &i in group {
        let o = &objects[i];
        if o.dark {
            if in_run.insert(rep[i]) {
                run.extend(o.shape.iter().cloned());
            }
        } else {
            in_run.clear();
            if !run.is_empty() {
                run.append(&mut acc.0);
                acc = union_all(&run);
                run.clear();
            }
            acc = acc.difference(&o.shape);
        }
    }
    if !run.is_empty() {
        run.append(&mut acc.0);
        acc = union_all(&run);
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;
    use geo::{Coord, LineString};

    /// The reference: every pair of objects tested, no copies shortcut, no index.
    fn brute_groups(objects: &[Object]) -> Groups {
        let mut groups = Groups::new(objects.len());
        for i in 0..objects.len() {
            for j in 0..i {
                if (objects[i].dark || objects[j].dark)
                    && objects[i].shape.intersects(&objects[j].shape)
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
            dark,
            shape: MultiPolygon::new(vec![Polygon::new(ls, vec![])]),
            exact: None,
            class: class.into(),
            component: None,
            pin: None,
            bbox: b,
        }
    }

    /// Rectangles and octagons on a 0.25 mm grid (so edges and corners touch exactly), with
    /// copies of earlier objects, some of them clear.
    fn layout(rng: &mut Rng, n: usize) -> Vec<Object> {
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
        objects
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
            join_touching(&objects, &rep, &mut fast);
            let slow = brute_groups(&objects);
            assert_eq!(partition(fast), partition(slow), "round {round}");

            let mut w1 = Vec::new();
            let mut w2 = Vec::new();
            let got = pads(&objects, &mut w1);
            let identity: Vec<usize> = (0..n).collect();
            let want = pads_of_groups(&objects, &identity, brute_groups(&objects), &mut w2);
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
        let objects: Vec<Object> = (0..10_000)
            .map(|_| object(true, square.clone(), "R 0.50x0.50"))
            .collect();
        let mut w = Vec::new();
        let got = pads(&objects, &mut w);
        assert_eq!(got.len(), 1);
        assert!((got[0].outline.area() - 0.25).abs() < 1e-12);
        assert_eq!(got[0].aperture.as_deref(), Some("R 0.50x0.50"));
    }
}
