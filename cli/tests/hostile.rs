//! Hostile but realistic inputs (issue 9, the host cases): every test runs the `dpsa` binary
//! under a 512 MiB address-space cap (`prlimit --as`, util-linux) and a 60 s timeout, and
//! asserts a clear error, a flagged result or a correct result. Test names carry the case
//! number of the issue.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_dpsa");
/// Address-space cap of every run, bytes.
const MEM_CAP: u64 = 512 << 20;
/// Wall-clock limit of every run.
const TIMEOUT: Duration = Duration::from_secs(60);

struct Run {
    ok: bool,
    stdout: String,
    stderr: String,
}

fn has_prlimit() -> bool {
    Command::new("prlimit")
        .arg("--version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
}

fn command(args: &[&str], cap: u64) -> Command {
    let mut c = if has_prlimit() {
        let mut c = Command::new("prlimit");
        c.arg(format!("--as={cap}")).arg("--").arg(BIN);
        c
    } else {
        eprintln!("prlimit not found (util-linux): running without the memory cap");
        Command::new(BIN)
    };
    c.arg("--quiet").args(args);
    c
}

/// Runs `dpsa --quiet args` under `cap` bytes of address space; kills it after [`TIMEOUT`].
fn run_capped(args: &[&str], cap: u64) -> Run {
    let mut child = command(args, cap)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start dpsa");
    let mut so = child.stdout.take().unwrap();
    let mut se = child.stderr.take().unwrap();
    let t_out = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = so.read_to_string(&mut s);
        s
    });
    let t_err = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = se.read_to_string(&mut s);
        s
    });
    let start = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if start.elapsed() > TIMEOUT {
            let _ = child.kill();
            let _ = child.wait();
            panic!("dpsa {args:?} ran longer than {TIMEOUT:?}");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let r = Run {
        ok: status.success(),
        stdout: t_out.join().unwrap(),
        stderr: t_err.join().unwrap(),
    };
    assert!(
        !r.stderr.contains("panicked"),
        "dpsa {args:?} panicked: {}",
        r.stderr
    );
    assert!(
        !r.stderr.contains("memory allocation"),
        "dpsa {args:?} ran out of memory: {}",
        r.stderr
    );
    r
}

fn run(args: &[&str]) -> Run {
    run_capped(args, MEM_CAP)
}

#[track_caller]
fn ok(args: &[&str]) -> Run {
    let r = run(args);
    assert!(r.ok, "dpsa {args:?} failed: {}", r.stderr);
    r
}

