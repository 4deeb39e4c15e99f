//! `dpsa program` (the teach step) against independent references: a real KiCad board's paste
//! layer, outline and a placement file written from its `.kicad_pcb` (with every pad's true
//! component beside it, `tests/data/teach/stm32-mini-pill/pads.ref.csv`), and a constructed
//! copper layer with known fiducials and known non-fiducials.

use dpsa_sim::inspection::gerber;
use dpsa_sim::inspection::program::Program;
use dpsa_sim::inspection::teach;
use std::path::{Path, PathBuf};
use std::process::Command;

fn data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data")
        .join(rel)
}

fn pill(name: &str) -> PathBuf {
    data("teach/stm32-mini-pill").join(name)
}

fn paste() -> PathBuf {
    data("gerber/stm32-mini-pill/pcb-F_Paste.gbr")
}

fn dpsa(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(args)
        .output()
        .unwrap()
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

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `dpsa program` of the mini pill (paste layer, outline, KiCad placement file, 120 um
/// stencil, then `extra`) into `out`; its summary.
fn teach_pill(out: &Path, extra: &[&str]) -> String {
    let (paste, edge, pos) = (paste(), pill("pcb-Edge_Cuts.gbr"), pill("pcb-top.pos"));
    let mut args = vec!["program", "--paste", s(&paste), "--outline", s(&edge)];
    args.extend(["--placement", s(&pos), "--stencil-um", "120"]);
    args.extend(extra);
    args.extend(["--out", s(out)]);
    ok(&args)
}

/// Every pad of the paste layer named as `dpsa inspect` names it from the program.
fn named_pads(program: &Path) -> gerber::PasteLayer {
    let mut prog = Program::load(program).unwrap();
    let mut layer = gerber::read_file(&prog.paste_layer_path(program)).unwrap();
    teach::apply_components(&mut prog, program, &mut layer.pads)
        .unwrap()
        .expect("the program names its pads");
    layer
}

/// The reference: (component, pad number, x, y) of every top paste pad, from the kicad_pcb.
fn reference() -> Vec<(String, String, f64, f64)> {
    std::fs::read_to_string(pill("pads.ref.csv"))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (
                f[0].to_string(),
                f[1].to_string(),
                f[2].parse().unwrap(),
                f[3].parse().unwrap(),
            )
        })
        .collect()
}

/// How many pads got the reference's component (each pad matched to the reference pad at
/// its centroid, within 0.01 mm).
fn agreement(layer: &gerber::PasteLayer) -> (usize, Vec<String>) {
    let r = reference();
    let mut good = 0;
    let mut wrong = Vec::new();
    for p in &layer.pads {
        let c = p.outline.centroid();
        let m = r
            .iter()
            .find(|(_, _, x, y)| (x - c[0]).hypot(y - c[1]) < 0.01)
            .unwrap_or_else(|| panic!("no reference pad at {c:?}"));
        if p.component.as_deref() == Some(m.0.as_str()) {
            good += 1;
        } else {
            wrong.push(format!("{} pad {} named {}", m.0, m.1, p.name()));
        }
    }
    (good, wrong)
}

