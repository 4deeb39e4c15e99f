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

/// The pads of a layer's objects, in the order of the file.
pub(super) fn pads(objects: &[Object], warnings: &mut Vec<String>) -> Vec<Pad> {
    let n = objects.len();
    let mut groups = Groups::new(n);
    // Sweep over x: candidates are the objects whose boxes overlap.
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| objects[a].bbox[0].total_cmp(&objects[b].bbox[0]));
    let mut active: Vec<usize> = Vec::new();
    for &i in &order {
        let bi = objects[i].bbox;
        active.retain(|&j| objects[j].bbox[2] + 1e-9 >= bi[0]);
        for &j in &active {
            if !(objects[i].dark || objects[j].dark) {
                continue; // two clear objects add nothing together
            }
            if boxes_meet(&bi, &objects[j].bbox)
                && groups.find(i) != groups.find(j)
                && objects[i].shape.intersects(&objects[j].shape)
            {
                groups.join(i, j);
            }
        }
        active.push(i);
    }
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
        let result = evaluate(group, objects);
        for poly in result.iter() {
            let area = super::shapes::area(&MultiPolygon::new(vec![poly.clone()]));
            if area < MIN_AREA_MM2 {
                slivers += 1;
                continue;
            }
            let contributors: Vec<usize> = darks
                .iter()
                .copied()
                .filter(|&i| {
                    boxes_meet(&objects[i].bbox, &bbox(poly)) && objects[i].shape.intersects(poly)
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
fn evaluate(group: &[usize], objects: &[Object]) -> MultiPolygon<f64> {
    let mut acc = MultiPolygon::<f64>::new(vec![]);
    let mut run: Vec<Polygon<f64>> = Vec::new();
    for &i in group {
        let o = &objects[i];
        if o.dark {
            run.extend(o.shape.iter().cloned());
        } else {
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