/// Asserts failure with one `error:` line containing every needle; returns stderr.
#[track_caller]
fn fails(args: &[&str], needles: &[&str]) -> String {
    let r = run(args);
    assert!(!r.ok, "dpsa {args:?} should fail; stdout: {}", r.stdout);
    assert!(r.stderr.contains("error:"), "dpsa {args:?}: {}", r.stderr);
    for n in needles {
        assert!(
            r.stderr.contains(n),
            "dpsa {args:?}: {n:?} not in: {}",
            r.stderr
        );
    }
    r.stderr
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// A small recording (`width = 256`, `board_length = 300`, 47 frames) in a fresh directory.
fn rec0(extra: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene.toml");
    let text = if extra.contains("width") {
        extra.to_string()
    } else {
        format!("width = 256\nboard_length = 300\n{extra}")
    };
    std::fs::write(&scene, text).unwrap();
    let rec = dir.path().join("rec");
    ok(&["simulate", "--scene", s(&scene), "--out", s(&rec)]);
    (dir, rec)
}

fn edit_manifest(rec: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let p = rec.join("manifest.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
    edit(&mut v);
    std::fs::write(&p, serde_json::to_string_pretty(&v).unwrap()).unwrap();
}

/// Names of the files in `dir` (for "nothing left behind" checks).
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn case02_failed_run_leaves_no_stream_and_keeps_the_old_one() {
    let (dir, rec) = rec0("");
    let out = dir.path().join("r.dpsa");
    std::fs::write(&out, b"previous stream").unwrap();
    std::fs::remove_file(rec.join("frames/000030.png")).unwrap();
    fails(
        &["reconstruct", s(&rec), "--out", s(&out)],
        &["frame 30", "missing"],
    );
    assert_eq!(std::fs::read(&out).unwrap(), b"previous stream");
    assert_eq!(names(dir.path()), ["r.dpsa", "rec", "scene.toml"]);
}

#[test]
fn case02_sigint_leaves_no_complete_looking_stream() {
    let (dir, rec) = rec0("width = 2048\nboard_length = 2048\ndeposits = 0\n");
    let out = dir.path().join("r.dpsa");
    let mut child = command(&["reconstruct", s(&rec), "--out", s(&out)], MEM_CAP)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let _ = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status();
    let status = child.wait().unwrap();
    if status.success() {
        // Finished before the signal: the stream must be whole.
        let full = dir.path().join("full.dpsa");
        ok(&["reconstruct", s(&rec), "--out", s(&full)]);
        assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&full).unwrap());
    } else {
        assert!(!out.exists(), "an interrupted run left {}", out.display());
        assert_eq!(status.code(), Some(130), "{status:?}");
    }
    // Neither way leaves a hidden temporary (`.r.dpsa.XXXXXX`) beside the output.
    let left: Vec<String> = names(dir.path())
        .into_iter()
        .filter(|n| n.starts_with(".r.dpsa"))
        .collect();
    assert!(left.is_empty(), "temporaries left: {left:?}");
}

#[test]
fn case03_concurrent_writers_leave_one_whole_stream() {
    let (dir, rec) = rec0("");
    let (_d2, rec2) = rec0("seed = 2\n");
    let a = dir.path().join("a.dpsa");
    let b = dir.path().join("b.dpsa");
    ok(&["reconstruct", s(&rec), "--out", s(&a)]);
    ok(&["reconstruct", s(&rec2), "--out", s(&b)]);
    let out = dir.path().join("same.dpsa");
    for _ in 0..3 {
        let (o1, o2) = (out.clone(), out.clone());
        let (r1, r2) = (rec.clone(), rec2.clone());
        let t1 = std::thread::spawn(move || ok(&["reconstruct", s(&r1), "--out", s(&o1)]));
        let t2 = std::thread::spawn(move || ok(&["reconstruct", s(&r2), "--out", s(&o2)]));
        t1.join().unwrap();
        t2.join().unwrap();
        let got = std::fs::read(&out).unwrap();
        assert!(
            got == std::fs::read(&a).unwrap() || got == std::fs::read(&b).unwrap(),
            "the stream is a mix of two runs"
        );
    }
    // The two boards' streams say which board they hold: their run ids (the recordings'
    // identities) differ, and a second reconstruct of one recording carries the same id.
    let run_id = |p: &Path| {
        let r = run(&["decode", s(p), "--json"]);
        let v: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
        v["stream"]["run_id"].as_u64().expect("a run id")
    };
    let (ia, ib) = (run_id(&a), run_id(&b));
    assert_ne!(ia, ib);
    assert_ne!(ia, 0);
    let again = dir.path().join("again.dpsa");
    ok(&["reconstruct", s(&rec), "--out", s(&again)]);
    assert_eq!(run_id(&again), ia);
}

#[test]
fn case04_output_inside_the_recording_is_refused() {
    let (_dir, rec) = rec0("");
    let manifest = std::fs::read(rec.join("manifest.json")).unwrap();
    let frame = std::fs::read(rec.join("frames/000003.png")).unwrap();
    let m = rec.join("manifest.json");
    let e = fails(
        &["reconstruct", s(&rec), "--out", s(&m)],
        &["refusing", "manifest.json", "inside the input directory"],
    );
    assert!(e.contains(s(&rec)), "{e}");
    let f = rec.join("frames/000003.png");
    fails(
        &["reconstruct", s(&rec), "--out", s(&f)],
        &["refusing", "000003.png"],
    );
    // Through a path with `..` and as --png.
    let dotted = rec.join("frames/../x.dpsa");
    fails(
        &["reconstruct", s(&rec), "--out", s(&dotted)],
        &["refusing"],
    );
    assert_eq!(std::fs::read(rec.join("manifest.json")).unwrap(), manifest);
    assert_eq!(std::fs::read(rec.join("frames/000003.png")).unwrap(), frame);
    assert!(!rec.join("x.dpsa").exists());
}