#[test]
fn a_kicad_board_is_taught_with_names_outline_and_families() {
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let out = dir.path().join("program.toml");
    let text = teach_pill(&out, &["--name", "pill"]);
    // The program loads and validates, with the outline's corner (the Edge.Cuts rectangle's
    // lines run through x = 126.746, y = -118.237, see pcb-Edge_Cuts.gbr).
    let prog = Program::load(&out).unwrap();
    assert_eq!(prog.placement.design_origin_mm, [126.746, -118.237]);
    assert_eq!(prog.stencil_um, 120.0);
    assert_eq!(prog.name.as_deref(), Some("pill"));
    assert!(prog.fiducials.points_mm.is_empty());
    let comp = prog.components.as_ref().unwrap();
    assert!(prog.components_path(&out).unwrap().is_file(), "{comp:?}");
    // The summary says there are no fiducials, and the program says so in its head.
    assert!(text.contains("fiducials: NONE"), "{text}");
    let file = std::fs::read_to_string(&out).unwrap();
    assert!(file.contains("# FIDUCIALS: NONE"), "{file}");
    assert!(text.contains("102 of 102 pads"), "{text}");
    // Every pad gets its true component, against the kicad_pcb's own pad list, but one of
    // USB1's, whose placement point is the connector's edge, 4.5 mm from its contacts: its
    // middle contact lies on the mirror axis (no partner) and is as near R3 as R4 (nearest
    // centre alone named 59 of the 102 right: a QFP's corner pads went to the capacitors).
    let layer = &named_pads(&out);
    let (good, wrong) = agreement(layer);
    eprintln!("{good} of 102 right; wrong: {wrong:?}");
    assert!(good >= 101, "{good} of 102 right: {wrong:#?}");
    assert!(wrong.iter().all(|w| w.starts_with("USB1 ")), "{wrong:#?}");
    // The LQFP's 48 pads: all U1, pins 1..=48 once each, and fine pitch.
    let mut pins: Vec<u32> = layer
        .pads
        .iter()
        .filter(|p| p.component.as_deref() == Some("U1"))
        .map(|p| p.pin.as_ref().unwrap().parse().unwrap())
        .collect();
    pins.sort();
    assert_eq!(pins, (1..=48).collect::<Vec<_>>());
    let fine: usize = text
        .lines()
        .find(|l| l.trim_end().ends_with("fine-pitch"))
        .and_then(|l| l.split_whitespace().next()?.parse().ok())
        .unwrap_or(0);
    assert_eq!(fine, 48, "{text}");
    // Its family default is written as an override with the package, and resolved at
    // inspection to the component.
    assert!(
        file.contains("package = \"LQFP-48_7x7mm_P0.5mm\""),
        "{file}"
    );
    let mut p2 = Program::load(&out).unwrap();
    let mut pads = gerber::read_file(&paste()).unwrap().pads;
    teach::apply_components(&mut p2, &out, &mut pads).unwrap();
    let u1 = pads
        .iter()
        .find(|p| p.component.as_deref() == Some("U1"))
        .unwrap();
    let c3 = pads
        .iter()
        .find(|p| p.component.as_deref() == Some("C3"))
        .unwrap();
    assert_eq!(p2.windows_for(u1).volume_pct.fail, [45.0, 160.0]);
    assert_eq!(p2.windows_for(c3).volume_pct.fail, [55.0, 145.0]);
}

#[test]
fn a_generic_csv_in_mil_names_the_pads_as_the_kicad_file() {
    // The same placements as pcb-top.pos, as a CSV of other column names, in mil.
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let pos = std::fs::read_to_string(pill("pcb-top.pos")).unwrap();
    let mut csv = String::from("Part;Footprint;X (mil);Y (mil);Angle;Layer\n");
    for l in pos.lines().filter(|l| !l.starts_with('#')) {
        let f: Vec<&str> = l.split_whitespace().collect();
        let mil = |v: &str| v.parse::<f64>().unwrap() / 0.0254;
        csv.push_str(&format!(
            "{};{};{:.4};{:.4};{};{}\n",
            f[0],
            f[2],
            mil(f[3]),
            mil(f[4]),
            f[5],
            f[6]
        ));
    }
    let csv_path = dir.path().join("placement.csv");
    std::fs::write(&csv_path, csv).unwrap();
    let a = dir.path().join("a.toml");
    let b = dir.path().join("b.toml");
    ok(&[
        "program",
        "--paste",
        s(&paste()),
        "--placement",
        s(&pill("pcb-top.pos")),
        "--out",
        s(&a),
    ]);
    let text = ok(&[
        "program",
        "--paste",
        s(&paste()),
        "--placement",
        s(&csv_path),
        "--placement-format",
        "csv",
        "--columns",
        "ref=Part,x=X (mil),y=Y (mil),rot=Angle,side=Layer,package=Footprint",
        "--units",
        "mil",
        "--out",
        s(&b),
    ]);
    // Without an outline: the paste layer's box, with a warning.
    let prog = Program::load(&b).unwrap();
    let bbox = gerber::read_file(&paste()).unwrap().bbox_mm;
    assert!((prog.placement.design_origin_mm[0] - bbox[0]).abs() < 1e-6);
    assert!((prog.placement.design_origin_mm[1] - bbox[1]).abs() < 1e-6);
    assert!(text.contains("paste layer box"), "{text}");
    let na: Vec<String> = named_pads(&a).pads.iter().map(|p| p.name()).collect();
    let nb: Vec<String> = named_pads(&b).pads.iter().map(|p| p.name()).collect();
    // The same names but where a pad is equally far from two components (USB1's middle
    // contact, between R3 and R4): the mil conversion's rounding may tip the tie.
    let differ: Vec<(&String, &String)> = na.iter().zip(&nb).filter(|(a, b)| a != b).collect();
    assert!(differ.len() <= 1, "{differ:?}");
    assert!(na.iter().all(|n| !n.starts_with('#')));
}

