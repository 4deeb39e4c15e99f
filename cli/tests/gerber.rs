//! The paste layer (Gerber) as pads: real files from six open-hardware boards (KiCad 5, 6, 7,
//! 9, EasyEDA, Eagle) against independent counts, synthetic files for every feature with
//! exact areas and centroids, bad input, and `dpsa pads`.

use dpsa_sim::inspection::gerber::{read_file, read_str, GerberError, PasteLayer};
use dpsa_sim::inspection::pads::{Outline, Pad};
use std::f64::consts::PI;
use std::path::{Path, PathBuf};

fn data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data/gerber")
        .join(rel)
}

fn layer(text: &str) -> PasteLayer {
    match read_str(text) {
        Ok(l) => l,
        Err(e) => panic!("{e}\n{text}"),
    }
}

/// `a` and `b` are the same outline within `tol` in every number.
#[track_caller]
fn same(a: &Outline, b: &Outline, tol: f64) {
    let nums = |o: &Outline| -> Vec<f64> {
        match o {
            Outline::Circle { centre, diameter } => vec![centre[0], centre[1], *diameter],
            Outline::RoundRect {
                centre,
                size,
                radius,
                rotation_deg,
            } => vec![
                centre[0],
                centre[1],
                size[0],
                size[1],
                *radius,
                *rotation_deg,
            ],
            Outline::Polygon { .. } => vec![f64::NAN],
        }
    };
    let (x, y) = (nums(a), nums(b));
    assert!(
        x.len() == y.len() && x.iter().zip(&y).all(|(p, q)| (p - q).abs() <= tol),
        "{a:?} vs {b:?}"
    );
}

#[track_caller]
fn close(a: f64, b: f64, tol: f64) {
    assert!((a - b).abs() <= tol, "{a} vs {b} (tol {tol})");
}

/// Area tolerance for curved outlines made of chords within 1 um: perimeter x 1 um, doubled.
fn curve_tol(p: &Pad) -> f64 {
    2e-3 * p.outline.perimeter() + 1e-9
}

// --- an independent reading of simple files ---------------------------------------------

/// What a plain text scan finds: the flash points (mm) and the number of regions. It knows
/// only `%FS`, `%MO`, `X..Y..D03` (modal X/Y) and `G36`, and no geometry: enough for files
/// that flash or region isolated pads.
struct Scan {
    flashes: Vec<[f64; 2]>,
    regions: usize,
}

fn scan(text: &str) -> Scan {
    let mut decimals = 6u32;
    let mut unit = 1.0;
    let mut cur = [0.0f64; 2];
    let mut flashes = Vec::new();
    let mut regions = 0;
    for word in text.split('*') {
        let w = word.trim().trim_start_matches('%').trim();
        if let Some(fs) = w.strip_prefix("FSLAX") {
            decimals = fs[1..2].parse().expect("FS digits");
        } else if w == "MOIN" {
            unit = 25.4;
        } else if w == "MOMM" {
            unit = 1.0;
        } else if w.starts_with("G36") {
            regions += 1;
        } else if w.ends_with("D03") && (w.starts_with('X') || w.starts_with('Y')) {
            let num = |axis: char| -> Option<f64> {
                let at = w.find(axis)? + 1;
                let digits: String = w[at..]
                    .chars()
                    .take_while(|c| c.is_ascii_digit() || *c == '-' || *c == '+')
                    .collect();
                Some(digits.parse::<f64>().ok()? / 10f64.powi(decimals as i32) * unit)
            };
            if let Some(x) = num('X') {
                cur[0] = x;
            }
            if let Some(y) = num('Y') {
                cur[1] = y;
            }
            flashes.push(cur);
        }
    }
    Scan { flashes, regions }
}

/// Every scanned flash point is the centre of exactly one pad with an exact outline.
#[track_caller]
fn flashes_are_pads(l: &PasteLayer, s: &Scan) {
    let mut centres: Vec<[f64; 2]> = l
        .pads
        .iter()
        .filter(|p| !matches!(p.outline, Outline::Polygon { .. }))
        .map(|p| p.outline.centroid())
        .collect();
    assert_eq!(centres.len(), s.flashes.len(), "flashed pads");
    for f in &s.flashes {
        let i = centres
            .iter()
            .position(|c| (c[0] - f[0]).abs() < 1e-9 && (c[1] - f[1]).abs() < 1e-9)
            .unwrap_or_else(|| panic!("no pad at flash {f:?}"));
        centres.swap_remove(i);
    }
}