/// Three 16-bit 8 x 8 PNGs for `dpsa phase`.
fn stack(dir: &Path) -> Vec<PathBuf> {
    (0..3)
        .map(|j| {
            let p = dir.join(format!("i{j}.png"));
            let data: Vec<u16> = (0..64)
                .map(|i| {
                    let ph = i as f64 * 0.3 + j as f64 * 2.0 * std::f64::consts::PI / 3.0;
                    (30000.0 + 20000.0 * ph.cos()) as u16
                })
                .collect();
            dpsa_sim::simulation::recording::write_frame_png(&p, 8, 8, &data).unwrap();
            p
        })
        .collect()
}

fn phase_args<'a>(imgs: &'a [PathBuf], steps: &[&'a str]) -> Vec<&'a str> {
    let mut a = vec!["phase"];
    for (i, st) in imgs.iter().zip(steps) {
        a.extend(["--image", s(i), "--step", st]);
    }
    a
}

#[test]
fn case05_non_finite_phase_steps_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let imgs = stack(dir.path());
    let png = dir.path().join("p.png");
    for bad in ["nan", "inf", "-inf", "1e300"] {
        let mut a = phase_args(&imgs, &["0", "120", bad]);
        a.extend(["--png", s(&png)]);
        fails(&a, &["--step", bad]);
        assert!(!png.exists());
    }
}

#[test]
fn case06_manifest_saturation_above_bit_depth_is_refused() {
    let (dir, rec) = rec0("");
    edit_manifest(&rec, |v| v["camera"]["saturation"] = 5000.into());
    let out = dir.path().join("r.dpsa");
    fails(
        &["reconstruct", s(&rec), "--out", s(&out)],
        &["camera.saturation", "5000", "1..=4095"],
    );
    assert!(!out.exists());
}

/// Case 8: one encoder glitch (a latch jump of +1e12 counts, then i64::MAX) used to make
/// `reconstruct` emit one packet per skipped row (terabytes). Now the jump is one gap record:
/// the stream stays the size of a clean run, and `decode` reports the gap and exits non-zero.
#[test]
fn case08_encoder_jump_gives_one_gap_record_not_a_flood() {
    let (dir, rec) = rec0("");
    let clean = dir.path().join("clean.dpsa");
    ok(&["reconstruct", s(&rec), "--out", s(&clean)]);
    edit_manifest(&rec, |v| {
        let frames = v["frames"].as_array_mut().unwrap();
        for f in frames.iter_mut().skip(20) {
            let l = f["latch"].as_i64().unwrap();
            f["latch"] = serde_json::json!(l.saturating_add(1_000_000_000_000));
        }
        let last = frames.len() - 1;
        frames[last]["latch"] = serde_json::json!(i64::MAX);
    });
    let out = dir.path().join("jump.dpsa");
    ok(&["reconstruct", s(&rec), "--out", s(&out)]);
    let (a, b) = (
        std::fs::metadata(&clean).unwrap().len(),
        std::fs::metadata(&out).unwrap().len(),
    );
    assert!(
        b <= a + a / 4,
        "a glitch grew the stream from {a} to {b} bytes"
    );
    let r = run(&["decode", s(&out), "--json"]);
    let v: serde_json::Value = serde_json::from_str(&r.stdout).expect("decode --json prints JSON");
    assert!(v.to_string().contains("gap"), "no gap record reported: {v}");
}