/// A copper layer: three fiducials (1.0 mm) in clear rings, one X2-marked fiducial with
/// copper close by, a 1.0 mm round pad under paste, a 1.0 mm round pad with copper 0.1 mm
/// from its edge, and component pads.
const COPPER: &str = "%FSLAX46Y46*%\n%MOMM*%\n%TF.FileFunction,Copper,L1,Top*%\n%ADD10C,1.000000*%\n%TA.AperFunction,FiducialPad,Local*%\n%ADD11C,1.000000*%\n%TD*%\n%ADD12R,1.200000X0.800000*%\nD10*\nX3000000Y3000000D03*\nX47000000Y3000000D03*\nX3000000Y27000000D03*\nX20000000Y10000000D03*\nX30000000Y10000000D03*\nD12*\nX31200000Y10000000D03*\nX20000000Y20000000D03*\nX22000000Y20000000D03*\nD11*\nX40000000Y20000000D03*\nD12*\nX41300000Y20000000D03*\nM02*\n";

/// The paste layer: the component pads and the round pad at (20, 10).
const PASTE: &str = "%FSLAX46Y46*%\n%MOMM*%\n%ADD10C,1.000000*%\n%ADD12R,1.200000X0.800000*%\nD10*\nX20000000Y10000000D03*\nD12*\nX20000000Y20000000D03*\nX22000000Y20000000D03*\nX31200000Y10000000D03*\nX41300000Y20000000D03*\nM02*\n";

#[test]
fn fiducials_are_round_bare_pads_in_a_clear_ring_or_marked_by_x2() {
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let cu = dir.path().join("top.gtl");
    let pa = dir.path().join("top.gtp");
    std::fs::write(&cu, COPPER).unwrap();
    std::fs::write(&pa, PASTE).unwrap();
    let out = dir.path().join("p.toml");
    let text = ok(&[
        "program",
        "--paste",
        s(&pa),
        "--copper",
        s(&cu),
        "--out",
        s(&out),
    ]);
    let prog = Program::load(&out).unwrap();
    assert_eq!(
        prog.fiducials.points_mm,
        vec![[3.0, 3.0], [47.0, 3.0], [3.0, 27.0], [40.0, 20.0]],
        "{text}"
    );
    assert_eq!(prog.fiducials.diameter_mm, 1.0);
    assert!(
        text.contains("(20.000, 10.000) d 1.000: paste on it"),
        "{text}"
    );
    assert!(
        text.contains("(30.000, 10.000) d 1.000: other copper within 2 radii"),
        "{text}"
    );
    assert!(text.contains("(40.000, 20.000)  x2"), "{text}");
    // A copper layer without fiducials: none, said clearly.
    let bare = dir.path().join("bare.gtl");
    std::fs::write(&bare, PASTE).unwrap();
    let text = ok(&[
        "program",
        "--paste",
        s(&pa),
        "--copper",
        s(&bare),
        "--out",
        s(&out),
    ]);
    assert!(
        text.contains("fiducials: NONE found on the copper layer"),
        "{text}"
    );
    assert!(Program::load(&out).unwrap().fiducials.points_mm.is_empty());
}

