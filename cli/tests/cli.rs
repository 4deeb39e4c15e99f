//! The `dpsa` command line: help texts, the simulate -> reconstruct -> compare -> decode chain
//! on a small scene, `phase` on real images, and clean errors for bad invocations.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn dpsa(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(args)
        .output()
        .expect("run the dpsa binary")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// Runs `dpsa args`, asserts success and no panic, returns stdout.
#[track_caller]
fn ok(args: &[&str]) -> String {
    let out = dpsa(args);
    let (so, se) = (text(&out.stdout), text(&out.stderr));
    assert!(
        out.status.success(),
        "dpsa {args:?} failed ({}):\nstdout: {so}\nstderr: {se}",
        out.status
    );
    assert!(!se.contains("panicked"), "dpsa {args:?}: {se}");
    so
}

/// Runs `dpsa args`, asserts failure with an `error:` message and no panic, returns stderr.
#[track_caller]
fn fails(args: &[&str]) -> String {
    let out = dpsa(args);
    let se = text(&out.stderr);
    assert!(
        !out.status.success(),
        "dpsa {args:?} should fail:\nstdout: {}",
        text(&out.stdout)
    );
    assert!(!se.contains("panicked"), "dpsa {args:?} panicked: {se}");
    assert!(
        se.contains("error:"),
        "dpsa {args:?}: no `error:` message: {se}"
    );
    se
}

fn json(stdout: &str) -> Value {
    serde_json::from_str(stdout).unwrap_or_else(|e| panic!("not JSON ({e}): {stdout}"))
}

/// `v` at a dotted path, e.g. `fixed_vs_ref.max_abs_lsb`.
#[track_caller]
fn at<'a>(v: &'a Value, path: &str) -> &'a Value {
    path.split('.').fold(v, |v, k| {
        v.get(k)
            .unwrap_or_else(|| panic!("JSON has no key {path}: {v}"))
    })
}

#[track_caller]
fn num(v: &Value, path: &str) -> f64 {
    at(v, path)
        .as_f64()
        .unwrap_or_else(|| panic!("{path} is not a number: {v}"))
}

/// Equal JSON values, numbers equal to 1e-12 relative (serde_json's default float parser
/// is not correctly rounded in the last bit).
fn same_json(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            x == y || (x - y).abs() <= 1e-12 * x.abs().max(y.abs())
        }
        (Value::Object(x), Value::Object(y)) => {
            x.len() == y.len()
                && x.iter()
                    .all(|(k, v)| y.get(k).is_some_and(|w| same_json(v, w)))
        }
        (Value::Array(x), Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(v, w)| same_json(v, w))
        }
        _ => a == b,
    }
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 temp path")
}

#[test]
fn help_texts() {
    let top = ok(&["--help"]);
    for sub in [
        "simulate",
        "reconstruct",
        "compare",
        "phase",
        "decode",
        "calibrate",
        "board",
        "board-bench",
        "pads",
        "demo",
        "line",
    ] {
        assert!(top.contains(sub), "dpsa --help does not list {sub}: {top}");
    }
    for (sub, options) in [
        ("simulate", &["--scene", "--seed", "--out"][..]),
        ("reconstruct", &["--out", "--png"][..]),
        ("compare", &["--json"][..]),
        (
            "phase",
            &["--image", "--step", "--min-modulation", "--json", "--png"][..],
        ),
        ("decode", &["--png", "--lsb-um", "--json"][..]),
        ("demo", &["--out", "--seed", "--scene", "--array"][..]),
        ("board", &["--cal", "--out", "--streams", "--json"][..]),
        ("pads", &["--json"][..]),
        (
            "line",
            &[
                "run",
                "init",
                "send",
                "boards",
                "product",
                "check",
                "store-bench",
            ][..],
        ),
    ] {
        let h = ok(&[sub, "--help"]);
        for o in options {
            assert!(h.contains(o), "dpsa {sub} --help does not mention {o}: {h}");
        }
    }
    let v = ok(&["--version"]);
    assert!(v.contains(env!("CARGO_PKG_VERSION")), "{v}");
}

