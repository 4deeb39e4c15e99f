//! Issue 19: board maps silently wrong although the tool has the evidence. Swapped cameras,
//! calibration files out of range or inconsistent, `dpsa board` refusing or warning from the
//! evidence, `dpsa calibrate` refusing a wrong plane height. One small calibration recording
//! and one short board of `scenes/array-small.toml` are made once for the whole binary.

use dpsa_sim::array::record::{self, ArrayRecording, ARRAY_FILE};
use dpsa_sim::array::scene::ArrayScene;
use dpsa_sim::calibration::{self, CalFile};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn small_scene() -> ArrayScene {
    ArrayScene::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-small.toml"))
        .unwrap()
}

/// Shared fixtures of this test process, under the target directory.
fn root() -> &'static Path {
    static ROOT: OnceLock<tempfile::TempDir> = OnceLock::new();
    ROOT.get_or_init(|| tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap())
        .path()
}

/// The calibration recording of the small scene (seed 3).
fn cal_recording() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let d = root().join("calrec");
        record::simulate_calibration(&small_scene(), 3, &d).unwrap();
        d
    })
}

/// Its calibration, in a file.
fn cal_file() -> &'static Path {
    static P: OnceLock<PathBuf> = OnceLock::new();
    P.get_or_init(|| {
        let rec = ArrayRecording::open(cal_recording()).unwrap();
        let cal = calibration::calibrate(&rec, 0.5).unwrap();
        let p = root().join("cal.toml");
        std::fs::write(&p, cal.to_toml().unwrap()).unwrap();
        p
    })
}

fn cal() -> CalFile {
    CalFile::load(cal_file()).unwrap()
}

/// A short board of the small scene (6 mm, 4 deposits, seed 3).
fn board() -> &'static Path {
    static DIR: OnceLock<PathBuf> = OnceLock::new();
    DIR.get_or_init(|| {
        let mut s = small_scene();
        s.board_length_mm = 6.0;
        s.deposits = 4;
        let d = root().join("board");
        record::simulate_board(&s, 3, &d).unwrap();
        d
    })
}

