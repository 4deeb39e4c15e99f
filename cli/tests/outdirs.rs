//! Output directories, inputs, modes and FIFOs (issue 19), through the `dpsa` binary:
//! an output that holds an input is refused; `board` and `inspect` replace their directory
//! whole (an interrupted run leaves the old one, two concurrent runs leave one of them, no
//! stale gallery image survives), refuse an unrelated non-empty directory, create files with
//! the umask's mode; `grr` removes its temporary directory on SIGINT; a FIFO or device given
//! as an ELF or an output is refused without hanging.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn exe() -> &'static str {
    env!("CARGO_BIN_EXE_dpsa")
}

fn scene(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs `dpsa args`, killed (and the test failed) if it has not finished within a minute:
/// a regression that blocks on a FIFO fails instead of hanging the suite.
fn dpsa(args: &[&str]) -> Output {
    let child = Command::new(exe())
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    finish(child, args)
}

fn finish(mut child: Child, what: &[&str]) -> Output {
    let t0 = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            return child.wait_with_output().unwrap();
        }
        if t0.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            let _ = child.wait();
            panic!("dpsa {what:?} did not finish within 60 s (blocked?)");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn ok(args: &[&str]) -> Output {
    let out = dpsa(args);
    assert!(
        out.status.success(),
        "dpsa {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

fn err(args: &[&str]) -> String {
    let out = dpsa(args);
    assert!(!out.status.success(), "dpsa {args:?} succeeded");
    assert_eq!(out.status.code(), Some(1), "dpsa {args:?}");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Two printed boards (seeds 5 and 6), their maps and their inspection reports.
struct Fixture {
    root: PathBuf,
    cal: PathBuf,
    boards: [PathBuf; 2],
    maps: [PathBuf; 2],
    reports: [PathBuf; 2],
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<(tempfile::TempDir, Fixture)> = OnceLock::new();
    &F.get_or_init(|| {
        let tmp = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap();
        let root = tmp.path().to_path_buf();
        let sc = scene("array-paste.toml");
        let cal_rec = root.join("cal-rec");
        ok(&[
            "simulate",
            "--scene",
            s(&sc),
            "--calibration",
            "--out",
            s(&cal_rec),
        ]);
        let cal = root.join("cal.toml");
        ok(&["calibrate", s(&cal_rec), "--out", s(&cal), "--quiet"]);
        let mk = |k: usize| {
            let b = root.join(format!("board{k}"));
            ok(&[
                "simulate",
                "--scene",
                s(&sc),
                "--seed",
                &(5 + k).to_string(),
                "--out",
                s(&b),
            ]);
            let m = root.join(format!("map{k}"));
            ok(&["board", s(&b), "--cal", s(&cal), "--out", s(&m)]);
            let r = root.join(format!("report{k}"));
            ok(&[
                "inspect",
                s(&m),
                "--program",
                s(&b.join("program.toml")),
                "--out",
                s(&r),
            ]);
            (b, m, r)
        };
        let (b0, m0, r0) = mk(0);
        let (b1, m1, r1) = mk(1);
        let f = Fixture {
            root,
            cal,
            boards: [b0, b1],
            maps: [m0, m1],
            reports: [r0, r1],
        };
        (tmp, f)
    })
    .1
}

/// A fresh directory under the fixture root.
fn scratch(name: &str) -> PathBuf {
    static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let d = fixture().root.join(format!("scratch-{name}-{n}"));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Every file under `dir` (relative path -> bytes).
fn snapshot(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    fn walk(base: &Path, d: &Path, out: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(base, &p, out);
            } else {
                let rel = p.strip_prefix(base).unwrap().to_string_lossy().into_owned();
                out.insert(rel, std::fs::read(&p).unwrap());
            }
        }
    }
    let mut m = BTreeMap::new();
    walk(dir, dir, &mut m);
    m
}

/// Entries of `dir` whose names start with a dot (temporaries).
fn hidden(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect()
}

fn copy_dir(from: &Path, to: &Path) {
    let st = Command::new("cp")
        .arg("-a")
        .arg(from)
        .arg(to)
        .status()
        .unwrap();
    assert!(st.success());
}

/// Which whole inspection report `dir` is: `Some(k)` when it is exactly report `k`'s files
/// (the same names, pads.csv, overview and gallery images byte for byte, report.json of the
/// same board); `None` for anything else (a mixture, a partial directory).
fn which_report(dir: &Path) -> Option<usize> {
    let got = snapshot(dir);
    (0..2).find(|&k| {
        let want = snapshot(&fixture().reports[k]);
        let same_names = got.keys().eq(want.keys());
        let same_files = got.iter().all(|(name, bytes)| {
            name == "report.json"
                || name == "cfx_units_inspected.json"
                || want.get(name) == Some(bytes)
        });
        let board = |b: &[u8]| -> String {
            let v: serde_json::Value = serde_json::from_slice(b).unwrap_or_default();
            v["board"].as_str().unwrap_or("").to_string()
        };
        same_names
            && same_files
            && board(&got["report.json"]) == board(&want["report.json"])
            && String::from_utf8_lossy(&got["cfx_units_inspected.json"])
                .contains(&format!("\"{}\"", unit_of(&fixture().maps[k])))
    })
}

/// The CFX unit of a map's inspection: its board id (`board.json`), else its directory name.
fn unit_of(map: &Path) -> String {
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(map.join("board.json")).unwrap()).unwrap();
    match meta["board_id"].as_str() {
        Some(id) => id.to_string(),
        None => map.file_name().unwrap().to_string_lossy().into_owned(),
    }
}

fn inspect_args(k: usize, out: &Path) -> Vec<String> {
    let f = fixture();
    vec![
        "inspect".into(),
        f.maps[k].display().to_string(),
        "--program".into(),
        f.boards[k].join("program.toml").display().to_string(),
        "--out".into(),
        out.display().to_string(),
    ]
}

fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

#[test]
fn an_output_that_holds_an_input_is_refused() {
    let f = fixture();
    // The board recording itself as the output: it holds the program, paste layer and truth.
    let rec = scratch("rec");
    let board = rec.join("board");
    copy_dir(&f.boards[0], &board);
    let before = snapshot(&board);
    let e = err(&[
        "inspect",
        s(&f.maps[0]),
        "--program",
        s(&board.join("program.toml")),
        "--out",
        s(&board),
    ]);
    assert!(
        e.contains("refusing") && e.contains(s(&board)) && e.contains("program.toml"),
        "{e}"
    );
    assert_eq!(snapshot(&board), before, "the inputs were changed");

    // A program elsewhere whose paste layer / truth lies in the output directory.
    let out = scratch("out");
    std::fs::copy(f.boards[0].join("paste.gbr"), out.join("paste.gbr")).unwrap();
    std::fs::copy(f.boards[0].join("print.json"), out.join("print.json")).unwrap();
    let text = std::fs::read_to_string(f.boards[0].join("program.toml")).unwrap();
    let mut lines: Vec<String> = text
        .lines()
        .filter(|l| !l.starts_with("paste_layer") && !l.starts_with("truth"))
        .map(String::from)
        .collect();
    lines.insert(0, format!("paste_layer = {:?}", s(&out.join("paste.gbr"))));
    let prog = rec.join("layer-in-out.toml");
    std::fs::write(&prog, lines.join("\n") + "\n").unwrap();
    let before = snapshot(&out);
    let e = err(&[
        "inspect",
        s(&f.maps[0]),
        "--program",
        s(&prog),
        "--out",
        s(&out),
    ]);
    assert!(e.contains(s(&out)) && e.contains("paste.gbr"), "{e}");
    // The truth given on the command line, inside the output.
    let e = err(&[
        "inspect",
        s(&f.maps[0]),
        "--program",
        s(&f.boards[0].join("program.toml")),
        "--truth",
        s(&out.join("print.json")),
        "--out",
        s(&out),
    ]);
    assert!(e.contains(s(&out)) && e.contains("print.json"), "{e}");
    assert_eq!(snapshot(&out), before, "the inputs were changed");

    // board: a calibration file inside the output directory.
    let m = scratch("map-with-cal");
    std::fs::copy(&f.cal, m.join("cal.toml")).unwrap();
    let e = err(&[
        "board",
        s(&f.boards[0]),
        "--cal",
        s(&m.join("cal.toml")),
        "--out",
        s(&m),
    ]);
    assert!(e.contains(s(&m)) && e.contains("cal.toml"), "{e}");
    assert!(m.join("cal.toml").is_file());
}

#[test]
fn an_unrelated_non_empty_directory_is_refused() {
    let f = fixture();
    let d = scratch("unrelated");
    std::fs::write(d.join("notes.txt"), b"mine").unwrap();
    let before = snapshot(&d);
    let e = err(&strs(&inspect_args(0, &d)));
    assert!(e.contains(s(&d)) && e.contains("notes.txt"), "{e}");
    let e = err(&["board", s(&f.boards[0]), "--cal", s(&f.cal), "--out", s(&d)]);
    assert!(e.contains(s(&d)) && e.contains("notes.txt"), "{e}");
    assert_eq!(snapshot(&d), before);
    // A board map is not an inspection report's directory, nor the other way round.
    let e = err(&strs(&inspect_args(0, &f.maps[1])));
    assert!(
        e.contains("board map") || e.contains("dpsa-board-map"),
        "{e}"
    );
    let parent = d.parent().unwrap();
    assert!(hidden(parent).is_empty(), "{:?}", hidden(parent));
}

#[test]
fn a_new_inspection_replaces_the_old_one_whole() {
    let d = scratch("rerun").join("out");
    copy_dir(&fixture().reports[0], &d);
    // An image of an earlier run that this one does not produce.
    std::fs::write(d.join("gallery").join("999_bridge_STALE.png"), b"old").unwrap();
    ok(&strs(&inspect_args(1, &d)));
    assert_eq!(which_report(&d), Some(1), "not report 1 whole");
    assert!(!d.join("gallery").join("999_bridge_STALE.png").exists());
    assert!(hidden(d.parent().unwrap()).is_empty());
}

/// Runs `args` until something appears in `watch` (the first sign of output), then sends
/// `signal` after `delay`; returns the exit status.
fn interrupt(args: &[&str], watch: &[&Path], signal: &str, delay: Duration) {
    let baseline: Vec<usize> = watch.iter().map(|w| entries(w)).collect();
    let mut child = Command::new(exe())
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            return;
        }
        let changed = watch
            .iter()
            .zip(&baseline)
            .any(|(w, &n)| entries(w) != n || modified_since(w, t0));
        if changed || t0.elapsed() > Duration::from_secs(30) {
            break;
        }
    }
    std::thread::sleep(delay);
    let st = Command::new("kill")
        .arg(format!("-{signal}"))
        .arg(child.id().to_string())
        .status()
        .unwrap();
    assert!(st.success());
    let _ = finish(child, args);
}

