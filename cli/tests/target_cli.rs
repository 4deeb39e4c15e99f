//! `dpsa target-run`: the firmware's measurements as one JSON object, and clean errors.
//!
//! The benchmark run needs QEMU and the Cortex-M7 build (`bash firmware/build.sh --install`);
//! without them it fails with that advice unless `DPSA_SKIP_FIRMWARE=1` is set. The figures
//! are checked for presence and sanity only: this is not a test that fails on time.

use dpsa_sim::simulation::recording::Recording;
use serde_json::Value;
use std::path::Path;
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

fn skip_firmware() -> bool {
    let skip = std::env::var("DPSA_SKIP_FIRMWARE").is_ok_and(|v| v == "1");
    if skip {
        eprintln!("DPSA_SKIP_FIRMWARE=1: firmware test skipped");
    }
    skip
}

#[track_caller]
fn num(v: &Value, path: &str) -> f64 {
    let x = path.split('.').fold(v, |v, k| {
        v.get(k)
            .unwrap_or_else(|| panic!("JSON has no key {path}: {v}"))
    });
    x.as_f64()
        .unwrap_or_else(|| panic!("{path} is not a number: {x}"))
}

/// A small recording (W = 96, 160 board rows) in `dir`.
fn small_recording(dir: &Path) -> String {
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, "width = 96\nboard_length = 160\ndeposits = 6\n").unwrap();
    let rec = dir.join("rec");
    let out = dpsa(&[
        "--quiet",
        "simulate",
        "--scene",
        scene.to_str().unwrap(),
        "--seed",
        "2",
        "--out",
        rec.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "simulate: {}", text(&out.stderr));
    rec.to_str().unwrap().to_string()
}

#[test]
fn bench_json_has_every_figure() {
    if skip_firmware() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path());
    let stream = dir.path().join("target.dpsa");
    let out = dpsa(&[
        "--quiet",
        "target-run",
        &rec,
        "--out",
        stream.to_str().unwrap(),
        "--bench",
        "--json",
    ]);
    let (so, se) = (text(&out.stdout), text(&out.stderr));
    assert!(
        out.status.success(),
        "dpsa target-run failed ({}); it needs QEMU and the Cortex-M7 build: run \
         `bash firmware/build.sh --install` or set DPSA_SKIP_FIRMWARE=1.\nstdout: {so}\nstderr: {se}",
        out.status
    );
    assert!(!se.contains("panicked"), "{se}");
    // The decoded firmware log is on stderr, stdout is exactly one JSON object.
    assert!(
        se.lines().any(|l| l.starts_with("target: INFO")),
        "no decoded log on stderr: {se}"
    );
    let v: Value =
        serde_json::from_str(&so).unwrap_or_else(|e| panic!("not one JSON object ({e}): {so}"));

    for key in [
        "instructions_per_pixel.total",
        "instructions_per_pixel.accumulate",
        "instructions_per_pixel.phase_height",
        "instructions_per_pixel.encode",
        "instructions_per_window_solve",
        "ram_bytes.static",
        "ram_bytes.state",
        "ram_bytes.stack_high_water",
        "ram_bytes.total",
        "realtime.pixels_per_second_per_camera",
        "realtime.board_seconds",
        "flash_bytes",
        "pixels_out",
        "elf_sections.text",
        "elf_sections.itcm",
    ] {
        assert!(num(&v, key) > 0.0, "{key} = {} is not > 0", num(&v, key));
    }
    for key in [
        "elf_sections.rodata",
        "elf_sections.data",
        "elf_sections.bss",
    ] {
        assert!(num(&v, key) >= 0.0, "{key}");
    }
    // SysTick counts 40 retired instructions per tick on mps2 at -icount shift=0; the firmware
    // calibrates it on a loop of known length.
    let ipt = num(&v, "instructions_per_tick");
    assert!(
        (ipt / 40.0 - 1.0).abs() < 0.01,
        "instructions_per_tick {ipt}"
    );
    // Geometry as recorded, and figures that add up.
    assert_eq!((num(&v, "width"), num(&v, "n")), (96.0, 4.0));
    assert_eq!(num(&v, "pixels_out"), num(&v, "rows_out") * 96.0);
    // Rows, a trigger record per frame, the stream header and end packets.
    let frames = Recording::open(&rec).unwrap().manifest.frames.len() as f64;
    assert_eq!(num(&v, "stream.triggers"), frames);
    assert_eq!(
        num(&v, "stream.packets"),
        num(&v, "rows_out") + frames + 2.0
    );
    assert_eq!(num(&v, "stream.corrupt"), 0.0);
    let p = |k: &str| num(&v, &format!("instructions_per_pixel.{k}"));
    assert!(p("total") > p("encode"), "{v}");
    assert!(
        num(&v, "ram_bytes.state") <= num(&v, "ram_bytes.state_total"),
        "{v}"
    );
    assert_eq!(
        num(&v, "ram_bytes.total"),
        num(&v, "ram_bytes.state_total")
            + num(&v, "ram_bytes.static")
            + num(&v, "ram_bytes.stack_high_water"),
        "{v}"
    );
    // The real-time model: 600 MHz and IPC 1 are assumptions; the rate follows the count.
    assert_eq!(
        (
            num(&v, "realtime.clock_hz"),
            num(&v, "realtime.ipc_assumed")
        ),
        (600e6, 1.0)
    );
    assert!(
        (num(&v, "realtime.pixels_per_second_per_camera") * p("total") / 600e6 - 1.0).abs() < 1e-9,
        "{v}"
    );
    assert!(
        num(&v, "flash_bytes") >= num(&v, "elf_sections.text") + num(&v, "elf_sections.itcm"),
        "{v}"
    );
    // The frame grabber's flash budget (README, firmware table): 64 KiB, whatever the geometry.
    assert!(
        num(&v, "flash_bytes") <= 65_536.0,
        "the firmware's flash is over its 64 KiB budget: {v}"
    );
    assert_eq!(
        std::fs::metadata(&stream).unwrap().len() as f64,
        num(&v, "stream.bytes")
    );

    // Without --json: a short summary.
    let out = dpsa(&[
        "--quiet",
        "target-run",
        &rec,
        "--bench",
        "--elf",
        v["elf"].as_str().unwrap(),
    ]);
    let so = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        so.contains("instructions per pixel") && so.contains("flash"),
        "{so}"
    );
}

