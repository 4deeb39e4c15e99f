//! Pad names from a placement file: every pad's component and pin.
//!
//! - A pad that already has its component from the layer (X2 `%TO.C` / `%TO.P`) keeps it.
//! - Any other pad goes to a top-side component whose placement centre is within
//!   `max_distance_mm` of its centroid (else it stays unnamed, `#index`). Nearest centre alone
//!   gives a QFP's corner pads to the decoupling capacitors beside it, so the choice is in two
//!   passes: (1) the nearest component about whose centre the pad has a mirror image (another
//!   pad of the same class within [`MIRROR_TOLERANCE_MM`] of the pad's image under a half turn
//!   about the centre, or the pad on the centre itself: chips, QFP, QFN with their thermal pad,
//!   SOIC, BGA), else the nearest across whose own x or y
//!   axis it has one (SOT-23's pins 1 and 2, switches, most connectors); (2) a pad with no mirror
//!   goes to the nearest component that got no pad in pass 1 (SOT-23, connectors whose
//!   placement point is not their centre), else to the nearest.
//! - Its pin: the X2 pin when the layer has one; else its 1-based index among the component's
//!   unnamed-pin pads in reading order of the component's own frame (turned back by its
//!   rotation): rows from top (larger y) to bottom, rows 10 um apart, left to right within a
//!   row. The index is deterministic, not the datasheet pin number.

use super::placement::{Component, Side};
use dpsa_gerber::pads::Pad;
use std::collections::BTreeMap;

/// How far a pad's mirror image may be from another pad's centroid, mm.
pub const MIRROR_TOLERANCE_MM: f64 = 0.05;

/// What naming did.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Naming {
    /// Pads named by the layer's own X2 attributes.
    pub from_layer: usize,
    /// Pads given a component from the placement file.
    pub from_placement: usize,
    /// Pads left without a component (no component centre near enough).
    pub unnamed: Vec<usize>,
    /// Top-side components that got no pad (through-hole parts, or too far).
    pub components_without_pads: Vec<String>,
}