fn entries(d: &Path) -> usize {
    std::fs::read_dir(d).map(|r| r.count()).unwrap_or(0)
}

/// Whether a file directly in `d` changed after `t0`.
fn modified_since(d: &Path, t0: Instant) -> bool {
    let since = std::time::SystemTime::now() - t0.elapsed();
    std::fs::read_dir(d).is_ok_and(|r| {
        r.flatten().any(|e| {
            e.metadata()
                .and_then(|m| m.modified())
                .is_ok_and(|t| t >= since)
        })
    })
}

#[test]
fn an_interrupted_board_leaves_the_old_map_whole() {
    let f = fixture();
    let old = snapshot(&f.maps[0]);
    let new = snapshot(&f.maps[1]);
    let parent = scratch("board-int");
    let m = parent.join("map");
    for (i, signal) in [
        "INT", "TERM", "INT", "TERM", "INT", "KILL", "INT", "TERM", "KILL", "INT",
    ]
    .iter()
    .enumerate()
    {
        let _ = std::fs::remove_dir_all(&m);
        copy_dir(&f.maps[0], &m);
        let args = ["board", s(&f.boards[1]), "--cal", s(&f.cal), "--out", s(&m)];
        interrupt(
            &args,
            &[&parent, &m],
            signal,
            Duration::from_millis(3 * i as u64),
        );
        let got = snapshot(&m);
        assert!(
            got == old || got == new,
            "{signal} after {i}: the map is neither the old one nor the new one whole: {:?}",
            got.keys().collect::<Vec<_>>()
        );
        if *signal != "KILL" {
            assert!(hidden(&parent).is_empty(), "{:?}", hidden(&parent));
            assert!(
                hidden(&m).iter().all(|h| h == ".dpsa-output"),
                "{:?}",
                hidden(&m)
            );
        }
        for h in hidden(&parent) {
            let _ = std::fs::remove_dir_all(parent.join(h));
        }
    }
}

