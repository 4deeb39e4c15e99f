//! `dpsa line` end to end on loopback: the small printed board (scenes/array-paste.toml)
//! streamed camera by camera to `dpsa line run` by `dpsa line send`, against offline
//! `dpsa board --streams` + `dpsa inspect` of the very same streams; a camera falling silent;
//! packet loss; garbage, idle and foreign connections; `kill -9` in the middle of a board.

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn dpsa<I, S>(args: I) -> Output
where
    I: IntoIterator<Item = S>,
    S: AsRef<std::ffi::OsStr>,
{
    Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .arg("--quiet")
        .args(args)
        .output()
        .unwrap()
}

fn ok(o: &Output, what: &str) -> String {
    assert!(
        o.status.success(),
        "{what}: {}\n{}",
        String::from_utf8_lossy(&o.stderr),
        String::from_utf8_lossy(&o.stdout)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The calibration, the board recording, its three camera streams and the offline
/// inspection of those streams (made once per test process).
struct Fixture {
    dir: PathBuf,
    cal: PathBuf,
    board: PathBuf,
    streams: PathBuf,
    /// Offline `pads.csv`: (name, level, volume um^3) per pad in layer order.
    offline: Vec<(String, String, Option<f64>)>,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        // `line-PID` under the target directory; those of earlier runs (a process no longer
        // alive) are removed first, so they do not pile up.
        let base = Path::new(env!("CARGO_TARGET_TMPDIR"));
        let me = std::process::id();
        for e in std::fs::read_dir(base).into_iter().flatten().flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let pid = name
                .strip_prefix("line-")
                .and_then(|p| p.parse::<u32>().ok());
            if pid.is_some_and(|p| p != me && !Path::new(&format!("/proc/{p}")).exists()) {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
        let dir = base.join(format!("line-{me}"));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-paste.toml");
        let (calrec, cal, board, streams) = (
            dir.join("calrec"),
            dir.join("cal.toml"),
            dir.join("board"),
            dir.join("streams"),
        );
        let s = |p: &Path| p.as_os_str().to_owned();
        ok(
            &dpsa([
                "simulate".into(),
                "--scene".into(),
                s(&scene),
                "--calibration".into(),
                "--out".into(),
                s(&calrec),
            ]),
            "simulate --calibration",
        );
        ok(
            &dpsa(["calibrate".into(), s(&calrec), "--out".into(), s(&cal)]),
            "calibrate",
        );
        ok(
            &dpsa([
                "simulate".into(),
                "--scene".into(),
                s(&scene),
                "--seed".into(),
                "4".into(),
                "--out".into(),
                s(&board),
            ]),
            "simulate",
        );
        std::fs::create_dir_all(&streams).unwrap();
        let mut paths = Vec::new();
        for i in 0..3 {
            let p = streams.join(format!("cam{i}.dpsa"));
            ok(
                &dpsa([
                    "reconstruct".into(),
                    s(&board.join(format!("cam{i}"))),
                    "--cal".into(),
                    s(&cal),
                    "--camera".into(),
                    i.to_string().into(),
                    "--out".into(),
                    s(&p),
                ]),
                "reconstruct",
            );
            paths.push(p);
        }
        let map = dir.join("map");
        let mut args = vec![
            "board".into(),
            s(&board),
            "--cal".into(),
            s(&cal),
            "--out".into(),
            s(&map),
            "--streams".into(),
        ];
        args.extend(paths.iter().map(|p| s(p)));
        ok(&dpsa(args), "board --streams");
        let insp = dir.join("inspection");
        ok(
            &dpsa([
                "inspect".into(),
                s(&map),
                "--program".into(),
                s(&board.join("program.toml")),
                "--no-truth".into(),
                "--out".into(),
                s(&insp),
            ]),
            "inspect",
        );
        let offline = pads_csv(&insp.join("pads.csv"));
        Fixture {
            dir,
            cal,
            board,
            streams,
            offline,
        }
    })
}

/// (name, level, volume) of every pad of a `pads.csv`.
fn pads_csv(path: &Path) -> Vec<(String, String, Option<f64>)> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |n: &str| head.iter().position(|h| *h == n).unwrap();
    let (name, level, vol) = (col("ComponentPad"), col("Level"), col("PasteVolume_um3"));
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (
                f[name].to_string(),
                f[level].to_string(),
                f[vol].parse().ok(),
            )
        })
        .collect()
}

/// A line of its own: `line.toml` in `dir` (fresh ports), with `edit` applied to its text.
fn line_config(dir: &Path, edit: impl Fn(String) -> String) -> PathBuf {
    let f = fixture();
    std::fs::create_dir_all(dir).unwrap();
    let cfg = dir.join("line.toml");
    let s = |p: &Path| p.as_os_str().to_owned();
    ok(
        &dpsa([
            "line".into(),
            "init".into(),
            "--cal".into(),
            s(&f.cal),
            "--program".into(),
            s(&f.board.join("program.toml")),
            "--data".into(),
            s(&dir.join("data")),
            "--board".into(),
            s(&f.board),
            "--out".into(),
            s(&cfg),
        ]),
        "line init",
    );
    let text = edit(std::fs::read_to_string(&cfg).unwrap());
    std::fs::write(&cfg, text).unwrap();
    cfg
}

/// `dpsa line run --config CFG [--boards N]` in the background, its log in `dir/run.log`.
fn start(cfg: &Path, boards: Option<usize>) -> Child {
    let log = std::fs::File::create(cfg.with_extension("log")).unwrap();
    let mut c = Command::new(env!("CARGO_BIN_EXE_dpsa"));
    c.args(["line", "run", "--config"]).arg(cfg);
    if let Some(n) = boards {
        c.args(["--boards", &n.to_string()]);
    }
    c.stdout(Stdio::piped()).stderr(log).spawn().unwrap()
}

