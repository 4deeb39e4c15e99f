//! The camera array (issue 10): calibration recordings of the small array scene, `dpsa
//! calibrate` against the simulator's truth, bad calibration input, and array board
//! recordings read by the single-camera tools.

use dpsa_sim::array::record::{self, ArrayRecording, PassKind, ARRAY_FILE};
use dpsa_sim::array::scene::ArrayScene;
use dpsa_sim::calibration::{self, CalFile};
use dpsa_sim::simulation::recording::Recording;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

fn small_scene() -> ArrayScene {
    ArrayScene::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-small.toml"))
        .unwrap()
}

/// The directory of this test process's shared fixtures (statics, never dropped), under the
/// target directory rather than /tmp: `array-fixtures/PID`. The fixtures of earlier runs (a
/// process no longer alive) are removed first, so they do not pile up run after run.
fn fixture_root() -> &'static Path {
    static ROOT: OnceLock<PathBuf> = OnceLock::new();
    ROOT.get_or_init(|| {
        let base = Path::new(env!("CARGO_TARGET_TMPDIR")).join("array-fixtures");
        let me = std::process::id();
        for e in std::fs::read_dir(&base).into_iter().flatten().flatten() {
            let pid = e.file_name().to_str().and_then(|n| n.parse::<u32>().ok());
            let alive = pid.is_some_and(|p| p != me && Path::new(&format!("/proc/{p}")).exists());
            if !alive {
                let _ = std::fs::remove_dir_all(e.path());
            }
        }
        let dir = base.join(me.to_string());
        std::fs::create_dir_all(&dir).unwrap();
        dir
    })
}

/// One calibration recording of the small scene (seed 3), shared by the tests.
fn calibration_recording() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let cal = fixture_root().join("cal");
        record::simulate_calibration(&small_scene(), 3, &cal).unwrap();
        cal
    })
}

/// The files of a board map (`dpsa board --out`).
const MAP_FILES: [&str; 5] = [
    "heights.png",
    "heights_um.tiff",
    "heights.colour.png",
    "camera.png",
    "board.json",
];

/// The board-map files of `a` and `b` are the same bytes (`what` names the two in the message).
fn assert_same_map(a: &Path, b: &Path, what: &str) {
    for f in MAP_FILES {
        let same = std::fs::read(a.join(f)).unwrap() == std::fs::read(b.join(f)).unwrap();
        assert!(same, "{f} differs between {what}");
    }
}

#[test]
fn calibration_meets_the_acceptance_targets() {
    let rec = calibration_recording();
    let tmp = tempfile::tempdir().unwrap();
    let cal_path = tmp.path().join("array.cal.toml");
    let out = Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(["calibrate", rec.to_str().unwrap(), "--out"])
        .arg(&cal_path)
        .arg("--json")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let get = |k: &str| {
        k.split('.')
            .fold(&j, |v, key| &v[key])
            .as_f64()
            .unwrap_or_else(|| panic!("{k} missing in {j}"))
    };
    assert_eq!(j["cameras"], 3);
    assert!(get("truth_error.t_z_rel_max") <= 0.002, "{j}");
    assert!(get("truth_error.f_x_rel_max") <= 1e-5, "{j}");
    assert!(get("truth_error.phi0_rms_mrad") <= 5.0, "{j}");
    assert!(get("truth_error.lateral_rms_um") <= 5.0, "{j}");
    assert!(get("truth_error.encoder_rel_max") <= 5e-4, "{j}");
    assert!(get("truth_error.rotation_err_mdeg_max") <= 20.0, "{j}");
    assert!(get("truth_error.background_rel_max") <= 0.01, "{j}");
    assert!(get("truth_error.modulation_rel_max") <= 0.01, "{j}");
    assert_eq!(get("truth_error.dead_pixels_missed"), 0.0, "{j}");
    assert_eq!(get("truth_error.dead_pixels_false"), 0.0, "{j}");
    assert!(get("holdout.bias_um_max") <= 0.5, "{j}");
    let ratio = get("holdout.rms_um") / get("holdout.crb_rms_um");
    assert!((0.95..=1.05).contains(&ratio), "{j}");
    assert!(get("holdout.rms_over_crb_max") <= 1.05, "{j}");
    assert!(get("holdout.pixels") > 100_000.0, "{j}");

    // The file reads back, refuses another array and goes into a camera's manifest.
    let cal = CalFile::load(&cal_path).unwrap();
    assert_eq!(cal.camera.len(), 3);
    assert_eq!(CalFile::from_toml(&cal.to_toml().unwrap()).unwrap(), cal);
    assert!(cal.check_array(&[(192, 40); 3]).is_ok());
    let e = cal.check_array(&[(192, 40); 2]).unwrap_err().to_string();
    assert!(e.contains("3 cameras") && e.contains("has 2"), "{e}");
    let e = cal
        .check_array(&[(192, 40), (256, 40), (192, 40)])
        .unwrap_err()
        .to_string();
    assert!(e.contains("camera 1"), "{e}");
    // The per-pixel flat field: the simulated illumination varies across the columns only, so
    // every live pixel sits at its column's level (10000) within the noise, and every dead
    // pixel the file lists is far below it.
    for c in &cal.camera {
        for map in [&c.background_map, &c.modulation_map] {
            assert_eq!(map.len(), c.rows as usize);
            assert!(map.iter().all(|row| row.len() == c.width as usize));
        }
        for (r, row) in c.modulation_map.iter().enumerate() {
            for (col, &v) in row.iter().enumerate() {
                let dead = c.dead_pixels.contains(&[r as u32, col as u32]);
                if dead {
                    assert!(v < 5000, "camera {} ({r}, {col}): {v}", c.id);
                } else {
                    assert!(
                        (9500..10500).contains(&v),
                        "camera {} ({r}, {col}): {v}",
                        c.id
                    );
                    let b = c.background_map[r][col];
                    assert!(
                        (9800..10200).contains(&b),
                        "camera {} ({r}, {col}): {b}",
                        c.id
                    );
                }
            }
        }
    }
    let mut bad = cal.clone();
    bad.camera[2].modulation_map.pop();
    let e = format!(
        "{:#}",
        CalFile::from_toml(&bad.to_toml().unwrap()).unwrap_err()
    );
    assert!(e.contains("modulation_map"), "{e}");
    let arr = ArrayRecording::open(rec).unwrap();
    let mut m = Recording::open(arr.camera_dir(1, Some("plane0")))
        .unwrap()
        .manifest;
    calibration::apply(&cal, 1, &mut m).unwrap();
    m.validate().unwrap();
    // Calibration has one shape: the core's configuration of the calibrated recording is the
    // calibration file's own (what a frame grabber configured with the file runs, and what
    // `board --streams` checks the streams' configuration hash against).
    assert_eq!(
        dpsa_sim::reconstruct::config(&m).unwrap(),
        dpsa_stream::config::of_calibration(&cal, 1).unwrap()
    );
    assert_eq!(
        m.calibration.fringe_period_px,
        cal.camera[1].fringe_period_px
    );
    // The fixed-point core with the calibrated configuration (its per-column height scale
    // included) measures the held-out plane: its heights are calibrated um in every column.
    let mut hold = Recording::open(arr.camera_dir(0, Some("holdout"))).unwrap();
    let cam = &cal.camera[0];
    calibration::apply(&cal, 0, &mut hold.manifest).unwrap();
    let (_, _, map) = dpsa_sim::reconstruct::reconstruct_map(&hold, false).unwrap();
    let mut errs = Vec::new();
    for row in map.rows.iter().filter(|r| r.is_valid()) {
        for (c, (&h, &ok)) in row.heights.iter().zip(&row.valid).enumerate() {
            if ok {
                let t = cam.height_per_turn_um[c];
                let mut v = f64::from(h) * map.lsb_um;
                v += t * ((450.0 - v) / t).round();
                errs.push(v - 450.0);
            }
        }
    }
    assert!(errs.len() > 50_000, "{}", errs.len());
    errs.sort_by(f64::total_cmp);
    let median = errs[errs.len() / 2];
    let within = errs.iter().filter(|e| e.abs() < 10.0).count() as f64 / errs.len() as f64;
    assert!(median.abs() < 0.5, "core median error {median} um");
    assert!(within > 0.99, "{within}");

    let text = std::fs::read_to_string(&cal_path).unwrap();
    assert!(
        text.starts_with("format = \"dpsa-calibration\"\nversion = 2\n"),
        "{}",
        &text[..80]
    );
    assert!(text.contains("\n[processing]\nn = "), "{}", &text[..400]);
    let e = CalFile::from_toml(&text.replace("version = 2", "version = 9")).unwrap_err();
    assert!(format!("{e:#}").contains("version 9"), "{e:#}");
    // A version 1 file (before the processing and sample range were part of it) is named
    // as such, with what to do.
    let e = CalFile::from_toml(&text.replace("version = 2", "version = 1")).unwrap_err();
    assert!(
        format!("{e:#}").contains("run `dpsa calibrate` again"),
        "{e:#}"
    );
}