// --- real files ---------------------------------------------------------------------------

#[test]
fn kicad5_flashes_and_regions_stm32_mini_pill() {
    let path = data("stm32-mini-pill/pcb-F_Paste.gbr");
    let l = read_file(&path).expect("reads");
    let s = scan(&std::fs::read_to_string(&path).expect("text"));
    assert_eq!((s.flashes.len(), s.regions), (54, 48));
    assert_eq!(l.pads.len(), 54 + 48); // gerbonara + shapely: 102
    flashes_are_pads(&l, &s);
    assert_eq!(l.units, "mm");
    assert_eq!(l.generator.as_deref(), Some("KiCad,Pcbnew,(5.1.5)-3"));
    // KiCad 5 writes its rounded pads as regions: 48 polygons of 1.475 x 0.3 mm (r 0.075).
    let regions: Vec<&Pad> = l
        .pads
        .iter()
        .filter(|p| p.aperture.as_deref() == Some("region"))
        .collect();
    assert_eq!(regions.len(), 48);
    let exact = 1.475 * 0.3 - (4.0 - PI) * 0.075 * 0.075;
    for p in &regions {
        close(p.outline.area(), exact, 2e-3);
    }
    // A pad by hand: D10 (R 1.9 x 1.9) at X128196000 Y-110320000.
    let p = l
        .pads
        .iter()
        .find(|p| p.aperture.as_deref() == Some("R 1.90x1.90"))
        .expect("D10 pad");
    same(
        &p.outline,
        &Outline::RoundRect {
            centre: [128.196, -110.32],
            size: [1.9, 1.9],
            radius: 0.0,
            rotation_deg: 0.0,
        },
        1e-12,
    );
    close(l.bbox_mm[0], 127.246, 1e-6);
    close(l.bbox_mm[3], -100.492, 1e-6);
}

#[test]
fn kicad6_roundrect_macros_heart() {
    let path = data("colordance-circle/heart-F_Paste.gtp");
    let l = read_file(&path).expect("reads");
    let s = scan(&std::fs::read_to_string(&path).expect("text"));
    assert_eq!((s.flashes.len(), s.regions), (68, 0));
    assert_eq!(l.pads.len(), 68);
    flashes_are_pads(&l, &s);
    // Every pad is exact (R or RoundRect), every pad is named (X2 %TO.C).
    assert!(l
        .pads
        .iter()
        .all(|p| matches!(p.outline, Outline::RoundRect { .. })));
    assert!(l.pads.iter().all(|p| p.component.is_some()));
    // D11 RoundRect,0.2 X -0.2/-0.275 .. : 0.8 x 0.95 mm, r 0.2.
    let d11 = l
        .pads
        .iter()
        .find(|p| p.aperture.as_deref() == Some("RoundRect 0.80x0.95 r0.20"))
        .expect("D11 class");
    match d11.outline {
        Outline::RoundRect {
            size,
            radius,
            rotation_deg,
            ..
        } => {
            close(size[0], 0.8, 1e-9);
            close(size[1], 0.95, 1e-9);
            close(radius, 0.2, 1e-9);
            close(rotation_deg, 0.0, 1e-9);
        }
        _ => unreachable!(),
    }
    assert_eq!(l.pads[0].component.as_deref(), Some("D1"));
    // D12 RoundRect,0.225 with corners (+-0.25, +-0.225): 0.95 x 0.9 mm, r 0.225.
    let d12 = l
        .pads
        .iter()
        .find(|p| p.aperture.as_deref() == Some("RoundRect 0.95x0.90 r0.225"))
        .expect("D12 class");
    close(
        d12.outline.area(),
        0.95 * 0.9 - (4.0 - PI) * 0.225 * 0.225,
        1e-9,
    );
}

#[test]
fn kicad7_and_kicad9_named_pads() {
    let l = read_file(&data("colordance-circle/colordance-brain-F_Paste.gtp")).expect("reads");
    assert_eq!(l.pads.len(), 4);
    let names: Vec<String> = l.pads.iter().map(Pad::name).collect();
    assert_eq!(names, ["D1#0", "D1#1", "BT1#2", "BT1#3"]);
    assert_eq!(
        l.generator.as_deref(),
        Some("KiCad,Pcbnew,7.0.2-6a45011f42~172~ubuntu22.04.1")
    );
    let l = read_file(&data("pd-stepper-blinds/power-pcb-F_Paste.gtp")).expect("reads");
    assert_eq!(l.pads.len(), 3);
    let comps: Vec<&str> = l
        .pads
        .iter()
        .filter_map(|p| p.component.as_deref())
        .collect();
    assert_eq!(comps, ["GND", "VBUS", "NTC"]);
    for p in &l.pads {
        close(p.outline.area(), 4.5 * 2.75, 1e-9);
    }
}