const SCENE: &str = "\
# small test scene
width = 128
board_length = 300
deposits = 12
seed = 9
";

#[test]
fn simulate_reconstruct_compare_decode() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = tmp.path().join("scene.toml");
    std::fs::write(&scene, SCENE).unwrap();
    let rec = tmp.path().join("rec");

    ok(&[
        "simulate",
        "--scene",
        s(&scene),
        "--seed",
        "3",
        "--out",
        s(&rec),
    ]);
    assert!(rec.join("manifest.json").is_file());
    assert!(rec.join("frames/000000.png").is_file());
    assert!(rec.join("truth/height_um.f32").is_file());
    // --seed overrides the scene's seed: the recording is the library's seed-3 simulation.
    let lib = tmp.path().join("lib");
    let sc = dpsa_sim::simulation::scene::Scene::from_toml_str(SCENE).unwrap();
    dpsa_sim::simulation::simulate::simulate(&sc, 3, &lib, false).unwrap();
    assert_eq!(
        std::fs::read(rec.join("manifest.json")).unwrap(),
        std::fs::read(lib.join("manifest.json")).unwrap()
    );
    for f in ["frames/000005.png", "truth/height_um.f32"] {
        assert_eq!(
            std::fs::read(rec.join(f)).unwrap(),
            std::fs::read(lib.join(f)).unwrap(),
            "{f}"
        );
    }
    let recording = dpsa_sim::simulation::recording::Recording::open(&rec).unwrap();

    // reconstruct: the stream and both images.
    let stream = tmp.path().join("s.dpsa");
    let png = tmp.path().join("h.png");
    ok(&[
        "reconstruct",
        s(&rec),
        "--out",
        s(&stream),
        "--png",
        s(&png),
    ]);
    let bytes = std::fs::read(&stream).unwrap();
    assert!(bytes.starts_with(b"DPSA"), "not a packet stream");
    let (lib_stats, lib_bytes) =
        dpsa_sim::reconstruct::reconstruct_bytes(&recording, false).unwrap();
    assert_eq!(
        bytes, lib_bytes,
        "the CLI stream differs from the library's"
    );
    let colour = tmp.path().join("h.colour.png");
    let h = image::open(&png).expect("h.png is an image");
    let c = image::open(&colour).expect("h.colour.png is an image");
    // One image row per row packet (the stream header, the end packet and the frames'
    // trigger records carry no row).
    let rows = lib_stats.packets - 2 - lib_stats.frames as u64;
    assert_eq!((h.width(), h.height()), (128, rows as u32));
    assert_eq!((c.width(), c.height()), (h.width(), h.height()));
    assert!(
        matches!(h.color(), image::ColorType::L16),
        "{:?}",
        h.color()
    );

    // compare --json.
    let cmp = json(&ok(&["compare", s(&rec), "--json", "--quiet"]));
    for key in [
        "fixed_vs_ref.max_abs_lsb",
        "fixed_vs_ref.rms_lsb",
        "fixed_vs_ref.valid_mismatch",
        "truth.fixed_rms_um",
        "truth.ref_rms_um",
        "truth.crb_rms_um",
        "truth.psp_rms_um",
        "pixels.valid",
        "pixels.total",
    ] {
        num(&cmp, key);
    }
    assert!(num(&cmp, "fixed_vs_ref.max_abs_lsb") <= 1.0, "{cmp}");
    assert_eq!(num(&cmp, "fixed_vs_ref.valid_mismatch"), 0.0, "{cmp}");
    let (valid, total) = (num(&cmp, "pixels.valid"), num(&cmp, "pixels.total"));
    assert!(valid > 0.5 * 128.0 * 300.0 && valid <= total, "{cmp}");
    assert_eq!(total, 128.0 * rows as f64);
    assert!(
        num(&cmp, "truth.fixed_rms_um") < num(&cmp, "truth.psp_rms_um"),
        "{cmp}"
    );
    // The CLI reports exactly what the library computes.
    let lib_cmp = dpsa_sim::reference::compare::compare_recording(&recording, false).unwrap();
    let lib_json = serde_json::to_value(&lib_cmp).unwrap();
    assert!(
        same_json(&cmp, &lib_json),
        "CLI: {cmp}\nlibrary: {lib_json}"
    );
    // The plain summary mentions the same figures.
    let summary = ok(&["compare", s(&rec), "--quiet"]);
    assert!(
        summary.contains("fixed vs ref") && summary.contains("CRB"),
        "{summary}"
    );

    // decode --json.
    let dec = json(&ok(&["decode", s(&stream), "--json"]));
    assert_eq!(num(&dec, "packets.ok"), lib_stats.packets as f64, "{dec}");
    assert_eq!(num(&dec, "packets.corrupt"), 0.0, "{dec}");
    // Every packet but the stream header, the end packet and the frames' trigger records is
    // a row.
    assert_eq!(num(&dec, "rows.decoded"), rows as f64, "{dec}");
    assert_eq!(
        num(&dec, "stream.triggers"),
        lib_stats.frames as f64,
        "{dec}"
    );
    assert_eq!(num(&dec, "pixels.valid"), valid, "{dec}");

    // A damaged stream decodes with the damage reported.
    let mut bad = bytes.clone();
    let mid = bad.len() / 2;
    bad[mid] ^= 0x55;
    let bad_stream = tmp.path().join("bad.dpsa");
    std::fs::write(&bad_stream, &bad).unwrap();
    let out = dpsa(&["decode", s(&bad_stream), "--json"]);
    assert_eq!(out.status.code(), Some(2), "damage: exit status 2");
    let dec = json(&text(&out.stdout));
    assert_eq!(num(&dec, "packets.corrupt"), 1.0, "{dec}");
    assert_eq!(
        num(&dec, "packets.ok"),
        lib_stats.packets as f64 - 1.0,
        "{dec}"
    );
    // The damaged packet is a row or a trigger record: the others all decode.
    assert_eq!(
        num(&dec, "rows.decoded") + num(&dec, "stream.triggers"),
        lib_stats.packets as f64 - 3.0,
        "{dec}"
    );
}