/// Waits up to `secs` for `child` to exit; its stdout (the summary) as JSON.
fn wait(mut child: Child, secs: u64, cfg: &Path) -> Value {
    let t0 = Instant::now();
    loop {
        if let Some(st) = child.try_wait().unwrap() {
            let out = child.wait_with_output().unwrap();
            let log = std::fs::read_to_string(cfg.with_extension("log")).unwrap_or_default();
            assert!(st.success(), "line run failed: {log}");
            return serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {log}"));
        }
        if t0.elapsed() > Duration::from_secs(secs) {
            let _ = child.kill();
            let log = std::fs::read_to_string(cfg.with_extension("log")).unwrap_or_default();
            panic!("line run did not end within {secs} s: {log}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

fn send(cfg: &Path, extra: &[&str]) -> Value {
    let f = fixture();
    let mut args: Vec<std::ffi::OsString> = vec![
        "line".into(),
        "send".into(),
        f.streams.as_os_str().into(),
        "--config".into(),
        cfg.as_os_str().into(),
    ];
    args.extend(extra.iter().map(|s| (*s).into()));
    serde_json::from_str(&ok(&dpsa(args), "line send")).unwrap()
}

fn stored(cfg: &Path) -> Vec<Value> {
    let out = ok(
        &dpsa([
            "line".as_ref(),
            "boards".as_ref(),
            "--config".as_ref(),
            cfg.as_os_str(),
            "--pads".as_ref(),
            "--prints".as_ref(),
        ]),
        "line boards",
    );
    let v: Value = serde_json::from_str(&out).unwrap();
    v.as_array().unwrap().clone()
}

fn board_of<'a>(boards: &'a [Value], run: &str) -> &'a Value {
    boards
        .iter()
        .find(|b| b["run_id"].as_str() == Some(run))
        .unwrap_or_else(|| panic!("board {run} not stored: {boards:?}"))
}

/// The stored pads of `b` equal the offline inspection of the same streams: every pad's
/// level, and its volume within 0.1 % (the line stitches chunk by chunk: the places of a
/// chunk and of a whole camera differ in the last bits).
fn assert_offline(b: &Value) {
    assert_offline_as(b, &fixture().offline);
}

/// [`assert_offline`] against the offline `pads.csv` rows `offline`.
fn assert_offline_as(b: &Value, offline: &[(String, String, Option<f64>)]) {
    assert_eq!(b["state"], "inspected", "{b}");
    let pads = b["pad_rows"].as_array().unwrap();
    assert_eq!(pads.len(), offline.len());
    for (p, (name, level, vol)) in pads.iter().zip(offline) {
        assert_eq!(p["name"].as_str(), Some(name.as_str()));
        assert_eq!(p["level"].as_str(), Some(level.as_str()), "pad {name}");
        match (p["volume_um3"].as_f64(), vol) {
            (Some(a), Some(b)) => assert!(
                (a - b).abs() <= 1e-3 * b.abs().max(1e3),
                "pad {name}: {a} vs {b}"
            ),
            (None, None) => {}
            (a, b) => panic!("pad {name}: volume {a:?} vs {b:?}"),
        }
    }
}

/// Three boards back to back: every one stored, inspected like the offline tools, a CFX
/// message each.
#[test]
fn boards_back_to_back_are_stored_as_the_offline_inspection() {
    let f = fixture();
    let dir = f.dir.join("back-to-back");
    let cfg = line_config(&dir, |t| t + "\n[maps]\nkeep_boards = 2\n");
    let run = start(&cfg, Some(3));
    let sent = send(&cfg, &["--rate", "max", "--boards", "3", "--seed", "11"]);
    let summary = wait(run, 120, &cfg);
    assert_eq!(summary["boards"], 3, "{summary}");
    assert_eq!(summary["incomplete"], 0, "{summary}");
    let boards = stored(&cfg);
    for run in sent["run_ids"].as_array().unwrap() {
        let run = run.as_str().unwrap();
        let b = board_of(&boards, run);
        assert_offline(b);
        for c in b["cameras"].as_array().unwrap() {
            assert_eq!(c["missing_rows"], 0, "{b}");
            assert_eq!(c["missing_packets"], 0, "{b}");
        }
        let msg: Value = serde_json::from_slice(
            &std::fs::read(dir.join("data/cfx").join(format!("{run}.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(
            msg["MessageBody"]["InspectedUnits"][0]["UnitIdentifier"],
            run
        );
    }
    // A UnitsInspected message and a printer proposal per board, nothing else.
    assert_eq!(std::fs::read_dir(dir.join("data/cfx")).unwrap().count(), 6);
    // The measured maps for the pages: the newest two kept (keep_boards = 2), each the map
    // the offline tools make of the same streams (`dpsa board`'s heights.png, in the same
    // 0.25 um steps) but for the last bits of the chunked stitching.
    assert_eq!(summary["maps_kept"], 3, "{summary}");
    assert_eq!(summary["maps_not_kept"], 0, "{summary}");
    // The processor time: some, never more than the cores had in the run (a clock tick of
    // slack per reading), shared out over the boards.
    let (cpu, secs) = (
        summary["cpu_s"].as_f64().unwrap(),
        summary["seconds"].as_f64().unwrap(),
    );
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as f64;
    assert!(cpu > 0.0 && cpu <= cores * secs + 0.02, "{summary}");
    let per_board = summary["cpu_s_per_board"].as_f64().unwrap();
    assert!((per_board * 3.0 - cpu).abs() < 1e-9, "{summary}");
    let maps = dir.join("data/maps");
    let kept = dpsa_formats::kept_map::kept(&maps, "line-1").unwrap();
    assert_eq!(kept.len(), 2, "{kept:?}");
    assert_eq!(std::fs::read_dir(&maps).unwrap().count(), 4);
    let offline = image::open(f.dir.join("map/heights.png"))
        .unwrap()
        .to_luma16();
    let runs: Vec<&str> = sent["run_ids"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r.as_str().unwrap())
        .collect();
    for id in kept {
        let k = dpsa_formats::kept_map::read_meta(&maps, "line-1", id)
            .unwrap()
            .unwrap();
        assert!(runs[1..].contains(&k.run_id.as_str()), "{k:?}");
        let (png, _) = dpsa_formats::kept_map::paths(&maps, "line-1", id);
        let live = image::open(&png).unwrap().to_luma16();
        assert_eq!(live.dimensions(), offline.dimensions());
        let (mut same_mask, mut within, mut both) = (0usize, 0usize, 0usize);
        for (a, b) in live.pixels().zip(offline.pixels()) {
            let (a, b) = (a.0[0], b.0[0]);
            same_mask += usize::from((a == 0) == (b == 0));
            if a != 0 && b != 0 {
                both += 1;
                within += usize::from(a.abs_diff(b) <= 1);
            }
        }
        let n = (live.width() * live.height()) as usize;
        assert!(same_mask as f64 >= 0.9999 * n as f64, "{same_mask} of {n}");
        assert!(within as f64 >= 0.999 * both as f64, "{within} of {both}");
        assert_eq!(
            k.valid as usize,
            live.pixels().filter(|p| p.0[0] != 0).count()
        );
    }
    // `dpsa spc` reads what the line stored: the three boards, and the board chart's mean of
    // the measured volumes equal to the stored pad rows' (pads the inspection could not
    // measure left out).
    let spc = spc_json(&dir);
    assert_eq!(spc["boards"], 3, "{spc}");
    assert_eq!(spc["with_program"], true);
    let vols: Vec<f64> = boards
        .iter()
        .flat_map(|b| b["pad_rows"].as_array().unwrap().clone())
        .filter(|p| p["class"] != "not_measurable")
        .filter_map(|p| p["volume_pct"].as_f64())
        .collect();
    let mean = vols.iter().sum::<f64>() / vols.len() as f64;
    let vol = spc["board"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["metric"] == "volume_pct")
        .unwrap();
    assert_eq!(vol["n"], vols.len(), "{vol}");
    assert!(
        (vol["mean"].as_f64().unwrap() - mean).abs() < 1e-9 * mean,
        "{vol} {mean}"
    );
    assert_eq!(
        spc["stencil"]["clean_recorded"], false,
        "{}",
        spc["stencil"]
    );
    // An operator records a clean after the third board: `dpsa spc` counts from it (nothing
    // printed since).
    let clean: Value = serde_json::from_str(&ok(
        &dpsa([
            "line".as_ref(),
            "clean".as_ref(),
            "--config".as_ref(),
            cfg.as_os_str(),
            "--note".as_ref(),
            "wiped after board 3".as_ref(),
        ]),
        "line clean",
    ))
    .unwrap();
    assert_eq!(clean["source"], "operator");
    assert_eq!(clean["product"], "array-small");
    let spc = spc_json(&dir);
    let st = &spc["stencil"];
    assert_eq!(st["clean_recorded"], true, "{st}");
    assert_eq!(st["since_board"], 3, "{st}");
    assert!(
        st["reasons"][0]
            .as_str()
            .unwrap()
            .contains("nothing printed since"),
        "{st}"
    );
    let bad = dpsa([
        "line".as_ref(),
        "clean".as_ref(),
        "--config".as_ref(),
        cfg.as_os_str(),
        "--product".as_ref(),
        "nope".as_ref(),
    ]);
    assert!(!bad.status.success());
}

/// `dpsa spc --json` of the line's store in `dir` under the fixture's program.
fn spc_json(dir: &Path) -> Value {
    let out = ok(
        &dpsa([
            "spc".as_ref(),
            "--store".as_ref(),
            dir.join("data/line.sqlite").as_os_str(),
            "--program".as_ref(),
            fixture().board.join("program.toml").as_os_str(),
            "--json".as_ref(),
        ]),
        "spc",
    );
    serde_json::from_str(&out).unwrap()
}

/// A stored placement (`dpsa line boards --prints`) as the loop takes it.
fn placement(v: &Value) -> dpsa_inspect::print::PrintOffset {
    let f = |k: &str| v[k].as_f64().unwrap_or_else(|| panic!("{k} of {v}"));
    let a = |k: &str, i: usize| v[k][i].as_f64().unwrap_or(f64::NAN);
    dpsa_inspect::print::PrintOffset {
        x_um: f("x_um"),
        y_um: f("y_um"),
        rotation_mdeg: f("rotation_mdeg"),
        stretch_ppm: f("stretch_ppm"),
        uncertainty: [0, 1, 2, 3].map(|i| a("uncertainty", i)),
        centre_mm: [a("centre_mm", 0), a("centre_mm", 1)],
        pads: v["pads"].as_u64().unwrap() as usize,
        outliers: v["outliers"].as_u64().unwrap() as usize,
        scale_um: f("scale_um"),
    }
}

/// The loop back to the printer, live: every board's placement and the correction proposed
/// after it stored with the board and spooled beside its CFX message; the proposals those a
/// loop replayed over the stored placements gives (dead band 0, so it moves every board, and
/// a conveyor of 1 board set in LINE.toml), across a restart of the service in the middle
/// (the loop resumed from the store goes on as if it had never stopped); the placements those
/// `dpsa spc` fits again from the stored pads.
#[test]
fn the_loop_back_to_the_printer_is_stored_spooled_and_resumed() {
    let f = fixture();
    let dir = f.dir.join("printer");
    let cfg = line_config(&dir, |t| {
        format!(
            "{t}\n[printer]\ndelay_boards = 1\ndead_band_um = 0.0\ndead_band_mdeg = 0.0\n\
             dead_band_sigmas = 0.0\n"
        )
    });
    let mut runs = Vec::new();
    for (n, seed) in [(3, "21"), (2, "22")] {
        let run = start(&cfg, Some(n));
        let sent = send(
            &cfg,
            &["--rate", "max", "--boards", &n.to_string(), "--seed", seed],
        );
        let summary = wait(run, 120, &cfg);
        assert_eq!(summary["boards"], n, "{summary}");
        runs.extend(
            sent["run_ids"]
                .as_array()
                .unwrap()
                .iter()
                .map(|r| r.as_str().unwrap().to_owned()),
        );
    }
    let mut boards = stored(&cfg);
    boards.reverse();
    assert_eq!(
        boards
            .iter()
            .map(|b| b["run_id"].as_str().unwrap())
            .collect::<Vec<_>>(),
        runs
    );
    let mut replay = dpsa_line::printer::Loop::new(dpsa_line::printer::LoopConfig {
        delay: 1,
        dead_band: [0.0, 0.0],
        sigmas: 0.0,
        ..Default::default()
    });
    let mut moved = 0;
    for (k, b) in boards.iter().enumerate() {
        let run = b["run_id"].as_str().unwrap();
        let p = &b["print"];
        let m = placement(&p["placement"]);
        assert!(m.pads > 100, "{p}");
        let want = replay.board(Some(&m)).correction;
        let got = &p["proposal"]["correction"];
        for (key, w) in [
            ("x_um", want.x_um),
            ("y_um", want.y_um),
            ("rotation_mdeg", want.rotation_mdeg),
        ] {
            let g = got[key].as_f64().unwrap();
            assert!(
                (g - w).abs() <= 1e-9 * w.abs().max(1.0),
                "board {k} {key}: {g} against {w}"
            );
        }
        moved += usize::from(p["proposal"]["held"] != serde_json::json!([true, true, true]));
        let msg: Value = serde_json::from_slice(
            &std::fs::read(dir.join("data/cfx").join(format!("{run}.printer.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(msg["MessageName"], "dpsa.SPI.PrinterCorrectionProposed");
        let body = &msg["MessageBody"];
        assert_eq!(body["Correction"]["X_um"], got["x_um"], "{msg}");
        assert_eq!(
            body["Correction"]["Theta_mdeg"], got["rotation_mdeg"],
            "{msg}"
        );
        assert_eq!(body["BasedOn"]["LastRunId"], run);
        // The boards weighing 1 % or more (5 at gain 0.6), across the restart too.
        let n = (k + 1).min(5);
        assert_eq!(body["BasedOn"]["Boards"], n, "{msg}");
        assert_eq!(
            body["BasedOn"]["FirstRunId"],
            runs[k + 1 - n].as_str(),
            "{msg}"
        );
        assert_eq!(body["Loop"]["delay"], 1);
    }
    assert!(moved >= 4, "the loop never moved: {boards:?}");
    // `dpsa spc` fits the placements again from the stored pads: the same.
    let spc = spc_json(&dir);
    let prints = spc["prints"].as_array().unwrap();
    assert_eq!(prints.len(), boards.len());
    for (s, b) in prints.iter().zip(&boards) {
        let m = &b["print"]["placement"];
        for key in ["x_um", "y_um", "rotation_mdeg", "stretch_ppm"] {
            let (a, c) = (s[key].as_f64().unwrap(), m[key].as_f64().unwrap());
            assert!(
                (a - c).abs() <= 1e-9 * c.abs().max(1.0),
                "{key}: spc {a}, line {c}"
            );
        }
    }
}

/// The loop closed through the line: a print process (a 60 um, -30 um, 0.7 mrad misprint from
/// the first board, in-control scatter around it) printed and imaged board by board by the
/// simulator, sent to the line as the cameras' streams, and the simulated printer applying the
/// line's own corrections (a conveyor of one board between them). The print is within 10 um of
/// the pads from the first board the correction could reach on, within 5 boards, never
/// overshooting by more than 20 %, and stays there; the line measures each print within 3 um
/// of what the simulator printed (its truth).
#[test]
fn the_printer_loop_closes_through_the_line() {
    let dir = fixture().dir.join("closed-loop");
    let cfg = line_config(&dir, |t| format!("{t}\n[printer]\ndelay_boards = 1\n"));
    let process = dir.join("process.toml");
    std::fs::write(
        &process,
        "boards = 8\nseed = 3\n\n[in_control]\nprint_offset_um = 2.0\n\
         print_rotation_mrad = 0.02\nboard_volume_pct = 1.0\n\n[[change]]\nkind = \"step\"\n\
         at = 0\nshift_um = [60.0, -30.0]\nturn_mrad = 0.7\n",
    )
    .unwrap();
    let run = start(&cfg, Some(8));
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-paste.toml");
    let out = ok(
        &dpsa([
            "print-process".as_ref(),
            "--process".as_ref(),
            process.as_os_str(),
            "--line".as_ref(),
            cfg.as_os_str(),
            "--scene".as_ref(),
            scene.as_os_str(),
            "--printer-applies".as_ref(),
            "--json".as_ref(),
        ]),
        "print-process --line",
    );
    let summary = wait(run, 120, &cfg);
    assert_eq!(summary["boards"], 8, "{summary}");
    let r: Value = serde_json::from_str(&out).unwrap();
    let boards = r["boards"].as_array().unwrap();
    assert_eq!(boards.len(), 8);
    let v = |b: &Value, k: &str, i: usize| b[k][i].as_f64().unwrap();
    let mut within = None;
    let mut overshoot = [0.0f64; 2];
    for (k, b) in boards.iter().enumerate() {
        // The line's measurement of the print against the simulator's.
        for i in 0..2 {
            let (printed, seen) = (v(b, "printed", i), v(b, "placement", i));
            assert!(
                (printed - seen).abs() <= 3.0,
                "board {k}: printed {printed}, measured {seen}"
            );
        }
        let off = v(b, "printed", 0).hypot(v(b, "printed", 1));
        if off <= 10.0 && within.is_none() {
            within = Some(k);
        }
        if within.is_some() {
            assert!(
                off <= 10.0,
                "board {k}: {off} um off after the loop closed: {r}"
            );
        }
        overshoot[0] = overshoot[0].max(-v(b, "printed", 0));
        overshoot[1] = overshoot[1].max(v(b, "printed", 1));
    }
    // Boards 0 and 1 were printed before any correction could reach the printer.
    let within = within.unwrap_or_else(|| panic!("never within 10 um: {r}"));
    assert!(
        (2..5).contains(&within),
        "within 10 um from board {within}: {r}"
    );
    assert!(
        overshoot[0] <= 12.0 && overshoot[1] <= 6.0,
        "overshoot {overshoot:?}: {r}"
    );
}

/// `dpsa line run --web`: the line's pages served while it runs (read-only), the board it
/// stored on the line page and its own page.
#[test]
fn the_line_serves_its_pages_while_it_runs() {
    let dir = fixture().dir.join("web");
    let cfg = line_config(&dir, |t| t);
    let log = std::fs::File::create(cfg.with_extension("log")).unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args([
            "line",
            "run",
            "--boards",
            "2",
            "--web",
            "127.0.0.1:0",
            "--config",
        ])
        .arg(&cfg)
        .stdout(Stdio::piped())
        .stderr(log)
        .spawn()
        .unwrap();
    // The address it chose, from its log.
    let t0 = Instant::now();
    let addr = loop {
        let text = std::fs::read_to_string(cfg.with_extension("log")).unwrap_or_default();
        if let Some(at) = text.split("http://").nth(1) {
            break at.split('/').next().unwrap().to_owned();
        }
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no address logged: {text}"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    // The whole response, head and body.
    let get_raw = |path: &str| -> Vec<u8> {
        use std::io::{Read, Write};
        let mut s = std::net::TcpStream::connect(&addr).unwrap();
        write!(
            s,
            "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut raw = Vec::new();
        s.read_to_end(&mut raw).unwrap();
        raw
    };
    let get = |path: &str| -> (String, String) {
        let raw = String::from_utf8(get_raw(path)).unwrap();
        let (head, body) = raw.split_once("\r\n\r\n").unwrap();
        (head.lines().next().unwrap().to_owned(), body.to_owned())
    };
    let (status, body) = get("/");
    assert!(status.contains(" 200 "), "{status}");
    assert!(body.contains("No board stored yet"), "{body}");
    let sent = send(&cfg, &["--rate", "max", "--seed", "31"]);
    let run = sent["run_ids"][0].as_str().unwrap().to_owned();
    // Stored: on the line page, linked to its page.
    let t0 = Instant::now();
    let link = loop {
        let (_, body) = get("/");
        // Its row's link (the run id also stands in the printer's paragraph).
        if let Some(at) = body.find(&format!("\">{run}</a>")) {
            let href = body[..at].rfind("href=\"").unwrap();
            break body[href + 6..at].trim_end_matches("\">").to_owned();
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "board {run} not on the page"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    // Listed from its start (open); its page once inspected.
    let t0 = Instant::now();
    let page = loop {
        let (status, page) = get(&link);
        assert!(status.contains(" 200 "), "{link}: {status}");
        assert!(page.contains(&format!("Board {run}")), "{page}");
        if page.contains("Pads that warned or failed") {
            break page;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "board {run} never inspected: {page}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    // The first call listed (the scene prints defects): its page shows the heights the line
    // kept around it, and the image is a PNG.
    let at = page
        .find(&format!("href=\"{link}/pad/"))
        .expect("a call listed");
    let pad = page[at + 6..].split('"').next().unwrap().to_owned();
    let (status, pad_page) = get(&pad);
    assert!(status.contains(" 200 "), "{pad}: {status}");
    let png = format!("{pad}/crop.png");
    assert!(pad_page.contains(&format!("href=\"{png}\"")), "{pad_page}");
    let bytes = get_raw(&png);
    assert!(bytes.starts_with(b"HTTP/1.1 200 "), "{png}");
    assert!(
        bytes.windows(8).any(|w| w == b"\x89PNG\r\n\x1a\n"),
        "{png}: no PNG"
    );
    // Its measured map, kept once the board is stored (by a thread of its own): the board
    // page's viewer, its description, a tile of it as PNG.
    let t0 = Instant::now();
    let info = loop {
        let (status, body) = get(&format!("{link}/map/{run}/info.json"));
        if status.contains(" 200 ") {
            break body;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "{link}/map/{run}/info.json: {status} {body}"
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    let info: Value = serde_json::from_str(&info).unwrap();
    assert_eq!(info["run_id"], run.as_str(), "{info}");
    assert!(info["levels"].as_u64().unwrap() >= 2, "{info}");
    let (_, page) = get(&link);
    assert!(
        page.contains(&format!("data-map=\"{link}/map/{run}/info.json\"")),
        "{page}"
    );
    let tile = get_raw(&format!("{link}/map/{run}/0/0/0.png"));
    assert!(tile.starts_with(b"HTTP/1.1 200 "), "the map's tile");
    let at = tile.windows(4).position(|w| w == b"\r\n\r\n").unwrap() + 4;
    let img = image::load_from_memory(&tile[at..]).unwrap();
    assert_eq!((img.width(), img.height()), (256, 256));
    // A second board: the line, told to take two, then ends.
    send(&cfg, &["--rate", "max", "--seed", "32"]);
    let summary = wait(child, 120, &cfg);
    assert_eq!(summary["boards"], 2, "{summary}");
    assert_eq!(summary["maps_kept"], 2, "{summary}");
}

/// A board the design cannot be registered on (its program's fiducials are 2.6 mm discs the
/// board does not have) is stored incomplete with the reason, and its map is kept all the
/// same, without a registration: what a process engineer looks at to see why.
#[test]
fn a_board_the_design_cannot_be_registered_on_keeps_its_map() {
    let f = fixture();
    let dir = f.dir.join("unregistered");
    let text = std::fs::read_to_string(f.board.join("program.toml")).unwrap();
    assert!(text.contains("\ndiameter_mm = 1.0\n"), "{text}");
    std::fs::write(
        f.board.join("program-nofid.toml"),
        text.replace("\ndiameter_mm = 1.0\n", "\ndiameter_mm = 2.6\n"),
    )
    .unwrap();
    let cfg = line_config(&dir, |t| {
        t.replace("program.toml\"", "program-nofid.toml\"")
    });
    assert!(std::fs::read_to_string(&cfg)
        .unwrap()
        .contains("program-nofid.toml"));
    let run = start(&cfg, Some(1));
    let sent = send(&cfg, &["--rate", "max", "--seed", "41"]);
    let summary = wait(run, 120, &cfg);
    assert_eq!(summary["incomplete"], 1, "{summary}");
    assert_eq!(summary["maps_kept"], 1, "{summary}");
    let run = sent["run_ids"][0].as_str().unwrap();
    let boards = stored(&cfg);
    let b = board_of(&boards, run);
    assert!(
        b["incomplete_reason"]
            .as_str()
            .unwrap()
            .contains("could not be registered"),
        "{b}"
    );
    let maps = dir.join("data/maps");
    let id = dpsa_formats::kept_map::kept(&maps, "line-1").unwrap();
    assert_eq!(id.len(), 1);
    let k = dpsa_formats::kept_map::read_meta(&maps, "line-1", id[0])
        .unwrap()
        .unwrap();
    assert_eq!((k.run_id.as_str(), k.design_to_board), (run, None));
    assert!(k.valid > 0);
}

/// A camera that falls silent in the first board: that board is incomplete with the camera
/// named, gets no CFX message, and the next board is inspected normally (none of the silent
/// board's rows in it).
#[test]
fn a_silent_camera_makes_its_board_incomplete_and_the_next_board_is_whole() {
    let f = fixture();
    let dir = f.dir.join("silent");
    let cfg = line_config(&dir, |t| t.replace("silent_s = 5.0", "silent_s = 1.0"));
    let run = start(&cfg, Some(2));
    let sent = send(
        &cfg,
        &[
            "--rate",
            "max",
            "--boards",
            "2",
            "--seed",
            "12",
            "--drop-camera",
            "1",
            "--at",
            "300",
            "--silent-for",
            "3",
        ],
    );
    let summary = wait(run, 120, &cfg);
    assert_eq!(summary["boards"], 2, "{summary}");
    let runs: Vec<&str> = sent["run_ids"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r.as_str().unwrap())
        .collect();
    let boards = stored(&cfg);
    let first = board_of(&boards, runs[0]);
    assert_eq!(first["state"], "incomplete", "{first}");
    assert!(first["verdict"].is_null());
    let why = first["incomplete_reason"].as_str().unwrap();
    assert!(
        why.contains("camera 1") && why.contains("silent for"),
        "{first}"
    );
    assert!(!dir
        .join("data/cfx")
        .join(format!("{}.json", runs[0]))
        .exists());
    // It was printed all the same: the loop back to the printer counts it, with no placement
    // (held), and proposes nothing to the spool.
    assert!(first["print"]["placement"].is_null(), "{first}");
    let reason = first["print"]["proposal"]["reason"].as_str().unwrap();
    assert!(reason.contains("no placement"), "{first}");
    assert!(!dir
        .join("data/cfx")
        .join(format!("{}.printer.json", runs[0]))
        .exists());
    assert_offline(board_of(&boards, runs[1]));
}

/// The retention (`[retention] pad_days`): three boards stored under a line that keeps every
/// pad row; the line restarted with a retention they are past: after its one board the
/// keeper has deleted the pad rows of the two oldest (two boards a board), and nothing else.
/// The boards, the new board's pads and the third old board's stay, and `dpsa spc` on the
/// store counts the two as pruned.
#[test]
fn the_retention_deletes_the_oldest_pad_rows_and_keeps_the_boards() {
    let f = fixture();
    let dir = f.dir.join("retention");
    let keep_all = line_config(&dir, |t| {
        let without = t.replace("[retention]\npad_days = 30.0\n", "");
        assert_ne!(without, t, "line init writes the retention");
        without
    });
    let run = start(&keep_all, Some(3));
    let old = send(
        &keep_all,
        &["--rate", "max", "--boards", "3", "--seed", "21"],
    );
    let summary = wait(run, 120, &keep_all);
    assert_eq!(summary["boards"], 3, "{summary}");
    assert_eq!(summary["pad_rows_pruned"], 0, "{summary}");
    // 0.0001 days: 8.64 s. The old boards ended before this sleep; the new one will end
    // after it, and is pruned only 8.64 s after its end.
    std::thread::sleep(Duration::from_secs(9));
    let text = std::fs::read_to_string(&keep_all).unwrap();
    std::fs::write(
        &keep_all,
        format!("{text}\n[retention]\npad_days = 0.0001\n"),
    )
    .unwrap();
    let run = start(&keep_all, Some(1));
    let new = send(&keep_all, &["--rate", "max", "--seed", "22"]);
    let summary = wait(run, 120, &keep_all);
    let pads = f.offline.len();
    assert_eq!(summary["pad_rows_pruned"], 2 * pads, "{summary}");
    let boards = stored(&keep_all);
    assert_eq!(boards.len(), 4);
    let rows = |run: &Value| {
        let b = board_of(&boards, run.as_str().unwrap());
        assert_eq!(b["state"], "inspected", "{b}");
        assert_eq!(b["pads"], pads, "the board's count is kept: {b}");
        b["pad_rows"].as_array().unwrap().len()
    };
    let olds: Vec<usize> = old["run_ids"]
        .as_array()
        .unwrap()
        .iter()
        .map(rows)
        .collect();
    assert_eq!(olds, [0, 0, pads], "the oldest first");
    assert_offline(board_of(&boards, new["run_ids"][0].as_str().unwrap()));
    let spc = spc_json(&dir);
    assert_eq!(spc["boards_pruned"], 2, "{spc}");
    assert_eq!(spc["boards"], 2, "{spc}");
}

/// `dpsa line product --config CFG [extra]` as JSON.
fn product(cfg: &Path, extra: &[&str]) -> Value {
    let mut args = vec!["line", "product", "--config", cfg.to_str().unwrap()];
    args.extend(extra);
    serde_json::from_str(&ok(&dpsa(args), "line product")).unwrap()
}

/// Waits until `n` boards of `cfg`'s line have ended (stored inspected or incomplete).
fn wait_ended(cfg: &Path, n: usize) {
    let t0 = Instant::now();
    while stored(cfg).iter().filter(|b| b["state"] != "open").count() < n {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "{n} boards not ended"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The line told the product of the boards that begin (`dpsa line product`, the data
/// directory's `product` file; the streams carry none): a board of the second product is
/// stored under it and inspected with its program; a file naming a product the configuration
/// does not have makes the board that begins incomplete with the reason, never inspected
/// against another product's program; `--default` goes back to the default product.
#[test]
fn each_board_is_inspected_as_the_product_the_line_is_told() {
    let f = fixture();
    let dir = f.dir.join("product");
    // The recording's program takes the paste's reflectance out of its maps (the scene's
    // machine does); the second product's program is the same without it.
    std::fs::create_dir_all(&dir).unwrap();
    let plain = dir.join("plain.toml");
    let original = std::fs::read_to_string(f.board.join("program.toml")).unwrap();
    assert!(
        original.contains("[reflectance]\nbackground_step = 0.574"),
        "{original}"
    );
    let layer = f.board.join("paste.gbr");
    let text: String = original
        .lines()
        .filter(|l| {
            !l.starts_with("truth = ")
                && *l != "[reflectance]"
                && !l.starts_with("background_step = ")
        })
        .map(|l| {
            if l.starts_with("paste_layer = ") {
                format!("paste_layer = {:?}\n", layer.to_str().unwrap())
            } else {
                format!("{l}\n")
            }
        })
        .collect();
    std::fs::write(&plain, text).unwrap();
    let cfg = line_config(&dir, |t| {
        // A second product: the first one's program and board under another id.
        let block: Vec<String> = t
            .split("[[product]]\n")
            .nth(1)
            .unwrap()
            .lines()
            .take_while(|l| !l.is_empty() && !l.starts_with('['))
            .map(|l| {
                if l.starts_with("id = ") {
                    "id = \"other\"".to_owned()
                } else if l.starts_with("program = ") {
                    format!("program = {:?}", plain.to_str().unwrap())
                } else {
                    l.to_owned()
                }
            })
            .collect();
        assert_eq!(block.len(), 4, "{t}");
        format!("{t}\n[[product]]\n{}\n", block.join("\n"))
    });
    let first = product(&cfg, &[]);
    assert_eq!(first["from"], "default_product", "{first}");
    let default_id = first["product"].as_str().unwrap().to_owned();
    assert_eq!(first["products"], serde_json::json!([default_id, "other"]));
    let o = dpsa([
        "line",
        "product",
        "--config",
        cfg.to_str().unwrap(),
        "--set",
        "nope",
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("not a product"));
    assert_eq!(product(&cfg, &["--set", "other"])["product"], "other");

    let run = start(&cfg, Some(3));
    let a = send(&cfg, &["--rate", "max", "--seed", "31"]);
    wait_ended(&cfg, 1);
    // A line controller that writes an id the line does not know.
    std::fs::write(dir.join("data/product"), "nonexistent\n").unwrap();
    let told = product(&cfg, &[]);
    assert!(told["product"].is_null(), "{told}");
    assert!(
        told["refused"].as_str().unwrap().contains("nonexistent"),
        "{told}"
    );
    let b = send(&cfg, &["--rate", "max", "--seed", "32"]);
    wait_ended(&cfg, 2);
    assert_eq!(
        product(&cfg, &["--default"])["product"],
        default_id.as_str()
    );
    let c = send(&cfg, &["--rate", "max", "--seed", "33"]);
    let summary = wait(run, 120, &cfg);
    assert_eq!(summary["boards"], 3, "{summary}");
    let boards = stored(&cfg);
    let run_of = |v: &Value| v["run_ids"][0].as_str().unwrap().to_owned();
    let board_a = board_of(&boards, &run_of(&a));
    assert_eq!(board_a["product"], "other", "{board_a}");
    // As `dpsa board --program` with the same program makes it offline, which differs from
    // the map with the reflectance taken out.
    let (map, insp) = (dir.join("map"), dir.join("inspection"));
    let s = |p: &Path| p.as_os_str().to_owned();
    let mut args = vec![
        "board".into(),
        s(&f.board),
        "--cal".into(),
        s(&f.cal),
        "--out".into(),
        s(&map),
        "--program".into(),
        s(&plain),
        "--json".into(),
        "--streams".into(),
    ];
    args.extend((0..3).map(|i| s(&f.streams.join(format!("cam{i}.dpsa")))));
    let report: Value = serde_json::from_str(&ok(&dpsa(args), "board --program")).unwrap();
    let step = &report["paste_reflectance"]["background_step"];
    assert_eq!(step.as_f64(), Some(0.0), "{report}");
    ok(
        &dpsa([
            "inspect".into(),
            s(&map),
            "--program".into(),
            s(&plain),
            "--no-truth".into(),
            "--out".into(),
            s(&insp),
        ]),
        "inspect",
    );
    let offline = pads_csv(&insp.join("pads.csv"));
    assert_offline_as(board_a, &offline);
    let moved = offline
        .iter()
        .zip(&f.offline)
        .filter(|(a, b)| match (a.2, b.2) {
            (Some(x), Some(y)) => (x - y).abs() > 2e-3 * y.abs().max(1e3),
            _ => false,
        })
        .count();
    assert!(
        moved > 10,
        "{moved} pads' volumes moved without the reflectance taken out"
    );
    let board_b = board_of(&boards, &run_of(&b));
    assert_eq!(board_b["state"], "incomplete", "{board_b}");
    let why = board_b["incomplete_reason"].as_str().unwrap();
    assert!(
        why.contains("nonexistent") && why.contains("product"),
        "{why}"
    );
    assert!(board_b["pad_rows"].as_array().unwrap().is_empty());
    let board_c = board_of(&boards, &run_of(&c));
    assert_eq!(board_c["product"], default_id.as_str(), "{board_c}");
    assert_offline(board_c);
}

/// 1 % of the packets lost: the board is inspected, the losses are stored, and no pad with
/// less than the program's coverage is judged (never pass or fail on interpolated data).
#[test]
fn packet_loss_is_counted_and_thin_pads_are_not_measurable() {
    let f = fixture();
    let dir = f.dir.join("loss");
    let cfg = line_config(&dir, |t| t);
    let run = start(&cfg, Some(1));
    let sent = send(&cfg, &["--rate", "max", "--loss", "0.01", "--seed", "13"]);
    assert!(sent["dropped"].as_u64().unwrap() > 0, "{sent}");
    wait(run, 120, &cfg);
    let boards = stored(&cfg);
    let b = board_of(&boards, sent["run_ids"][0].as_str().unwrap());
    assert_eq!(b["state"], "inspected", "{b}");
    let lost: u64 = b["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["missing_packets"].as_u64().unwrap())
        .sum();
    assert!(lost > 0, "{b}");
    for p in b["pad_rows"].as_array().unwrap() {
        if p["coverage"].as_f64().unwrap() < 0.85 {
            assert_eq!(p["class"], "not_measurable", "{p}");
            assert_eq!(p["level"], "fail", "{p}");
        }
    }
}

/// Garbage, 100 idle clients, a foreign camera's stream: each refused or timed out (a camera's
/// port takes a few connections at once, the rest are refused at once), and a board after them
/// is inspected normally.
#[test]
fn bad_clients_are_refused_and_the_line_goes_on() {
    use std::io::Write;
    let f = fixture();
    let dir = f.dir.join("bad-clients");
    let cfg = line_config(&dir, |t| t.replace("header_s = 5.0", "header_s = 1.0"));
    let addrs = listen_addrs(&cfg);
    assert_eq!(addrs.len(), 3);
    let run = start(&cfg, Some(1));
    let mut garbage = connect_when_listening(&addrs[0]);
    let junk: Vec<u8> = (0..3_000_000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    let _ = garbage.write_all(&junk);
    let idle: Vec<_> = (0..100)
        .map(|i| connect_when_listening(&addrs[i % 2]))
        .collect();
    let mut foreign = connect_when_listening(&addrs[2]);
    let _ = foreign.write_all(&std::fs::read(f.streams.join("cam0.dpsa")).unwrap());
    std::thread::sleep(Duration::from_millis(1500));
    drop(idle);
    let sent = send(&cfg, &["--rate", "max", "--seed", "14"]);
    wait(run, 120, &cfg);
    let boards = stored(&cfg);
    assert_eq!(boards.len(), 1, "{boards:?}");
    assert_offline(board_of(&boards, sent["run_ids"][0].as_str().unwrap()));
    let log = std::fs::read_to_string(cfg.with_extension("log")).unwrap();
    assert!(log.contains("without a stream header"), "{log}");
    assert!(
        log.contains("camera 0's stream on camera 2's port"),
        "{log}"
    );
    assert!(log.contains("no stream header within"), "{log}");
    assert!(
        log.contains("connections on this camera's port already"),
        "{log}"
    );
}

/// A camera's stream of a board sent twice on one connection, the second copy after the
/// first one's end and before the other cameras end: the second copy's rows are dropped with a
/// log line, never pushed into the board's map, and the board is stored as the offline
/// inspection of the same streams.
#[test]
fn a_cameras_stream_sent_twice_on_one_connection_is_taken_once() {
    use std::io::Write;
    let f = fixture();
    let dir = f.dir.join("twice");
    let cfg = line_config(&dir, |t| t);
    let addrs = listen_addrs(&cfg);
    assert_eq!(addrs.len(), 3);
    let run = start(&cfg, Some(1));
    let stream = |i: usize| std::fs::read(f.streams.join(format!("cam{i}.dpsa"))).unwrap();
    let mut cam0 = connect_when_listening(&addrs[0]);
    cam0.write_all(&stream(0)).unwrap();
    cam0.write_all(&stream(0)).unwrap();
    // The line reads both copies of camera 0 before the others come.
    let log_path = cfg.with_extension("log");
    let t0 = Instant::now();
    while !std::fs::read_to_string(&log_path)
        .unwrap_or_default()
        .contains("rows after this camera's end of the board: dropped")
    {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "{}",
            std::fs::read_to_string(&log_path).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let mut others: Vec<_> = (1..3).map(|i| connect_when_listening(&addrs[i])).collect();
    for (k, c) in others.iter_mut().enumerate() {
        c.write_all(&stream(k + 1)).unwrap();
    }
    wait(run, 120, &cfg);
    drop((cam0, others));
    let boards = stored(&cfg);
    assert_eq!(boards.len(), 1, "{boards:?}");
    assert_offline(&boards[0]);
    let log = std::fs::read_to_string(&log_path).unwrap();
    assert!(log.contains("a second stream of it is dropped"), "{log}");
}

/// `kill -9` in the middle of a board: on restart the store checks out, the board is
/// recorded incomplete with the reason, and the next board is inspected normally.
#[test]
fn kill_9_mid_board_leaves_a_sound_store_and_the_board_incomplete() {
    let f = fixture();
    let dir = f.dir.join("kill");
    let cfg = line_config(&dir, |t| t);
    let run = start(&cfg, None);
    // At 5 mm/s the small board (20 mm) takes 4 s: killed once it is in the store as open.
    let sender = send_slow(&cfg, "15");
    wait_for_state(&cfg, "open");
    let mut run = run;
    run.kill().unwrap();
    run.wait().unwrap();
    let _ = sender.join();
    let run2 = start(&cfg, Some(1));
    let sent = send(&cfg, &["--rate", "max", "--seed", "16"]);
    let summary = wait(run2, 120, &cfg);
    assert_eq!(summary["recovered"], 1, "{summary}");
    let boards = stored(&cfg);
    assert_eq!(boards.len(), 2, "{boards:?}");
    let killed = boards.iter().find(|b| b["state"] == "incomplete").unwrap();
    assert!(
        killed["incomplete_reason"]
            .as_str()
            .unwrap()
            .contains("stopped"),
        "{killed}"
    );
    assert!(killed["pad_rows"].as_array().unwrap().is_empty());
    assert_offline(board_of(&boards, sent["run_ids"][0].as_str().unwrap()));
    // The restart checked the whole store (a small one), and `dpsa line check` finds it
    // sound, whole and on its newest board.
    assert_eq!(summary["store_checked"], "whole", "{summary}");
    assert!(
        summary["store_bytes_at_start"].as_u64().unwrap() > 0,
        "{summary}"
    );
    let check = |extra: &[&str]| {
        let mut args = vec!["line", "check", "--config", cfg.to_str().unwrap()];
        args.extend(extra);
        dpsa(args)
    };
    for (extra, checked) in [
        (&[][..], "whole"),
        (&["--newest", "1"][..], "newest 1 boards"),
    ] {
        let v: Value = serde_json::from_str(&ok(&check(extra), "line check")).unwrap();
        assert_eq!(v["ok"], true, "{v}");
        assert_eq!(v["checked"], checked, "{v}");
    }
    let o = check(&["--newest", "0"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--newest"));
    let elsewhere = dir.join("nothing-here.sqlite");
    let o = check(&["--store", elsewhere.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("no store"));
    assert!(!elsewhere.exists(), "line check never makes a store");
}

/// A configuration with a wrong key is refused before anything starts, naming the key.
#[test]
fn a_bad_configuration_names_its_key() {
    let f = fixture();
    let dir = f.dir.join("bad-config");
    let cfg = line_config(&dir, |t| t.replace("silent_s = 5.0", "silent_s = -1.0"));
    let o = dpsa([
        "line".as_ref(),
        "run".as_ref(),
        "--config".as_ref(),
        cfg.as_os_str(),
    ]);
    assert!(!o.status.success());
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("timeouts.silent_s"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let cfg2 = line_config(&dir.join("2"), |t| {
        t.replace("default_product", "default_prodcut")
    });
    let o = dpsa([
        "line".as_ref(),
        "run".as_ref(),
        "--config".as_ref(),
        cfg2.as_os_str(),
    ]);
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("default_prodcut"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // The store and the line's name: named, and a password never shown.
    for (i, (extra, key)) in [
        ("store = \"mysql://line:s3cret@db/factory\"", "store:"),
        (
            "store = \"postgres://line:s3cret@db:port/factory\"",
            "store:",
        ),
        ("line = \"smt 3\"", "line:"),
    ]
    .into_iter()
    .enumerate()
    {
        let cfg = line_config(&dir.join(format!("key{i}")), |t| {
            t.replace("default_product", &format!("{extra}\ndefault_product"))
        });
        for cmd in ["run", "boards"] {
            let o = dpsa([
                "line".as_ref(),
                cmd.as_ref(),
                "--config".as_ref(),
                cfg.as_os_str(),
            ]);
            let e = String::from_utf8_lossy(&o.stderr);
            assert!(!o.status.success(), "{extra}");
            assert!(e.contains(key) && !e.contains("s3cret"), "{extra}: {e}");
        }
    }
    // The loop back to the printer's keys, and the maps': a count out of range, an unknown
    // key, a directory that cannot be made (under a file).
    std::fs::write(dir.join("a-file"), b"x").unwrap();
    let under_a_file = format!("dir = \"{}\"", dir.join("a-file/maps").display());
    for (i, (section, extra, key)) in [
        ("printer", "gain = 2.0", "printer.gain"),
        ("printer", "delay_boards = 1000", "printer.delay_boards"),
        ("printer", "max_step_um = nan", "printer.max_step_um"),
        ("printer", "dead_band = 5.0", "unknown field `dead_band`"),
        ("maps", "keep_boards = 20000", "maps.keep_boards"),
        ("maps", "keep = 3", "unknown field `keep`"),
        ("maps", under_a_file.as_str(), "maps.dir"),
        ("retention", "pad_days = 0.0", "retention.pad_days"),
        ("retention", "pad_days = 40000.0", "retention.pad_days"),
        ("retention", "pad_days = nan", "retention.pad_days"),
        ("retention", "days = 3", "unknown field `days`"),
    ]
    .into_iter()
    .enumerate()
    {
        let cfg = line_config(&dir.join(format!("section{i}")), |t| {
            // `line init` writes the retention's table: the bad key goes in its place.
            let t = t.replace("[retention]\npad_days = 30.0\n", "");
            format!("{t}\n[{section}]\n{extra}\n")
        });
        let o = dpsa([
            "line".as_ref(),
            "run".as_ref(),
            "--config".as_ref(),
            cfg.as_os_str(),
        ]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && e.contains(key), "{extra}: {e}");
    }
    let good = line_config(&dir.join("good"), |t| t);
    let o = dpsa([
        "line".as_ref(),
        "boards".as_ref(),
        "--config".as_ref(),
        good.as_os_str(),
        "--store".as_ref(),
        "mysql://line:s3cret@db/factory".as_ref(),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("--store") && !e.contains("s3cret"),
        "{e}"
    );
}

/// `dpsa line send` of one board at 5 mm/s (the small board takes 4 s) in a thread.
fn send_slow(cfg: &Path, seed: &str) -> std::thread::JoinHandle<Output> {
    let (cfg, seed) = (cfg.to_path_buf(), seed.to_string());
    std::thread::spawn(move || {
        let f = fixture();
        let args = [
            "line".as_ref(),
            "send".as_ref(),
            f.streams.as_os_str(),
            "--config".as_ref(),
            cfg.as_os_str(),
        ];
        dpsa(args.into_iter().chain([
            "--seed".as_ref(),
            seed.as_ref(),
            "--rate".as_ref(),
            "5".as_ref(),
        ]))
    })
}

/// Waits until the line has stored board state `state` for some board.
fn wait_for_state(cfg: &Path, state: &str) {
    let t0 = Instant::now();
    while !stored(cfg).iter().any(|b| b["state"] == state) {
        assert!(t0.elapsed() < Duration::from_secs(30), "no board {state}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn signal(child: &Child, sig: &str) {
    let st = Command::new("kill")
        .args([sig, &child.id().to_string()])
        .status()
        .unwrap();
    assert!(st.success());
}

/// `SIGTERM` in the middle of a board: the board is finished and stored, then the line exits.
#[test]
fn sigterm_finishes_the_board_in_progress_then_exits() {
    let f = fixture();
    let dir = f.dir.join("sigterm");
    let cfg = line_config(&dir, |t| t);
    let run = start(&cfg, None);
    let sender = send_slow(&cfg, "17");
    wait_for_state(&cfg, "open");
    signal(&run, "-TERM");
    let summary = wait(run, 60, &cfg);
    let sent: Value = serde_json::from_str(&ok(&sender.join().unwrap(), "line send")).unwrap();
    assert_eq!(summary["boards"], 1, "{summary}");
    let boards = stored(&cfg);
    assert_offline(board_of(&boards, sent["run_ids"][0].as_str().unwrap()));
}

/// The cameras' addresses of a line configuration (`listen = "..."`), in camera order.
/// A connection to `addr` once the line listens there: it binds its ports at its start, so
/// refused connections are tried again for up to 30 s.
fn connect_when_listening(addr: &str) -> std::net::TcpStream {
    let t0 = Instant::now();
    loop {
        match std::net::TcpStream::connect(addr) {
            Ok(s) => return s,
            Err(e) if t0.elapsed() > Duration::from_secs(30) => panic!("{addr}: {e}"),
            Err(_) => std::thread::sleep(Duration::from_millis(50)),
        }
    }
}

/// The cameras' listening addresses of a line's configuration, in its order.
fn listen_addrs(cfg: &Path) -> Vec<String> {
    std::fs::read_to_string(cfg)
        .unwrap()
        .lines()
        .filter_map(|l| l.trim().strip_prefix("listen = \""))
        .map(|l| l.trim_end_matches('"').to_string())
        .collect()
}

/// Cameras do not connect at the same instant: a camera of the board in progress that
/// connects after `SIGTERM` is still taken, and the board ends whole.
#[test]
fn sigterm_still_takes_a_late_camera_of_the_board_in_progress() {
    use std::io::Write;
    let f = fixture();
    let dir = f.dir.join("sigterm-late");
    let cfg = line_config(&dir, |t| t);
    let addrs = listen_addrs(&cfg);
    assert_eq!(addrs.len(), 3, "{addrs:?}");
    let stream = |i: usize| std::fs::read(f.streams.join(format!("cam{i}.dpsa"))).unwrap();
    let send = |i: usize| {
        let mut c = connect_when_listening(&addrs[i]);
        c.write_all(&stream(i)).unwrap();
        c.shutdown(std::net::Shutdown::Write).unwrap();
        c
    };
    let run = start(&cfg, None);
    // Camera 0's whole stream: the board is open, waiting for the others.
    let c0 = send(0);
    wait_for_state(&cfg, "open");
    signal(&run, "-TERM");
    // The line looks at its signals every 100 ms: it is stopping when the others come.
    std::thread::sleep(Duration::from_millis(500));
    let late: Vec<_> = (1..3).map(send).collect();
    let summary = wait(run, 60, &cfg);
    drop((c0, late));
    assert_eq!(summary["boards"], 1, "{summary}");
    assert_eq!(summary["incomplete"], 0, "{summary}");
    let boards = stored(&cfg);
    assert_eq!(boards.len(), 1, "{boards:?}");
    assert_offline(&boards[0]);
}

/// `SIGINT` twice: the line exits at once (status 130); the board in progress is found open
/// at the next start and recorded incomplete.
#[test]
fn sigint_twice_exits_at_once_and_the_board_is_recovered() {
    let f = fixture();
    let dir = f.dir.join("sigint");
    let cfg = line_config(&dir, |t| t);
    let mut run = start(&cfg, None);
    let sender = send_slow(&cfg, "18");
    wait_for_state(&cfg, "open");
    let t0 = Instant::now();
    signal(&run, "-INT");
    std::thread::sleep(Duration::from_millis(100));
    signal(&run, "-INT");
    let st = run.wait().unwrap();
    assert_eq!(st.code(), Some(130));
    assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
    let _ = sender.join();
    let run2 = start(&cfg, Some(1));
    send(&cfg, &["--rate", "max", "--seed", "19"]);
    let summary = wait(run2, 60, &cfg);
    assert_eq!(summary["recovered"], 1, "{summary}");
    let boards = stored(&cfg);
    let b = boards.iter().find(|b| b["state"] == "incomplete").unwrap();
    assert!(
        b["incomplete_reason"].as_str().unwrap().contains("stopped"),
        "{b}"
    );
}

/// The firmware on the line: three QEMU frame grabbers (the Cortex-M7 firmware on each
/// camera's recording, its stream on the board's UART, carried by QEMU as a TCP connection to
/// the camera's port) and `dpsa line run`: the stored pads equal offline `board --streams` +
/// `inspect` of the host's streams (the firmware's streams are the host's byte for byte,
/// `tests/firmware.rs`). Skipped with `DPSA_SKIP_FIRMWARE=1`, as the firmware tests.
#[test]
fn three_qemu_frame_grabbers_feed_the_line() {
    if std::env::var("DPSA_SKIP_FIRMWARE").is_ok_and(|v| v == "1") {
        eprintln!("DPSA_SKIP_FIRMWARE=1: skipped");
        return;
    }
    let f = fixture();
    let dir = f.dir.join("qemu");
    let cfg = line_config(&dir, |t| t);
    let addrs = listen_addrs(&cfg);
    let run = start(&cfg, Some(1));
    let grabbers: Vec<_> = addrs
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let (cam, cal, a) = (f.board.join(format!("cam{i}")), f.cal.clone(), a.clone());
            std::thread::spawn(move || {
                dpsa([
                    "target-run".into(),
                    cam.into_os_string(),
                    "--cal".into(),
                    cal.into_os_string(),
                    "--camera".into(),
                    i.to_string().into(),
                    "--link".into(),
                    std::ffi::OsString::from(a),
                ])
            })
        })
        .collect();
    for g in grabbers {
        ok(&g.join().unwrap(), "target-run --link");
    }
    let summary = wait(run, 120, &cfg);
    assert_eq!(summary["boards"], 1, "{summary}");
    let boards = stored(&cfg);
    assert_eq!(boards.len(), 1);
    let b = &boards[0];
    assert_offline(b);
    // The firmware's run id is the recording's board id.
    let array: Value =
        serde_json::from_slice(&std::fs::read(f.board.join("array.json")).unwrap()).unwrap();
    assert_eq!(b["run_id"], array["board_id"], "{b}");
}