/// A copy of the shared recording's layout (symlinked passes) with `array.json` edited.
fn variant(
    edit: impl FnOnce(&mut serde_json::Value),
    link: impl Fn(usize, &str) -> Option<String>,
) -> tempfile::TempDir {
    let src = calibration_recording();
    let dir = tempfile::tempdir().unwrap();
    let mut j: serde_json::Value =
        serde_json::from_slice(&std::fs::read(src.join(ARRAY_FILE)).unwrap()).unwrap();
    let passes: Vec<String> = j["passes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["name"].as_str().unwrap().to_string())
        .collect();
    for cam in 0..3 {
        std::fs::create_dir_all(dir.path().join(format!("cam{cam}"))).unwrap();
        for p in &passes {
            if let Some(from) = link(cam, p) {
                std::os::unix::fs::symlink(
                    src.join(format!("cam{cam}")).join(from),
                    dir.path().join(format!("cam{cam}")).join(p),
                )
                .unwrap();
            }
        }
    }
    edit(&mut j);
    std::fs::write(dir.path().join(ARRAY_FILE), serde_json::to_vec(&j).unwrap()).unwrap();
    dir
}

fn calibrate_err(dir: &Path) -> String {
    let rec = ArrayRecording::open(dir).unwrap();
    format!("{:#}", calibration::calibrate(&rec, 0.5).unwrap_err())
}

#[test]
fn bad_calibration_input_is_refused() {
    let same = |_: usize, p: &str| Some(p.to_string());
    // Too few planes.
    let d = variant(
        |j| {
            let passes = j["passes"].as_array_mut().unwrap();
            passes.retain(|p| p["name"] != "plane2" && p["name"] != "plane3");
        },
        same,
    );
    let e = calibrate_err(d.path());
    assert!(e.contains("2 calibration planes, at least 3"), "{e}");
    // Two planes at the same height.
    let d = variant(
        |j| j["passes"][1]["height_um"] = j["passes"][0]["height_um"].clone(),
        same,
    );
    let e = calibrate_err(d.path());
    assert!(e.contains("at least 5 um"), "{e}");
    // A missing camera.
    let d = variant(|_| {}, |cam, p| (cam != 2).then(|| p.to_string()));
    let e = calibrate_err(d.path());
    assert!(e.contains("camera 2") && e.contains("missing"), "{e}");
    // No lateral target: the target pass shows a bare plane.
    let d = variant(
        |_| {},
        |_, p| {
            Some(if p == "target" {
                "plane0".into()
            } else {
                p.to_string()
            })
        },
    );
    let e = calibrate_err(d.path());
    assert!(e.contains("lateral target not found"), "{e}");
    // A board recording is not a calibration recording; no array.json at all.
    let d = variant(|j| j["kind"] = "board".into(), same);
    assert!(calibrate_err(d.path()).contains("not a calibration recording"));
    let empty = tempfile::tempdir().unwrap();
    let e = format!("{:#}", ArrayRecording::open(empty.path()).unwrap_err());
    assert!(e.contains("no array.json"), "{e}");
    // Plane heights inconsistent with the images (a plane listed 250 um off).
    let d = variant(|j| j["passes"][2]["height_um"] = 850.0.into(), same);
    let e = calibrate_err(d.path());
    assert!(e.contains("do not lie on one line"), "{e}");
}

#[test]
fn board_recording_is_read_by_the_single_camera_tools() {
    let tmp = tempfile::tempdir().unwrap();
    let mut scene = small_scene();
    scene.board_length_mm = 6.0;
    scene.deposits = 4;
    record::simulate_board(&scene, 5, &tmp.path().join("zfr")).unwrap();
    scene.frame_format = dpsa_sim::array::frames::FrameFormat::Png;
    record::simulate_board(&scene, 5, &tmp.path().join("png")).unwrap();
    let (a, b) = (
        ArrayRecording::open(&tmp.path().join("zfr")).unwrap(),
        ArrayRecording::open(&tmp.path().join("png")).unwrap(),
    );
    assert_eq!(a.manifest.cameras.len(), 3);
    assert!(a.manifest.passes.is_empty());
    let truth = a.truth().unwrap().unwrap();
    assert_eq!(truth.deposits.len(), 4);
    let board = truth.board.as_ref().unwrap();
    let raster = dpsa_sim::simulation::recording::read_f32(
        &a.dir.join(&board.file),
        (board.rows * board.cols) as usize,
    )
    .unwrap();
    // The bow: 0 at the board edges, up to warp_um in the middle, plus deposits.
    let mid = raster[(board.rows / 2 * board.cols + board.cols / 2) as usize];
    assert!((f64::from(mid) - 300.0).abs() < 160.0, "{mid}");
    for cam in 0..3 {
        let ra = Recording::open(a.camera_dir(cam, None)).unwrap();
        let rb = Recording::open(b.camera_dir(cam, None)).unwrap();
        assert!(ra.manifest.frames[0].file.ends_with(".zfr"));
        assert!(rb.manifest.frames[0].file.ends_with(".png"));
        for k in [0, ra.len() / 2, ra.len() - 1] {
            assert_eq!(ra.frame(k).unwrap().data, rb.frame(k).unwrap().data);
        }
    }
    // The fixed-point core and the f64 reference on one camera, against its truth.
    let rec = Recording::open(a.camera_dir(1, None)).unwrap();
    let cmp = dpsa_sim::reference::compare::compare_recording(&rec, false).unwrap();
    assert!(
        cmp.fixed_vs_ref.pixels_compared > 10_000,
        "{:?}",
        cmp.fixed_vs_ref
    );
    assert!(
        cmp.fixed_vs_ref.max_abs_lsb.unwrap() <= 1.0,
        "{:?}",
        cmp.fixed_vs_ref
    );
    assert!(rec.truth().unwrap().is_some());
    // A calibration pass name in a board recording: plain error, no panic.
    assert!(a.manifest.passes.iter().all(|p| p.kind != PassKind::Target));
    // A non-empty directory that holds no array recording is refused, untouched.
    let other = tmp.path().join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("notes.txt"), b"mine").unwrap();
    assert!(record::simulate_board(&scene, 5, &other).is_err());
    assert_eq!(std::fs::read(other.join("notes.txt")).unwrap(), b"mine");
}