/// `--front-end`: the rows come from the RTL's Verilator models (fpga/: pixel units and row
/// codec), the firmware takes them from their logs: the stream is `dpsa reconstruct`'s byte for byte, the per-pixel
/// stages are not the MCU's (`null`), and the MCU's share is below the M7-only total.
#[test]
fn front_end_run_is_the_hosts_stream_and_the_mcus_share() {
    if skip_firmware() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path());
    let (fe, m7, host) = (
        dir.path().join("fe.dpsa"),
        dir.path().join("m7.dpsa"),
        dir.path().join("host.dpsa"),
    );
    let run = |out: &Path, front_end: bool| -> Value {
        let mut args = vec![
            "--quiet",
            "target-run",
            &rec,
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(["--bench", "--json"]);
        if front_end {
            args.push("--front-end");
        }
        let o = dpsa(&args);
        assert!(o.status.success(), "{}", text(&o.stderr));
        serde_json::from_str(&text(&o.stdout)).unwrap()
    };
    let with = run(&fe, true);
    let without = run(&m7, false);
    let o = dpsa(&[
        "--quiet",
        "reconstruct",
        &rec,
        "--out",
        host.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let host = std::fs::read(&host).unwrap();
    assert_eq!(std::fs::read(&fe).unwrap(), host, "front end vs host");
    assert_eq!(std::fs::read(&m7).unwrap(), host, "M7 only vs host");
    assert!(num(&with, "front_end.rows") > 100.0, "{with}");
    assert_eq!(with["front_end"]["stream_equals_core"], Value::Bool(true));
    assert_eq!(with["front_end"]["codec"], Value::from("fabric"));
    assert!(num(&with, "front_end.coded_rows") >= num(&with, "front_end.rows"));
    assert!(
        with["instructions_per_pixel"]["accumulate"].is_null(),
        "{with}"
    );
    assert!(
        with["instructions_per_pixel"]["phase_height"].is_null(),
        "{with}"
    );
    assert!(without["front_end"].is_null());
    let (a, b) = (
        num(&with, "instructions_per_pixel.total"),
        num(&without, "instructions_per_pixel.total"),
    );
    // The per-pixel stages (about 110 instructions a pixel) left the MCU.
    assert!(a > 0.0 && a < b - 50.0, "front end {a}, M7 only {b}");
}

#[test]
fn target_run_refuses_bad_invocations() {
    let help = text(&dpsa(&["target-run", "--help"]).stdout);
    for opt in [
        "--out",
        "--intra-period",
        "--elf",
        "--bench",
        "--json",
        "--cal",
        "--camera",
        "--front-end",
    ] {
        assert!(help.contains(opt), "target-run --help lacks {opt}: {help}");
    }
    let dir = tempfile::tempdir().unwrap();
    let rec = small_recording(dir.path());
    // Neither --out nor --bench: nothing to do.
    let out = dpsa(&["target-run", &rec]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("--out"), "{}", text(&out.stderr));
    // An ELF that does not exist, and a file that is not an ELF.
    let missing = dir.path().join("missing.elf");
    let out = dpsa(&[
        "target-run",
        &rec,
        "--out",
        "/dev/null",
        "--elf",
        missing.to_str().unwrap(),
    ]);
    let se = text(&out.stderr);
    assert!(
        !out.status.success() && se.contains("error:") && se.contains("missing.elf"),
        "{se}"
    );
    // A calibration file that does not exist; --camera without --cal.
    let out = dpsa(&[
        "target-run",
        &rec,
        "--out",
        "/dev/null",
        "--cal",
        "/nonexistent.toml",
    ]);
    let se = text(&out.stderr);
    assert!(
        out.status.code() == Some(1) && se.contains("calibration file /nonexistent.toml"),
        "{se}"
    );
    let out = dpsa(&["target-run", &rec, "--out", "/dev/null", "--camera", "1"]);
    assert!(!out.status.success() && text(&out.stderr).contains("--cal"));
    let not_elf = dir.path().join("rec/manifest.json");
    let out = dpsa(&[
        "target-run",
        &rec,
        "--out",
        "/dev/null",
        "--elf",
        not_elf.to_str().unwrap(),
    ]);
    let se = text(&out.stderr);
    assert!(
        !out.status.success() && se.contains("error:") && !se.contains("panicked"),
        "{se}"
    );
}

/// A calibration file of an array board recording made from its simulator truth (the true
/// encoder scale, fringe, reference phase, height per turn and placement): what
/// `dpsa calibrate` estimates, without the calibration recording.
fn truth_calibration(board: &Path) -> dpsa_sim::calibration::CalFile {
    use dpsa_sim::calibration::file::{CalFile, CameraCal, Lateral, CAL_FORMAT, CAL_VERSION};
    let arr = dpsa_sim::array::record::ArrayRecording::open(board).unwrap();
    let t = arr.truth().unwrap().unwrap();
    // The frame grabbers' sample range and processing: the recording's own.
    let m0 = Recording::open(arr.camera_dir(0, None)).unwrap().manifest;
    let camera = t
        .cameras
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let f = m.fringe_frequency.iter().sum::<f64>() / m.fringe_frequency.len() as f64;
            CameraCal {
                id: m.id,
                width: m.width,
                rows: m.rows,
                bit_depth: m0.camera.bit_depth,
                saturation: m0.camera.saturation,
                counts_per_pixel: m.counts_per_pixel,
                counts_per_mm: t.counts_per_mm,
                fringe_period_px: 1.0 / f,
                fringe_frequency_poly: [f, 0.0, 0.0],
                fx_height_error_um: 0.0,
                fx_over_budget: false,
                height_per_turn_um: m.height_per_turn_um.clone(),
                reference_phase_rad: m.reference_phase_rad.clone(),
                core_reference_phase_rad: m.reference_phase_rad.clone(),
                background_dn: t.plane_background_dn[i].clone(),
                modulation_dn: t.plane_modulation_dn[i].clone(),
                dead_pixels: m.dead_pixels.clone(),
                background_map: Vec::new(),
                modulation_map: Vec::new(),
                lateral: Lateral {
                    x0_mm: m.x0_mm,
                    y0_mm: m.y0_mm,
                    pitch_mm: m.pitch_mm,
                    rotation_rad: m.rotation_rad,
                    row_pitch_mm: m.counts_per_pixel / t.counts_per_mm,
                    fit_rms_um: 0.0,
                    marks: 0,
                },
            }
        })
        .collect();
    CalFile {
        format: CAL_FORMAT.into(),
        version: CAL_VERSION,
        counts_per_mm: t.counts_per_mm,
        height_lsb_um: 0.25,
        fx_budget_um: 0.5,
        processing: m0.processing,
        camera,
    }
}