#[test]
fn case09_frames_that_are_devices_or_fifos_are_refused() {
    let (dir, rec) = rec0("");
    let out = dir.path().join("r.dpsa");
    let f = rec.join("frames/000005.png");
    std::fs::remove_file(&f).unwrap();
    std::os::unix::fs::symlink("/dev/zero", &f).unwrap();
    fails(
        &["reconstruct", s(&rec), "--out", s(&out)],
        &["000005.png", "not a regular file"],
    );
    std::fs::remove_file(&f).unwrap();
    assert!(Command::new("mkfifo").arg(&f).status().unwrap().success());
    fails(
        &["reconstruct", s(&rec), "--out", s(&out)],
        &["000005.png", "not a regular file"],
    );
    // An oversized frame file is refused from its length.
    std::fs::remove_file(&f).unwrap();
    let big = std::fs::File::create(&f).unwrap();
    big.set_len(64 << 20).unwrap();
    fails(
        &["reconstruct", s(&rec), "--out", s(&out)],
        &["000005.png", "bytes"],
    );
    // The manifest itself.
    let m = rec.join("manifest.json");
    std::fs::remove_file(&m).unwrap();
    std::os::unix::fs::symlink("/dev/zero", &m).unwrap();
    fails(
        &["compare", s(&rec)],
        &["manifest.json", "not a regular file"],
    );
    assert!(!out.exists());
    // Streams are read in pieces, but only from regular files: a device never ends.
    fails(
        &["decode", "/dev/zero"],
        &["/dev/zero", "not a regular file"],
    );
    fails(
        &["codec-bench", "/dev/zero"],
        &["/dev/zero", "not a regular file"],
    );
    let fifo = dir.path().join("fifo.dpsa");
    assert!(Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap()
        .success());
    fails(&["decode", s(&fifo)], &["fifo.dpsa", "not a regular file"]);
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= u32::from(b);
        for _ in 0..8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
        }
    }
    !c
}

fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend((data.len() as u32).to_be_bytes());
    let mut body = kind.to_vec();
    body.extend_from_slice(data);
    out.extend_from_slice(&body);
    out.extend(crc32(&body).to_be_bytes());
}

#[test]
fn case12_phase_refuses_huge_images_from_the_header() {
    let dir = tempfile::tempdir().unwrap();
    let mut png = vec![0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];
    let mut ihdr = Vec::new();
    ihdr.extend(20000u32.to_be_bytes());
    ihdr.extend(20000u32.to_be_bytes());
    ihdr.extend([8, 0, 0, 0, 0]);
    chunk(&mut png, b"IHDR", &ihdr);
    chunk(
        &mut png,
        b"IDAT",
        &[0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
    );
    chunk(&mut png, b"IEND", &[]);
    let imgs: Vec<PathBuf> = (0..3)
        .map(|j| {
            let p = dir.path().join(format!("huge{j}.png"));
            std::fs::write(&p, &png).unwrap();
            p
        })
        .collect();
    fails(
        &phase_args(&imgs, &["0", "120", "240"]),
        &["huge0.png", "20000 x 20000", "64 Mpx"],
    );
}

#[test]
fn case13_compare_holds_one_window_of_frames() {
    // 553 frames of 4096 x 64: 290 MB of decoded frames, more than the 256 MiB cap of this run.
    let (_dir, rec) = rec0("width = 64\nrows = 4096\nboard_length = 300\ndeposits = 10\n");
    let r = run_capped(&["compare", s(&rec), "--json"], 256 << 20);
    assert!(r.ok, "{}", r.stderr);
    let v: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    assert!(v["fixed_vs_ref"]["max_abs_lsb"].as_f64().unwrap() <= 1.0);
}

#[test]
fn case13_compare_of_a_long_board_streams_its_rows() {
    // 131,072 board rows x 64 px = 8.4 Mpx. Holding the fixed map, the f64 reference, the PSP
    // baseline and the truth took ~90 bytes per board pixel (~750 MB); folded row by row the
    // comparison fits in 192 MiB of address space, and every board row is compared.
    let (_dir, rec) = rec0("width = 64\nboard_length = 131072\n");
    let r = run_capped(&["compare", s(&rec), "--json"], 192 << 20);
    assert!(r.ok, "{}", r.stderr);
    let v: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    let num = |a: &str, b: &str| v[a][b].as_f64().unwrap();
    assert!(num("fixed_vs_ref", "max_abs_lsb") <= 1.0, "{v}");
    assert_eq!(num("fixed_vs_ref", "valid_mismatch"), 0.0, "{v}");
    assert!(num("rows", "total") >= 131_072.0, "{v}");
    assert!(num("truth", "pixels") > 0.9 * 131_072.0 * 62.0, "{v}");
    assert!(num("truth", "fixed_over_crb") < 1.1, "{v}");
}

#[test]
fn case14_simulate_estimates_and_refuses_huge_output() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("big.toml");
    std::fs::write(&scene, "width = 8192\nrows = 4096\nboard_length = 16384\n").unwrap();
    let out = dir.path().join("rec");
    fails(
        &["simulate", "--scene", s(&scene), "--out", s(&out)],
        &["GB", "20 GB limit", "--force"],
    );
    assert!(!out.exists());
}