#[test]
fn an_interrupted_inspection_leaves_the_old_report_whole() {
    let f = fixture();
    let parent = scratch("insp-int");
    let d = parent.join("out");
    for (i, signal) in ["INT", "TERM", "KILL", "INT", "TERM", "INT", "KILL", "INT"]
        .iter()
        .enumerate()
    {
        let _ = std::fs::remove_dir_all(&d);
        copy_dir(&f.reports[0], &d);
        let args = inspect_args(1, &d);
        interrupt(
            &strs(&args),
            &[&parent, &d],
            signal,
            Duration::from_millis(4 * i as u64),
        );
        assert!(
            which_report(&d).is_some(),
            "{signal} after {i}: neither the old report nor the new one whole: {:?}",
            snapshot(&d).keys().collect::<Vec<_>>()
        );
        if *signal != "KILL" {
            assert!(hidden(&parent).is_empty(), "{:?}", hidden(&parent));
        }
        for h in hidden(&parent) {
            let _ = std::fs::remove_dir_all(parent.join(h));
        }
    }
}

#[test]
fn concurrent_inspections_leave_one_whole_report() {
    let parent = scratch("concurrent");
    let d = parent.join("out");
    for round in 0..6 {
        let a = inspect_args(round % 2, &d);
        let b = inspect_args(1 - round % 2, &d);
        let spawn = |args: &[String]| {
            Command::new(exe())
                .args(args)
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        };
        let (ca, cb) = (spawn(&a), spawn(&b));
        let (oa, ob) = (finish(ca, &strs(&a)), finish(cb, &strs(&b)));
        for o in [&oa, &ob] {
            assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        }
        assert!(
            which_report(&d).is_some(),
            "round {round}: pads.csv, report.json and the images are not from one run: {:?}",
            snapshot(&d).keys().collect::<Vec<_>>()
        );
        assert!(hidden(&parent).is_empty(), "{:?}", hidden(&parent));
    }
}

