//! The paste layer reader's limits: a FIFO is refused (not read forever), and the object,
//! vertex and size limits are clear errors. Each read runs on a thread with a timeout guard, so
//! a regression fails instead of hanging.

use dpsa_sim::inspection::gerber::{
    read_file, read_str, GerberError, PasteLayer, MAX_FILE_BYTES, MAX_OBJECTS,
};
use std::sync::mpsc;
use std::time::Duration;

/// `f` on a thread; a failure if it takes over `secs` (the guard, not a speed figure).
fn within<T: Send + 'static>(secs: u64, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(Duration::from_secs(secs))
        .expect("the reader did not return in time (hangs?)")
}

#[cfg(unix)]
#[test]
fn a_fifo_is_refused_not_read_forever() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("paste.gtp");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .expect("mkfifo");
    assert!(made.success());
    let path = fifo.clone();
    let r: Result<PasteLayer, GerberError> = within(30, move || read_file(&path));
    let e = r.expect_err("a FIFO must be refused");
    let msg = e.to_string();
    assert!(matches!(e, GerberError::Io { .. }), "{msg}");
    assert!(msg.contains("paste.gtp") && msg.contains("FIFO"), "{msg}");
}

#[test]
fn a_directory_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().to_path_buf();
    let e = within(30, move || read_file(&p)).expect_err("a directory");
    assert!(e.to_string().contains("directory"), "{e}");
}

#[test]
fn too_many_objects_by_step_and_repeat() {
    // 1001 x 1000 copies: one more row than MAX_OBJECTS allows; refused before expanding.
    assert_eq!(MAX_OBJECTS, 1_000_000);
    let text = "%FSLAX46Y46*%\n%MOMM*%\n%ADD10C,0.1*%\n%SRX1001Y1000I0.2J0.2*%\nD10*\nX0Y0D03*\n%SR*%\nM02*\n";
    let e = within(60, move || read_str(text)).expect_err("too many objects");
    assert!(
        matches!(
            e,
            GerberError::TooManyObjects {
                limit: 1_000_000,
                ..
            }
        ),
        "{e}"
    );
    // Exactly at the limit of copies the count is fine; one flash under it reads.
    let ok =
        "%FSLAX46Y46*%\n%MOMM*%\n%ADD10C,0.1*%\n%SRX2Y1I0.2J0.2*%\nD10*\nX0Y0D03*\n%SR*%\nM02*\n";
    assert_eq!(read_str(ok).unwrap().pads.len(), 2);
}

#[test]
fn a_file_over_the_size_limit_is_refused_before_reading() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("big.gtp");
    let f = std::fs::File::create(&p).unwrap();
    f.set_len(MAX_FILE_BYTES + 1).unwrap(); // sparse: no disk used
    let e = within(30, move || read_file(&p)).expect_err("too large");
    assert!(
        matches!(e, GerberError::TooLarge { bytes, .. } if bytes == MAX_FILE_BYTES + 1),
        "{e}"
    );
}

#[test]
fn too_many_vertices_is_refused() {
    // A 50 mm circle (1 um chords: over 300 vertices) stepped and repeated 500,000 times: under
    // the object limit, over the vertex limit; refused before expanding.
    let text =
        "%FSLAX46Y46*%\n%MOMM*%\n%ADD10C,50*%\n%SRX1000Y500I0J0*%\nD10*\nX0Y0D03*\n%SR*%\nM02*\n";
    let e = within(60, move || read_str(text)).expect_err("too complex");
    assert!(matches!(e, GerberError::TooComplex { .. }), "{e}");
}