#[test]
fn case14_simulate_replaces_its_own_recordings_only() {
    let (dir, rec) = rec0("");
    // A shorter board into the same directory: no stale frame of the first run survives.
    let short = dir.path().join("short.toml");
    std::fs::write(&short, "width = 256\nboard_length = 100\n").unwrap();
    ok(&["simulate", "--scene", s(&short), "--out", s(&rec)]);
    let m: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(rec.join("manifest.json")).unwrap()).unwrap();
    let frames = m["frames"].as_array().unwrap().len();
    assert_eq!(names(&rec.join("frames")).len(), frames);
    // A directory with other files is not a recording: refused, untouched.
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("notes.txt"), b"mine").unwrap();
    fails(
        &["simulate", "--scene", s(&short), "--out", s(&other)],
        &["refusing", "notes.txt"],
    );
    assert_eq!(names(&other), ["notes.txt"]);
}

#[test]
fn case15_scenes_the_core_cannot_run_are_refused_at_load() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rec");
    for (text, knob) in [
        ("min_modulation = 2e6\n", "`min_modulation`"),
        ("height_per_turn_um = 1e-300\n", "`height_per_turn_um`"),
        (
            "rows = 4096\nn = 8\nmean_step_px = 3000.0\n",
            "`mean_step_px`",
        ),
        (
            "rows = 4096\nn = 8\nmax_step_rows = 3000\n",
            "`max_step_rows`",
        ),
    ] {
        let scene = dir.path().join("s.toml");
        std::fs::write(&scene, format!("width = 256\nboard_length = 300\n{text}")).unwrap();
        fails(
            &["simulate", "--scene", s(&scene), "--out", s(&out)],
            &[knob],
        );
        assert!(!out.exists());
    }
}

#[test]
fn case15_useless_settings_warn() {
    for (extra, needle) in [
        ("fringe_period_px = 2.0\n", "fringe_period_px = 2"),
        ("counts_per_pixel = 1.52587890625e-5\n", "counts_per_pixel"),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let scene = dir.path().join("s.toml");
        std::fs::write(&scene, format!("width = 256\nboard_length = 300\n{extra}")).unwrap();
        let r = ok(&[
            "simulate",
            "--scene",
            s(&scene),
            "--out",
            s(&dir.path().join("rec")),
        ]);
        assert!(
            r.stderr.contains("warning:") && r.stderr.contains(needle),
            "{extra}: {}",
            r.stderr
        );
        // The recording's manifest warns again when it is read.
        let out = dir.path().join("r.dpsa");
        let r = ok(&["reconstruct", s(&dir.path().join("rec")), "--out", s(&out)]);
        assert!(r.stderr.contains("warning:"), "{extra}: {}", r.stderr);
    }
}