fn real_dir() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real");
    assert!(
        dir.join("README.md").is_file(),
        "the real fringe images are missing: expected {} (shared/data/real beside the repository)",
        dir.display()
    );
    dir
}

#[test]
fn phase_on_the_lens_stack() {
    let dir = real_dir().join("fpp_tools_lens");
    let tmp = tempfile::tempdir().unwrap();
    let png = tmp.path().join("phase.png");
    let mut args: Vec<String> = vec!["phase".into()];
    for (file, step) in [("000", "0"), ("090", "90"), ("180", "180"), ("270", "270")] {
        args.push("--image".into());
        args.push(
            dir.join(format!("lens_orig_{file}.jpg"))
                .to_string_lossy()
                .into_owned(),
        );
        args.push("--step".into());
        args.push(step.into());
    }
    args.extend([
        "--json".into(),
        "--png".into(),
        png.to_string_lossy().into_owned(),
    ]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let rep = json(&ok(&args));
    let total = 933.0 * 862.0;
    assert_eq!(num(&rep, "total_pixels"), total, "{rep}");
    let valid = num(&rep, "valid_pixels");
    assert!(valid > 0.4 * total && valid < total, "{rep}");
    assert!(num(&rep, "fixed_vs_ref_rms_rad") <= 1e-3, "{rep}");
    assert!(num(&rep, "fixed_vs_ref_max_rad") <= 1e-2, "{rep}");
    assert_eq!(num(&rep, "valid_mismatch"), 0.0, "{rep}");
    let img = image::open(&png).expect("phase png");
    assert_eq!((img.width(), img.height()), (933, 862));

    // Negative steps are accepted (3-step sets are written -120 0 120).
    let k = real_dir().join("kamino410_object1");
    let (a, b, c) = (
        k.join("pat00.png"),
        k.join("pat01.png"),
        k.join("pat02.png"),
    );
    let rep = json(&ok(&[
        "phase",
        "--image",
        s(&a),
        "--step",
        "-120",
        "--image",
        s(&b),
        "--step",
        "0",
        "--image",
        s(&c),
        "--step",
        "120",
        "--json",
    ]));
    assert!(num(&rep, "fixed_vs_ref_rms_rad") <= 1e-3, "{rep}");
}

#[test]
fn bad_invocations_fail_cleanly() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("no-such-recording");

    let e = fails(&["compare", s(&missing)]);
    assert!(e.contains("no-such-recording"), "{e}");
    let e = fails(&[
        "reconstruct",
        s(&missing),
        "--out",
        s(&tmp.path().join("x.dpsa")),
    ]);
    assert!(e.contains("no-such-recording"), "{e}");
    let e = fails(&["decode", s(&tmp.path().join("none.dpsa"))]);
    assert!(e.contains("none.dpsa"), "{e}");

    // A scene file with a misspelt knob.
    let scene = tmp.path().join("bad.toml");
    std::fs::write(&scene, "width = 64\nboard_lenght = 100\n").unwrap();
    let e = fails(&[
        "simulate",
        "--scene",
        s(&scene),
        "--out",
        s(&tmp.path().join("r")),
    ]);
    assert!(e.contains("board_lenght"), "{e}");

    // A recording with a truncated frame.
    std::fs::write(&scene, SCENE).unwrap();
    let rec = tmp.path().join("rec");
    ok(&[
        "simulate",
        "--scene",
        s(&scene),
        "--out",
        s(&rec),
        "--quiet",
    ]);
    let f = rec.join("frames/000003.png");
    let bytes = std::fs::read(&f).unwrap();
    std::fs::write(&f, &bytes[..bytes.len() / 2]).unwrap();
    let e = fails(&[
        "reconstruct",
        s(&rec),
        "--out",
        s(&tmp.path().join("y.dpsa")),
    ]);
    assert!(e.contains("frame 3"), "{e}");
    let e = fails(&["compare", s(&rec), "--json"]);
    assert!(e.contains("frame 3"), "{e}");

    // Mismatched phase arguments.
    let lens = real_dir().join("fpp_tools_lens/lens_orig_000.jpg");
    let e = fails(&[
        "phase",
        "--image",
        s(&lens),
        "--image",
        s(&lens),
        "--image",
        s(&lens),
        "--step",
        "0",
        "--step",
        "90",
    ]);
    assert!(e.contains("step"), "{e}");

    // Usage errors (clap) also say `error:` and do not panic.
    fails(&["simulate"]);
    fails(&["no-such-command"]);
}

