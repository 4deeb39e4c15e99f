//! `dpsa spc` on a store of a known print process: the mini pill's program (a real KiCad
//! paste layer and placement file, 102 pads in five package families), 40 boards written
//! straight into the store with in-control variation, and a step down of 12 % in the volume
//! of one package's pads from board 30 on (an aperture row clogging). The alarm must name
//! that package, from the step on; the figures must be those of the stored values.

use dpsa_line::store::{BoardStart, CameraLoss, Location, Outcome, PadRow, Store};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

const BOARDS: usize = 40;
const STEP_AT: usize = 30;
const CLOGGED: &str = "LQFP-48_7x7mm_P0.5mm";
/// From this board on the print is shifted along x (the stencil moved at a change-over) ...
const SHIFT_AT: usize = 33;
/// ... by this much, um.
const SHIFT_UM: f64 = 25.0;
/// And it is turned throughout by this much, mrad (9.2 um over the board's 32 mm).
const TURN_MRAD: f64 = 0.3;

fn dpsa(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(args)
        .output()
        .expect("run dpsa")
}

fn ok(args: &[&str]) -> String {
    let o = dpsa(args);
    assert!(
        o.status.success(),
        "dpsa {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout).unwrap()
}

fn data(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data")
        .join(p)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The pads of the program: (stored name, package, the opening's centre in mm).
fn pads(program: &Path) -> Vec<(String, Option<String>, [f64; 2])> {
    let mut prog = dpsa_inspect::program::Program::load(program).unwrap();
    let (mut pads, _) = dpsa_inspect::run::paste_layer_pads(&prog, program).unwrap();
    dpsa_inspect::teach::apply_components(&mut prog, program, &mut pads).unwrap();
    let packages = dpsa_inspect::teach::component_packages(&prog, program).unwrap();
    pads.iter()
        .map(|p| {
            let pkg = p.component.as_ref().and_then(|c| packages.get(c).cloned());
            (dpsa_inspect::report::cfx_pad(p), pkg, p.outline.centroid())
        })
        .collect()
}

struct Fixture {
    dir: tempfile::TempDir,
    program: PathBuf,
    store: PathBuf,
    /// volume_pct of every pad on every board, as stored.
    volumes: Vec<Vec<f64>>,
    pads: Vec<(String, Option<String>, [f64; 2])>,
}

fn fixture() -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let program = dir.path().join("program.toml");
    let paste = data("gerber/stm32-mini-pill/pcb-F_Paste.gbr");
    ok(&[
        "program",
        "--paste",
        s(&paste),
        "--outline",
        s(&data("teach/stm32-mini-pill/pcb-Edge_Cuts.gbr")),
        "--placement",
        s(&data("teach/stm32-mini-pill/pcb-top.pos")),
        "--out",
        s(&program),
    ]);
    let pads = pads(&program);
    assert_eq!(pads.len(), 102);
    assert!(
        pads.iter()
            .filter(|p| p.1.as_deref() == Some(CLOGGED))
            .count()
            >= 40
    );
    let hash = {
        let prog = dpsa_inspect::program::Program::load(&program).unwrap();
        let a = std::fs::read(&program).unwrap();
        let b = std::fs::read(prog.paste_layer_path(&program)).unwrap();
        dpsa_line::config::fnv_hex(&[&a, &b])
    };
    let store_path = dir.path().join("data/line.sqlite");
    let mut store = Store::open(&Location::Sqlite(store_path.clone()), "line-1").unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let noise = Normal::new(0.0, 4.0).unwrap();
    let mut volumes = Vec::new();
    let n = pads.len() as f64;
    let centre = [0, 1].map(|k| pads.iter().map(|p| p.2[k]).sum::<f64>() / n);
    for b in 0..BOARDS {
        let id = store
            .begin_board(&BoardStart {
                run_id: 0x1000 + b as u64,
                product: "mini-pill".into(),
                program_hash: hash.clone(),
                calibration_hash: "00000000000000aa".into(),
                started_unix_s: 1_700_000_000.0 + 10.0 * b as f64,
            })
            .unwrap();
        let mut rows = Vec::new();
        let mut vols = Vec::new();
        let tx = if b >= SHIFT_AT { SHIFT_UM } else { 0.0 };
        for (k, (name, pkg, at)) in pads.iter().enumerate() {
            let q = [at[0] - centre[0], at[1] - centre[1]];
            let step = if b >= STEP_AT && pkg.as_deref() == Some(CLOGGED) {
                -12.0
            } else {
                0.0
            };
            let v = 100.0 + step + noise.sample(&mut rng);
            vols.push(v);
            rows.push(PadRow {
                pad: k as u32,
                name: name.clone(),
                level: "pass".into(),
                class: None,
                volume_um3: Some(v * 1e4),
                volume_pct: Some(v),
                area_mm2: Some(0.1),
                area_pct: Some(100.0 + noise.sample(&mut rng)),
                height_um: Some(100.0),
                height_pct: Some(100.0 + noise.sample(&mut rng)),
                offset_x_um: Some(tx - TURN_MRAD * q[1] + noise.sample(&mut rng)),
                offset_y_um: Some(TURN_MRAD * q[0] + noise.sample(&mut rng)),
                coverage: 1.0,
                uncertainty_um3: None,
            });
        }
        volumes.push(vols);
        let cams: Vec<CameraLoss> = Vec::new();
        store
            .finish_board(
                id,
                1_700_000_005.0 + 10.0 * b as f64,
                &cams,
                &Outcome::Inspected {
                    verdict: "pass".into(),
                    pads: rows,
                },
            )
            .unwrap();
    }
    drop(store);
    Fixture {
        dir,
        program,
        store: store_path,
        volumes,
        pads,
    }
}

/// Every file under `dir`.
fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

#[test]
fn a_clogging_package_raises_its_alarm_and_the_figures_are_the_stored_values() {
    let f = fixture();
    let out = f.dir.path().join("spc");
    let text = ok(&[
        "spc",
        "--store",
        s(&f.store),
        "--program",
        s(&f.program),
        "--out",
        s(&out),
        "--json",
    ]);
    let v: Value = serde_json::from_str(&text).unwrap();
    // `DPSA_SPC_KEEP=DIR` keeps this output for a look (the charts in docs/spc.md).
    if let Some(keep) = std::env::var_os("DPSA_SPC_KEEP") {
        let keep = PathBuf::from(keep);
        let _ = std::fs::remove_dir_all(&keep);
        std::fs::create_dir_all(&keep).unwrap();
        for e in walk(&out) {
            let to = keep.join(e.strip_prefix(&out).unwrap());
            std::fs::create_dir_all(to.parent().unwrap()).unwrap();
            std::fs::copy(&e, to).unwrap();
        }
    }
    assert_eq!(v["boards"], BOARDS);
    assert_eq!(v["with_program"], true);
    // The stencil: the fine apertures (area ratio under 0.8 at the program's stencil) counted
    // as here; none clogged (the LQFP's step is a row of larger apertures), no smears.
    let fine = {
        let prog = dpsa_inspect::program::Program::load(&f.program).unwrap();
        let (pads, _) = dpsa_inspect::run::paste_layer_pads(&prog, &f.program).unwrap();
        pads.iter()
            .filter(|p| p.outline.area() / (p.outline.perimeter() * prog.stencil_um / 1000.0) < 0.8)
            .count()
    };
    assert_eq!(v["stencil"]["fine_pads"], fine, "{}", v["stencil"]);
    assert_eq!(v["stencil"]["recommend"], false, "{}", v["stencil"]);
    assert_eq!(v["product"], "mini-pill");
    // The clogged package's volume alarms, open, from the step on, naming its pads.
    let alarms = v["alarms"].as_array().unwrap();
    let clog: Vec<&Value> = alarms
        .iter()
        .filter(|a| a["kind"] == "family" && a["name"] == CLOGGED && a["metric"] == "volume_pct")
        .collect();
    assert!(!clog.is_empty(), "no alarm on {CLOGGED}: {alarms:?}");
    let run = |b: usize| format!("{:016x}", 0x1000 + b);
    let first: Vec<&str> = clog
        .iter()
        .map(|a| a["first_fired_run_id"].as_str().unwrap())
        .collect();
    assert!(clog.iter().any(|a| a["open"] == true), "{clog:?}");
    assert!(
        first
            .iter()
            .any(|r| *r >= run(STEP_AT).as_str() && *r <= run(STEP_AT + 2).as_str()),
        "first fired {first:?}, the step is at {}",
        run(STEP_AT)
    );
    let named: Vec<String> = f
        .pads
        .iter()
        .filter(|p| p.1.as_deref() == Some(CLOGGED))
        .map(|p| p.0.clone())
        .collect();
    for a in &clog {
        for p in a["pads"].as_array().unwrap() {
            assert!(named.contains(&p[0].as_str().unwrap().to_owned()), "{p}");
        }
    }
    // The print's placement on every board: the shift from its board on, the turn throughout,
    // each within 4 of its stated uncertainties; the print's x alarms from the shift on.
    let prints = v["prints"].as_array().unwrap();
    assert_eq!(prints.len(), BOARDS);
    let turn_mdeg = TURN_MRAD.to_degrees();
    for (b, p) in prints.iter().enumerate() {
        let want = if b >= SHIFT_AT { SHIFT_UM } else { 0.0 };
        let u = p["uncertainty"].as_array().unwrap();
        let (x, ux) = (p["x_um"].as_f64().unwrap(), u[0].as_f64().unwrap());
        let (r, ur) = (p["rotation_mdeg"].as_f64().unwrap(), u[2].as_f64().unwrap());
        assert!((x - want).abs() < 4.0 * ux && ux < 2.0, "board {b}: {p}");
        assert!((r - turn_mdeg).abs() < 4.0 * ur, "board {b}: {p}");
    }
    let shift: Vec<&Value> = alarms
        .iter()
        .filter(|a| a["kind"] == "print" && a["metric"] == "print_x_um")
        .collect();
    assert!(
        shift
            .iter()
            .any(|a| a["open"] == true && a["first_fired_run_id"] == run(SHIFT_AT)),
        "{shift:?}"
    );
    assert!(
        shift
            .iter()
            .all(|a| a["first_fired_run_id"].as_str().unwrap() >= run(SHIFT_AT).as_str()),
        "{shift:?}"
    );
    // The board's volume figures are those of the stored values: mean and overall sigma.
    let all: Vec<f64> = f.volumes.iter().flatten().copied().collect();
    let mean = all.iter().sum::<f64>() / all.len() as f64;
    let sd = (all.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (all.len() - 1) as f64).sqrt();
    let board = v["board"].as_array().unwrap();
    let vol = board.iter().find(|s| s["metric"] == "volume_pct").unwrap();
    assert_eq!(vol["n"], all.len());
    assert!((vol["mean"].as_f64().unwrap() - mean).abs() < 1e-9 * mean);
    assert!((vol["sigma_overall"].as_f64().unwrap() - sd).abs() < 1e-9 * sd);
    // The board's pads have different windows (the families' overrides): no board Ppk. The
    // clogged family's Ppk is its values' against its pads' fail window.
    assert!(vol["limits"].is_null() && vol["pp"]["k"].is_null(), "{vol}");
    let fam: Vec<f64> = f
        .volumes
        .iter()
        .flat_map(|b| {
            b.iter()
                .zip(&f.pads)
                .filter(|(_, p)| p.1.as_deref() == Some(CLOGGED))
                .map(|(v, _)| *v)
        })
        .collect();
    let fm = fam.iter().sum::<f64>() / fam.len() as f64;
    let fsd = (fam.iter().map(|x| (x - fm).powi(2)).sum::<f64>() / (fam.len() - 1) as f64).sqrt();
    let window = {
        let prog = dpsa_inspect::program::Program::load(&f.program).unwrap();
        let (pads, _) = dpsa_inspect::run::paste_layer_pads(&prog, &f.program).unwrap();
        let mut prog = prog;
        let mut pads = pads;
        dpsa_inspect::teach::apply_components(&mut prog, &f.program, &mut pads).unwrap();
        let k = f
            .pads
            .iter()
            .position(|p| p.1.as_deref() == Some(CLOGGED))
            .unwrap();
        prog.windows_for(&pads[k]).volume_pct.fail
    };
    let fs = v["families"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == CLOGGED && s["metric"] == "volume_pct")
        .unwrap();
    assert_eq!(fs["limits"]["lsl"].as_f64(), Some(window[0]));
    assert_eq!(fs["limits"]["usl"].as_f64(), Some(window[1]));
    let ppk = ((window[1] - fm).min(fm - window[0])) / (3.0 * fsd);
    assert!(
        (fs["pp"]["k"].as_f64().unwrap() - ppk).abs() < 1e-9 * ppk.abs(),
        "{fs} {ppk}"
    );
    // The files: tables, every value, charts that decode, the alarm's chart among them.
    for t in [
        "board.csv",
        "families.csv",
        "components.csv",
        "pads.csv",
        "boards.csv",
        "alarms.csv",
        "spc.json",
    ] {
        assert!(out.join(t).is_file(), "{t}");
    }
    let values = std::fs::read_to_string(out.join("values.csv")).unwrap();
    assert_eq!(values.lines().count(), 1 + BOARDS * f.pads.len());
    // The printer's correction: the shift and the turn taken out, y (never moved) held.
    let m: Value =
        serde_json::from_slice(&std::fs::read(out.join("printer_correction.json")).unwrap())
            .unwrap();
    assert_eq!(m["MessageName"], "dpsa.SPI.PrinterCorrectionProposed");
    let body = &m["MessageBody"];
    assert_eq!(body["BasedOn"]["LastRunId"], run(BOARDS - 1));
    // The estimate is the printed error within 4 of its uncertainties; the correction follows
    // it to within the dead band (5 um, 5 mdeg) and is then held.
    let (c, e, u) = (
        &body["Correction"],
        &body["Estimate"],
        &body["EstimateUncertainty"],
    );
    let g = |v: &Value, k: &str| v[k].as_f64().unwrap();
    assert!(
        (g(e, "X_um") - SHIFT_UM).abs() < 4.0 * g(u, "X_um"),
        "{body}"
    );
    assert!(
        (g(e, "Theta_mdeg") - turn_mdeg).abs() < 4.0 * g(u, "Theta_mdeg"),
        "{body}"
    );
    assert!(
        (g(c, "X_um") - g(e, "X_um")).abs() <= 5.0 && g(c, "X_um") > 15.0,
        "{body}"
    );
    assert!(
        (g(c, "Theta_mdeg") - g(e, "Theta_mdeg")).abs() <= 5.0,
        "{body}"
    );
    assert_eq!(c["Y_um"].as_f64(), Some(0.0), "{body}");
    assert_eq!(body["Held"]["Y"], true);
    assert_eq!(
        v["printer"]["MessageBody"]["Correction"],
        body["Correction"]
    );
    let offsets = std::fs::read_to_string(out.join("print_offsets.csv")).unwrap();
    assert_eq!(offsets.lines().count(), 1 + BOARDS);
    assert!(out.join("charts/print-print_x_um.png").is_file());
    let chart = out.join(format!("charts/family-{CLOGGED}-volume_pct.png"));
    let img = image::open(&chart).unwrap_or_else(|e| panic!("{}: {e}", chart.display()));
    assert_eq!(image::GenericImageView::dimensions(&img), (1100, 700));
    let svg = std::fs::read_to_string(out.join(format!("charts/family-{CLOGGED}-volume_pct.svg")))
        .unwrap();
    assert!(
        svg.contains("WE1") || svg.contains("WE2") || svg.contains("WE3") || svg.contains("WE4")
    );
    // Run again: the earlier output is replaced whole.
    ok(&[
        "spc",
        "--store",
        s(&f.store),
        "--program",
        s(&f.program),
        "--out",
        s(&out),
        "--last",
        "20",
    ]);
    let values = std::fs::read_to_string(out.join("values.csv")).unwrap();
    assert_eq!(values.lines().count(), 1 + 20 * f.pads.len());
}

/// Without the program: the stored names and components, no limits and no families.
#[test]
fn without_the_program_there_are_charts_but_no_capability() {
    let f = fixture();
    let text = ok(&["spc", "--store", s(&f.store), "--json", "--rules", "nelson"]);
    let v: Value = serde_json::from_str(&text).unwrap();
    assert_eq!(v["with_program"], false);
    assert_eq!(v["families"].as_array().unwrap().len(), 0);
    let vol = v["board"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["metric"] == "volume_pct")
        .unwrap()
        .clone();
    assert!(vol["cp"]["k"].is_null() && vol["mean"].is_number());
    assert_eq!(v["rules"].as_array().unwrap().len(), 8);
    let arl = &v["rules_in_control_arl"];
    assert!((arl["N1"].as_f64().unwrap() - 370.4).abs() < 0.05, "{arl}");
    assert!(
        arl["N3"].is_null() && arl["N8"].as_f64().unwrap() > 10_000.0,
        "{arl}"
    );
}

#[test]
fn bad_requests_are_refused_with_a_reason() {
    let f = fixture();
    let st = s(&f.store);
    let cases: Vec<(Vec<&str>, &str)> = vec![
        (
            vec!["spc", "--store", "/nonexistent/line.sqlite"],
            "no store at",
        ),
        (
            vec!["spc", "--store", st, "--product", "nope"],
            "no inspected board of product",
        ),
        (vec!["spc", "--store", st, "--rules", "N9"], "is no rule"),
        (
            vec!["spc", "--store", st, "--alarms", "shelf"],
            "is no scope",
        ),
        (
            vec!["spc", "--store", st, "--alarms", "family:WE9"],
            "is no rule",
        ),
        (
            vec![
                "spc",
                "--store",
                st,
                "--rules",
                "nelson",
                "--alarms",
                "board:WE4",
            ],
            "the rule is not read",
        ),
        (
            vec!["spc", "--store", st, "--alarms", "board,board:WE1"],
            "given twice",
        ),
        (vec!["spc", "--store", st, "--last", "1"], "--last"),
        (
            vec!["spc", "--store", "ftp://x"],
            "neither a PostgreSQL URL",
        ),
    ];
    for (args, said) in cases {
        let o = dpsa(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(said), "{args:?}: {err}");
    }
    // Another program's boards are never mixed in.
    let other = f.dir.path().join("other.toml");
    let text = std::fs::read_to_string(&f.program)
        .unwrap()
        .replace("stencil_um = 100.0", "stencil_um = 120.0");
    std::fs::write(&other, text).unwrap();
    let o = dpsa(&["spc", "--store", st, "--program", s(&other)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("under this program"),
        "{err}"
    );
    // An output directory holding the store (or the program) is refused, whatever its kind.
    let o = dpsa(&["spc", "--store", st, "--out", s(f.store.parent().unwrap())]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && f.store.is_file(), "{err}");
    // An output directory holding something else is refused before any work.
    let busy = f.dir.path().join("busy");
    std::fs::create_dir_all(&busy).unwrap();
    std::fs::write(busy.join("keep.txt"), "mine").unwrap();
    let o = dpsa(&["spc", "--store", st, "--out", s(&busy)]);
    assert!(!o.status.success());
    assert_eq!(
        std::fs::read_to_string(busy.join("keep.txt")).unwrap(),
        "mine"
    );
}

/// `dpsa print-process` then `dpsa spc`: each injected change of a known print process raises
/// its alarm within the number of boards `docs/spc.md` states ("A known process"), counted
/// from the first board it touches; the stencil's clean is found where it was made.
#[test]
fn a_known_print_process_raises_each_alarm_within_its_delay() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let mini = d.join("mini.toml");
    ok(&[
        "program",
        "--paste",
        s(&data("gerber/stm32-mini-pill/pcb-F_Paste.gbr")),
        "--outline",
        s(&data("teach/stm32-mini-pill/pcb-Edge_Cuts.gbr")),
        "--placement",
        s(&data("teach/stm32-mini-pill/pcb-top.pos")),
        "--out",
        s(&mini),
    ]);
    // The small board's layer: 68 fine apertures (BGA and 0201 openings, area ratio < 0.8).
    let small = d.join("small.toml");
    let layer = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-small.paste.gbr");
    ok(&["program", "--paste", s(&layer), "--out", s(&small)]);
    const AT: usize = 30;
    let run = |name: &str, program: &Path, change: &str| -> Value {
        let process = d.join(format!("{name}.toml"));
        std::fs::write(
            &process,
            format!("boards = 60\nseed = 1\nproduct = \"{name}\"\n{change}"),
        )
        .unwrap();
        let store = d.join(format!("{name}.sqlite"));
        let text = ok(&[
            "print-process",
            "--process",
            s(&process),
            "--program",
            s(program),
            "--store",
            s(&store),
            "--json",
        ]);
        let w: Value = serde_json::from_str(&text).unwrap();
        assert_eq!(w["boards"], 60);
        // A second run does not write over the store.
        let again = dpsa(&[
            "print-process",
            "--process",
            s(&process),
            "--program",
            s(program),
            "--store",
            s(&store),
        ]);
        assert!(!again.status.success());
        assert!(String::from_utf8_lossy(&again.stderr).contains("exists"));
        let text = ok(&[
            "spc",
            "--store",
            s(&store),
            "--program",
            s(program),
            "--json",
        ]);
        serde_json::from_str(&text).unwrap()
    };
    // The first board (from AT on) an alarm of this chart fired on, if any.
    let first_after = |v: &Value, kind: &str, name: Option<&str>, metric: &str| {
        v["alarms"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|a| {
                a["kind"] == kind && a["metric"] == metric && name.is_none_or(|n| a["name"] == n)
            })
            .map(|a| {
                let id = a["first_fired_run_id"].as_str().unwrap();
                (u64::from_str_radix(id, 16).unwrap() - 0x5100_0000) as usize
            })
            .filter(|b| *b >= AT)
            .min()
    };
    // Name, program, the change, the chart (scope, family, measure), boards it may take.
    type Case<'a> = (
        &'a str,
        &'a Path,
        &'a str,
        &'a str,
        Option<&'a str>,
        &'a str,
        usize,
    );
    let cases: [Case; 4] = [
        (
            "step",
            &mini,
            "[[change]]\nkind = \"step\"\nat = 30\nshift_um = [25.0, 0.0]\n",
            "print",
            None,
            "print_x_um",
            1,
        ),
        (
            "drift",
            &mini,
            "[[change]]\nkind = \"drift\"\nfrom = 30\num_per_board = [0.0, 1.5]\n",
            "print",
            None,
            "print_y_um",
            6,
        ),
        (
            "viscosity",
            &mini,
            "[[change]]\nkind = \"viscosity\"\nfrom = 30\npct_per_board = -0.5\n",
            "board",
            None,
            "volume_pct",
            6,
        ),
        (
            "clogging",
            &small,
            "[[change]]\nkind = \"clogging\"\nfrom = 30\npct_per_print = 1.0\n",
            "family",
            Some("C 0.27"),
            "volume_pct",
            5,
        ),
    ];
    for (name, program, change, kind, family, metric, delay) in cases {
        let v = run(name, program, change);
        let b = first_after(&v, kind, family, metric);
        assert!(
            b.is_some_and(|b| b <= AT + delay),
            "{name}: the {kind} {metric} alarm first fired on board {b:?} from {AT} on, \
             stated within {delay}"
        );
        if name == "clogging" {
            assert_eq!(v["stencil"]["recommend"], true, "{}", v["stencil"]);
            assert_eq!(v["stencil"]["fine_pads"], 68);
        }
    }
    // Clogging from the start and a clean before board 30: the clean is found there, and
    // the clogging since is still seen.
    let v = run(
        "clean",
        &small,
        "[[change]]\nkind = \"clogging\"\nfrom = 0\npct_per_print = 0.5\n\
         [[change]]\nkind = \"clean\"\nat = 30\n",
    );
    let st = &v["stencil"];
    assert_eq!(st["clean_found"], true, "{st}");
    assert_eq!(st["since_board"], AT, "{st}");
    assert_eq!(st["recommend"], true, "{st}");
}