#[test]
fn case16_frame_paths_must_be_relative_plain_and_unique() {
    let (dir, rec) = rec0("");
    let out = dir.path().join("r.dpsa");
    for (file, needle) in [
        ("/etc/passwd", "frames[2].file"),
        ("../rec/frames/000002.png", "frames[2].file"),
        ("frames/000001.png", "listed twice"),
    ] {
        let original = std::fs::read(rec.join("manifest.json")).unwrap();
        edit_manifest(&rec, |v| v["frames"][2]["file"] = file.into());
        fails(&["reconstruct", s(&rec), "--out", s(&out)], &[needle]);
        std::fs::write(rec.join("manifest.json"), original).unwrap();
    }
}

#[test]
fn case17_messages_are_one_sentence_with_the_cause_once() {
    let (dir, rec) = rec0("");
    // Disk full.
    let e = fails(
        &["reconstruct", s(&rec), "--out", "/dev/full"],
        &["/dev/full", "no space"],
    );
    assert!(!e.contains("Os {") && !e.contains("Sink("), "{e}");
    // A directory as output: the cause once.
    let e = fails(
        &["reconstruct", s(&rec), "--out", s(dir.path())],
        &["is a directory"],
    );
    assert_eq!(e.matches("directory").count(), 1, "{e}");
    // A frame that is a directory.
    let f = rec.join("frames/000004.png");
    std::fs::remove_file(&f).unwrap();
    std::fs::create_dir(&f).unwrap();
    let e = fails(
        &[
            "reconstruct",
            s(&rec),
            "--out",
            s(&dir.path().join("x.dpsa")),
        ],
        &["000004.png"],
    );
    assert_eq!(e.matches("directory").count(), 1, "{e}");
    // NaN in the manifest names the field.
    let (_d, rec2) = rec0("");
    let m = rec2.join("manifest.json");
    let text = std::fs::read_to_string(&m).unwrap();
    let text = text.replacen("\"min_modulation\": 60.0", "\"min_modulation\": NaN", 1);
    std::fs::write(&m, text).unwrap();
    fails(&["compare", s(&rec2)], &["min_modulation", "NaN"]);
    // A tiny counts_per_pixel is reported as given, not as 0.
    let scene = dir.path().join("c.toml");
    std::fs::write(
        &scene,
        "width = 256\nboard_length = 300\ncounts_per_pixel = 1e-6\n",
    )
    .unwrap();
    fails(
        &[
            "simulate",
            "--scene",
            s(&scene),
            "--out",
            s(&dir.path().join("r")),
        ],
        &["`counts_per_pixel`", "0.000001 counts/px"],
    );
    // --png without .png: refused before the stream is written.
    let out = dir.path().join("s.dpsa");
    fails(
        &[
            "reconstruct",
            s(&rec),
            "--out",
            s(&out),
            "--png",
            s(&dir.path().join("h.tif")),
        ],
        &["--png", ".png"],
    );
    assert!(!out.exists());
}

#[test]
fn case18_lsb_um_must_be_a_positive_number() {
    let (dir, rec) = rec0("");
    let out = dir.path().join("r.dpsa");
    ok(&["reconstruct", s(&rec), "--out", s(&out)]);
    for bad in ["nan", "inf", "0", "-0.25"] {
        fails(&["decode", s(&out), "--lsb-um", bad], &["--lsb-um"]);
    }
}

#[test]
fn case18_negative_numbers_where_meaningful() {
    let dir = tempfile::tempdir().unwrap();
    let imgs = stack(dir.path());
    let r = ok(&phase_args(&imgs, &["0", "-120", "-240"]));
    assert!(r.stdout.contains("valid pixels"), "{}", r.stdout);
    let mut a = phase_args(&imgs, &["0", "120", "240"]);
    a.extend(["--min-modulation", "-5"]);
    let e = fails(&a, &["--min-modulation", "-5", ">= 0"]);
    assert!(!e.contains("unexpected argument"), "{e}");
    let mut a = phase_args(&imgs, &["0", "120", "240"]);
    a.extend(["--min-modulation", "nan"]);
    fails(&a, &["--min-modulation", "finite"]);
}