/// Names `pads` from the placement file's top-side components (see the module's rule).
pub(crate) fn assign(pads: &mut [Pad], components: &[Component], max_distance_mm: f64) -> Naming {
    let top: Vec<&Component> = components.iter().filter(|c| c.side == Side::Top).collect();
    let mut n = Naming::default();
    // Grid of component centres for the nearest search (cells of max_distance).
    let cell = max_distance_mm.max(0.1);
    let key = |p: [f64; 2]| ((p[0] / cell).floor() as i64, (p[1] / cell).floor() as i64);
    let mut grid: BTreeMap<(i64, i64), Vec<usize>> = BTreeMap::new();
    for (i, c) in top.iter().enumerate() {
        grid.entry(key(c.at_mm)).or_default().push(i);
    }
    let mut members: Vec<Vec<usize>> = vec![Vec::new(); top.len()];
    let mut used = vec![false; top.len()];
    // Pad centroids on a grid of 0.5 mm cells, for the mirror test.
    let centres: Vec<[f64; 2]> = pads.iter().map(|p| p.outline.centroid()).collect();
    let pkey = |p: [f64; 2]| ((p[0] / 0.5).floor() as i64, (p[1] / 0.5).floor() as i64);
    let mut pgrid: BTreeMap<(i64, i64), Vec<usize>> = BTreeMap::new();
    for (k, c) in centres.iter().enumerate() {
        pgrid.entry(pkey(*c)).or_default().push(k);
    }
    let has_pad_at = |k: usize, m: [f64; 2]| -> bool {
        let (gx, gy) = pkey(m);
        (-1..=1).any(|dx| {
            (-1..=1).any(|dy| {
                pgrid
                    .get(&(gx + dx, gy + dy))
                    .into_iter()
                    .flatten()
                    .any(|&q| {
                        q != k
                            && pads[q].aperture == pads[k].aperture
                            && (centres[q][0] - m[0]).hypot(centres[q][1] - m[1])
                                <= MIRROR_TOLERANCE_MM
                    })
            })
        })
    };
    // The pad's images through the component's centre: the half turn, and the reflections
    // across the component's own two axes.
    let mirrored = |k: usize, comp: &Component, axes: bool| -> bool {
        let c = comp.at_mm;
        let (dx, dy) = (centres[k][0] - c[0], centres[k][1] - c[1]);
        let (s, co) = comp.rotation_deg.to_radians().sin_cos();
        // Along the component's axes.
        let (u, v) = (co * dx + s * dy, -s * dx + co * dy);
        let back = |u: f64, v: f64| [c[0] + co * u - s * v, c[1] + s * u + co * v];
        if axes {
            has_pad_at(k, back(-u, v)) || has_pad_at(k, back(u, -v))
        } else {
            // A pad on the centre (a thermal pad, a BGA's middle ball) is its own image.
            u.hypot(v) <= MIRROR_TOLERANCE_MM || has_pad_at(k, back(-u, -v))
        }
    };
    // Pass 1: the nearest component about whose centre the pad has a mirror image.
    let mut symmetric = vec![false; top.len()];
    let mut owner: Vec<Option<usize>> = vec![None; pads.len()];
    let mut deferred: Vec<(usize, Vec<(f64, usize)>)> = Vec::new();
    for k in 0..pads.len() {
        if pads[k].component.is_some() {
            n.from_layer += 1;
            if let Some(i) = top
                .iter()
                .position(|c| Some(&c.reference) == pads[k].component.as_ref())
            {
                used[i] = true;
            }
            continue;
        }
        let p = centres[k];
        let (gx, gy) = key(p);
        let mut cands: Vec<(f64, usize)> = Vec::new();
        for dx in -1..=1 {
            for dy in -1..=1 {
                for &i in grid.get(&(gx + dx, gy + dy)).into_iter().flatten() {
                    let c = top[i].at_mm;
                    let d = (p[0] - c[0]).hypot(p[1] - c[1]);
                    if d <= max_distance_mm {
                        cands.push((d, i));
                    }
                }
            }
        }
        // Nearest first; ties go to the earlier component of the file.
        cands.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        // The half turn first: a row of pads beside another part reflects onto itself
        // across that part's axis more easily than it turns onto itself about its centre.
        let hit = cands
            .iter()
            .find(|&&(_, i)| mirrored(k, top[i], false))
            .or_else(|| cands.iter().find(|&&(_, i)| mirrored(k, top[i], true)));
        match hit {
            Some(&(_, i)) => {
                owner[k] = Some(i);
                symmetric[i] = true;
            }
            None => deferred.push((k, cands)),
        }
    }
    // Pass 2: the nearest component none of whose pads was placed by its mirror image (a
    // footprint that is not symmetric about its centre), else the nearest.
    for (k, cands) in deferred {
        owner[k] = cands
            .iter()
            .find(|&&(_, i)| !symmetric[i])
            .or(cands.first())
            .map(|&(_, i)| i);
    }
    for (k, pad) in pads.iter_mut().enumerate() {
        if pad.component.is_some() {
            continue;
        }
        match owner[k] {
            Some(i) => {
                pad.component = Some(top[i].reference.clone());
                used[i] = true;
                n.from_placement += 1;
                if pad.pin.is_none() {
                    members[i].push(k);
                }
            }
            None => n.unnamed.push(pad.index),
        }
    }
    for (i, m) in members.iter().enumerate() {
        let c = top[i];
        let (s, co) = (-c.rotation_deg).to_radians().sin_cos();
        let mut order: Vec<(i64, i64, usize)> = m
            .iter()
            .map(|&k| {
                let p = pads[k].outline.centroid();
                let (dx, dy) = (p[0] - c.at_mm[0], p[1] - c.at_mm[1]);
                let (u, v) = (co * dx - s * dy, s * dx + co * dy);
                // Rows 10 um apart, top first; then left to right (1 um steps).
                (-(v / 0.01).round() as i64, (u / 0.001).round() as i64, k)
            })
            .collect();
        order.sort();
        for (j, &(_, _, k)) in order.iter().enumerate() {
            pads[k].pin = Some((j + 1).to_string());
        }
    }
    n.components_without_pads = top
        .iter()
        .zip(&used)
        .filter(|(_, u)| !**u)
        .map(|(c, _)| c.reference.clone())
        .collect();
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_gerber::pads::Outline;

    fn pad(index: usize, x: f64, y: f64) -> Pad {
        Pad {
            index,
            outline: Outline::RoundRect {
                centre: [x, y],
                size: [0.5, 0.5],
                radius: 0.0,
                rotation_deg: 0.0,
            },
            component: None,
            pin: None,
            aperture: None,
        }
    }

    fn comp(r: &str, x: f64, y: f64, rot: f64, side: Side) -> Component {
        Component {
            reference: r.into(),
            at_mm: [x, y],
            rotation_deg: rot,
            side,
            package: None,
        }
    }

    #[test]
    fn nearest_top_component_and_reading_order_in_its_frame() {
        // R1 at (10, 10), turned 90 deg: its own "left" pad (u = -1) lies at y = 9 and its
        // "right" pad at y = 11. Reading order in its frame: left first.
        let mut pads = vec![
            pad(0, 10.0, 11.0),
            pad(1, 10.0, 9.0),
            pad(2, 30.0, 30.0),
            pad(3, 20.5, 10.0),
        ];
        pads[3].component = Some("U9".into());
        pads[3].pin = Some("7".into());
        let comps = [
            comp("R1", 10.0, 10.0, 90.0, Side::Top),
            comp("B1", 10.0, 10.2, 0.0, Side::Bottom),
            comp("C5", 21.0, 10.0, 0.0, Side::Top),
        ];
        let n = assign(&mut pads, &comps, 5.0);
        assert_eq!(pads[1].name(), "R1-1");
        assert_eq!(pads[0].name(), "R1-2");
        // Too far from every component: unnamed.
        assert_eq!(pads[2].name(), "#2");
        // The layer's own names are kept.
        assert_eq!(pads[3].name(), "U9-7");
        assert_eq!(n.from_layer, 1);
        assert_eq!(n.from_placement, 2);
        assert_eq!(n.unnamed, vec![2]);
        assert_eq!(n.components_without_pads, vec!["C5".to_string()]);
    }
}
