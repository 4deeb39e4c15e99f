//! Fiducials from the top copper layer.
//!
//! A copper pad is taken as a fiducial when it is
//!
//! 1. round: a disc (a circle flash standing alone, so the reader keeps it a circle) of
//!    [`MIN_DIAMETER_MM`]..=[`MAX_DIAMETER_MM`];
//! 2. bare: no paste opening reaches it (every paste pad's outline is at least its radius
//!    away from its centre: a pad that gets paste is a component's pad);
//! 3. either marked by X2 (its aperture carries `.AperFunction,FiducialPad`), or standing in a
//!    clear ring: no other copper within [`CLEAR_RING`] radii of its centre (a ring at least
//!    one radius wide), as fiducials are drawn for the camera to find them.
//!
//! Candidates of the most common diameter are kept (a board's fiducials are all alike).

use dpsa_gerber::pads::{Outline, Pad, Point};

/// Smallest fiducial diameter taken, mm.
pub const MIN_DIAMETER_MM: f64 = 0.5;
/// Largest fiducial diameter taken, mm.
pub const MAX_DIAMETER_MM: f64 = 3.0;
/// Nearest other copper to a fiducial's centre, in radii.
pub const CLEAR_RING: f64 = 2.0;

/// The fiducials found.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct Found {
    /// Centres, design frame, mm (in the copper layer's order).
    pub points_mm: Vec<Point>,
    /// Their (common) diameter, mm; 0 when none was found.
    pub diameter_mm: f64,
    /// How each was recognised: `x2` or `clear ring`.
    pub how: Vec<&'static str>,
    /// Round bare copper pads that were not taken, and why (at most 20).
    pub rejected: Vec<String>,
}

/// The places (mm) where a Gerber file flashes an aperture it marks `FiducialPad` (X2), read
/// from its text: `%TA.AperFunction,FiducialPad...*%` (or KiCad's `G04 #@! TA...` form)
/// before a `%ADDnn...*%` marks aperture `nn` until the attribute is changed or deleted; then
/// every `D03` (flash) of a marked aperture at the modal coordinates. Absolute coordinates
/// only; flashes inside step-and-repeat blocks are not expanded (their first copy counts).
pub(crate) fn x2_fiducial_flashes(text: &str) -> Vec<Point> {
    let mut scale = 1.0; // mm per unit
    let mut fs: Option<(bool, u32, u32, u32, u32)> = None; // trailing, xi, xd, yi, yd
    let mut fiducial = false;
    let mut marked: Vec<u32> = Vec::new();
    let mut current: Option<u32> = None;
    let (mut x, mut y) = (0.0f64, 0.0f64);
    let mut out = Vec::new();
    let coord = |v: &str, int: u32, dec: u32, trailing: bool| -> Option<f64> {
        let (neg, digits) = match v.as_bytes().first()? {
            b'-' => (true, &v[1..]),
            b'+' => (false, &v[1..]),
            _ => (false, v),
        };
        if digits.is_empty() || !digits.bytes().all(|c| c.is_ascii_digit()) || digits.len() > 18 {
            return None;
        }
        let n: f64 = if trailing {
            let mut d = digits.to_string();
            while (d.len() as u32) < int + dec {
                d.push('0');
            }
            d.parse().ok()?
        } else {
            digits.parse().ok()?
        };
        let v = n / 10f64.powi(dec as i32);
        Some(if neg { -v } else { v })
    };
    for raw in text.split('*') {
        let st = raw
            .trim_start_matches(|c: char| c == '%' || c.is_whitespace())
            .trim();
        let st = st.strip_prefix("G04 #@! ").unwrap_or(st);
        if st.starts_with("G04") {
            continue;
        }
        if let Some(f) = st.strip_prefix("FS") {
            let trailing = f.starts_with('T');
            let digits: Vec<u32> = f.chars().filter_map(|c| c.to_digit(10)).collect();
            if digits.len() == 4 {
                fs = Some((trailing, digits[0], digits[1], digits[2], digits[3]));
            }
        } else if st.starts_with("MOIN") {
            scale = 25.4;
        } else if st.starts_with("MOMM") {
            scale = 1.0;
        } else if let Some(f) = st.strip_prefix("TA.AperFunction,") {
            fiducial = f.starts_with("FiducialPad");
        } else if st.starts_with("TD") && (st == "TD" || st.contains("AperFunction")) {
            fiducial = false;
        } else if let Some(def) = st.strip_prefix("ADD") {
            let code: String = def.chars().take_while(char::is_ascii_digit).collect();
            if let (true, Ok(c)) = (fiducial, code.parse()) {
                marked.push(c);
            }
        } else if st.starts_with(['X', 'Y', 'I', 'J', 'D', 'G']) {
            let st = st.strip_prefix("G54").unwrap_or(st);
            // Select: `Dnn` (nn >= 10) alone.
            if let Some(d) = st.strip_prefix('D') {
                if let Ok(c) = d.parse::<u32>() {
                    if c >= 10 {
                        current = Some(c);
                    }
                    if c == 3 && current.is_some_and(|c| marked.contains(&c)) {
                        out.push([x * scale, y * scale]);
                    }
                }
                continue;
            }
            let Some((trailing, xi, xd, yi, yd)) = fs else {
                continue;
            };
            // X..Y..[I..J..]Dnn: update the modal point; a D03 of a marked aperture counts.
            let body = st.trim_start_matches(|c: char| c == 'G' || c.is_ascii_digit());
            let mut rest = body;
            let mut op = None;
            while let Some(c) = rest.chars().next() {
                let len = rest[1..]
                    .find(|ch: char| ch.is_ascii_alphabetic())
                    .map_or(rest.len(), |i| i + 1);
                let v = &rest[1..len];
                match c {
                    'X' => x = coord(v, xi, xd, trailing).unwrap_or(x),
                    'Y' => y = coord(v, yi, yd, trailing).unwrap_or(y),
                    'D' => op = v.parse::<u32>().ok(),
                    _ => {}
                }
                rest = &rest[len..];
            }
            if op == Some(3) && current.is_some_and(|c| marked.contains(&c)) {
                out.push([x * scale, y * scale]);
            }
        }
    }
    out
}