/// The calibration of the shared calibration recording, in a file (made once).
fn calibration_file() -> &'static Path {
    static CAL: OnceLock<PathBuf> = OnceLock::new();
    CAL.get_or_init(|| {
        let rec = ArrayRecording::open(calibration_recording()).unwrap();
        let cal = calibration::calibrate(&rec, 0.5).unwrap();
        let path = fixture_root().join("cal.toml");
        std::fs::write(&path, cal.to_toml().unwrap()).unwrap();
        path
    })
}

/// `dpsa board` on the small scene: the core on every camera with its calibration, the
/// cameras unwrapped, placed and blended into one map in mm, against the board truth.
#[test]
fn board_map_of_the_small_scene_against_its_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let board = tmp.path().join("board");
    record::simulate_board(&small_scene(), 3, &board).unwrap();
    let cal_path = calibration_file().to_path_buf();
    let out_dir = tmp.path().join("map");
    let out = Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args(["--quiet", "board", board.to_str().unwrap(), "--cal"])
        .arg(&cal_path)
        .arg("--out")
        .arg(&out_dir)
        .arg("--json")
        .output()
        .unwrap();
    let se = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{se}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let num = |a: &str, b: &str| v[a][b].as_f64().unwrap_or_else(|| panic!("{a}.{b}: {v}"));
    // A 300 um bow (0.6 turn at 500 um per turn) and 40 deposits: no pixel on a wrong turn.
    assert_eq!(num("truth", "wrong_turn_pixels"), 0.0, "{v}");
    assert!(num("pixels", "valid_fraction") >= 0.97, "{v}");
    assert!(num("seams", "height_step_um_max") <= 0.3, "{v}");
    // Every seam axis has walls to measure (40 deposits), and the cameras meet within 5 um.
    for seam in v["seams"]["per_seam"].as_array().unwrap() {
        assert!(
            seam["shift_x_um"].is_f64() && seam["shift_y_um"].is_f64(),
            "{v}"
        );
    }
    assert!(num("seams", "lateral_um_max") <= 5.0, "{v}");
    // Against the Cramer-Rao bound of the map's own pixels (each camera pixel's bound carried
    // through the resampling and blending weights): the acceptance bound of 1.05.
    let (rms, crb) = (num("truth", "rms_um"), num("truth", "crb_rms_um"));
    assert!(crb > 0.5 && crb < 2.5, "{v}");
    assert!(rms <= 1.05 * crb, "{v}");
    // Every camera has three dead pixels; each feeds about one board row in eight.
    for k in 0..3 {
        let masked = v["pixels"]["dead_masked"][k].as_u64().unwrap();
        assert!((150..600).contains(&masked), "{v}");
    }
    assert!(num("truth", "bias_um").abs() < 0.5, "{v}");
    for f in MAP_FILES {
        assert!(out_dir.join(f).is_file(), "{f}");
    }
    // A calibration recording is not a board.
    let out = Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .args([
            "--quiet",
            "board",
            calibration_recording().to_str().unwrap(),
            "--cal",
        ])
        .arg(&cal_path)
        .arg("--out")
        .arg(tmp.path().join("map2"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("calibration recording"));
}

// ---------------------------------------------------------------------------------------------
// `dpsa board --streams`: the cameras' packet streams instead of the core.

/// Runs `dpsa --quiet ARGS`.
fn dpsa<I, S>(args: I) -> std::process::Output
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

/// Two short boards of the small scene (6 mm, seeds 3 and 4) and each camera's host stream
/// (`dpsa reconstruct --cal CAL --camera I`).
struct ShortBoards {
    dir: PathBuf,
    boards: [PathBuf; 2],
    /// `streams[board][camera]`.
    streams: [[PathBuf; 3]; 2],
}

fn short_boards() -> &'static ShortBoards {
    static B: OnceLock<ShortBoards> = OnceLock::new();
    B.get_or_init(|| {
        let dir = fixture_root().join("short");
        std::fs::create_dir_all(&dir).unwrap();
        let mut scene = small_scene();
        scene.board_length_mm = 6.0;
        scene.deposits = 4;
        let boards = [dir.join("board3"), dir.join("board4")];
        let mut streams: [[PathBuf; 3]; 2] = Default::default();
        for (k, seed) in [3u64, 4].into_iter().enumerate() {
            record::simulate_board(&scene, seed, &boards[k]).unwrap();
            for (cam, slot) in streams[k].iter_mut().enumerate() {
                let s = dir.join(format!("b{seed}_cam{cam}.dpsa"));
                let out = dpsa([
                    "reconstruct".as_ref(),
                    boards[k].join(format!("cam{cam}")).as_os_str(),
                    "--cal".as_ref(),
                    calibration_file().as_os_str(),
                    "--camera".as_ref(),
                    cam.to_string().as_ref(),
                    "--out".as_ref(),
                    s.as_os_str(),
                ]);
                assert!(
                    out.status.success(),
                    "{}",
                    String::from_utf8_lossy(&out.stderr)
                );
                *slot = s;
            }
        }
        ShortBoards {
            dir,
            boards,
            streams,
        }
    })
}

/// `dpsa board BOARD --cal CAL --out OUT --json [--streams S...]`.
fn board_cmd(board: &Path, out: &Path, streams: &[&Path]) -> std::process::Output {
    let mut args: Vec<&std::ffi::OsStr> = vec![
        "board".as_ref(),
        board.as_os_str(),
        "--cal".as_ref(),
        calibration_file().as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--json".as_ref(),
    ];
    if !streams.is_empty() {
        args.push("--streams".as_ref());
        args.extend(streams.iter().map(|s| s.as_os_str()));
    }
    dpsa(args)
}

