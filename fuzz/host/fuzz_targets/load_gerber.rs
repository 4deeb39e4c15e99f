//! Arbitrary bytes as a top paste layer (Gerber RS-274X / X2, docs/inspection.md): what
//! `dpsa pads` and `dpsa inspect` do with the text of a paste-layer file.
//!
//! The reader runs within `Limits::FUZZ` (2,000 objects, 10,000 vertices): the same checks,
//! met sooner, so that an input of 130 bytes that steps and repeats a macro into 10^5 objects
//! takes milliseconds instead of the second (ten or more, instrumented) it may take at the
//! reader's limits, and the fuzzer explores instead of waiting.
//!
//! Oracles besides "no panic, no hang, no overflow, no allocation beyond the reader's limits":
//! a layer that reads has at most `Limits::FUZZ.objects` pads, indexed in file order, each with
//! a finite bounding box and a finite, positive area (slivers are dropped, never kept as empty
//! pads).

#![no_main]

use dpsa_gerber::{read_bytes_with, Limits};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    // UTF-8 or, failing that, Latin-1, as `read_file` takes a file.
    let Ok(layer) = read_bytes_with(data.to_vec(), &Limits::FUZZ) else {
        return;
    };
    assert!(
        layer.pads.len() <= Limits::FUZZ.objects,
        "{} pads",
        layer.pads.len()
    );
    for (i, p) in layer.pads.iter().enumerate() {
        assert_eq!(p.index, i, "pads out of file order");
        assert!(
            p.outline.bbox().iter().all(|v| v.is_finite()),
            "pad {i}: a bounding box that is not finite: {:?}",
            p.outline
        );
        let a = p.outline.area();
        assert!(a.is_finite() && a > 0.0, "pad {i}: area {a}");
    }
});