#[test]
fn an_output_that_is_an_input_and_bad_placement_files_are_refused() {
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let pa = dir.path().join("paste.gbr");
    std::fs::write(&pa, PASTE).unwrap();
    let pos = dir.path().join("top.pos");
    std::fs::write(&pos, "## Unit = mm\nR1 1k R_0402 20 20 0 top\n").unwrap();
    for target in [&pa, &pos] {
        let o = dpsa(&[
            "program",
            "--paste",
            s(&pa),
            "--placement",
            s(&pos),
            "--out",
            s(target),
        ]);
        assert!(!o.status.success());
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("it is the input"), "{e}");
    }
    assert_eq!(std::fs::read_to_string(&pa).unwrap(), PASTE);
    // A placement file with a bad number: refused naming the file and line, nothing written.
    std::fs::write(&pos, "## Unit = mm\nR1 1k R_0402 2x 20 0 top\n").unwrap();
    let out = dir.path().join("p.toml");
    let o = dpsa(&[
        "program",
        "--paste",
        s(&pa),
        "--placement",
        s(&pos),
        "--out",
        s(&out),
    ]);
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("top.pos") && e.contains("line 2") && e.contains("PosX"),
        "{e}"
    );
    assert!(!out.exists());
    // csv without columns.
    let o = dpsa(&[
        "program",
        "--paste",
        s(&pa),
        "--placement",
        s(&pos),
        "--placement-format",
        "csv",
        "--out",
        s(&out),
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--columns"));
}

#[test]
fn programs_without_a_placement_file_are_unchanged() {
    // A program of every default has no new key: the simulator's programs stay byte for byte.
    let t = Program::new("paste.gbr").to_toml_string();
    assert!(!t.contains("components") && !t.contains("package"), "{t}");
    // And a `package` override without [components] is refused, naming it.
    let e = Program::from_toml_str(
        "paste_layer = \"a\"\n[[override]]\npackage = \"QFN-32\"\nvolume_pct = { warn = [60.0, 140.0], fail = [50.0, 150.0] }\n",
        Path::new("p.toml"),
    )
    .unwrap_err();
    assert!(e.to_string().contains("override[0].package"), "{e}");
}

/// The shipped small board (`scenes/array-paste.toml`): its paste layer, a copper layer with
/// the scene's fiducials and a few copper pads, and its outline (the 20 x 13.9 mm board from
/// the origin) -> `dpsa program` gives the same placement, fiducials and stencil as the
/// program `dpsa simulate` writes from the scene itself; then `dpsa inspect` judges a
/// simulated print of that board with it.
#[test]
fn the_taught_program_of_the_simulated_board_inspects_it() {
    use dpsa_sim::array::{record, scene::ArrayScene};
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    let scene = ArrayScene::load(&scenes.join("array-paste.toml")).unwrap();
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let d = dir.path();
    let mut cu = String::from(
        "%FSLAX46Y46*%\n%MOMM*%\n%ADD10C,1.000000*%\n%ADD11R,0.500000X0.500000*%\nD10*\n",
    );
    let um = |v: f64| (v * 1e6).round() as i64;
    for f in &scene.fiducials {
        cu.push_str(&format!("X{}Y{}D03*\n", um(f[0]), um(f[1])));
    }
    // Copper pads beside the paste (not fiducials: square).
    cu.push_str("D11*\nX10000000Y7000000D03*\nM02*\n");
    std::fs::write(d.join("cu.gbr"), cu).unwrap();
    std::fs::write(
        d.join("edge.gbr"),
        "%FSLAX46Y46*%\n%MOMM*%\n%ADD10C,0.100000*%\nD10*\nX0Y0D02*\nX20000000Y0D01*\nX20000000Y13900000D01*\nX0Y13900000D01*\nX0Y0D01*\nM02*\n",
    )
    .unwrap();
    let prog = d.join("program.toml");
    let layer = scenes.join(scene.paste_layer.as_ref().unwrap());
    ok(&[
        "program",
        "--paste",
        s(&layer),
        "--copper",
        s(&d.join("cu.gbr")),
        "--outline",
        s(&d.join("edge.gbr")),
        "--stencil-um",
        &scene.print.stencil_um.to_string(),
        "--out",
        s(&prog),
    ]);
    let taught = Program::load(&prog).unwrap();
    let want = record::inspection_program(&scene);
    assert_eq!(taught.fiducials.points_mm, want.fiducials.points_mm);
    assert_eq!(taught.fiducials.diameter_mm, want.fiducials.diameter_mm);
    assert_eq!(
        taught.placement.design_origin_mm,
        want.placement.design_origin_mm
    );
    assert_eq!(taught.stencil_um, want.stencil_um);
    // The simulated print of that board, measured and inspected with the taught program.
    let board = d.join("board");
    record::simulate_board(&scene, 5, &board).unwrap();
    let caldir = d.join("cal");
    record::simulate_calibration(&scene, 3, &caldir).unwrap();
    let cal = dpsa_sim::calibration::calibrate(
        &record::ArrayRecording::open(&caldir).unwrap(),
        dpsa_sim::calibration::FX_BUDGET_UM,
    )
    .unwrap();
    let calf = d.join("cal.toml");
    std::fs::write(&calf, cal.to_toml().unwrap()).unwrap();
    let map = d.join("map");
    ok(&["board", s(&board), "--cal", s(&calf), "--out", s(&map)]);
    // The search radius is the simulator's (it knows its placement error).
    let mut t = std::fs::read_to_string(&prog).unwrap();
    t = t.replace(
        "search_mm = 1.5",
        &format!("search_mm = {}", want.fiducials.search_mm),
    );
    std::fs::write(&prog, t).unwrap();
    // `dpsa inspect --json` of the map with a program, into `d/OUT`.
    let inspect = |program: &Path, out: &str| -> (String, serde_json::Value) {
        let text = ok(&[
            "inspect",
            s(&map),
            "--program",
            s(program),
            "--truth",
            s(&board.join("print.json")),
            "--out",
            s(&d.join(out)),
            "--json",
        ]);
        let v = serde_json::from_str(&text).unwrap();
        (text, v)
    };
    let (out, r) = inspect(&prog, "insp");
    assert_eq!(r["registration"]["fiducials"].as_array().unwrap().len(), 3);
    let total = r["pads"]["total"].as_u64().unwrap();
    assert_eq!(total, gerber::read_file(&layer).unwrap().pads.len() as u64);
    assert!(
        r["pads"]["measured"].as_u64().unwrap() > total * 9 / 10,
        "{out}"
    );
    let by_fiducials = r["truth"]["registration_error_um"].as_f64().unwrap();

    // The same program without its fiducials: `dpsa inspect` registers the design by its
    // paste pattern, and says so.
    let mut nofid = Program::load(&prog).unwrap();
    nofid.fiducials.points_mm.clear();
    let nofid_path = prog.with_file_name("nofid.toml");
    std::fs::write(&nofid_path, nofid.to_toml_string()).unwrap();
    let (out, r) = inspect(&nofid_path, "insp-nofid");
    assert_eq!(r["registration"]["method"], "paste pattern", "{out}");
    assert!(
        r["registration"]["pads_used"].as_u64().unwrap() > total / 2,
        "{out}"
    );
    let by_paste = r["truth"]["registration_error_um"].as_f64().unwrap();
    eprintln!("registration error: fiducials {by_fiducials:.1} um, paste pattern {by_paste:.1} um");
    assert!(by_paste < 30.0, "{out}");
    assert!(
        r["pads"]["measured"].as_u64().unwrap() > total * 9 / 10,
        "{out}"
    );

    // The same layer without its X2 names (`%TO` lines dropped) and a KiCad placement file
    // of the generator's components: `dpsa inspect` names every pad with the component the
    // generator gave it (the X2 names of the first inspection are the reference).
    let gen = dpsa_sim::array::layout::generate(dpsa_sim::array::layout::LayoutBoard::Small);
    let stripped: String = std::fs::read_to_string(&layer)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with("%TO") && !l.starts_with("%TD"))
        .map(|l| format!("{l}\n"))
        .collect();
    let bare = d.join("bare.gbr");
    std::fs::write(&bare, stripped).unwrap();
    let mut pos = String::from("## Unit = mm, Angle = deg.\n");
    for c in &gen.components {
        pos.push_str(&format!(
            "{} val {} {:.4} {:.4} {:.1} top\n",
            c.refdes,
            c.family.name(),
            c.centre[0],
            c.centre[1],
            c.rotation_deg
        ));
    }
    std::fs::write(d.join("top.pos"), pos).unwrap();
    let prog2 = d.join("program2.toml");
    ok(&[
        "program",
        "--paste",
        s(&bare),
        "--copper",
        s(&d.join("cu.gbr")),
        "--outline",
        s(&d.join("edge.gbr")),
        "--placement",
        s(&d.join("top.pos")),
        "--out",
        s(&prog2),
    ]);
    let t = std::fs::read_to_string(&prog2).unwrap().replace(
        "search_mm = 1.5",
        &format!("search_mm = {}", want.fiducials.search_mm),
    );
    std::fs::write(&prog2, t).unwrap();
    ok(&[
        "inspect",
        s(&map),
        "--program",
        s(&prog2),
        "--out",
        s(&d.join("insp2")),
    ]);
    let components = |dir: &str| -> Vec<String> {
        std::fs::read_to_string(d.join(dir).join("pads.csv"))
            .unwrap()
            .lines()
            .skip(1)
            .map(|l| l.split(',').nth(1).unwrap().to_string())
            .collect()
    };
    let (x2, placed) = (components("insp"), components("insp2"));
    assert_eq!(x2.len(), total as usize);
    assert!(x2.iter().all(|c| !c.is_empty()));
    assert_eq!(placed, x2);
}

