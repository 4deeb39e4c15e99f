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
    // A 50 mm circle with a hole (not a plain flash: its pad keeps its polygon, over 600
    // vertices) stepped and repeated 500,000 times: under the object limit, over the vertex
    // limit; refused before expanding.
    let text = "%FSLAX46Y46*%\n%MOMM*%\n%ADD10C,50X10*%\n%SRX1000Y500I0J0*%\nD10*\nX0Y0D03*\n%SR*%\nM02*\n";
    let e = within(60, move || read_str(text)).expect_err("too complex");
    assert!(matches!(e, GerberError::TooComplex { line: 4, .. }), "{e}");
}

#[test]
fn a_huge_aperture_stroked_along_an_arc_is_refused_at_once() {
    // A 9 m disc swept along a half circle of 100 mm radius (the disc covers the centre, so
    // the stroke is the union of a capsule per chord): over a million vertices, refused
    // before any is made.
    let text = "%FSLAX46Y46*%\n%MOMM*%\n%ADD10C,9000*%\nD10*\nG75*\nX0Y100000000D02*\nG03X0Y-100000000I0J-100000000D01*\nM02*\n";
    let e = within(10, move || read_str(text)).expect_err("too complex");
    assert!(
        matches!(e, GerberError::StrokeTooComplex { line: 7, vertices, .. } if vertices > 200_000),
        "{e}"
    );
    assert!(e.to_string().contains("C 9000"), "{e}");
    // The load_gerber fuzz target's out-of-memory input (97 bytes; 1.2 GB and 12 s before):
    // a 9,092 mm disc along an "arc" from its own centre to a point 100 m away; and its
    // timeout input (the same with a 92 mm disc, 1,111 capsules): not one circle.
    for text in [
        "%FSLAX45Y46*%\n%MOMM*%\n%ADD10C,09092*%\nD10*\nG75*\nX0Y1D02*\nG01X100000002Y0D01*\nG03X100020Y0002000*\n",
        "%FSLAX43YAM46*%\n%MOMM*%\n%ADD10C,092*%\nD10*\nG75*\nX0Y1D02*\nG01X1000003Y0D01*\nG03X000110Y0000000*\n",
    ] {
        let e = within(10, move || read_str(text)).expect_err("not one circle");
        assert!(
            e.line() == 8 && e.to_string().contains("not one circle"),
            "{e}"
        );
    }
}

/// A layer of `n` flashes of 0.2 x 0.1 mm on a 0.5 mm grid, `per_row` to a row, with the
/// apertures, polarity, attributes and a step and repeat spread over the file: long enough
/// to be read in several chunks.
fn long_layer(n: usize) -> String {
    let mut t = String::from("%FSLAX46Y46*%\n%MOMM*%\n%ADD10R,0.2X0.1*%\nD10*\n");
    for i in 0..n {
        if i == n / 2 {
            // A second aperture defined deep in the file, a component attribute.
            t.push_str("%ADD11C,0.3*%\n%TO.C,U7*%\nD11*\n");
        }
        t.push_str(&format!(
            "X{}Y{}D03*\n",
            (i % 200) * 500_000,
            (i / 200) * 500_000
        ));
    }
    t.push_str("%TD*%\nM02*\n");
    t
}

#[test]
fn a_layer_read_in_chunks_is_read_whole() {
    use dpsa_sim::inspection::gerber::CHUNK_STATEMENTS;
    use dpsa_sim::inspection::pads::Outline;
    // Three and a half chunks of flashes: every pad where the file put it, with its
    // aperture and attribute, whichever chunk it was in.
    let n = CHUNK_STATEMENTS * 7 / 2;
    let layer = within(120, move || read_str(&long_layer(n))).expect("reads");
    assert_eq!(layer.pads.len(), n);
    assert!(layer.complete);
    for (i, p) in layer.pads.iter().enumerate() {
        let want = [(i % 200) as f64 * 0.5, (i / 200) as f64 * 0.5];
        let (centre, second) = match &p.outline {
            Outline::RoundRect { centre, .. } => (centre, false),
            Outline::Circle { centre, .. } => (centre, true),
            o => panic!("pad {i}: {o:?}"),
        };
        assert!(
            (centre[0] - want[0]).abs() < 1e-9 && (centre[1] - want[1]).abs() < 1e-9,
            "pad {i} at {centre:?}, want {want:?}"
        );
        assert_eq!(second, i >= n / 2, "pad {i}");
        assert_eq!(
            p.component.as_deref(),
            (i >= n / 2).then_some("U7"),
            "pad {i}"
        );
    }
}

#[test]
fn errors_deep_in_a_long_file_name_their_line() {
    use dpsa_sim::inspection::gerber::CHUNK_STATEMENTS;
    let n = CHUNK_STATEMENTS * 3;
    // A coordinate the parser refuses (the format has 4 integer digits... as decimals) far
    // into the third chunk, and an aperture defined twice chunks apart.
    let mut lines: Vec<String> = long_layer(n).lines().map(str::to_string).collect();
    let at = 2 * CHUNK_STATEMENTS + 1234;
    lines[at] = "X1.5Y2D03*".into();
    let text = lines.join("\n");
    let e = within(120, move || read_str(&text)).expect_err("bad coordinate");
    assert_eq!(e.line(), at + 1, "{e}");

    let mut lines: Vec<String> = long_layer(n).lines().map(str::to_string).collect();
    let at = 2 * CHUNK_STATEMENTS + 99;
    lines.insert(at, "%ADD10C,0.5*%".into());
    let text = lines.join("\n");
    let e = within(120, move || read_str(&text)).expect_err("defined twice");
    assert_eq!(e.line(), at + 1, "{e}");
    assert!(e.to_string().contains("D10 is defined twice"), "{e}");
}
