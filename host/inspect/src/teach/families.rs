//! Package families and their default windows.
//!
//! Each pad is put in one family, first rule that holds:
//!
//! | family | rule |
//! | --- | --- |
//! | `large` | opening area >= 4 mm^2 (thermal pads, connectors, power parts) |
//! | `bga` | the component's package name contains `BGA`, or the pad is round and < 0.6 mm wide with round neighbours at <= 1.0 mm pitch |
//! | `chip-0201`, `chip-0402`, `chip-0603`, `chip-0805+` | the package name has an imperial chip code (`0201`, `R_0402_1005Metric`, `C0603`, ...; the first code found; metric-only names such as `1005` are not read) |
//! | `fine-pitch` | the pad's pitch (nearest pad centre of the same component, else of any pad) <= 0.5 mm |
//! | `pitch-0.65` | pitch <= 0.65 mm |
//! | `standard` | everything else |
//!
//! The defaults (see `docs/inspection.md`, "Teach"): openings whose area ratio (area over
//! wall area, `A / (perimeter x stencil)`) is near or below 0.66 release paste less fully and
//! less repeatably, so their volume and area windows open downwards; large openings release
//! almost all their paste, so their windows are tighter. `standard` and `chip-0603`,
//! `chip-0805+`, `pitch-0.65` keep the program's default windows.

use crate::program::{Override, Window};
use dpsa_gerber::pads::Pad;
use std::collections::BTreeMap;

/// The family of every pad (see the module's table). `packages` maps a component to its
/// package name.
pub fn classify(pads: &[Pad], packages: &BTreeMap<String, String>) -> Vec<&'static str> {
    let centres: Vec<[f64; 2]> = pads.iter().map(|p| p.outline.centroid()).collect();
    // Pitch: the nearest other pad centre, preferring the same component; grid of 2 mm cells.
    let cell = 2.0;
    let key = |p: [f64; 2]| ((p[0] / cell).floor() as i64, (p[1] / cell).floor() as i64);
    let mut grid: BTreeMap<(i64, i64), Vec<usize>> = BTreeMap::new();
    for (i, c) in centres.iter().enumerate() {
        grid.entry(key(*c)).or_default().push(i);
    }
    let pitch = |i: usize| -> f64 {
        let (gx, gy) = key(centres[i]);
        let mut same = f64::INFINITY;
        let mut any = f64::INFINITY;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for &j in grid.get(&(gx + dx, gy + dy)).into_iter().flatten() {
                    if j == i {
                        continue;
                    }
                    let d = (centres[i][0] - centres[j][0]).hypot(centres[i][1] - centres[j][1]);
                    any = any.min(d);
                    if pads[i].component.is_some() && pads[i].component == pads[j].component {
                        same = same.min(d);
                    }
                }
            }
        }
        if same.is_finite() {
            same
        } else {
            any
        }
    };
    pads.iter()
        .enumerate()
        .map(|(i, p)| {
            let package = p
                .component
                .as_ref()
                .and_then(|c| packages.get(c))
                .map(|s| s.to_ascii_uppercase());
            let area = p.outline.area();
            if area >= 4.0 {
                return "large";
            }
            let round = matches!(p.outline, dpsa_gerber::pads::Outline::Circle { diameter, .. } if diameter < 0.6);
            let pi = pitch(i);
            if package.as_deref().is_some_and(|s| s.contains("BGA")) || (round && pi <= 1.0) {
                return "bga";
            }
            if let Some(f) = package.as_deref().and_then(chip_code) {
                return f;
            }
            if pi <= 0.5 + 1e-6 {
                "fine-pitch"
            } else if pi <= 0.65 + 1e-6 {
                "pitch-0.65"
            } else {
                "standard"
            }
        })
        .collect()
}

/// The chip family of a package name: the first imperial size code in it, as a whole number.
fn chip_code(name: &str) -> Option<&'static str> {
    let b = name.as_bytes();
    for i in 0..b.len().saturating_sub(3) {
        let w = &name[i..i + 4];
        let edge_before = i == 0 || !b[i - 1].is_ascii_digit();
        let edge_after = i + 4 == b.len() || !b[i + 4].is_ascii_digit();
        if !(edge_before && edge_after) {
            continue;
        }
        return match w {
            "0201" => Some("chip-0201"),
            "0402" => Some("chip-0402"),
            "0603" => Some("chip-0603"),
            "0805" | "1206" | "1210" | "1812" | "2010" | "2512" => Some("chip-0805+"),
            _ => continue,
        };
    }
    None
}

/// The default windows of a family, as an override without a match key (`None`: the
/// program's default windows).
pub fn default_override(family: &str) -> Option<Override> {
    let w = |warn: [f64; 2], fail: [f64; 2]| Some(Window { warn, fail });
    match family {
        // Small openings, area ratio near 0.66: lower and more variable transfer.
        "chip-0201" | "bga" | "fine-pitch" => Some(Override {
            volume_pct: w([60.0, 140.0], [45.0, 160.0]),
            area_pct: w([55.0, 165.0], [35.0, 210.0]),
            ..Override::default()
        }),
        "chip-0402" => Some(Override {
            volume_pct: w([62.0, 138.0], [50.0, 150.0]),
            ..Override::default()
        }),
        // Large openings release nearly all their paste: tighter.
        "large" => Some(Override {
            volume_pct: w([70.0, 130.0], [60.0, 140.0]),
            ..Override::default()
        }),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chip_codes_are_whole_imperial_numbers() {
        assert_eq!(chip_code("R_0402_1005METRIC"), Some("chip-0402"));
        assert_eq!(chip_code("C0603"), Some("chip-0603"));
        assert_eq!(chip_code("C_0805"), Some("chip-0805+"));
        assert_eq!(chip_code("R_1005METRIC"), None);
        assert_eq!(chip_code("SOT-23"), None);
        assert_eq!(chip_code("X04025"), None);
        for f in ["chip-0201", "bga", "fine-pitch", "chip-0402", "large"] {
            let o = default_override(f).unwrap();
            let mut p = crate::program::Program::new("a.gbr");
            p.overrides.push(Override {
                component: Some("U1".into()),
                ..o
            });
            p.validate().unwrap();
        }
    }
}
