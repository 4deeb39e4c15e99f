//! Replays the committed seeds of the `load_recording` fuzz target (`fuzz/host/`) through the
//! same oracles: a manifest that loads builds the core's configuration, and a frame that
//! decodes has the camera's size and only samples within the bit depth. The seeds are crafted
//! to take each branch: a valid recording, one without truth, a saturation above the bit depth,
//! a truncated PNG, a frame path with `..`.

use dpsa_sim::reconstruct;
use dpsa_sim::simulation::recording::{decode_frame, max_value, Manifest};
use std::path::{Path, PathBuf};

/// What one seed did: (manifest loaded, frame decoded).
fn replay(data: &[u8]) -> (bool, bool) {
    let Some((len, rest)) = data.split_first_chunk::<2>() else {
        return (false, false);
    };
    let m = usize::from(u16::from_le_bytes(*len)).min(rest.len());
    let (json, png) = rest.split_at(m);
    let Ok(manifest) = Manifest::parse(json, Path::new("manifest.json")) else {
        return (false, false);
    };
    reconstruct::config(&manifest)
        .expect("a manifest that validates builds the core's configuration");
    let Ok(frame) = decode_frame(&manifest, 0, png, Path::new("frames/000000.png")) else {
        return (true, false);
    };
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
    (true, true)
}

fn seeds() -> Vec<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/host/corpus/load_recording");
    let mut v: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("the seed folder exists")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "bin"))
        .collect();
    v.sort();
    v
}

#[test]
fn seeds_take_every_branch_and_keep_the_oracles() {
    let got: Vec<(String, (bool, bool))> = seeds()
        .iter()
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                replay(&std::fs::read(p).unwrap()),
            )
        })
        .collect();
    let want = [
        ("01-valid.bin", (true, true)),
        ("02-one-frame-no-truth.bin", (true, true)),
        ("03-saturation-above-depth.bin", (false, false)),
        ("04-truncated-png.bin", (true, false)),
        ("05-dotdot-path.bin", (false, false)),
    ];
    let want: Vec<(String, (bool, bool))> = want.iter().map(|(n, r)| (n.to_string(), *r)).collect();
    assert_eq!(got, want);
}

#[test]
fn every_prefix_of_a_valid_seed_is_handled() {
    // Cut points through the manifest and the PNG: no panic, and the oracles hold wherever
    // something loads.
    let data = std::fs::read(&seeds()[0]).unwrap();
    for cut in (0..data.len()).step_by(7) {
        replay(&data[..cut]);
    }
}