fn mode(p: &Path) -> u32 {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(p).unwrap().permissions().mode() & 0o7777
}

/// `dpsa args` under `umask`.
fn with_umask(umask: &str, args: &[&str]) {
    let mut cmd = format!("umask {umask} && exec '{}'", exe());
    for a in args {
        cmd.push_str(&format!(" '{a}'"));
    }
    let out = Command::new("sh").arg("-c").arg(&cmd).output().unwrap();
    assert!(
        out.status.success(),
        "{cmd}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn outputs_get_the_umask_mode() {
    let f = fixture();
    for (umask, file, dir) in [("022", 0o644, 0o755), ("027", 0o640, 0o750)] {
        let d = scratch("modes");
        let gbr = d.join("small.gbr");
        with_umask(umask, &["layout", "--board", "small", "--out", s(&gbr)]);
        assert_eq!(mode(&gbr), file, "layout under umask {umask}");
        let m = d.join("map");
        with_umask(
            umask,
            &["board", s(&f.boards[0]), "--cal", s(&f.cal), "--out", s(&m)],
        );
        let r = d.join("report");
        with_umask(umask, &strs(&inspect_args(0, &r)));
        for dir_path in [&m, &r, &r.join("gallery")] {
            assert_eq!(
                mode(dir_path),
                dir,
                "{} under umask {umask}",
                dir_path.display()
            );
        }
        for p in [
            m.join("board.json"),
            m.join("heights_um.tiff"),
            r.join("pads.csv"),
        ] {
            assert_eq!(mode(&p), file, "{} under umask {umask}", p.display());
        }
        let rec = d.join("rec");
        with_umask(
            umask,
            &[
                "simulate",
                "--scene",
                s(&scene("array-small.toml")),
                "--out",
                s(&rec),
            ],
        );
        assert_eq!(mode(&rec.join("array.json")), file);
        let cal = d.join("cal.toml");
        with_umask(
            umask,
            &[
                "calibrate",
                s(&f.root.join("cal-rec")),
                "--out",
                s(&cal),
                "--quiet",
            ],
        );
        assert_eq!(mode(&cal), file);
    }
}

#[test]
fn an_interrupted_grr_removes_its_temporary_directory() {
    let tmp = scratch("grr-tmpdir");
    let child = Command::new(exe())
        .args([
            "grr",
            "--scene",
            s(&scene("array-paste.toml")),
            "--repeats",
            "3",
        ])
        .env("TMPDIR", &tmp)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Wait until the study has written into its temporary directory, then interrupt.
    let t0 = Instant::now();
    let size = |d: &Path| -> u64 {
        let out = Command::new("du").arg("-sb").arg(d).output().unwrap();
        String::from_utf8_lossy(&out.stdout)
            .split_whitespace()
            .next()
            .and_then(|n| n.parse().ok())
            .unwrap_or(0)
    };
    while size(&tmp) < 20 << 20 && t0.elapsed() < Duration::from_secs(50) {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(size(&tmp) >= 20 << 20, "grr wrote nothing into TMPDIR");
    let st = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(st.success());
    let out = finish(child, &["grr"]);
    assert_eq!(out.status.code(), Some(130));
    let left: Vec<_> = std::fs::read_dir(&tmp)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .collect();
    assert!(left.is_empty(), "left in TMPDIR: {left:?}");
}

fn mkfifo(p: &Path) {
    let st = Command::new("mkfifo").arg(p).status().unwrap();
    assert!(st.success());
}

#[test]
fn fifos_and_devices_are_refused_without_hanging() {
    let f = fixture();
    let d = scratch("fifo");
    let fifo = d.join("fifo");
    mkfifo(&fifo);
    // layout --out FIFO.
    let e = err(&["layout", "--board", "small", "--out", s(&fifo)]);
    assert!(e.contains(s(&fifo)) && e.contains("FIFO"), "{e}");
    // target-run --elf FIFO / a device: refused before anything is read.
    let rec = f.boards[0].join("cam0");
    let out = d.join("stream.dpsa");
    for elf in [fifo.as_path(), Path::new("/dev/zero")] {
        let e = err(&["target-run", s(&rec), "--elf", s(elf), "--out", s(&out)]);
        assert!(
            e.contains(s(elf)) && e.contains("not a regular file"),
            "{e}"
        );
    }
    // An ELF larger than the cap is refused from its length.
    let big = d.join("big.elf");
    std::fs::File::create(&big)
        .unwrap()
        .set_len((64 << 20) + 1)
        .unwrap();
    let e = err(&["target-run", s(&rec), "--elf", s(&big), "--out", s(&out)]);
    assert!(e.contains(s(&big)) && e.contains("bytes"), "{e}");
    // target-run --out FIFO: refused before QEMU runs.
    let elf = d.join("some.elf");
    std::fs::write(&elf, b"\x7fELF").unwrap();
    let e = err(&["target-run", s(&rec), "--elf", s(&elf), "--out", s(&fifo)]);
    assert!(e.contains(s(&fifo)) && e.contains("FIFO"), "{e}");
    assert!(!out.exists());
}
