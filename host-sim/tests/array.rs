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

/// One calibration recording of the small scene (seed 3), shared by the tests.
fn calibration_recording() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let cal = dir.path().join("cal");
        record::simulate_calibration(&small_scene(), 3, &cal).unwrap();
        (dir, cal)
    })
    .1
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
    let arr = ArrayRecording::open(rec).unwrap();
    let mut m = Recording::open(arr.camera_dir(1, Some("plane0")))
        .unwrap()
        .manifest;
    cal.camera[1].apply(&mut m, cal.height_lsb_um).unwrap();
    m.validate().unwrap();
    assert_eq!(
        m.calibration.fringe_period_px,
        cal.camera[1].fringe_period_px
    );
    // The fixed-point core with the calibrated configuration (its per-column height scale
    // included) measures the held-out plane: its heights are calibrated um in every column.
    let mut hold = Recording::open(arr.camera_dir(0, Some("holdout"))).unwrap();
    let cam = &cal.camera[0];
    cam.apply(&mut hold.manifest, cal.height_lsb_um).unwrap();
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
        text.starts_with("format = \"dpsa-calibration\"\nversion = 1\n"),
        "{}",
        &text[..80]
    );
    let e = CalFile::from_toml(&text.replace("version = 1", "version = 9")).unwrap_err();
    assert!(format!("{e:#}").contains("version 9"), "{e:#}");
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
    assert!(record::simulate_board(&scene, 5, &tmp.path().join("png")).is_err());
}

/// `dpsa board` on the small scene: the core on every camera with its calibration, the
/// cameras unwrapped, placed and blended into one map in mm, against the board truth.
#[test]
fn board_map_of_the_small_scene_against_its_truth() {
    let cal_rec = ArrayRecording::open(calibration_recording()).unwrap();
    let cal = calibration::calibrate(&cal_rec, 0.5).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let board = tmp.path().join("board");
    record::simulate_board(&small_scene(), 3, &board).unwrap();
    let cal_path = tmp.path().join("cal.toml");
    std::fs::write(&cal_path, cal.to_toml().unwrap()).unwrap();
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
    // A 300 um bow (0.6 turn at 500 um per turn) and 10 deposits: no pixel on a wrong turn.
    assert_eq!(num("unwrap", "wrong_turn_pixels"), 0.0, "{v}");
    assert!(num("pixels", "valid_fraction") >= 0.97, "{v}");
    assert!(num("seams", "height_step_um_max") <= 0.3, "{v}");
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
    for f in [
        "heights.png",
        "heights_um.tiff",
        "heights.colour.png",
        "camera.png",
        "board.json",
    ] {
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