/// The core's map of short board `k` (made once per board).
fn core_map(k: usize) -> PathBuf {
    let b = short_boards();
    let out = b.dir.join(format!("core_map{k}"));
    static DONE: OnceLock<()> = OnceLock::new();
    static DONE1: OnceLock<()> = OnceLock::new();
    [&DONE, &DONE1][k].get_or_init(|| {
        let o = board_cmd(&b.boards[k], &out, &[]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    });
    out
}

fn json_of(out: &std::process::Output) -> serde_json::Value {
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "{e}: stdout {} stderr {}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        )
    })
}

fn array_board_id(board: &Path) -> String {
    let j: serde_json::Value =
        serde_json::from_slice(&std::fs::read(board.join(ARRAY_FILE)).unwrap()).unwrap();
    j["board_id"].as_str().unwrap().to_string()
}

#[test]
fn board_from_the_host_streams_is_the_core_map_byte_for_byte() {
    let b = short_boards();
    // One board identity: in array.json and every camera's manifest, the run id of every
    // camera's stream, unchanged by the calibration; two boards differ.
    let id = array_board_id(&b.boards[0]);
    assert_eq!(id.len(), 16);
    assert_ne!(id, array_board_id(&b.boards[1]));
    let cal = CalFile::load(calibration_file()).unwrap();
    for cam in 0..3 {
        let mut rec = Recording::open(b.boards[0].join(format!("cam{cam}"))).unwrap();
        assert_eq!(format!("{:016x}", rec.run_id()), id);
        calibration::apply(&cal, cam, &mut rec.manifest).unwrap();
        assert_eq!(
            format!("{:016x}", rec.run_id()),
            id,
            "calibration changed the run id"
        );
        let (_, rep) =
            dpsa_sim::stream::decode_stream(&std::fs::read(&b.streams[0][cam]).unwrap(), 0.25);
        assert_eq!(
            rep.stream.run_id,
            Some(u64::from_str_radix(&id, 16).unwrap())
        );
        assert_eq!(rep.stream.camera, Some(cam as u8));
    }

    // The streams in another order than the cameras.
    let core = core_map(0);
    let out = b.dir.join("streams_map");
    let s = &b.streams[0];
    let o = board_cmd(&b.boards[0], &out, &[&s[2], &s[0], &s[1]]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!String::from_utf8_lossy(&o.stderr).contains("warning"));
    let v = json_of(&o);
    assert_eq!(v["streams"]["status"], 0, "{v}");
    assert_eq!(v["streams"]["damaged"], false, "{v}");
    assert_eq!(
        v["streams"]["missing_rows"],
        serde_json::json!([0, 0, 0]),
        "{v}"
    );
    assert_eq!(v["streams"]["gap_board_pixels"], 0, "{v}");
    assert_eq!(v["streams"]["run_id"], id.as_str(), "{v}");
    assert_eq!(
        v["streams"]["cameras"][0]["file"],
        s[0].display().to_string()
    );
    assert!(v["pixels"]["valid_fraction"].as_f64().unwrap() > 0.9, "{v}");
    assert_same_map(&core, &out, "the core and the streams");
}

/// Copies directory `from` to `to` (files and subdirectories).
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let dst = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dst);
        } else {
            std::fs::copy(e.path(), dst).unwrap();
        }
    }
}

