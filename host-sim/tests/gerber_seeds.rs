//! Replays the committed seeds of the `load_gerber` fuzz target (`fuzz/host/corpus/load_gerber`)
//! through the same oracle: a layer that reads has at most `MAX_OBJECTS` pads, in order, each with finite
//! geometry and positive area. The seeds are crafted to read: flashes, a region with a clear
//! dot, strokes with an arc, a macro in a step and repeat, copies on one point with X2
//! attributes in inches, touching pads without M02, and a fuzzer's timeout (a macro stepped
//! 4 x 2230 times).

use dpsa_sim::inspection::gerber::{read_str, MAX_OBJECTS};
use std::path::Path;

#[test]
fn load_gerber_seeds_replay() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/host/corpus/load_gerber");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("gbr") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        let layer = read_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(!layer.pads.is_empty(), "{}", path.display());
        assert!(layer.pads.len() <= MAX_OBJECTS);
        for (i, p) in layer.pads.iter().enumerate() {
            assert_eq!(p.index, i);
            assert!(p.outline.bbox().iter().all(|v| v.is_finite()));
            let a = p.outline.area();
            assert!(a.is_finite() && a > 0.0, "{}: pad {i}", path.display());
        }
        seen += 1;
    }
    assert_eq!(seen, 7, "the seven committed seeds");
}

/// The seeds' pad counts, checked by hand from their geometry.
#[test]
fn load_gerber_seed_pad_counts() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/host/corpus/load_gerber");
    let count = |name: &str| {
        let text = std::fs::read_to_string(dir.join(name)).unwrap();
        read_str(&text).unwrap().pads.len()
    };
    assert_eq!(count("01-flashes.gbr"), 3);
    assert_eq!(count("02-region-clear.gbr"), 1); // a square with a hole
    assert_eq!(count("03-strokes-arc.gbr"), 1); // a line and an arc that meet
    assert_eq!(count("04-macro-step-repeat.gbr"), 6); // 3 x 2, 1 mm apart
    assert_eq!(count("05-copies-x2-inch.gbr"), 1); // three copies on one point
    assert_eq!(count("06-touching-no-m02.gbr"), 2); // two squares share an edge; one apart

    // A fuzzer's timeout (the R-tree of a group's pieces, `merge.rs`): a macro of a 0.5 mm
    // wide centre line and a 0.2 mm dot 8 mm beside it, stepped 4 x 2230 times 1 mm apart
    // along y with the 4 columns on one point: the lines touch into one strip, the dots stay
    // apart: 1 + 2230 pads.
    assert_eq!(count("07-stepped-entangled-macro.gbr"), 2231);
}