/// Boxes on a grid of cells: which boxes, grown by the largest reach a search uses, cover a
/// point's cell. A box covering more than [`BoxIndex::MAX_CELLS`] cells (a copper pour) is
/// kept aside and checked for every point.
struct BoxIndex {
    cell: f64,
    cells: std::collections::HashMap<(i64, i64), Vec<usize>>,
    big: Vec<usize>,
}

impl BoxIndex {
    const MAX_CELLS: i64 = 4096;
    /// The largest reach of a search, mm: the clear ring of the widest fiducial.
    const REACH: f64 = CLEAR_RING * MAX_DIAMETER_MM / 2.0;

    fn new(boxes: &[[f64; 4]]) -> BoxIndex {
        let cell = 4.0;
        let mut ix = BoxIndex {
            cell,
            cells: Default::default(),
            big: Vec::new(),
        };
        for (i, b) in boxes.iter().enumerate() {
            let lo = ix.key([b[0] - Self::REACH, b[1] - Self::REACH]);
            let hi = ix.key([b[2] + Self::REACH, b[3] + Self::REACH]);
            if (hi.0 - lo.0 + 1).saturating_mul(hi.1 - lo.1 + 1) > Self::MAX_CELLS {
                ix.big.push(i);
                continue;
            }
            for gx in lo.0..=hi.0 {
                for gy in lo.1..=hi.1 {
                    ix.cells.entry((gx, gy)).or_default().push(i);
                }
            }
        }
        ix
    }

    fn key(&self, p: Point) -> (i64, i64) {
        (
            (p[0] / self.cell).floor() as i64,
            (p[1] / self.cell).floor() as i64,
        )
    }

    /// The boxes that may lie within [`BoxIndex::REACH`] of `p`.
    fn near(&self, p: Point) -> impl Iterator<Item = usize> + '_ {
        self.cells
            .get(&self.key(p))
            .into_iter()
            .flatten()
            .chain(&self.big)
            .copied()
    }
}