/// `board --streams` takes where each row came from (dead-pixel masks, row places) from the
/// trigger log inside the streams: with every camera's frames deleted and the latches of the
/// recording's manifests scrambled, the map is the core's byte for byte; the core itself can
/// no longer run on that recording.
#[test]
fn board_streams_need_no_frames_only_their_trigger_logs() {
    let b = short_boards();
    let tmp = tempfile::tempdir().unwrap();
    let board = tmp.path().join("board");
    copy_dir(&b.boards[0], &board);
    for cam in 0..3 {
        let dir = board.join(format!("cam{cam}"));
        let path = dir.join("manifest.json");
        let mut m: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        let frames = m["frames"].as_array_mut().unwrap();
        assert!(frames.len() > 20);
        for f in frames.iter_mut() {
            // Deleted, and its latch no longer the one the frame grabber latched.
            std::fs::remove_file(dir.join(f["file"].as_str().unwrap())).unwrap();
            let l = f["latch"].as_i64().unwrap();
            f["latch"] = serde_json::json!(l * 3 + 17);
        }
        std::fs::write(&path, serde_json::to_vec_pretty(&m).unwrap()).unwrap();
    }
    let s = &b.streams[0];
    let out = tmp.path().join("map");
    let o = board_cmd(&board, &out, &[&s[0], &s[1], &s[2]]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v = json_of(&o);
    assert_eq!(
        v["pixels"]["unplaced_rows"],
        serde_json::json!([0, 0, 0]),
        "{v}"
    );
    let dead: u64 = v["pixels"]["dead_masked"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| d.as_u64().unwrap())
        .sum();
    assert!(
        dead > 0,
        "the calibration's dead pixels masked nothing: {v}"
    );
    let core = core_map(0);
    assert_same_map(
        &core,
        &out,
        "the core's map and the streams' without the frames",
    );
    // The core needs the frames: on this recording it is refused.
    let o = board_cmd(&board, &tmp.path().join("core"), &[]);
    assert!(!o.status.success());

    // No camera recording at all, only `array.json` (and the simulator's truth): the
    // production library (what `cargo build -p dpsa --no-default-features` runs for
    // `board --streams`) and the command both give the core's map byte for byte.
    for cam in 0..3 {
        std::fs::remove_dir_all(board.join(format!("cam{cam}"))).unwrap();
    }
    let cal = CalFile::load(calibration_file()).unwrap();
    let streams: Vec<PathBuf> = s.iter().map(PathBuf::from).collect();
    let lib = tmp.path().join("lib-map");
    let built = dpsa_board::run::from_streams(
        &board,
        &cal,
        &streams,
        &lib,
        false,
        Default::default(),
        Default::default(),
    )
    .unwrap();
    assert_eq!(built.report.pixels.unplaced_rows, vec![0, 0, 0]);
    let cli = tmp.path().join("cli-map");
    let o = board_cmd(&board, &cli, &[&s[0], &s[1], &s[2]]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_same_map(
        &core,
        &lib,
        "the core's map and the library's without recordings",
    );
    assert_same_map(
        &core,
        &cli,
        "the core's map and the command's without recordings",
    );
}

/// A trigger record lost from a stream: the rows whose window the replay can no longer
/// confirm are left invalid and reported, never masked or placed from the wrong frames; the
/// rest of the map is the complete one.
#[test]
fn a_lost_trigger_record_leaves_its_rows_invalid_and_reported() {
    let b = short_boards();
    let tmp = tempfile::tempdir().unwrap();
    let core = core_map(0);
    let (width, clean) = png16(&core.join("heights.png"));
    let n = clean.len();
    let s = &b.streams[0];
    let bytes = std::fs::read(&s[1]).unwrap();
    let pk = packets_of(&bytes);
    let triggers: Vec<usize> = (0..pk.len())
        .filter(|&i| pk[i].2 == dpsa_core::packets::Kind::Trigger)
        .collect();
    let frames = Recording::open(b.boards[0].join("cam1"))
        .unwrap()
        .manifest
        .frames
        .len();
    assert_eq!(triggers.len(), frames, "one trigger record per frame");
    // Drop the middle frame's record.
    let k = triggers[triggers.len() / 2];
    let (start, len, _, latch) = pk[k];
    let mut cut = bytes[..start].to_vec();
    cut.extend_from_slice(&bytes[start + len..]);
    let path = tmp.path().join("no_trigger.dpsa");
    std::fs::write(&path, &cut).unwrap();
    let out = tmp.path().join("map");
    let o = board_cmd(&b.boards[0], &out, &[&s[0], &path, &s[2]]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("trigger record lost"), "{stderr}");
    let v = json_of(&o);
    assert_eq!(v["streams"]["cameras"][1]["missing_packets"], 1, "{v}");
    let unplaced = &v["pixels"]["unplaced_rows"];
    assert_eq!(
        (unplaced[0].as_u64(), unplaced[2].as_u64()),
        (Some(0), Some(0))
    );
    // The rows whose window held the lost frame: up to n windows of max_step_rows rows each.
    let (_, rep) = dpsa_sim::stream::decode_stream(&bytes, 0.25);
    let (nn, step) = (
        u64::from(rep.stream.n.unwrap()),
        u64::from(rep.stream.max_step_rows.unwrap()),
    );
    let u = unplaced[1].as_u64().unwrap();
    assert!(
        u > 0 && u <= (nn + 1) * step,
        "{u} rows unplaced (n {nn}, step {step})"
    );
    // Only near the lost frame does the map change.
    let cal = CalFile::load(calibration_file()).unwrap();
    let o_k = (latch as f64 / cal.camera[1].counts_per_pixel).round();
    let h = f64::from(cal.camera[1].rows);
    let (_, map) = png16(&out.join("heights.png"));
    let coords1 = camera_coords(1, width, n);
    let changed: Vec<usize> = (0..n).filter(|&i| map[i] != clean[i]).collect();
    assert!(!changed.is_empty());
    for &i in &changed {
        let r = coords1[i].0;
        assert!(
            r > o_k - 2.0 && r < o_k + h + 2.0 + (nn * step) as f64,
            "pixel {i} (camera 1 row {r:.1}) changed far from the lost frame (rows {o_k}..)"
        );
    }
}

/// `board --streams` with predicted-row streams (`reconstruct --intra-period K`, every K > 1
/// the docs name) gives the core's map byte for byte, as the intra-period-1 streams do (issue
/// 19: such streams lost their predicted rows, 24 % of the map).
#[test]
fn board_from_predicted_row_streams_is_the_core_map_byte_for_byte() {
    let b = short_boards();
    let core = core_map(0);
    for k in [2u32, 8, dpsa_core::packets::PREDICTED_INTRA_PERIOD] {
        let streams: Vec<PathBuf> = (0..3)
            .map(|cam| {
                let s = b.dir.join(format!("b3_cam{cam}_k{k}.dpsa"));
                let out = dpsa([
                    "reconstruct".as_ref(),
                    b.boards[0].join(format!("cam{cam}")).as_os_str(),
                    "--cal".as_ref(),
                    calibration_file().as_os_str(),
                    "--camera".as_ref(),
                    cam.to_string().as_ref(),
                    "--intra-period".as_ref(),
                    k.to_string().as_ref(),
                    "--out".as_ref(),
                    s.as_os_str(),
                ]);
                assert!(
                    out.status.success(),
                    "{}",
                    String::from_utf8_lossy(&out.stderr)
                );
                // Most rows are predicted (an intra row at least every K rows).
                use dpsa_core::packets::{codec, Item, Kind, Stream};
                let bytes = std::fs::read(&s).unwrap();
                let (mut rows, mut predicted) = (0usize, 0usize);
                for item in Stream::new(&bytes) {
                    if let Item::Packet { packet, .. } = item {
                        if packet.kind == Kind::Row {
                            rows += 1;
                            let (kind, _) = codec::peek(packet.payload).unwrap();
                            predicted += usize::from(kind == codec::RowKind::Predicted);
                        }
                    }
                }
                assert!(
                    predicted >= rows - rows.div_ceil(k as usize) && rows > 100,
                    "K {k} camera {cam}: {predicted} of {rows} rows predicted"
                );
                s
            })
            .collect();
        let out = b.dir.join(format!("streams_map_k{k}"));
        let refs: Vec<&Path> = streams.iter().map(PathBuf::as_path).collect();
        let o = board_cmd(&b.boards[0], &out, &refs);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let v = json_of(&o);
        assert_eq!(v["streams"]["status"], 0, "K {k}: {v}");
        assert_eq!(v["streams"]["damaged"], false, "K {k}: {v}");
        assert_eq!(
            v["streams"]["missing_rows"],
            serde_json::json!([0, 0, 0]),
            "K {k}: {v}"
        );
        assert_same_map(&core, &out, &format!("K {k}: the core and the streams"));
    }
}

#[test]
fn board_streams_that_do_not_belong_are_refused() {
    let b = short_boards();
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("map");
    let [a, o] = &b.streams;
    let err = |streams: &[&Path]| {
        let r = board_cmd(&b.boards[0], &out, streams);
        assert_eq!(r.status.code(), Some(1), "{streams:?}");
        assert!(!out.exists(), "a refused run wrote {}", out.display());
        String::from_utf8_lossy(&r.stderr).into_owned()
    };
    // Camera 1 of another board among this board's streams.
    let e = err(&[&a[0], &o[1], &a[2]]);
    assert!(e.contains("streams from different boards"), "{e}");
    // All three of another board.
    let e = err(&[&o[0], &o[1], &o[2]]);
    assert!(e.contains("another board than"), "{e}");
    // Camera count: too few, one twice.
    let e = err(&[&a[0], &a[1]]);
    assert!(e.contains("2 streams for 3 calibrated cameras"), "{e}");
    let e = err(&[&a[0], &a[0], &a[2]]);
    assert!(e.contains("both camera 0"), "{e}");
    // A stream made without the calibration (the manifest's nominal one).
    let nominal = tmp.path().join("nominal.dpsa");
    let r = dpsa([
        "reconstruct".as_ref(),
        b.boards[0].join("cam1").as_os_str(),
        "--out".as_ref(),
        nominal.as_os_str(),
    ]);
    assert!(r.status.success());
    let e = err(&[&a[0], &nominal, &a[2]]);
    assert!(
        e.contains("camera 1") && e.contains("another configuration"),
        "{e}"
    );
    // A stream of another width (a single-camera recording, 96 px wide, camera 0).
    let scene = dpsa_sim::simulation::scene::Scene {
        width: 96,
        board_length: 60,
        deposits: 2,
        ..Default::default()
    };
    let single = tmp.path().join("single");
    dpsa_sim::simulation::simulate::simulate(&scene, 1, &single, false).unwrap();
    let narrow = tmp.path().join("narrow.dpsa");
    let r = dpsa([
        "reconstruct".as_ref(),
        single.as_os_str(),
        "--out".as_ref(),
        narrow.as_os_str(),
    ]);
    assert!(r.status.success());
    let e = err(&[&narrow, &a[1], &a[2]]);
    assert!(e.contains("96 px wide") && e.contains("192"), "{e}");
    // A stream whose header packet is gone cannot be matched to a camera or a board.
    let bytes = std::fs::read(&a[1]).unwrap();
    let (_, head) = dpsa_core::packets::decode(&bytes).unwrap();
    let headless = tmp.path().join("headless.dpsa");
    std::fs::write(&headless, &bytes[head..]).unwrap();
    let e = err(&[&a[0], &headless, &a[2]]);
    assert!(e.contains("no stream header"), "{e}");
    // A directory or a FIFO is not a stream; the output may not be a stream.
    let e = err(&[&a[0], tmp.path(), &a[2]]);
    assert!(e.contains("packet stream"), "{e}");
    let r = board_cmd(&b.boards[0], &a[1], &[&a[0], &a[1], &a[2]]);
    assert!(!r.status.success());
    assert!(String::from_utf8_lossy(&r.stderr).contains("refusing to write"));
}

/// Without `--program` the map takes the recording's own program: its paste's reflectance is
/// taken out (the JSON says which); a recording without one takes nothing out; a broken one is
/// refused, named, before anything is written. With the streams only `array.json` of the
/// recording is read, so a directory of it and a program stands for the recording.
#[test]
fn board_takes_the_recordings_own_program() {
    let b = short_boards();
    let tmp = tempfile::tempdir().unwrap();
    let rec = tmp.path().join("rec");
    std::fs::create_dir_all(&rec).unwrap();
    std::fs::copy(b.boards[0].join("array.json"), rec.join("array.json")).unwrap();
    let [a, _] = &b.streams;
    let streams = [a[0].as_path(), a[1].as_path(), a[2].as_path()];
    let step = |out: &Path| {
        let r = board_cmd(&rec, out, &streams);
        let j = json_of(&r);
        j["paste_reflectance"]["background_step"].as_f64().unwrap()
    };
    assert_eq!(step(&tmp.path().join("none")), 0.0);
    let program =
        "paste_layer = \"paste.gbr\"\nstencil_um = 120.0\n\n[reflectance]\nbackground_step = 0.5\n";
    std::fs::write(rec.join("program.toml"), program).unwrap();
    assert_eq!(step(&tmp.path().join("own")), 0.5);
    std::fs::write(rec.join("program.toml"), "paste_layer = [\n").unwrap();
    let out = tmp.path().join("broken");
    let r = board_cmd(&rec, &out, &streams);
    assert_eq!(r.status.code(), Some(1));
    let e = String::from_utf8_lossy(&r.stderr);
    assert!(
        e.contains("the recording's own program")
            && e.contains("--program")
            && e.contains("program.toml"),
        "{e}"
    );
    assert!(!out.exists());
}

/// Every packet of a stream: (start, length, kind, board row).
fn packets_of(bytes: &[u8]) -> Vec<(usize, usize, dpsa_core::packets::Kind, i64)> {
    let mut pos = 0;
    let mut out = Vec::new();
    while pos < bytes.len() {
        let (p, len) = dpsa_core::packets::decode(&bytes[pos..]).unwrap();
        out.push((pos, len, p.kind, p.header.row));
        pos += len;
    }
    out
}

/// 16-bit grey image as a row-major vector.
fn png16(path: &Path) -> (usize, Vec<u16>) {
    let img = image::open(path).unwrap().into_luma16();
    (img.width() as usize, img.into_raw())
}

/// `camera.png`'s camera indices (an indexed PNG: its samples, not its colours).
fn png8(path: &Path) -> Vec<u8> {
    dpsa_formats::images::read_png_indexed(path).unwrap().0
}

/// A camera's board row and column of every board pixel of a map.
fn camera_coords(cam: usize, width: usize, n: usize) -> Vec<(f64, f64)> {
    let cal = CalFile::load(calibration_file()).unwrap();
    let b = short_boards();
    let rec = Recording::open(b.boards[0].join(format!("cam{cam}"))).unwrap();
    let p =
        dpsa_sim::board::run::placement(&cal.camera[cam], rec.manifest.processing.max_step_rows);
    let pitch = small_scene().pixel_mm;
    (0..n)
        .map(|k| {
            let (i, j) = (k / width, k % width);
            p.to_camera((i as f64 + 0.5) * pitch, (j as f64 + 0.5) * pitch)
        })
        .collect()
}

#[test]
fn lost_packets_and_a_truncated_stream_leave_their_rows_invalid_and_reported() {
    let b = short_boards();
    let tmp = tempfile::tempdir().unwrap();
    let core = core_map(0);
    let (width, clean) = png16(&core.join("heights.png"));
    let n = clean.len();

    // Camera 1 (the middle one) loses 40 row packets from the middle of the board.
    let bytes = std::fs::read(&b.streams[0][1]).unwrap();
    let pk = packets_of(&bytes);
    let coords1 = camera_coords(1, width, n);
    let mid = coords1[n / 2 + width / 2].0.round() as i64;
    let (lo, hi) = (mid - 20, mid + 19);
    let mut cut = Vec::new();
    let mut removed = 0;
    for &(start, len, kind, row) in &pk {
        if kind == dpsa_core::packets::Kind::Row && (lo..=hi).contains(&row) {
            removed += 1;
        } else {
            cut.extend_from_slice(&bytes[start..start + len]);
        }
    }
    assert_eq!(removed, 40);
    let holed = tmp.path().join("holed.dpsa");
    std::fs::write(&holed, &cut).unwrap();
    let out = tmp.path().join("holed_map");
    let s = &b.streams[0];
    let o = board_cmd(&b.boards[0], &out, &[&s[0], &holed, &s[2]]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("warning: camera 1") && stderr.contains("40 board rows lost"),
        "{stderr}"
    );
    let v = json_of(&o);
    let st = &v["streams"];
    assert_eq!(st["damaged"], true);
    assert_eq!(st["status"], 2);
    assert_eq!(st["missing_rows"], serde_json::json!([0, 40, 0]), "{st}");
    assert_eq!(
        st["cameras"][1]["lost_ranges"],
        serde_json::json!([[lo, hi]]),
        "{st}"
    );
    assert_eq!(st["cameras"][1]["missing_packets"], 40, "{st}");
    assert_eq!(st["cameras"][1]["end_packet"], true, "{st}");
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("board.json")).unwrap()).unwrap();
    assert_eq!(meta["missing_rows"], serde_json::json!([0, 40, 0]));
    let (_, holed_map) = png16(&out.join("heights.png"));
    let cam = png8(&out.join("camera.png"));
    // Where camera 1 lost its rows it contributes nothing, and where only camera 1 sees the
    // board the map is invalid: not filled from the rows around the gap.
    let (mut inside, mut filled_before, mut flagged) = (0, 0, 0);
    for k in 0..n {
        let (r, c) = coords1[k];
        if r > (lo - 1) as f64 && r < (hi + 1) as f64 && (0.0..=191.0).contains(&c) {
            assert_ne!(cam[k], 1, "pixel {k}: camera 1 inside its lost rows");
            if (60.0..=130.0).contains(&c) {
                inside += 1;
                filled_before += usize::from(clean[k] != 0);
                assert_eq!(holed_map[k], 0, "pixel {k} inside the gap is not invalid");
                flagged += 1;
            }
        }
    }
    assert!(inside > 1000, "{inside}");
    assert!(
        filled_before > inside * 9 / 10,
        "{filled_before} of {inside}"
    );
    let gap_px = st["gap_board_pixels"].as_u64().unwrap();
    assert!(gap_px >= flagged, "{gap_px} < {flagged}");
    // Far from the gap the map is the complete one.
    let far: Vec<usize> = (0..n)
        .filter(|&k| (coords1[k].0 - mid as f64).abs() > 60.0)
        .collect();
    let same = far.iter().filter(|&&k| holed_map[k] == clean[k]).count();
    assert!(far.len() > n / 4);
    assert_eq!(same, far.len(), "the map changed far from the gap");

    // Camera 2's stream cut off at 60 % of its bytes, inside a packet.
    let bytes = std::fs::read(&s[2]).unwrap();
    let short = &bytes[..bytes.len() * 6 / 10 + 7];
    let (m, _) = dpsa_sim::stream::decode_stream(short, 0.25);
    let last = m.last_row().unwrap();
    let trunc = tmp.path().join("truncated.dpsa");
    std::fs::write(&trunc, short).unwrap();
    let out = tmp.path().join("truncated_map");
    let o = board_cmd(&b.boards[0], &out, &[&s[0], &s[1], &trunc]);
    assert_eq!(
        o.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let v = json_of(&o);
    let c2 = &v["streams"]["cameras"][2];
    assert_eq!(c2["truncated"], true, "{c2}");
    assert_eq!(c2["end_packet"], false, "{c2}");
    assert!(String::from_utf8_lossy(&o.stderr).contains("no end packet"));
    assert_eq!(c2["lost_ranges"][0][0], last + 1, "{c2}");
    let lost = c2["missing_rows"].as_u64().unwrap();
    let (_, cut_map) = png16(&out.join("heights.png"));
    let cam = png8(&out.join("camera.png"));
    let coords2 = camera_coords(2, width, n);
    let mut beyond = 0;
    for k in 0..n {
        let (r, c) = coords2[k];
        if r > (last + 1) as f64 && (0.0..=191.0).contains(&c) {
            assert_ne!(cam[k], 2, "pixel {k}: camera 2 past its last row");
            if c >= 60.0 {
                beyond += 1;
                assert_eq!(cut_map[k], 0, "pixel {k} past the cut is not invalid");
            }
        }
    }
    assert!(beyond > 1000, "{beyond}");
    // Every board row the camera would still have covered is counted lost.
    let max_r = coords2.iter().map(|p| p.0).fold(f64::MIN, f64::max);
    assert!(
        lost as f64 >= max_r - last as f64,
        "{lost} rows lost, {max_r} {last}"
    );

    // Camera 1's packets spliced into camera 0's stream with continuing sequence numbers (the
    // first half of one, the second half of the other): they are not camera 0's rows.
    let (b0, b1) = (std::fs::read(&s[0]).unwrap(), std::fs::read(&s[1]).unwrap());
    let (p0, p1) = (packets_of(&b0), packets_of(&b1));
    let k = p0.len() / 2;
    let mut spliced = b0[..p0[k].0].to_vec();
    spliced.extend_from_slice(&b1[p1[k].0..]);
    let foreign = (p1.len() - k) as u64;
    let (_, rep) = dpsa_sim::stream::decode_stream(&spliced, 0.25);
    assert_eq!(rep.stream.other_camera, foreign);
    let path = tmp.path().join("spliced.dpsa");
    std::fs::write(&path, &spliced).unwrap();
    let o = board_cmd(
        &b.boards[0],
        &tmp.path().join("spliced_map"),
        &[&path, &s[1], &s[2]],
    );
    assert_eq!(
        o.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let v = json_of(&o);
    let c0 = &v["streams"]["cameras"][0];
    assert!(c0["damaged_packets"].as_u64().unwrap() >= foreign, "{c0}");
    assert_eq!(c0["lost_ranges"][0][0], p0[k].3, "{c0}");
    assert_eq!(c0["truncated"], true, "{c0}"); // its end packet was camera 1's
    assert!(c0["missing_rows"].as_u64().unwrap() > 0, "{c0}");
}

/// `dpsa board-bench` on a short board: every stage timed and summed, the pixel counts those
/// of the board map and of the core's rows (numpy skipped: CI machines need not have it).
#[test]
fn board_bench_reports_every_stage_of_the_board() {
    let b = short_boards();
    let out = dpsa([
        "board-bench".as_ref(),
        b.boards[0].as_os_str(),
        "--cal".as_ref(),
        calibration_file().as_os_str(),
        "--no-numpy".as_ref(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v = json_of(&out);
    let s = &v["seconds"];
    let stage = |k: &str| s[k].as_f64().unwrap_or_else(|| panic!("{k}: {v}"));
    // The stitching is the provenance and the assembly's wall time: the waits for the
    // unwrapping and the resampling are on the assembling thread, one after the other, so
    // within it; the blend runs beside them in a thread of its own, at most as long as the
    // assembly.
    let stitching = stage("stitching");
    let on_thread = stage("provenance") + stage("unwrap") + stage("resample");
    assert!(stitching >= on_thread - 1e-9, "{v}");
    assert!(
        stage("provenance") + stage("blend") <= stitching + 1e-9,
        "{v}"
    );
    // No program in this recording: no inspection stage.
    assert!(
        v["inspection"].is_null() && stage("inspection") == 0.0,
        "{v}"
    );
    let total = stage("core") + stitching + stage("inspection");
    assert!((stage("total") - total).abs() < 1e-9, "{v}");
    // The line's feed, with the frame grabbers' rows and with the core on this host: every
    // camera's rows at 220 mm/s, then the latency to the map.
    let rows = v["core_pixels"].as_u64().unwrap() as f64 / 3.0 / 192.0;
    for key in ["line", "line_core_on_host"] {
        let line = &v[key];
        assert_eq!(line["conveyor_mm_s"], 220.0, "{key}: {v}");
        let feed = line["feed_s"].as_f64().unwrap();
        assert!(
            (feed - rows * 0.0278 / 220.0).abs() < 0.1 * feed,
            "{key}: {v}"
        );
        let latency = line["latency_after_last_row_s"].as_f64().unwrap();
        assert!(
            latency > 0.0 && line["map_after_last_row_s"].as_f64().unwrap() <= latency,
            "{key}: {v}"
        );
        // The rows handed on as they came, a chunk at a time with their places, give the map
        // of the whole cameras at once.
        assert_eq!(line["map_differs_px"], 0, "{key}: {v}");
        // Processor time after the last row: no more than the cores had in the latency (a
        // clock tick of slack per reading and thread start), and the share busy says so.
        let cpu = line["cpu_s_after_last_row"].as_f64().unwrap();
        let threads = v["threads"].as_f64().unwrap();
        assert!(cpu >= 0.0 && cpu <= threads * latency + 0.05, "{key}: {v}");
        let busy = line["busy_after_last_row"].as_f64().unwrap();
        assert!(
            (busy - cpu / (threads * latency)).abs() < 1e-9,
            "{key}: {v}"
        );
        let to_last = line["cpu_s_to_last_row"].as_f64().unwrap();
        assert!(to_last >= 0.0, "{key}: {v}");
        // The floor: the work the cores could not have done by the last row, over the
        // threads; never above the latency (the same tick of slack), never below 0.
        let floor = line["latency_floor_s"].as_f64().unwrap();
        assert!(floor >= 0.0 && floor <= latency + 0.05, "{key}: {v}");
        let rows_s = line["feed_s"].as_f64().unwrap() + line["core_backlog_s"].as_f64().unwrap();
        assert!(
            (floor - ((to_last + cpu - threads * rows_s) / threads).max(0.0)).abs() < 0.05,
            "{key}: {v}"
        );
    }
    // The first run's processor time, within what its cores had.
    let cpu = &v["cpu_seconds"];
    let threads = v["threads"].as_f64().unwrap();
    for (k, wall) in [
        ("stitching", stitching),
        ("inspection", stage("inspection")),
    ] {
        let c = cpu[k]
            .as_f64()
            .unwrap_or_else(|| panic!("cpu_seconds.{k}: {v}"));
        assert!(
            c >= 0.0 && c <= threads * wall + 0.05,
            "cpu_seconds.{k}: {v}"
        );
    }
    let line = &v["line"];
    assert!(v["core_camera0_mpx_s"].as_f64().unwrap() > 0.0, "{v}");
    assert!(stage("load") > 0.0 && stage("core_camera0") > 0.0, "{v}");
    assert_eq!(v["cameras"], 3);
    // Every camera's rows are 192 px wide; a 6 mm board at 27.7 um is about 217 rows each.
    let core_px = v["core_pixels"].as_u64().unwrap();
    assert_eq!(core_px % 192, 0, "{v}");
    assert!((3 * 150 * 192..3 * 400 * 192).contains(&core_px), "{v}");
    // The map the bench stitched has the grid `dpsa board` writes.
    let map = json_of(&board_cmd(&b.boards[0], &b.dir.join("bench-map"), &[]));
    let g = &map["grid"];
    assert_eq!(
        v["board_pixels"].as_u64().unwrap(),
        g["rows"].as_u64().unwrap() * g["width"].as_u64().unwrap()
    );
    assert!(line["map_rows_done_at_last_row"].as_u64().unwrap() <= g["rows"].as_u64().unwrap());
    assert!(
        v["numpy"].is_null() && v["core_over_numpy"].is_null(),
        "{v}"
    );
    assert!(
        v["numpy_error"].as_str().unwrap().contains("skipped"),
        "{v}"
    );
}

/// A board printed from the small generated paste layer (`scenes/array-paste.toml`): simulated
/// through the command line, quickly, with the layer and the print in the recording, and the
/// board truth showing the print.
#[test]
fn paste_board_recording_carries_its_layer_and_print() {
    use dpsa_sim::array::print::{paste_height, Defect, DepositIndex, Print};
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    let scene_path = scenes.join("array-paste.toml");
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("board");
    let t0 = std::time::Instant::now();
    let o = dpsa([
        std::ffi::OsStr::new("simulate"),
        "--scene".as_ref(),
        scene_path.as_os_str(),
        "--seed".as_ref(),
        "4".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let secs = t0.elapsed().as_secs_f64();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(secs < 30.0, "simulating array-paste took {secs:.1} s");
    eprintln!("array-paste simulated in {secs:.2} s");
    let rec = ArrayRecording::open(&out).unwrap();
    assert_eq!(
        rec.manifest.paste_layer.as_deref(),
        Some(record::PASTE_LAYER_FILE)
    );
    assert_eq!(rec.manifest.print.as_deref(), Some(record::PRINT_FILE));
    assert_eq!(
        std::fs::read(out.join(record::PASTE_LAYER_FILE)).unwrap(),
        std::fs::read(scenes.join("array-small.paste.gbr")).unwrap()
    );
    let print: Print =
        serde_json::from_slice(&std::fs::read(out.join(record::PRINT_FILE)).unwrap()).unwrap();
    let layer = dpsa_sim::array::layout::generate(dpsa_sim::array::layout::LayoutBoard::Small);
    assert_eq!(print.pads.len(), layer.pads.len());
    for (d, n) in [
        (Defect::Missing, 2),
        (Defect::Insufficient, 2),
        (Defect::Excess, 2),
        (Defect::Offset, 2),
        (Defect::Bridge, 4),
        (Defect::Smear, 2),
    ] {
        assert_eq!(print.count(d), n, "{d:?}");
    }
    assert_eq!(print.fiducials.len(), 3);
    // The board truth raster is the warp plus the printed deposits.
    let truth = rec.truth().unwrap().unwrap();
    assert!(truth.deposits.is_empty());
    let board = truth.board.as_ref().unwrap();
    let raster = dpsa_sim::simulation::recording::read_f32(
        &out.join(&board.file),
        board.rows as usize * board.cols as usize,
    )
    .unwrap();
    let scene = ArrayScene::load(&scene_path).unwrap();
    let index = DepositIndex::new(&print.deposits);
    let cols = board.cols as usize;
    let mut paste_pixels = 0;
    for i in (0..board.rows as usize).step_by(3) {
        for j in (0..cols).step_by(3) {
            let (x, y) = (
                (i as f64 + 0.5) * board.pitch_mm,
                (j as f64 + 0.5) * board.pitch_mm,
            );
            let (h, paste) = paste_height(&print.deposits, &index, [x, y]);
            let want = scene.warp(x, y) + h;
            assert!(
                (f64::from(raster[i * cols + j]) - want).abs() < 0.01,
                "{x} {y}"
            );
            paste_pixels += usize::from(paste);
        }
    }
    assert!(paste_pixels > 500, "{paste_pixels}");
    // A missing pad's opening is bare board.
    let missing = print
        .pads
        .iter()
        .find(|p| p.defect == Defect::Missing)
        .unwrap();
    let c = print
        .design_to_board
        .apply(layer.pads[missing.pad].outline.centroid());
    assert_eq!(paste_height(&print.deposits, &index, c), (0.0, false));
}

/// A paste layer that misses the board under the scene's placement is refused before any
/// work, naming the problem.
#[test]
fn a_layer_that_misses_the_board_is_refused() {
    let mut scene =
        ArrayScene::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-paste.toml"))
            .unwrap();
    scene.placement.design_origin_mm = [6.0, 0.0];
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("board");
    let e = format!("{:#}", record::simulate_board(&scene, 1, &out).unwrap_err());
    assert!(
        e.contains("fall outside") && e.contains("design_origin_mm"),
        "{e}"
    );
    assert!(!out.exists());
}