fn dpsa<S: AsRef<std::ffi::OsStr>>(args: &[S]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dpsa"))
        .arg("--quiet")
        .args(args)
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn read_json(p: &Path) -> Value {
    serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap()
}

/// A new directory `name` under the fixtures.
fn fresh(name: &str) -> PathBuf {
    let d = root().join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A copy of the board: `array.json` copied (then `edit_array`), camera `i`'s directory
/// linked from `from(i)`, or for the cameras `edit_cam` changes, a directory with every entry
/// linked but an edited `manifest.json`.
fn board_variant(
    name: &str,
    from: impl Fn(usize) -> usize,
    edit_array: impl Fn(&mut Value),
    edit_cam: impl Fn(usize, &mut Value) -> bool,
) -> PathBuf {
    let src = board();
    let d = fresh(name);
    let mut a = read_json(&src.join(ARRAY_FILE));
    edit_array(&mut a);
    std::fs::write(d.join(ARRAY_FILE), serde_json::to_vec(&a).unwrap()).unwrap();
    std::os::unix::fs::symlink(src.join("truth"), d.join("truth")).unwrap();
    for i in 0..3 {
        let cam_src = src.join(format!("cam{}", from(i)));
        let mut m = read_json(&cam_src.join("manifest.json"));
        let dst = d.join(format!("cam{i}"));
        if edit_cam(i, &mut m) {
            std::fs::create_dir_all(&dst).unwrap();
            for e in std::fs::read_dir(&cam_src).unwrap().flatten() {
                if e.file_name() != "manifest.json" {
                    std::os::unix::fs::symlink(e.path(), dst.join(e.file_name())).unwrap();
                }
            }
            std::fs::write(dst.join("manifest.json"), serde_json::to_vec(&m).unwrap()).unwrap();
        } else {
            std::os::unix::fs::symlink(&cam_src, &dst).unwrap();
        }
    }
    d
}

fn board_run(board: &Path, cal: &Path, out: &Path) -> Output {
    dpsa(&[
        "board".as_ref(),
        board.as_os_str(),
        "--cal".as_ref(),
        cal.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--json".as_ref(),
    ])
}

/// `dpsa board` refused before any file is written: the error.
fn board_refused(board: &Path, cal: &Path) -> String {
    let out = board.with_extension("map");
    let o = board_run(board, cal, &out);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(!out.exists(), "a refused run wrote {}", out.display());
    stderr(&o)
}

fn write_cal(name: &str, cal: &CalFile) -> PathBuf {
    let p = root().join(name);
    std::fs::write(&p, cal.to_toml().unwrap()).unwrap();
    p
}

// ---------------------------------------------------------------------------------------------
// 1. Swapped cameras.

#[test]
fn swapped_camera_directories_are_refused() {
    let d = board_variant("swapped-dirs", |i| [1, 0, 2][i], |_| {}, |_, _| false);
    let e = board_refused(&d, cal_file());
    assert!(
        e.contains("camera 0's place") && e.contains("camera.id = 1") && e.contains("swapped"),
        "{e}"
    );
}

#[test]
fn swapped_calibration_blocks_are_refused() {
    // Blocks swapped with their ids: the file's own order check names both.
    let mut c = cal();
    c.camera.swap(0, 1);
    let e = format!(
        "{:#}",
        CalFile::from_toml(&c.to_toml().unwrap()).unwrap_err()
    );
    assert!(e.contains("camera 0: id") && e.contains("says id 1"), "{e}");
    // Blocks swapped and renumbered: each is a valid camera, but not where the design puts it.
    c.camera[0].id = 0;
    c.camera[1].id = 1;
    let p = write_cal("swapped.cal.toml", &c);
    let e = board_refused(board(), &p);
    assert!(
        e.contains("calibration camera 0")
            && e.contains("design camera 1")
            && e.contains("swapped"),
        "{e}"
    );
}

#[test]
fn reconstruct_refuses_another_cameras_calibration() {
    let out = root().join("cam0-as-1.dpsa");
    let rec = board().join("cam0");
    let o = dpsa(&[
        "reconstruct".as_ref(),
        rec.as_os_str(),
        "--cal".as_ref(),
        cal_file().as_os_str(),
        "--camera".as_ref(),
        "1".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(e.contains("camera 0's") && e.contains("camera 1's"), "{e}");
    assert!(!out.exists());
    // Its own camera is fine.
    let o = dpsa(&[
        "reconstruct".as_ref(),
        rec.as_os_str(),
        "--cal".as_ref(),
        cal_file().as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
}

// ---------------------------------------------------------------------------------------------
// 2. Every field of the calibration file, on reading.

type Edit = fn(&mut CalFile);

#[test]
fn every_calibration_field_is_validated_on_reading() {
    let good = cal();
    good.validate().unwrap();
    // (camera named, field named, edit). Every row must be refused naming both.
    let table: Vec<(Option<usize>, &str, Edit)> = vec![
        (None, "counts_per_mm", |c| c.counts_per_mm = f64::NAN),
        (None, "counts_per_mm", |c| c.counts_per_mm *= 1.01),
        (None, "counts_per_mm", |c| c.counts_per_mm = -1.0),
        (None, "height_lsb_um", |c| c.height_lsb_um = 0.0),
        (None, "height_lsb_um", |c| c.height_lsb_um = f64::NAN),
        (None, "fx_budget_um", |c| c.fx_budget_um = -1.0),
        (None, "camera", |c| c.camera.clear()),
        (Some(1), "id", |c| c.camera[1].id = 2),
        (Some(1), "width", |c| c.camera[1].width = 0),
        (Some(1), "rows", |c| c.camera[1].rows = 100_000),
        (Some(1), "bit_depth", |c| c.camera[1].bit_depth = 17),
        (Some(1), "saturation", |c| c.camera[1].saturation = 0),
        (Some(1), "saturation", |c| c.camera[1].saturation = 5000),
        (Some(0), "processing.n", |c| c.processing.n = 2),
        (Some(0), "processing.max_step_rows", |c| {
            c.processing.max_step_rows = 0
        }),
        (Some(0), "processing.min_modulation", |c| {
            c.processing.min_modulation = f64::NAN
        }),
        (Some(0), "processing.max_noise_gain", |c| {
            c.processing.max_noise_gain = 100.0
        }),
        (Some(1), "counts_per_pixel", |c| {
            c.camera[1].counts_per_pixel *= 2.0
        }),
        (Some(1), "counts_per_pixel", |c| {
            c.camera[1].counts_per_pixel = f64::NAN
        }),
        (Some(1), "counts_per_pixel", |c| {
            c.camera[1].counts_per_pixel = 0.0
        }),
        (Some(1), "counts_per_pixel", |c| {
            c.camera[1].counts_per_pixel = -11.0
        }),
        (Some(1), "counts_per_pixel", |c| {
            c.camera[1].counts_per_pixel = 1e-9
        }),
        (Some(1), "counts_per_mm", |c| {
            c.camera[1].counts_per_mm = f64::INFINITY
        }),
        (Some(1), "counts_per_mm", |c| {
            c.camera[1].counts_per_mm *= 2.0
        }),
        (Some(1), "fringe_period_px", |c| {
            c.camera[1].fringe_period_px = f64::NAN
        }),
        (Some(1), "fringe_period_px", |c| {
            c.camera[1].fringe_period_px = 1.0
        }),
        (Some(1), "fringe_period_px", |c| {
            c.camera[1].fringe_period_px = 1e300
        }),
        (Some(1), "fringe_period_px", |c| {
            c.camera[1].fringe_period_px *= 1.001
        }),
        (Some(1), "fringe_frequency_poly", |c| {
            c.camera[1].fringe_frequency_poly[1] = f64::NAN
        }),
        (Some(1), "fringe_frequency_poly", |c| {
            c.camera[1].fringe_frequency_poly = [0.6, 0.0, 0.0]
        }),
        (Some(1), "fx_height_error_um", |c| {
            c.camera[1].fx_height_error_um = -1.0
        }),
        (Some(1), "fx_over_budget", |c| {
            c.camera[1].fx_over_budget = true
        }),
        (Some(1), "fx_over_budget", |c| {
            c.camera[1].fx_height_error_um = 7.0
        }),
        (Some(1), "height_per_turn_um[17]", |c| {
            c.camera[1].height_per_turn_um[17] *= 2.0
        }),
        (Some(1), "height_per_turn_um[17]", |c| {
            c.camera[1].height_per_turn_um[17] = f64::NAN
        }),
        (Some(1), "height_per_turn_um[0]", |c| {
            c.camera[1].height_per_turn_um[0] = 0.0
        }),
        (Some(1), "height_per_turn_um[5]", |c| {
            c.camera[1].height_per_turn_um[5] = -500.0
        }),
        (Some(1), "height_per_turn_um", |c| {
            c.camera[1].height_per_turn_um.pop();
        }),
        (Some(1), "height_per_turn_um", |c| {
            c.camera[1]
                .height_per_turn_um
                .iter_mut()
                .for_each(|t| *t *= 1e4)
        }),
        (Some(1), "reference_phase_rad[3]", |c| {
            c.camera[1].reference_phase_rad[3] = f64::INFINITY
        }),
        (Some(1), "core_reference_phase_rad[3]", |c| {
            c.camera[1].core_reference_phase_rad[3] = f64::NAN
        }),
        (Some(1), "core_reference_phase_rad", |c| {
            c.camera[1].core_reference_phase_rad.push(0.0)
        }),
        (Some(1), "background_dn[4]", |c| {
            c.camera[1].background_dn[4] = -3.0
        }),
        (Some(1), "modulation_dn[4]", |c| {
            c.camera[1].modulation_dn[4] = f64::NAN
        }),
        (Some(1), "modulation_dn[4]", |c| {
            c.camera[1].modulation_dn[4] = 1e9
        }),
        (Some(1), "background_map", |c| {
            c.camera[1].background_map.pop();
        }),
        (Some(1), "dead_pixels", |c| {
            c.camera[1].dead_pixels.push([40, 0])
        }),
        (Some(1), "lateral.x0_mm", |c| {
            c.camera[1].lateral.x0_mm = f64::NAN
        }),
        (Some(1), "lateral.y0_mm", |c| {
            c.camera[1].lateral.y0_mm = f64::NEG_INFINITY
        }),
        (Some(1), "lateral.y0_mm", |c| {
            c.camera[1].lateral.y0_mm = 1e300
        }),
        (Some(1), "lateral.pitch_mm", |c| {
            c.camera[1].lateral.pitch_mm = f64::NAN
        }),
        (Some(1), "lateral.pitch_mm", |c| {
            c.camera[1].lateral.pitch_mm = 0.0
        }),
        (Some(1), "lateral.pitch_mm", |c| {
            c.camera[1].lateral.pitch_mm = -0.0277
        }),
        (Some(1), "lateral.pitch_mm", |c| {
            c.camera[1].lateral.pitch_mm = 1e300
        }),
        // A pitch changed alone contradicts the row pitch (and the encoder step) derived
        // from it.
        (Some(1), "lateral.row_pitch_mm", |c| {
            c.camera[1].lateral.pitch_mm *= 1.01
        }),
        (Some(1), "lateral.rotation_rad", |c| {
            c.camera[1].lateral.rotation_rad = f64::NAN
        }),
        (Some(1), "lateral.rotation_rad", |c| {
            c.camera[1].lateral.rotation_rad = 0.5
        }),
        (Some(1), "lateral.row_pitch_mm", |c| {
            c.camera[1].lateral.row_pitch_mm *= 2.0
        }),
        (Some(1), "lateral.fit_rms_um", |c| {
            c.camera[1].lateral.fit_rms_um = f64::NAN
        }),
        (Some(1), "lateral.fit_rms_um", |c| {
            c.camera[1].lateral.fit_rms_um = 1e3
        }),
    ];
    for (k, (cam, field, edit)) in table.iter().enumerate() {
        let mut c = good.clone();
        edit(&mut c);
        let text = c.to_toml().unwrap();
        let e = match CalFile::from_toml(&text) {
            Ok(_) => panic!("row {k} ({cam:?} {field}): accepted"),
            Err(e) => format!("{e:#}"),
        };
        let want = match cam {
            Some(i) => format!("camera {i}: {field}"),
            None => field.to_string(),
        };
        assert!(e.contains(&want), "row {k}: wanted {want:?} in {e:?}");
        assert!(!e.contains('\n'), "row {k}: not one sentence: {e}");
    }
    // Through the command line: `board` names the file, the camera and the field.
    let mut c = good.clone();
    c.camera[2].fringe_period_px = f64::NAN;
    let p = write_cal("nan-period.cal.toml", &c);
    let e = board_refused(board(), &p);
    assert!(
        e.contains("nan-period.cal.toml") && e.contains("camera 2: fringe_period_px"),
        "{e}"
    );
}

// ---------------------------------------------------------------------------------------------
// 3. `dpsa board`: refused up front, or the map written with `warning:` and exit status 2.

#[test]
fn board_refuses_a_wrong_pixel_pitch_and_doubled_latches() {
    let d = board_variant(
        "pixel-1000",
        |i| i,
        |a| a["pixel_mm"] = 1000.0.into(),
        |_, _| false,
    );
    let e = board_refused(&d, cal_file());
    assert!(e.contains("`pixel_mm` is 1000"), "{e}");
    // pixel_mm 20 % off: in range for array.json, but not the cameras' calibrated pitch.
    let d = board_variant(
        "pixel-20pct",
        |i| i,
        |a| a["pixel_mm"] = (a["pixel_mm"].as_f64().unwrap() * 1.2).into(),
        |_, _| false,
    );
    let e = board_refused(&d, cal_file());
    assert!(
        e.contains("pixel_mm") && e.contains("calibrated pitch"),
        "{e}"
    );

    let d = board_variant(
        "doubled-latches",
        |i| i,
        |_| {},
        |i, m| {
            if i != 1 {
                return false;
            }
            for f in m["frames"].as_array_mut().unwrap() {
                f["latch"] = (f["latch"].as_i64().unwrap() * 2).into();
            }
            true
        },
    );
    let e = board_refused(&d, cal_file());
    assert!(
        e.contains("camera 1") && e.contains("latch") && e.contains("max_step_rows"),
        "{e}"
    );
}

#[test]
fn board_warns_from_the_evidence_with_exit_status_2() {
    // The clean board: no warning, exit 0.
    let out = root().join("clean.map");
    let o = board_run(board(), cal_file(), &out);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let v: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["warnings"], serde_json::json!([]), "{v}");
    assert!(!stderr(&o).contains("warning"));

    // Camera 1's reference-phase table half a turn off: a valid file, a wrong map. The seams
    // show it (half a turn, about 250 um, against a 0.3 um budget).
    let mut c = cal();
    c.camera[1]
        .core_reference_phase_rad
        .iter_mut()
        .for_each(|p| *p += std::f64::consts::PI);
    let p = write_cal("half-turn.cal.toml", &c);
    let out = root().join("half-turn.map");
    let o = board_run(board(), &p, &out);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(
        e.contains("warning: the cameras' heights differ by up to") && e.contains("seam"),
        "{e}"
    );
    let v: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(
        v["seams"]["height_step_um_max"].as_f64().unwrap() > 3.0,
        "{v}"
    );
    assert!(!v["warnings"].as_array().unwrap().is_empty());
    assert!(out.join("heights.png").is_file());

    // Camera 2 finds no pixel valid (its frame grabber configured to take every sample as
    // saturated): it contributes nothing, and the map says so.
    let mut c = cal();
    c.camera[2].saturation = 1;
    let p = write_cal("mute-camera.cal.toml", &c);
    let out = root().join("mute.map");
    let o = board_run(board(), &p, &out);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(
        e.contains("warning: camera 2 contributes almost nothing"),
        "{e}"
    );
    assert!(out.join("heights.png").is_file());
}

// ---------------------------------------------------------------------------------------------
// 4. `dpsa calibrate`.

/// A copy of the calibration recording (passes linked) with `array.json` edited and camera
/// directories taken from `from(i)`.
fn cal_variant(name: &str, edit: impl Fn(&mut Value), from: impl Fn(usize) -> usize) -> PathBuf {
    let src = cal_recording();
    let d = fresh(name);
    let mut a = read_json(&src.join(ARRAY_FILE));
    edit(&mut a);
    std::fs::write(d.join(ARRAY_FILE), serde_json::to_vec(&a).unwrap()).unwrap();
    for i in 0..3 {
        std::os::unix::fs::symlink(
            src.join(format!("cam{}", from(i))),
            d.join(format!("cam{i}")),
        )
        .unwrap();
    }
    d
}

fn calibrate_refused(dir: &Path) -> String {
    let out = dir.with_extension("cal.toml");
    let o = dpsa(&[
        "calibrate".as_ref(),
        dir.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        !out.exists(),
        "a refused calibration wrote {}",
        out.display()
    );
    stderr(&o)
}

#[test]
fn calibrate_refuses_a_wrong_plane_height() {
    // The good calibration's held-out plane is within its image-only Cramer-Rao bound.
    let rep =
        calibration::evaluate(&ArrayRecording::open(cal_recording()).unwrap(), &cal()).unwrap();
    for c in &rep.per_camera {
        assert!(
            c.holdout_rms_over_bound > 0.95 && c.holdout_rms_over_bound < 1.1,
            "{c:?}"
        );
        // The bound from the images alone agrees with the truth's.
        let t = c.holdout_crb_rms_um.unwrap();
        assert!((c.holdout_bound_um / t - 1.0).abs() < 0.02, "{c:?}");
    }
    // Plane 1 listed 50 um off: within the phase-line check (0.5 rad), but the held-out plane
    // measures 12 um off, 6 times its bound.
    let d = cal_variant(
        "plane50",
        |a| a["passes"][1]["height_um"] = 350.0.into(),
        |i| i,
    );
    let e = calibrate_refused(&d);
    assert!(
        e.contains("held-out plane") && e.contains("Cramer-Rao bound") && e.contains("array.json"),
        "{e}"
    );
}

#[test]
fn calibrate_refuses_another_cameras_frames() {
    let d = cal_variant("cal-swapped", |_| {}, |i| [1, 0, 2][i]);
    let e = calibrate_refused(&d);
    assert!(
        e.contains("camera 0") && e.contains("camera 1's frames") && e.contains("swapped"),
        "{e}"
    );
}

// ---------------------------------------------------------------------------------------------
// 5. `dpsa inspect`: the truth of another board, a board.json this build cannot read, a
// program whose fiducials are one mark.

/// Two printed boards of `scenes/array-paste.toml` (seeds 4 and 5; array-small's cameras, so
/// the shared calibration serves) and the map of the first.
struct Paste {
    boards: [PathBuf; 2],
    map: PathBuf,
}

fn paste() -> &'static Paste {
    static P: OnceLock<Paste> = OnceLock::new();
    P.get_or_init(|| {
        let scene = ArrayScene::load(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/array-paste.toml"),
        )
        .unwrap();
        let boards = [root().join("paste4"), root().join("paste5")];
        for (b, seed) in boards.iter().zip([4, 5]) {
            record::simulate_board(&scene, seed, b).unwrap();
        }
        let map = root().join("paste4.map");
        let o = board_run(&boards[0], cal_file(), &map);
        assert!(o.status.success(), "{}", stderr(&o));
        Paste { boards, map }
    })
}

fn inspect(map: &Path, program: &Path, truth: Option<&Path>, out: &Path) -> Output {
    let mut a: Vec<&std::ffi::OsStr> = vec![
        "inspect".as_ref(),
        map.as_os_str(),
        "--program".as_ref(),
        program.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
        "--json".as_ref(),
    ];
    if let Some(t) = truth {
        a.push("--truth".as_ref());
        a.push(t.as_os_str());
    }
    dpsa(&a)
}

fn inspect_refused(map: &Path, program: &Path, truth: Option<&Path>) -> String {
    let out = map.with_extension("inspect-refused");
    let o = inspect(map, program, truth, &out);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        !out.exists(),
        "a refused inspection wrote {}",
        out.display()
    );
    stderr(&o)
}

#[test]
fn inspect_refuses_another_boards_truth() {
    let p = paste();
    let program = p.boards[0].join("program.toml");
    // Its own truth: inspected.
    let o = inspect(&p.map, &program, None, &root().join("paste4.inspect"));
    assert!(o.status.success(), "{}", stderr(&o));
    // The map and the print carry the board's identity, array.json's.
    let id = read_json(&p.boards[0].join(ARRAY_FILE))["board_id"].clone();
    assert_eq!(read_json(&p.map.join("board.json"))["board_id"], id);
    assert_eq!(read_json(&p.boards[0].join("print.json"))["board_id"], id);
    // Board 5's print truth for board 4's map.
    let other = p.boards[1].join("print.json");
    let e = inspect_refused(&p.map, &program, Some(&other));
    let other_id = read_json(&p.boards[1].join(ARRAY_FILE))["board_id"].clone();
    assert!(
        e.contains(other_id.as_str().unwrap()) && e.contains(id.as_str().unwrap()),
        "{e}"
    );
}

#[test]
fn inspect_refuses_a_map_it_cannot_read_and_one_fiducial_three_times() {
    let p = paste();
    let program = p.boards[0].join("program.toml");
    // board.json edited: a copy of the map with the other files linked.
    let variant = |name: &str, edit: &dyn Fn(&mut Value)| -> PathBuf {
        let d = fresh(name);
        for e in std::fs::read_dir(&p.map).unwrap().flatten() {
            if e.file_name() != "board.json" {
                std::os::unix::fs::symlink(e.path(), d.join(e.file_name())).unwrap();
            }
        }
        let mut j = read_json(&p.map.join("board.json"));
        edit(&mut j);
        std::fs::write(d.join("board.json"), serde_json::to_vec(&j).unwrap()).unwrap();
        d
    };
    let m = variant("map-v9", &|j| j["version"] = 9.into());
    let e = inspect_refused(&m, &program, None);
    assert!(e.contains("version 9"), "{e}");
    let m = variant("map-inch", &|j| j["units"]["lengths"] = "inch".into());
    let e = inspect_refused(&m, &program, None);
    assert!(e.contains("\"inch\"") && e.contains("units"), "{e}");
    let m = variant("map-lsb0", &|j| j["units"]["png_lsb_um"] = 0.0.into());
    let e = inspect_refused(&m, &program, None);
    assert!(e.contains("png_lsb_um"), "{e}");

    // The program's three fiducials at one place.
    let text = std::fs::read_to_string(&program).unwrap();
    let one = text.replace(
        "points_mm = [[1.0, 1.0], [19.0, 1.0], [1.0, 12.9]]",
        "points_mm = [[1.0, 1.0], [1.0, 1.0], [1.0, 1.0]]",
    );
    assert_ne!(one, text);
    let prog = p.boards[0].join("one-fiducial.toml");
    std::fs::write(&prog, one).unwrap();
    let e = inspect_refused(&p.map, &prog, None);
    assert!(
        e.contains("fiducials.points_mm") && e.contains("fiducials 0 and 1"),
        "{e}"
    );
}