/// Finds the fiducials among the copper pads (see the module's rule). `x2` holds the places
/// of the file's X2 fiducial flashes ([`x2_fiducial_flashes`]).
pub(crate) fn find(copper: &[Pad], paste: &[Pad], x2: &[Point]) -> Found {
    let mut found = Found::default();
    let mut cands: Vec<(Point, f64, &'static str)> = Vec::new();
    let paste_boxes: Vec<[f64; 4]> = paste.iter().map(|p| p.outline.bbox()).collect();
    let copper_boxes: Vec<[f64; 4]> = copper.iter().map(|p| p.outline.bbox()).collect();
    let paste_ix = BoxIndex::new(&paste_boxes);
    let copper_ix = BoxIndex::new(&copper_boxes);
    for (k, pad) in copper.iter().enumerate() {
        let Outline::Circle { centre, diameter } = pad.outline else {
            continue;
        };
        if !(MIN_DIAMETER_MM..=MAX_DIAMETER_MM).contains(&diameter) {
            continue;
        }
        let r = diameter / 2.0;
        let near = |b: &[f64; 4], reach: f64| {
            centre[0] >= b[0] - reach
                && centre[0] <= b[2] + reach
                && centre[1] >= b[1] - reach
                && centre[1] <= b[3] + reach
        };
        let pasted = paste_ix
            .near(centre)
            .any(|j| near(&paste_boxes[j], r) && paste[j].outline.signed_distance(centre) < r);
        let at = format!("({:.3}, {:.3}) d {:.3}", centre[0], centre[1], diameter);
        if pasted {
            if found.rejected.len() < 20 {
                found.rejected.push(format!("{at}: paste on it"));
            }
            continue;
        }
        let marked = x2
            .iter()
            .any(|q| (q[0] - centre[0]).hypot(q[1] - centre[1]) < 1e-3);
        if marked {
            cands.push((centre, diameter, "x2"));
            continue;
        }
        let reach = CLEAR_RING * r;
        let crowded = copper_ix.near(centre).any(|j| {
            j != k
                && near(&copper_boxes[j], reach)
                && copper[j].outline.signed_distance(centre) < reach
        });
        if crowded {
            if found.rejected.len() < 20 {
                found
                    .rejected
                    .push(format!("{at}: other copper within {CLEAR_RING} radii"));
            }
            continue;
        }
        cands.push((centre, diameter, "clear ring"));
    }
    // The most common diameter (to 1 um); ties: the larger.
    let mut counts: Vec<(i64, usize)> = Vec::new();
    for c in &cands {
        let key = (c.1 * 1000.0).round() as i64;
        match counts.iter_mut().find(|(k, _)| *k == key) {
            Some(e) => e.1 += 1,
            None => counts.push((key, 1)),
        }
    }
    if let Some(&(key, _)) = counts.iter().max_by_key(|(k, n)| (*n, *k)) {
        for c in cands {
            if (c.1 * 1000.0).round() as i64 == key {
                found.points_mm.push(c.0);
                found.diameter_mm = c.1;
                found.how.push(c.2);
            } else if found.rejected.len() < 20 {
                found.rejected.push(format!(
                    "({:.3}, {:.3}) d {:.3}: not the fiducials' diameter {:.3}",
                    c.0[0],
                    c.0[1],
                    c.1,
                    key as f64 / 1000.0
                ));
            }
        }
    }
    found
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn x2_fiducial_flashes_are_read_in_both_forms() {
        // Inch, leading zeros omitted: the marked D12 flashed twice (the second at a modal
        // X), D13 (same size, unmarked) not.
        let t = "%FSLAX24Y24*%\n%MOIN*%\n%TA.AperFunction,FiducialPad,Local*%\n%ADD12C,0.0400*%\n%TD*%\n%ADD13C,0.0400*%\nD12*\nX10000Y-5000D03*\nY20000D03*\nD13*\nX30000Y0D03*\nM02*\n";
        let f = x2_fiducial_flashes(t);
        assert_eq!(f.len(), 2, "{f:?}");
        assert!((f[0][0] - 25.4).abs() < 1e-9 && (f[0][1] + 12.7).abs() < 1e-9);
        assert!((f[1][0] - 25.4).abs() < 1e-9 && (f[1][1] - 50.8).abs() < 1e-9);
        let t = "%FSLAX46Y46*%\n%MOMM*%\nG04 #@! TA.AperFunction,FiducialPad,Global*\n%ADD20C,1.000000*%\nG04 #@! TA.AperFunction,SMDPad,CuDef*\n%ADD21C,1.5*%\nG04 next*\nD20*\nX1500000Y2000000D03*\nG54D21*\nX0Y0D03*\nM02*\n";
        assert_eq!(x2_fiducial_flashes(t), vec![[1.5, 2.0]]);
    }
}