#[test]
fn easyeda_unclosed_regions_obrounds_rotated_macro() {
    let path = data("simplefocmini/Gerber_TopPasteMaskLayer.GTP");
    let l = read_file(&path).expect("reads");
    let s = scan(&std::fs::read_to_string(&path).expect("text"));
    assert_eq!((s.flashes.len(), s.regions), (39, 10));
    assert_eq!(l.pads.len(), 49); // gerbonara + shapely: 49
    flashes_are_pads(&l, &s);
    assert!(l.generator.is_none());
    assert!(l
        .warnings
        .iter()
        .any(|w| w.contains("10 region contour(s) not closed")));
    // Obround 0.343 x 1.731: a RoundRect with the half short side as radius.
    let o = l
        .pads
        .iter()
        .find(|p| p.aperture.as_deref().is_some_and(|a| a.starts_with("O ")))
        .expect("obround");
    match o.outline {
        Outline::RoundRect { size, radius, .. } => close(radius, size[0].min(size[1]) / 2.0, 1e-12),
        _ => panic!("{o:?}"),
    }
    // MACRO1 = one centre line 2.7501 x 6.2001 turned by 90 degrees.
    let m = l
        .pads
        .iter()
        .find(|p| {
            p.aperture
                .as_deref()
                .is_some_and(|a| a.starts_with("MACRO1"))
        })
        .expect("macro pad");
    match m.outline {
        Outline::RoundRect {
            size, rotation_deg, ..
        } => {
            close(size[0], 2.7501, 1e-9);
            close(size[1], 6.2001, 1e-9);
            close(rotation_deg, 90.0, 1e-9);
        }
        _ => panic!("{m:?}"),
    }
    // Total paste area as gerbonara + shapely found it: 53.742 mm^2.
    close(
        l.pads.iter().map(|p| p.outline.area()).sum::<f64>(),
        53.742,
        1e-3,
    );
}

#[test]
fn eagle_hatched_pads_merge() {
    // Eagle fills some pads with strokes of a 0.0675 mm circle: 509 objects, 237 openings
    // (gerbonara + shapely: 237, 183.337 mm^2).
    let l = read_file(&data("snappergps-pcb-2/solderpaste_top.gbr")).expect("reads");
    assert_eq!(l.pads.len(), 237);
    let stroked: Vec<&Pad> = l
        .pads
        .iter()
        .filter(|p| matches!(p.outline, Outline::Polygon { .. }))
        .collect();
    assert_eq!(stroked.len(), 28);
    let total: f64 = l.pads.iter().map(|p| p.outline.area()).sum();
    close(total, 183.337, 0.1);
    // The first hatched pad: a 2.026 x 7.926 mm rectangle outline (0.0675 strokes about
    // X17.4557..17.6583, Y7.7792..8.5718 cm-ish coordinates, format 3.4).
    let p = stroked
        .iter()
        .find(|p| {
            let c = p.outline.centroid();
            (c[0] - 17.557).abs() < 0.01 && (c[1] - 8.1755).abs() < 0.01
        })
        .expect("hatched pad at (17.557, 8.176)");
    let b = p.outline.bbox();
    close(b[2] - b[0], 0.2026 + 0.0675, 1e-3);
    close(b[3] - b[1], 0.7926 + 0.0675, 1e-3);
}

// --- synthetic files: every feature with exact figures -----------------------------------

const MM: &str = "%FSLAX46Y46*%\n%MOMM*%\n";

