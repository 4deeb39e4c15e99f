//! What a new user hits (issue 19): memory of `calibrate`, inputs of the wrong kind, messages
//! for bad keys, the array demo, the CFX message's identities and the board's Cramer-Rao line.

use dpsa_sim::array::record;
use dpsa_sim::array::scene::ArrayScene;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn dpsa(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(args)
        .output()
        .unwrap()
}

fn stderr_of(args: &[&str]) -> String {
    let o = dpsa(args);
    assert!(!o.status.success(), "{args:?} succeeded");
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn fixtures() -> &'static Path {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| tempfile::tempdir().unwrap()).path()
}

/// A calibration recording of the small array scene (seed 5) and its calibration file.
fn calibration() -> &'static (PathBuf, PathBuf) {
    static CAL: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();
    CAL.get_or_init(|| {
        let scene = ArrayScene::load(&root().join("scenes/array-small.toml")).unwrap();
        let rec = fixtures().join("calrec");
        record::simulate_calibration(&scene, 5, &rec).unwrap();
        let cal = fixtures().join("cal.toml");
        let o = dpsa(&[
            "calibrate",
            rec.to_str().unwrap(),
            "--out",
            cal.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        (rec, cal)
    })
}

/// `calibrate` on the small scene used to peak at 320-430 MB (every plane's reference rows
/// and pixels collected, three cameras at once) and died with SIGABRT and no message under a
/// 512 MB address limit; it now streams the planes and runs within 256 MB of address space.
#[test]
fn calibrate_runs_within_256_mb_of_address_space() {
    let (rec, _) = calibration();
    let out = fixtures().join("limited.cal.toml");
    let o = Command::new("sh")
        .arg("-c")
        .arg("ulimit -v 262144 && exec \"$0\" calibrate \"$1\" --out \"$2\"")
        .arg(env!("CARGO_BIN_EXE_dpsa"))
        .arg(rec)
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "status {:?}: {}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
    // The same calibration as without the limit.
    let a = std::fs::read_to_string(&out).unwrap();
    let b = std::fs::read_to_string(&calibration().1).unwrap();
    assert_eq!(a, b);
}

/// Files of every kind, made small: only their first bytes or marker files are read before
/// the refusal.
struct Kinds {
    gerber: PathBuf,
    scene: PathBuf,
    cal: PathBuf,
    program: PathBuf,
    recording: PathBuf,
    board_rec: PathBuf,
    cal_rec: PathBuf,
    map: PathBuf,
    stream: PathBuf,
    png: PathBuf,
}

fn kinds(d: &Path) -> Kinds {
    let dir_with = |name: &str, file: &str, text: &str| {
        let p = d.join(name);
        std::fs::create_dir_all(&p).unwrap();
        std::fs::write(p.join(file), text).unwrap();
        p
    };
    let file = |name: &str, bytes: &[u8]| {
        let p = d.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };
    Kinds {
        gerber: root().join("scenes/array-small.paste.gbr"),
        scene: root().join("scenes/array-small.toml"),
        cal: file(
            "a.cal.toml",
            b"format = \"dpsa-calibration\"\nversion = 1\ncounts_per_mm = 400.0\n",
        ),
        program: file(
            "program.toml",
            b"name = \"x\"\npaste_layer = \"paste.gbr\"\nstencil_um = 100.0\n\n[placement]\n",
        ),
        recording: dir_with(
            "rec",
            "manifest.json",
            "{\n  \"format\": \"dpsa-recording\",\n  \"version\": 1\n}\n",
        ),
        board_rec: dir_with(
            "boardrec",
            "array.json",
            "{\n  \"format\": \"dpsa-array-recording\",\n  \"version\": 1,\n  \"kind\": \"board\"\n}\n",
        ),
        cal_rec: dir_with(
            "calrec",
            "array.json",
            "{\n  \"format\": \"dpsa-array-recording\",\n  \"version\": 1,\n  \"kind\": \"calibration\"\n}\n",
        ),
        map: dir_with(
            "map",
            "board.json",
            "{\n  \"format\": \"dpsa-board-map\",\n  \"version\": 1\n}\n",
        ),
        stream: file("s.dpsa", b"DPSA\x02\x00\x10\x00\x00\x00\x00\x00\x00\x00\x00\x00"),
        png: file("i.png", b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR"),
    }
}

/// Every input the CLI takes, given a file of another kind: one sentence naming what the
/// file is, the option it was given as, what that option takes and the command that makes it.
#[test]
fn a_file_of_the_wrong_kind_is_named_for_what_it_is() {
    let tmp = tempfile::tempdir().unwrap();
    let k = kinds(tmp.path());
    let out = tmp.path().join("out");
    let o = out.to_str().unwrap();
    let s = |p: &PathBuf| p.to_str().unwrap().to_string();
    let (g, sc, cal, prog) = (s(&k.gerber), s(&k.scene), s(&k.cal), s(&k.program));
    let (rec, brec, crec, map) = (s(&k.recording), s(&k.board_rec), s(&k.cal_rec), s(&k.map));
    let (stream, png) = (s(&k.stream), s(&k.png));
    // (arguments, what the input is, how it was given, what that takes)
    let cases: Vec<(Vec<&str>, &str, &str, &str)> = vec![
        (
            vec!["inspect", &rec, "--program", &prog, "--out", o],
            "a single-camera recording",
            "MAPDIR",
            "a board map directory",
        ),
        (
            vec!["inspect", &brec, "--program", &prog, "--out", o],
            "an array board recording",
            "MAPDIR",
            "a board map directory",
        ),
        (
            vec!["inspect", &map, "--program", &g, "--out", o],
            "a Gerber file",
            "--program",
            "an inspection program",
        ),
        (
            vec!["inspect", &map, "--program", &cal, "--out", o],
            "an array calibration file",
            "--program",
            "an inspection program",
        ),
        (
            vec!["inspect", &map, "--program", &png, "--out", o],
            "a PNG image",
            "--program",
            "an inspection program",
        ),
        (
            vec![
                "inspect",
                &map,
                "--program",
                &prog,
                "--truth",
                &prog,
                "--out",
                o,
            ],
            "an inspection program",
            "--truth",
            "a simulator print truth",
        ),
        (
            vec!["board", &crec, "--cal", &cal, "--out", o],
            "an array calibration recording",
            "DIR",
            "an array board recording",
        ),
        (
            vec!["board", &map, "--cal", &cal, "--out", o],
            "a board map directory",
            "DIR",
            "an array board recording",
        ),
        (
            vec!["board", &brec, "--cal", &g, "--out", o],
            "a Gerber file",
            "--cal",
            "an array calibration file",
        ),
        (
            vec!["board", &brec, "--cal", &prog, "--out", o],
            "an inspection program",
            "--cal",
            "an array calibration file",
        ),
        (
            vec!["board", &brec, "--cal", &sc, "--out", o],
            "an array scene file",
            "--cal",
            "an array calibration file",
        ),
        (
            vec!["board", &brec, "--cal", &cal, "--out", o, "--streams", &png],
            "a PNG image",
            "--streams",
            "a packet stream",
        ),
        (
            vec!["calibrate", &brec, "--out", o],
            "an array board recording",
            "DIR",
            "an array calibration recording",
        ),
        (
            vec!["reconstruct", &brec, "--out", o],
            "an array board recording",
            "DIR",
            "a single-camera recording",
        ),
        (
            vec!["reconstruct", &rec, "--out", o, "--cal", &prog],
            "an inspection program",
            "--cal",
            "an array calibration file",
        ),
        (
            vec!["compare", &map],
            "a board map directory",
            "DIR",
            "a single-camera recording",
        ),
        (
            vec!["decode", &g],
            "a Gerber file",
            "STREAM",
            "a packet stream",
        ),
        (
            vec!["pads", &prog],
            "an inspection program",
            "FILE",
            "a Gerber file",
        ),
        (
            vec!["pads", &stream],
            "a packet stream",
            "FILE",
            "a Gerber file",
        ),
        (
            vec!["target-run", &map, "--out", o],
            "a board map directory",
            "DIR",
            "a single-camera recording",
        ),
        (
            vec!["frame-bench", &brec],
            "an array board recording",
            "DIR",
            "a single-camera recording",
        ),
        (
            vec!["board-bench", &rec, "--cal", &cal],
            "a single-camera recording",
            "DIR",
            "an array board recording",
        ),
        (
            vec!["codec-bench", &g],
            "a Gerber file",
            "INPUT",
            "a single-camera recording",
        ),
        (
            vec!["simulate", "--scene", &g, "--seed", "1", "--out", o],
            "a Gerber file",
            "--scene",
            "a single-camera scene file",
        ),
    ];
    for (args, found, given, takes) in cases {
        let e = stderr_of(&args);
        let want = format!("is {found}");
        assert!(e.contains(&want), "{args:?}: {e}");
        assert!(
            e.contains(&format!("; {given} takes {takes}")),
            "{args:?}: {e}"
        );
        assert!(
            !e.contains("TOML parse error") && !e.contains("does not exist"),
            "{args:?}: {e}"
        );
        assert_eq!(e.trim_end().lines().count(), 1, "{args:?}: {e}");
        assert!(!out.exists(), "{args:?} wrote its output");
    }
}

/// A `%LS` (or `%LR`, `%LP`) with a bad value is reported with its own syntax, not the
/// parser's `%LM` pattern.
#[test]
fn a_bad_load_transform_names_its_own_command() {
    let tmp = tempfile::tempdir().unwrap();
    let layer = std::fs::read_to_string(root().join("scenes/array-small.paste.gbr")).unwrap();
    for (word, want) in [
        (
            "%LSabc*%",
            "%LS (load scaling) takes a decimal scale factor above 0",
        ),
        (
            "%LS0*%",
            "%LS (load scaling) takes a decimal scale factor above 0",
        ),
        ("%LS*%", "%LS (load scaling)"),
        ("%LRx*%", "%LR (load rotation) takes a decimal angle"),
        ("%LPQ*%", "%LP (load polarity) takes C or D"),
        ("%LMQ*%", "%LM (load mirroring) takes N, X, Y or XY"),
    ] {
        let text = layer.replacen("%MOMM*%\n", &format!("%MOMM*%\n{word}\n"), 1);
        let p = tmp.path().join("bad.gbr");
        std::fs::write(&p, text).unwrap();
        let e = stderr_of(&["pads", p.to_str().unwrap()]);
        assert!(e.contains(want), "{word}: {e}");
        assert!(e.contains("line 9"), "{word}: {e}");
        assert!(!e.contains("regex"), "{word}: {e}");
    }
    // Good values still read.
    let text = layer.replacen("%MOMM*%\n", "%MOMM*%\n%LS1.0*%\n%LR0*%\n%LMN*%\n", 1);
    let p = tmp.path().join("good.gbr");
    std::fs::write(&p, text).unwrap();
    assert!(dpsa(&["pads", p.to_str().unwrap()]).status.success());
}

/// `pixel_mm`, `board_length_mm` or `board_width_mm` of 0 in an array recording's
/// `array.json` is named as such (it used to size an 18446744073709551615 x ... px map, or
/// fail in the PNG encoder with "Zero height not allowed").
#[test]
fn a_zero_size_in_array_json_names_the_key() {
    let (rec, cal) = calibration();
    let text = std::fs::read_to_string(rec.join("array.json")).unwrap();
    for (key, from) in [
        ("pixel_mm", "\"pixel_mm\": 0.0277"),
        ("board_length_mm", "\"board_length_mm\": 20.0"),
        ("board_width_mm", "\"board_width_mm\": 13.9"),
    ] {
        assert!(text.contains(from), "{from}");
        let tmp = tempfile::tempdir().unwrap();
        let bad = tmp.path().join("calrec");
        std::fs::create_dir_all(&bad).unwrap();
        std::fs::write(
            bad.join("array.json"),
            text.replace(from, &format!("\"{key}\": 0.0")),
        )
        .unwrap();
        let e = stderr_of(&[
            "calibrate",
            bad.to_str().unwrap(),
            "--out",
            tmp.path().join("c.toml").to_str().unwrap(),
        ]);
        assert!(e.contains(&format!("`{key}` is 0")), "{key}: {e}");
        assert!(
            !e.contains("18446744073709551615") && !e.contains("Zero height"),
            "{e}"
        );
        // The board command reads the same file the same way.
        let brd = tmp.path().join("boardrec");
        std::fs::create_dir_all(&brd).unwrap();
        std::fs::write(
            brd.join("array.json"),
            text.replace(from, &format!("\"{key}\": 0.0"))
                .replace("\"kind\": \"calibration\"", "\"kind\": \"board\""),
        )
        .unwrap();
        let e = stderr_of(&[
            "board",
            brd.to_str().unwrap(),
            "--cal",
            cal.to_str().unwrap(),
            "--out",
            tmp.path().join("map").to_str().unwrap(),
        ]);
        assert!(e.contains(&format!("`{key}` is 0")), "{key}: {e}");
    }
}

/// A board through the small array with `camera_truth = false` (as the paper board): the
/// summary says why there is no Cramer-Rao bound instead of `n/a um (ratio n/a)`.
#[test]
fn a_board_without_camera_truth_says_why_it_has_no_bound() {
    let (_, cal) = calibration();
    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(root().join("scenes/array-small.toml")).unwrap();
    let scene_path = tmp.path().join("s.toml");
    std::fs::write(
        &scene_path,
        text.replacen(
            "deposits = 40\n",
            "deposits = 40\ncamera_truth = false\n",
            1,
        ),
    )
    .unwrap();
    let scene = ArrayScene::load(&scene_path).unwrap();
    assert!(!scene.camera_truth);
    let brd = tmp.path().join("board");
    record::simulate_board(&scene, 7, &brd).unwrap();
    let o = dpsa(&[
        "board",
        brd.to_str().unwrap(),
        "--cal",
        cal.to_str().unwrap(),
        "--out",
        tmp.path().join("map").to_str().unwrap(),
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains("truth: rms "), "{text}");
    assert!(!text.contains("n/a um (ratio n/a)"), "{text}");
    assert!(
        text.contains("no Cramer-Rao bound (it needs the cameras' truth files"),
        "{text}"
    );
}

/// `demo --array small` runs the array alone (not the single-camera scene first), prints the
/// recordings' measured size, and its CFX message names the board by its identity, the recipe
/// by the program's name and the inspecting tool, with limits rounded to what they mean.
#[test]
fn demo_array_runs_the_array_alone_and_its_cfx_names_the_board() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let o = dpsa(&["demo", "--array", "small", "--out", out.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!out.join("recording").exists(), "{text}");
    assert!(
        !text.contains("1/8") && !text.contains("reconstructing"),
        "{text}"
    );
    for step in ["1/4", "2/4", "3/4", "4/4"] {
        assert!(text.contains(step), "{step}: {text}");
    }
    assert!(text.contains("MB of recordings)"), "{text}");

    // The printed timings add up to the whole: the board's steps and the inspection's.
    for (prefix, steps) in [("time: open ", 7usize), ("  time: map load ", 4usize)] {
        let line = text
            .lines()
            .find(|l| l.starts_with(prefix))
            .unwrap_or_else(|| panic!("no {prefix:?} line: {text}"));
        let nums: Vec<f64> = line
            .split(|c: char| !(c.is_ascii_digit() || c == '.'))
            .filter_map(|w| w.parse().ok())
            .collect();
        assert_eq!(nums.len(), steps + 1, "{line}");
        let (sum, total) = (nums[..steps].iter().sum::<f64>(), nums[steps]);
        assert!(sum <= total + 0.01 * steps as f64, "{line}");
        assert!(
            sum >= 0.8 * total - 0.05,
            "{line}: the steps miss part of the run"
        );
    }

    // The README's two line commands on the demo's own line.toml: the service, and the
    // board recording sent to it (each camera through the core with the line's calibration).
    let line = out.join("line.toml");
    assert!(line.is_file(), "{text}");
    let mut run = Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(["line", "run", "--boards", "1", "--config"])
        .arg(&line)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let board_dir = out.join("array-board");
    let sent = dpsa(&[
        "line",
        "send",
        board_dir.to_str().unwrap(),
        "--config",
        line.to_str().unwrap(),
        "--rate",
        "max",
    ]);
    assert!(
        sent.status.success(),
        "{}",
        String::from_utf8_lossy(&sent.stderr)
    );
    let t0 = std::time::Instant::now();
    while run.try_wait().unwrap().is_none() {
        assert!(t0.elapsed().as_secs() < 120, "line run did not end");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let summary: Value = serde_json::from_slice(&run.wait_with_output().unwrap().stdout).unwrap();
    assert_eq!(summary["boards"], 1, "{summary}");
    assert_eq!(summary["incomplete"], 0, "{summary}");

    let board: Value =
        serde_json::from_slice(&std::fs::read(out.join("array-board").join("array.json")).unwrap())
            .unwrap();
    let id = board["board_id"].as_str().expect("a board id").to_string();
    let map: Value =
        serde_json::from_slice(&std::fs::read(out.join("board-map").join("board.json")).unwrap())
            .unwrap();
    assert_eq!(map["board_id"].as_str(), Some(id.as_str()));
    let cfx: Value = serde_json::from_slice(
        &std::fs::read(out.join("inspection").join("cfx_units_inspected.json")).unwrap(),
    )
    .unwrap();
    let body = &cfx["MessageBody"];
    assert_eq!(
        body["InspectedUnits"][0]["UnitIdentifier"].as_str(),
        Some(id.as_str())
    );
    assert_eq!(body["RecipeName"].as_str(), Some("array-small"));
    let who = body["Inspector"]["OperatorIdentifier"].as_str().unwrap();
    assert_eq!(who, concat!("dpsa ", env!("CARGO_PKG_VERSION")));
    let ms = body["InspectedUnits"][0]["Inspections"][0]["Measurements"]
        .as_array()
        .unwrap();
    assert!(ms.len() > 100);
    // Every number printed with at most its meaningful decimals: volumes whole um^3,
    // heights and offsets to 0.01 um.
    for m in ms {
        for (field, places) in [
            ("PasteVolume", 0),
            ("PasteHeight", 2),
            ("PasteXOffset", 2),
            ("PasteYOffset", 2),
        ] {
            for key in [
                "Value",
                "ExpectedValue",
                "MinimumAcceptableValue",
                "MaximumAcceptableValue",
            ] {
                let v = &m[field][key];
                if v.is_null() {
                    continue;
                }
                let t = v.to_string();
                let decimals = t.split_once('.').map_or(0, |(_, f)| f.len());
                let whole = t.ends_with(".0") && places == 0;
                assert!(decimals <= places.max(1) || whole, "{field}.{key} = {t}");
                if places == 0 {
                    assert_eq!(v.as_f64().unwrap().fract(), 0.0, "{field}.{key} = {t}");
                }
            }
        }
    }
}

/// `HeightPct` is the mean height in % of the stencil: with the usual 100 um stencil it equals
/// `PasteHeight_um` in number; with a 125 um stencil it is 0.8 x it.
#[test]
fn height_pct_is_the_height_over_the_stencil() {
    let (_, cal) = calibration();
    let tmp = tempfile::tempdir().unwrap();
    let scene = ArrayScene::load(&root().join("scenes/array-paste.toml")).unwrap();
    let brd = tmp.path().join("board");
    record::simulate_board(&scene, 3, &brd).unwrap();
    let map = tmp.path().join("map");
    let o = dpsa(&[
        "board",
        brd.to_str().unwrap(),
        "--cal",
        cal.to_str().unwrap(),
        "--out",
        map.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let program = std::fs::read_to_string(brd.join("program.toml")).unwrap();
    assert!(program.contains("stencil_um = 100.0"), "{program}");
    let p125 = brd.join("program125.toml");
    std::fs::write(
        &p125,
        program.replace("stencil_um = 100.0", "stencil_um = 125.0"),
    )
    .unwrap();
    let insp = tmp.path().join("insp");
    let o = dpsa(&[
        "inspect",
        map.to_str().unwrap(),
        "--program",
        p125.to_str().unwrap(),
        "--out",
        insp.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let csv = std::fs::read_to_string(insp.join("pads.csv")).unwrap();
    let mut lines = csv.lines();
    let head: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| head.iter().position(|h| *h == name).unwrap();
    let (h, pct) = (col("PasteHeight_um"), col("HeightPct"));
    let mut checked = 0;
    for l in lines {
        // No quoted fields in the columns before these (pad names without commas here).
        let f: Vec<&str> = l.split(',').collect();
        let (Ok(h), Ok(p)) = (f[h].parse::<f64>(), f[pct].parse::<f64>()) else {
            continue;
        };
        assert!((p - h * 100.0 / 125.0).abs() <= 0.011, "{l}");
        if h.abs() > 20.0 {
            assert!((p - h).abs() > 1.0, "{l}");
        }
        checked += 1;
    }
    assert!(checked > 100, "{checked}");
}