/// A real board from its design files to a verdict per pad, the way a line runs it: the STM32
/// mini pill's KiCad paste layer, outline and placement file taught into a program; the
/// simulated small array (`scenes/stm32-mini-pill.toml`: that layer printed with two defects of
/// every class, no fiducials) calibrated and then recording the board; each camera's frame
/// grabber (`reconstruct --cal --camera`) sending its packet stream; `board --streams` (the
/// production path, no camera recording read) and `inspect`. The simulator's print truth is
/// the independent reference of the verdicts.
#[test]
fn a_real_board_goes_from_its_gerber_files_to_verdicts_through_the_streams() {
    let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/stm32-mini-pill.toml");
    let dir = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
    let d = dir.path();
    let prog = d.join("program.toml");
    teach_pill(&prog, &[]);
    let (calrec, board) = (d.join("calrec"), d.join("board"));
    for (extra, seed, out) in [(Some("--calibration"), "3", &calrec), (None, "5", &board)] {
        let mut args = vec!["--quiet", "simulate", "--scene", s(&scene)];
        args.extend(extra);
        args.extend(["--seed", seed, "--out", s(out)]);
        ok(&args);
    }
    let cal = d.join("cal.toml");
    ok(&["--quiet", "calibrate", s(&calrec), "--out", s(&cal)]);
    // The frame grabbers: one stream per camera. Then nothing of the cameras' recordings is
    // needed any more.
    let mut streams = Vec::new();
    for i in 0..3 {
        let st = d.join(format!("cam{i}.dpsa"));
        ok(&[
            "--quiet",
            "reconstruct",
            s(&board.join(format!("cam{i}"))),
            "--cal",
            s(&cal),
            "--camera",
            &i.to_string(),
            "--out",
            s(&st),
        ]);
        streams.push(st);
    }
    let truth = d.join("print.json");
    std::fs::rename(board.join("print.json"), &truth).unwrap();
    for i in 0..3 {
        std::fs::remove_dir_all(board.join(format!("cam{i}"))).unwrap();
    }
    let map = d.join("map");
    let mut args = vec![
        "--quiet",
        "board",
        s(&board),
        "--cal",
        s(&cal),
        "--out",
        s(&map),
    ];
    args.push("--streams");
    args.extend(streams.iter().map(|p| s(p)));
    ok(&args);
    let text = ok(&[
        "--quiet",
        "inspect",
        s(&map),
        "--program",
        s(&prog),
        "--truth",
        s(&truth),
        "--out",
        s(&d.join("inspection")),
        "--json",
    ]);
    let r: serde_json::Value = serde_json::from_str(&text).unwrap();
    // Every pad of the real layer measured, under the name the placement file gives it.
    assert_eq!(r["pads"]["total"], 102, "{text}");
    assert_eq!(r["pads"]["measured"], 102, "{text}");
    let csv = std::fs::read_to_string(d.join("inspection/pads.csv")).unwrap();
    assert!(csv.lines().skip(1).all(|l| !l.starts_with('#')), "{csv}");
    assert!(csv.contains("\nU1.25,"), "{csv}");
    // No fiducials on this board: the paste pattern registers it, within 30 um of the truth.
    assert_eq!(r["registration"]["method"], "paste pattern", "{text}");
    assert!(
        r["truth"]["registration_error_um"].as_f64().unwrap() < 30.0,
        "{text}"
    );
    // Against the print truth: every injected defect fails, no good pad fails.
    let det = &r["detection"];
    assert!(det["injected"].as_u64().unwrap() >= 10, "{text}");
    assert_eq!(det["missed"], 0, "{text}");
    assert_eq!(det["false_fail"], 0, "{text}");
    // Good pads: volume within a few percent of the truth.
    assert!(
        r["truth"]["volume_err_pct"]["rms"].as_f64().unwrap() < 3.0,
        "{text}"
    );
}