/// Issue 10: each camera of the array is one frame grabber running the same firmware with
/// its own calibration (`target-run --cal CAL --camera I`); the three firmware streams of a
/// short board of the small array scene are the host's byte for byte and stitch into the
/// same board map, file for file, as the host streams.
#[test]
fn firmware_streams_of_an_array_stitch_into_the_host_map() {
    if skip_firmware() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut scene = dpsa_sim::array::scene::ArrayScene::load(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-small.toml"),
    )
    .unwrap();
    scene.board_length_mm = 6.0;
    scene.deposits = 4;
    let board = dir.path().join("board");
    dpsa_sim::array::record::simulate_board(&scene, 7, &board).unwrap();
    let cal = dir.path().join("cal.toml");
    std::fs::write(&cal, truth_calibration(&board).to_toml().unwrap()).unwrap();
    let s = |p: &Path| p.to_str().unwrap().to_string();
    let (mut host, mut target) = (Vec::new(), Vec::new());
    for cam in 0..3 {
        let rec = s(&board.join(format!("cam{cam}")));
        let id = cam.to_string();
        let h = dir.path().join(format!("host{cam}.dpsa"));
        let out = dpsa(&[
            "--quiet",
            "reconstruct",
            &rec,
            "--cal",
            &s(&cal),
            "--camera",
            &id,
            "--out",
            &s(&h),
        ]);
        assert!(out.status.success(), "{}", text(&out.stderr));
        let t = dir.path().join(format!("target{cam}.dpsa"));
        let out = dpsa(&[
            "--quiet",
            "target-run",
            &rec,
            "--cal",
            &s(&cal),
            "--camera",
            &id,
            "--out",
            &s(&t),
        ]);
        assert!(
            out.status.success(),
            "dpsa target-run failed; it needs QEMU and the Cortex-M7 build (`bash firmware/build.sh \
             --install`, or DPSA_SKIP_FIRMWARE=1): {}",
            text(&out.stderr)
        );
        let (hb, tb) = (std::fs::read(&h).unwrap(), std::fs::read(&t).unwrap());
        assert!(hb.len() > 10_000, "camera {cam}: {} bytes", hb.len());
        assert!(
            hb == tb,
            "camera {cam}: the firmware's stream differs from the host's"
        );
        host.push(s(&h));
        target.push(s(&t));
    }
    // Three calibrations, one board: one run id (the board identity) in all six streams.
    let maps: Vec<Value> = [&host, &target]
        .iter()
        .enumerate()
        .map(|(k, streams)| {
            let out_dir = dir.path().join(format!("map{k}"));
            let mut args = vec![
                "--quiet".to_string(),
                "board".into(),
                s(&board),
                "--cal".into(),
                s(&cal),
                "--out".into(),
                s(&out_dir),
                "--json".into(),
                "--streams".into(),
            ];
            // The firmware streams in reverse camera order: matched by their camera ids.
            if k == 1 {
                args.extend(streams.iter().rev().cloned());
            } else {
                args.extend(streams.iter().cloned());
            }
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            let out = dpsa(&args);
            assert!(out.status.success(), "{}", text(&out.stderr));
            serde_json::from_slice(&out.stdout).unwrap()
        })
        .collect();
    assert_eq!(maps[0]["streams"]["status"], 0);
    assert_eq!(maps[1]["streams"]["status"], 0);
    assert_eq!(maps[0]["streams"]["run_id"], maps[1]["streams"]["run_id"]);
    assert!(num(&maps[1], "pixels.valid_fraction") > 0.9, "{}", maps[1]);
    for f in ["heights.png", "heights_um.tiff", "camera.png", "board.json"] {
        let a = std::fs::read(dir.path().join("map0").join(f)).unwrap();
        let b = std::fs::read(dir.path().join("map1").join(f)).unwrap();
        assert!(
            a == b,
            "{f}: the firmware streams' map differs from the host streams'"
        );
    }
}
