//! The recording format (docs/recording.md) as a format of its own: a recording written by a
//! script that shares no code with the simulator (`tests/data/recording/make_recording.py`,
//! plain Python from the model in docs/model.md) is read by `dpsa reconstruct`, and its
//! heights are the script's surface; the damaged recordings the script writes are refused
//! with a sentence naming what is wrong, and no stream is left behind.

use std::path::{Path, PathBuf};
use std::process::Command;

fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data/recording/make_recording.py")
}

fn make(dir: &Path, damage: Option<&str>) {
    let mut c = Command::new("python3");
    c.arg(script()).arg(dir);
    if let Some(d) = damage {
        c.args(["--damage", d]);
    }
    let out = c.output().expect("python3 runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn reconstruct(rec: &Path, stream: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(["--quiet", "reconstruct"])
        .arg(rec)
        .arg("--out")
        .arg(stream)
        .output()
        .expect("dpsa runs")
}

#[test]
fn a_recording_written_without_the_simulator_reads_to_its_surface() {
    let dir = tempfile::tempdir().unwrap();
    make(dir.path(), None);
    let stream = dir.path().join("s.bin");
    let out = reconstruct(&dir.path().join("rec"), &stream);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (map, report) = dpsa_sim::stream::decode_stream(&std::fs::read(&stream).unwrap(), 0.25);
    assert_eq!(report.corrupt, 0);
    let expected: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("expected.json")).unwrap()).unwrap();
    let rows = expected["rows"].as_array().unwrap();
    let (mut valid, mut block, mut worst) = (0usize, 0usize, 0.0f64);
    for r in &map.rows {
        let want = rows[r.row as usize].as_array().unwrap();
        for (c, (&h, &ok)) in r.heights.iter().zip(&r.valid).enumerate() {
            if !ok {
                continue;
            }
            let want = want[c].as_f64().unwrap();
            let got = f64::from(h) * 0.25;
            worst = worst.max((got - want).abs());
            valid += 1;
            block += usize::from(want > 0.0);
        }
    }
    // Noise-free frames: the core's fixed point within 1 LSB (0.25 um) of the surface
    // everywhere, the 60 um block included (30 rows x 24 columns).
    assert!(worst <= 0.25, "worst {worst} um");
    assert!(valid >= 100 * 64, "{valid} valid pixels");
    assert_eq!(block, 30 * 24);
}

#[test]
fn damaged_recordings_are_refused_naming_the_fault() {
    for (damage, says) in [
        ("missing-frame", "000009.png is missing"),
        ("short-frame", "is 14 rows x 64 columns, expected 16 x 64"),
        ("unknown-key", "unknown field `bitdepth`"),
        ("latch-text", "expected i64"),
        ("bit-depth", "above the 12-bit maximum 4095"),
    ] {
        let dir = tempfile::tempdir().unwrap();
        make(dir.path(), Some(damage));
        let stream = dir.path().join("s.bin");
        let out = reconstruct(&dir.path().join("rec"), &stream);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{damage}: {err}");
        assert!(err.contains(says), "{damage}: {err}");
        assert!(!stream.exists(), "{damage}: a stream was left behind");
    }
}
