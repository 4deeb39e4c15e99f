//! Arbitrary bytes as a recording's manifest and first frame (docs/model.md, "Recording
//! format"): what `Recording::open` and `Recording::frame` do with the bytes of the files,
//! without the file system.
//!
//! Input layout: 2 bytes little-endian `m`, then `m` bytes of `manifest.json`, then the rest
//! as the PNG of frame 0.
//!
//! Oracles besides "no panic, no hang, no overflow, no allocation beyond the caps":
//! - a manifest that loads is one the fixed-point core accepts: `dpsa_stream::config` builds
//!   its integer configuration (nothing that passes validation fails later in the core);
//! - a frame that decodes has exactly `rows x width` samples, none above `2^bit_depth - 1`,
//!   and carries the trigger of its manifest entry.

#![no_main]

use dpsa_formats::recording::{max_value, Manifest};
use dpsa_sim::simulation::recording::decode_frame;
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let Some((len, rest)) = data.split_first_chunk::<2>() else {
        return;
    };
    let m = usize::from(u16::from_le_bytes(*len)).min(rest.len());
    let (json, png) = rest.split_at(m);
    let Ok(manifest) = Manifest::parse(json, Path::new("manifest.json")) else {
        return;
    };
    if let Err(e) = dpsa_stream::config::config(&manifest) {
        panic!("a manifest that validates must build the core's configuration: {e}");
    }
    if manifest.frames.is_empty() {
        return;
    }
    if let Ok(frame) = decode_frame(&manifest, 0, png, Path::new("frames/000000.png")) {
        let (rows, width) = (
            manifest.camera.rows as usize,
            manifest.camera.width as usize,
        );
        assert_eq!(
            (frame.rows, frame.width, frame.data.len()),
            (rows, width, rows * width)
        );
        let max = max_value(manifest.camera.bit_depth);
        assert!(frame.data.iter().all(|&v| v <= max));
        assert_eq!(frame.trigger, manifest.frames[0].trigger());
    }
});