#[test]
fn inch_trailing_zeros_incremental() {
    // Trailing-zero format 2.4: "X01" = 01.0000 inch; incremental: each move adds.
    let l = layer("%FSTIX24Y24*%\n%MOIN*%\n%ADD10C,0.1*%\nD10*\nX01Y01D03*\nX01Y-005D03*\nM02*\n");
    assert_eq!(l.units, "inch");
    assert_eq!(l.pads.len(), 2);
    same(
        &l.pads[0].outline,
        &Outline::Circle {
            centre: [25.4, 25.4],
            diameter: 2.54,
        },
        1e-12,
    );
    let c = l.pads[1].outline.centroid();
    close(c[0], 50.8, 1e-9);
    close(c[1], 25.4 - 12.7, 1e-9);
    // The same with the deprecated G91 word and leading zeros omitted.
    let l = layer(
        "%FSLAX24Y24*%\n%MOIN*%\nG91*\n%ADD10C,0.1*%\nD10*\nX10000Y0D03*\nX10000D03*\nM02*\n",
    );
    close(l.pads[1].outline.centroid()[0], 50.8, 1e-9);
}

#[test]
fn step_and_repeat() {
    let l = layer(&format!(
        "{MM}%ADD10R,1X0.5*%\n%SRX3Y2I5.0J4.0*%\nD10*\nX0Y0D03*\n%SR*%\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 6);
    let mut centres: Vec<[f64; 2]> = l.pads.iter().map(|p| p.outline.centroid()).collect();
    centres.sort_by(|a, b| a[1].total_cmp(&b[1]).then(a[0].total_cmp(&b[0])));
    let want = [[0., 0.], [5., 0.], [10., 0.], [0., 4.], [5., 4.], [10., 4.]];
    for (c, w) in centres.iter().zip(want) {
        close(c[0], w[0], 1e-12);
        close(c[1], w[1], 1e-12);
    }
    close(l.bbox_mm[2], 10.5, 1e-12);
}

#[test]
fn clear_polarity_splits_a_pad_in_two() {
    // A 4 x 1 rectangle, then a clear 0.5 x 2 bar through its middle: two 1.75 x 1 pads.
    let l = layer(&format!(
        "{MM}%ADD10R,4X1*%\n%ADD11R,0.5X2*%\nD10*\nX0Y0D03*\n%LPC*%\nD11*\nX0Y0D03*\n%LPD*%\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 2);
    let mut c: Vec<[f64; 2]> = l.pads.iter().map(|p| p.outline.centroid()).collect();
    c.sort_by(|a, b| a[0].total_cmp(&b[0]));
    close(c[0][0], -1.125, 1e-9);
    close(c[1][0], 1.125, 1e-9);
    for p in &l.pads {
        close(p.outline.area(), 1.75, 1e-9);
    }
    // A clear object only removes what came before it: dark after clear stays.
    let l = layer(&format!(
        "{MM}%ADD10R,4X1*%\n%ADD11R,0.5X2*%\n%LPC*%\nD11*\nX0Y0D03*\n%LPD*%\nD10*\nX0Y0D03*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 1);
    close(l.pads[0].outline.area(), 4.0, 1e-12);
    // A clear hole inside a pad: one pad with a hole.
    let l = layer(&format!(
        "{MM}%ADD10R,2X2*%\n%ADD11R,0.5X0.5*%\nD10*\nX0Y0D03*\n%LPC*%\nD11*\nX0Y0D03*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 1);
    close(l.pads[0].outline.area(), 4.0 - 0.25, 1e-9);
    assert!(matches!(&l.pads[0].outline, Outline::Polygon { holes, .. } if holes.len() == 1));
}

#[test]
fn overlapping_and_touching_flashes_merge() {
    // Two 1 mm circles 0.5 mm apart: one pad of 2 discs minus their lens.
    let l = layer(&format!(
        "{MM}%ADD10C,1*%\nD10*\nX0Y0D03*\nX500000Y0D03*\nX5000000Y0D03*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 2);
    let (r, d) = (0.5f64, 0.5f64);
    let lens = 2.0 * r * r * (d / (2.0 * r)).acos() - d / 2.0 * (4.0 * r * r - d * d).sqrt();
    let merged = &l.pads[0];
    close(
        merged.outline.area(),
        2.0 * PI * r * r - lens,
        curve_tol(merged),
    );
    close(merged.outline.centroid()[0], 0.25, 1e-4);
    assert_eq!(merged.aperture.as_deref(), Some("C 1.00"));
    // The lone third circle stays exact.
    assert!(matches!(l.pads[1].outline, Outline::Circle { .. }));
    // Rectangles sharing an edge are one pad.
    let l = layer(&format!(
        "{MM}%ADD10R,1X1*%\nD10*\nX0Y0D03*\nX1000000Y0D03*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 1);
    close(l.pads[0].outline.area(), 2.0, 1e-9);
    close(l.pads[0].outline.centroid()[0], 0.5, 1e-9);
}

#[test]
fn stroked_pads() {
    // C 0.2 from (0,0) to (2,0): a capsule; R 0.2 x 0.4 from (0,5) to (1,5): 1.2 x 0.4.
    let l = layer(&format!(
        "{MM}%ADD10C,0.2*%\n%ADD11R,0.2X0.4*%\nG01*\nD10*\nX0Y0D02*\nX2000000Y0D01*\nD11*\nX0Y5000000D02*\nX1000000Y5000000D01*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 2);
    let cap = &l.pads[0];
    close(cap.outline.area(), 2.0 * 0.2 + PI * 0.01, curve_tol(cap));
    close(cap.outline.centroid()[0], 1.0, 1e-9);
    assert_eq!(cap.aperture.as_deref(), Some("stroke C 0.20"));
    // Through the overlay, which snaps to a grid of about 2^-28 of the shape's extent (a few
    // nm here): exact to 1e-8 mm^2.
    close(l.pads[1].outline.area(), 1.2 * 0.4, 1e-8);
    let c = l.pads[1].outline.centroid();
    close(c[0], 0.5, 1e-9);
    close(c[1], 5.0, 1e-9);
}

#[test]
fn rotated_macro_outline_and_centre_line() {
    // A right triangle (outline primitive) turned by 30 degrees about the macro origin.
    let l = layer(&format!(
        "{MM}%AMTRI*\n4,1,3,0,0,1,0,0,1,0,0,$1*%\n%ADD10TRI,30*%\nD10*\nX10000000Y0D03*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 1);
    let p = &l.pads[0];
    // The polygon union works on a fine integer grid: 1e-8 mm^2.
    close(p.outline.area(), 0.5, 1e-8);
    let (s, c) = 30f64.to_radians().sin_cos();
    let g = [1.0 / 3.0, 1.0 / 3.0];
    let want = [10.0 + c * g[0] - s * g[1], s * g[0] + c * g[1]];
    close(p.outline.centroid()[0], want[0], 1e-8);
    close(p.outline.centroid()[1], want[1], 1e-8);
    assert_eq!(p.aperture.as_deref(), Some("TRI"));
    // A centre line with a rotation parameter and an expression: exact RoundRect.
    let l = layer(&format!(
        "{MM}%AMBAR*\n$3=$1x2*\n21,1,$3,$2,0,0,$4*%\n%ADD10BAR,0.5X0.4X0X30*%\nD10*\nX0Y0D03*\nM02*\n"
    ));
    same(
        &l.pads[0].outline,
        &Outline::RoundRect {
            centre: [0.0, 0.0],
            size: [1.0, 0.4],
            radius: 0.0,
            rotation_deg: 30.0,
        },
        1e-12,
    );
    // %LR turns a plain rectangle flash.
    let l = layer(&format!(
        "{MM}%ADD10R,1X0.5*%\n%LR45*%\nD10*\nX0Y0D03*\nM02*\n"
    ));
    assert!(
        matches!(l.pads[0].outline, Outline::RoundRect { rotation_deg, .. } if (rotation_deg - 45.0).abs() < 1e-9)
    );
}

#[test]
fn kicad_roundrect_and_four_circle_rounded_rectangles_are_exact() {
    let kicad = "%AMRoundRect*\n0 Rectangle with rounded corners*\n4,1,4,$2,$3,$4,$5,$6,$7,$8,$9,$2,$3,0*\n1,1,$1+$1,$2,$3*\n1,1,$1+$1,$4,$5*\n1,1,$1+$1,$6,$7*\n1,1,$1+$1,$8,$9*\n20,1,$1+$1,$2,$3,$4,$5,0*\n20,1,$1+$1,$4,$5,$6,$7,0*\n20,1,$1+$1,$6,$7,$8,$9,0*\n20,1,$1+$1,$8,$9,$2,$3,0*%\n";
    let l = layer(&format!(
        "{MM}{kicad}%ADD10RoundRect,0.25X-0.5X-0.3X0.5X-0.3X0.5X0.3X-0.5X0.3X0*%\nD10*\nX1000000Y2000000D03*\nM02*\n"
    ));
    same(
        &l.pads[0].outline,
        &Outline::RoundRect {
            centre: [1.0, 2.0],
            size: [1.5, 1.1],
            radius: 0.25,
            rotation_deg: 0.0,
        },
        1e-12,
    );
    // A KiCad RoundRect turned by 30 degrees (its corners turned): the same shape as the
    // reference outline everywhere.
    let (s30, c30) = 30f64.to_radians().sin_cos();
    let corners: Vec<String> = [[-0.5, -0.3], [0.5, -0.3], [0.5, 0.3], [-0.5, 0.3]]
        .iter()
        .map(|p: &[f64; 2]| {
            format!(
                "{:.6}X{:.6}",
                c30 * p[0] - s30 * p[1],
                s30 * p[0] + c30 * p[1]
            )
        })
        .collect();
    let l = layer(&format!(
        "{MM}{kicad}%ADD10RoundRect,0.1X{}X0*%\nD10*\nX0Y0D03*\nM02*\n",
        corners.join("X")
    ));
    let reference = Outline::RoundRect {
        centre: [0.0, 0.0],
        size: [1.2, 0.8],
        radius: 0.1,
        rotation_deg: 30.0,
    };
    assert!(
        matches!(l.pads[0].outline, Outline::RoundRect { .. }),
        "{:?}",
        l.pads[0]
    );
    for i in 0..=20 {
        for j in 0..=20 {
            let p = [-0.8 + 0.08 * f64::from(i), -0.8 + 0.08 * f64::from(j)];
            close(
                l.pads[0].outline.signed_distance(p),
                reference.signed_distance(p),
                2e-6,
            );
        }
    }
    // Altium-style: two centre lines and four corner circles.
    let l = layer(&format!(
        "{MM}%AMRR*\n21,1,1.0,0.4,0,0,0*\n21,1,0.8,0.6,0,0,0*\n1,1,0.2,0.4,0.2*\n1,1,0.2,-0.4,0.2*\n1,1,0.2,-0.4,-0.2*\n1,1,0.2,0.4,-0.2*%\n%ADD10RR*%\nD10*\nX0Y0D03*\nM02*\n"
    ));
    same(
        &l.pads[0].outline,
        &Outline::RoundRect {
            centre: [0.0, 0.0],
            size: [1.0, 0.6],
            radius: 0.1,
            rotation_deg: 0.0,
        },
        1e-12,
    );
    // Four corner circles alone do not fill a rectangle: a polygon.
    let l = layer(&format!(
        "{MM}%AMDOTS*\n1,1,0.2,0.4,0.2*\n1,1,0.2,-0.4,0.2*\n1,1,0.2,-0.4,-0.2*\n1,1,0.2,0.4,-0.2*%\n%ADD10DOTS*%\nD10*\nX0Y0D03*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 4);
}

#[test]
fn arcs_in_regions_and_holes() {
    // A half disc: line from (-1,0) to (1,0), counter-clockwise arc back about (0,0).
    let l = layer(&format!(
        "{MM}G75*\nG36*\nX-1000000Y0D02*\nG01*\nX1000000Y0D01*\nG03*\nX-1000000Y0I-1000000J0D01*\nG37*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 1);
    let p = &l.pads[0];
    close(p.outline.area(), PI / 2.0, curve_tol(p));
    // Centroids of curved outlines: within the 1 um of the chords.
    close(p.outline.centroid()[1], 4.0 / (3.0 * PI), 1e-3);
    // Clockwise the other way: the lower half.
    let l = layer(&format!(
        "{MM}G75*\nG36*\nX-1000000Y0D02*\nG01*\nX1000000Y0D01*\nG02*\nX-1000000Y0I-1000000J0D01*\nG37*\nM02*\n"
    ));
    close(l.pads[0].outline.centroid()[1], -4.0 / (3.0 * PI), 1e-3);
    // A circle aperture with a hole, a rectangle with a hole.
    let l = layer(&format!(
        "{MM}%ADD10C,1X0.4*%\n%ADD11R,2X1X0.5*%\nD10*\nX0Y0D03*\nD11*\nX5000000Y0D03*\nM02*\n"
    ));
    let p = &l.pads[0];
    close(p.outline.area(), PI * (0.25 - 0.04), curve_tol(p));
    close(
        l.pads[1].outline.area(),
        2.0 - PI * 0.0625,
        curve_tol(&l.pads[1]),
    );
    assert_eq!(l.pads[0].aperture.as_deref(), Some("C 1.00"));
}

#[test]
fn x2_component_and_pin_attributes() {
    let l = layer(&format!(
        "{MM}%ADD10C,0.5*%\nD10*\n%TO.C,R1*%\nX0Y0D03*\n%TO.P,U3,14*%\nX2000000Y0D03*\n%TD*%\nX4000000Y0D03*\n%TO.C,C7*%\nX6000000Y0D03*\n%TD.C*%\nX8000000Y0D03*\nM02*\n"
    ));
    let names: Vec<String> = l.pads.iter().map(Pad::name).collect();
    assert_eq!(names, ["R1#0", "U3-14", "#2", "C7#3", "#4"]);
}

// --- bad input ----------------------------------------------------------------------------

#[track_caller]
fn fails(text: &str) -> GerberError {
    match read_str(text) {
        Ok(l) => panic!("accepted ({} pads):\n{text}", l.pads.len()),
        Err(e) => e,
    }
}

#[test]
fn bad_input_is_a_clear_error() {
    let e = fails(&format!("{MM}%AMFOO*\n1,1,1,0,0*\n%ADD10C,1*%\nM02*\n"));
    assert!(
        matches!(
            e,
            GerberError::Syntax { .. } | GerberError::UnterminatedMacro { .. }
        ),
        "{e}"
    );
    let e = fails(&format!("{MM}%AMFOO*\n1,1,1,0,0*\n"));
    assert!(
        matches!(e, GerberError::UnterminatedMacro { line: 3 }),
        "{e}"
    );
    let e = fails(&format!("{MM}%ADD10C,1*%\nD11*\nX0Y0D03*\nM02*\n"));
    assert!(
        matches!(e, GerberError::UndefinedAperture { line: 5, code: 11 }),
        "{e}"
    );
    let e = fails(&format!(
        "{MM}G36*\nX0Y0D02*\nX1000000Y0D01*\nX0Y1000000D01*\n"
    ));
    assert!(matches!(e, GerberError::UnclosedRegion { line: 3 }), "{e}");
    // A contour of one segment draws nothing (Altium and TARGET 3001! write such slivers):
    // skipped with a warning, not a pad.
    let l = read_str(&format!(
        "{MM}%ADD10C,1*%\nD10*\nX5000000Y0D03*\nG36*\nX0Y0D02*\nX1000000Y0D01*\nG37*\nM02*\n"
    ))
    .unwrap();
    assert_eq!(l.pads.len(), 1);
    assert!(
        l.warnings
            .iter()
            .any(|w| w.contains("1 region contour(s) with no area")),
        "{:?}",
        l.warnings
    );
    let e = fails("%FSLAX46Y46*%\n%ADD10C,1*%\nD10*\nX0Y0D03*\nM02*\n");
    assert!(matches!(e, GerberError::NoUnits { line: 2 }), "{e}");
    let e = fails("%FSLAX46Y46*%\n%MOIN*%\n%ADD10C,0.01*%\nD10*\nX9999000000Y0D03*\nM02*\n");
    assert!(matches!(e, GerberError::OutOfRange { line: 5, .. }), "{e}");
    let e = fails(&format!("{MM}%ADD10C,100000*%\nM02*\n"));
    assert!(matches!(e, GerberError::OutOfRange { line: 3, .. }), "{e}");
    let e = fails(&format!(
        "{MM}%ADD10C,1*%\n%SRX100000Y100000I0.1J0.1*%\nD10*\nX0Y0D03*\n%SR*%\nM02*\n"
    ));
    assert!(matches!(e, GerberError::TooManyObjects { .. }), "{e}");
    let e = fails(&format!(
        "{MM}%ADD10C,1*%\n%SRX1000Y999I0.01J0.01*%\nD10*\nX0Y0D03*\nX1Y0D03*\n%SR*%\nM02*\n"
    ));
    assert!(matches!(e, GerberError::TooManyObjects { .. }), "{e}");
    let e = fails("\u{0}\u{1}\u{2}garbage\u{7f}");
    assert!(matches!(e, GerberError::Binary { line: 1 }), "{e}");
    let e = fails(&format!(
        "{MM}%ADD10O,1X0.5*%\nD10*\nX0Y0D02*\nX1000000Y0D01*\nM02*\n"
    ));
    assert!(matches!(e, GerberError::Unsupported { line: 6, .. }), "{e}");
    let e = fails(&format!("{MM}G0*\nM02*\n"));
    assert!(matches!(e, GerberError::Syntax { line: 3, .. }), "{e}");
    // Every error names its line in its message.
    assert!(fails(&format!("{MM}%ADD10C,1*%\nD11*\nX0Y0D03*\n"))
        .to_string()
        .starts_with("line 5"));
}

#[test]
fn missing_m02_is_a_warning_when_the_geometry_is_complete() {
    let l = layer(&format!("{MM}%ADD10C,1*%\nD10*\nX0Y0D03*\n"));
    assert_eq!(l.pads.len(), 1);
    assert!(
        l.warnings.iter().any(|w| w.contains("no M02")),
        "{:?}",
        l.warnings
    );
    // ...but an open step and repeat at the end is not complete.
    let e = fails(&format!("{MM}%ADD10C,1*%\n%SRX2Y1I1J0*%\nD10*\nX0Y0D03*\n"));
    assert!(matches!(e, GerberError::Truncated { line: 4, .. }), "{e}");
}

#[test]
fn size_cap_and_binary_files() {
    let big = " ".repeat((64 << 20) + 1);
    assert!(matches!(read_str(&big), Err(GerberError::TooLarge { .. })));
    let dir = tempfile::tempdir().expect("tempdir");
    let p = dir.path().join("bin.gbr");
    std::fs::write(&p, [b'%', b'F', b'S', 0xff, 0xfe, b'\n']).expect("write");
    assert!(matches!(
        read_file(&p),
        Err(GerberError::Binary { line: 1 })
    ));
    let e = read_file(&dir.path().join("missing.gbr")).expect_err("missing file");
    assert!(e.to_string().contains("missing.gbr"));
}

#[test]
fn arbitrary_text_never_panics() {
    use proptest::prelude::*;
    let alphabet = prop::sample::select(
        "%*XYIJD0123456789-.,GMFSLATOCRPBmo\n$x/()é"
            .chars()
            .collect::<Vec<_>>(),
    );
    let mut runner = proptest::test_runner::TestRunner::new(proptest::test_runner::Config {
        cases: 300,
        failure_persistence: None,
        ..Default::default()
    });
    let header =
        format!("{MM}%ADD10C,1*%\n%ADD11R,1X2*%\n%AMM*1,1,$1,0,0*%\n%ADD12M,0.5*%\nD10*\n");
    runner
        .run(&prop::collection::vec(alphabet, 0..200), |chars| {
            let body: String = chars.into_iter().collect();
            let _ = read_str(&body);
            let _ = read_str(&format!("{header}{body}"));
            Ok(())
        })
        .expect("no panic");
}

// --- dpsa pads ----------------------------------------------------------------------------

#[test]
fn cli_pads_json_and_errors() {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(["pads", "--json"])
        .arg(data("stm32-mini-pill/pcb-F_Paste.gbr"))
        .output()
        .expect("run dpsa");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
    assert_eq!(v["pads"]["count"], 102);
    assert_eq!(v["units"], "mm");
    assert_eq!(v["generator"], "KiCad,Pcbnew,(5.1.5)-3");
    let b = v["pads"]["bbox_mm"].as_array().expect("bbox");
    assert_eq!(b.len(), 4);
    assert!((b[0].as_f64().expect("x") - 127.246).abs() < 1e-6);
    assert_eq!(v["pads"]["classes"]["region"], 48);
    assert_eq!(v["pads"]["named"], 0);
    let hist: u64 = v["pads"]["area_histogram"]
        .as_array()
        .expect("histogram")
        .iter()
        .map(|b| b["count"].as_u64().expect("count"))
        .sum();
    assert_eq!(hist, 102);
    // Text summary.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .arg("pads")
        .arg(data("colordance-circle/heart-F_Paste.gtp"))
        .output()
        .expect("run dpsa");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("68 pads"), "{text}");
    // A bad file: non-zero exit, the file and the line in the message, no panic.
    let dir = tempfile::tempdir().expect("tempdir");
    let bad = dir.path().join("bad.gbr");
    std::fs::write(&bad, "%FSLAX46Y46*%\n%MOMM*%\nD11*\nX0Y0D03*\n").expect("write");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .arg("pads")
        .arg(&bad)
        .output()
        .expect("run dpsa");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("bad.gbr") && err.contains("line 4") && err.contains("D11"),
        "{err}"
    );
    assert!(!err.contains("panicked"), "{err}");
}