/// The README's main command: `dpsa demo` runs the single camera and then the camera array
/// end to end, and writes what it says it writes.
#[test]
fn demo_runs_the_camera_and_the_array() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let text = ok(&["demo", "--out", out.to_str().unwrap()]);
    for step in [
        "1/8",
        "4/8",
        "5/8",
        "7/8",
        "8/8",
        "pads, 193 measured",
        "fixed/CRB",
        "board map",
        "Cramer-Rao bound",
    ] {
        assert!(text.contains(step), "{step}: {text}");
    }
    assert!(text.contains("scenes/paper-board.toml"), "{text}");
    for f in [
        "heights.dpsa",
        "compare.json",
        "array.cal.toml",
        "board-map/heights.png",
        "board-map/heights_um.tiff",
        "board-map/report.json",
        "inspection/pads.csv",
        "inspection/cfx_units_inspected.json",
        "inspection/overview.png",
    ] {
        assert!(out.join(f).is_file(), "{f}");
    }
    let r: Value =
        serde_json::from_slice(&std::fs::read(out.join("board-map/report.json")).unwrap()).unwrap();
    assert_eq!(r["truth"]["wrong_turn_pixels"], 0, "{r}");
    assert!(r["truth"]["over_crb"].as_f64().unwrap() <= 1.05, "{r}");
}
