//! The Gerber reader on what real exporters write (issue 20): deprecated and redundant
//! statements read as the specification says, and every input the reader cannot read
//! correctly refused with its line. Each file is a small synthetic text whose pads (count,
//! centres, sizes) are computed by hand in the test.

use dpsa_sim::inspection::gerber::{read_file, read_str, GerberError, PasteLayer};
use dpsa_sim::inspection::pads::Outline;
use std::f64::consts::PI;

const MM: &str = "%FSLAX46Y46*%\n%MOMM*%\n";

#[track_caller]
fn layer(text: &str) -> PasteLayer {
    match read_str(text) {
        Ok(l) => l,
        Err(e) => panic!("{e}\n{text}"),
    }
}

#[track_caller]
fn fails(text: &str) -> GerberError {
    match read_str(text) {
        Ok(l) => panic!("accepted ({} pads):\n{text}", l.pads.len()),
        Err(e) => e,
    }
}

/// The error names `line` first (`line N: ...`).
#[track_caller]
fn fails_at(text: &str, line: usize) -> GerberError {
    let e = fails(text);
    assert_eq!(e.line(), line, "{e}\n{text}");
    assert!(e.to_string().starts_with(&format!("line {line}:")), "{e}");
    e
}

#[track_caller]
fn close(a: f64, b: f64, tol: f64) {
    assert!((a - b).abs() <= tol, "{a} vs {b} (tol {tol})");
}

/// Every pad is a circle of diameter `d` and the centres are `want`, in order.
#[track_caller]
fn circles(l: &PasteLayer, d: f64, want: &[[f64; 2]]) {
    assert_eq!(l.pads.len(), want.len(), "{:?}", l.pads);
    for (p, w) in l.pads.iter().zip(want) {
        match &p.outline {
            Outline::Circle { centre, diameter } => {
                close(*diameter, d, 1e-9);
                close(centre[0], w[0], 1e-9);
                close(centre[1], w[1], 1e-9);
            }
            o => panic!("not a circle: {o:?}"),
        }
    }
}

#[test]
fn a_unit_stated_twice_the_same_way_is_accepted() {
    // Altium: %MOIN*% then G70*; 2.4 format: X10000 = 1.0000 inch.
    let l = layer("%FSLAX24Y24*%\n%MOIN*%\nG70*\n%ADD10C,0.0100*%\nD10*\nX10000Y20000D03*\nM02*\n");
    assert_eq!(l.units, "inch");
    circles(&l, 0.254, &[[25.4, 50.8]]);
    // KiCad 2013: G71 then %MOMM*%.
    let l =
        layer("%FSLAX46Y46*%\nG71*\n%MOMM*%\n%ADD10C,0.5*%\nD10*\nX1000000Y2000000D03*\nM02*\n");
    assert_eq!(l.units, "mm");
    circles(&l, 0.5, &[[1.0, 2.0]]);
    // Twice the same %MO.
    let l = layer("%FSLAX46Y46*%\n%MOMM*%\n%MOMM*%\n%ADD10C,0.5*%\nD10*\nX0Y0D03*\nM02*\n");
    circles(&l, 0.5, &[[0.0, 0.0]]);
}

#[test]
fn units_that_disagree_are_refused_naming_both_lines() {
    let e = fails_at(
        "%FSLAX24Y24*%\n%MOIN*%\nG71*\n%ADD10C,0.01*%\nD10*\nX0Y0D03*\nM02*\n",
        3,
    );
    assert!(e.to_string().contains("line 2"), "{e}");
    let e = fails_at("%FSLAX46Y46*%\nG71*\n\n%MOIN*%\nM02*\n", 4);
    assert!(e.to_string().contains("line 2"), "{e}");
}

#[test]
fn a_byte_order_mark_is_skipped() {
    let l = layer(&format!(
        "\u{feff}{MM}%ADD10C,0.5*%\nD10*\nX1000000Y0D03*\nM02*\n"
    ));
    circles(&l, 0.5, &[[1.0, 0.0]]);
}

#[test]
fn a_latin1_comment_is_read_and_latin1_elsewhere_is_binary() {
    let dir = tempfile::tempdir().expect("tempdir");
    let p = dir.path().join("latin1.gbr");
    let mut bytes = b"G04 Cr\xe9\xe9 par Altium*\n".to_vec();
    bytes.extend_from_slice(MM.as_bytes());
    bytes.extend_from_slice(b"%ADD10C,0.5*%\nD10*\nX2000000Y3000000D03*\nM02*\n");
    std::fs::write(&p, &bytes).expect("write");
    let l = read_file(&p).expect("Latin-1 comment");
    circles(&l, 0.5, &[[2.0, 3.0]]);
    // The same byte in a coordinate is not text.
    let mut bytes = MM.as_bytes().to_vec();
    bytes.extend_from_slice(b"%ADD10C,0.5*%\nD10*\nX2000000\xe9Y3000000D03*\nM02*\n");
    std::fs::write(&p, &bytes).expect("write");
    let e = read_file(&p).expect_err("Latin-1 coordinate");
    assert!(matches!(e, GerberError::Binary { line: 5 }), "{e}");
}

#[test]
fn coordinates_without_an_operation_repeat_the_previous_one() {
    // Old generators: X..Y..D03* then X..Y..* flashes again.
    let l = layer(&format!(
        "{MM}%ADD10C,0.5*%\nD10*\nX0Y0D03*\nX1000000Y0*\nX2000000Y500000*\nM02*\n"
    ));
    circles(&l, 0.5, &[[0.0, 0.0], [1.0, 0.0], [2.0, 0.5]]);
    // ... and D02 moves: the last word flashes at the point of the second move.
    let l = layer(&format!(
        "{MM}%ADD10C,0.5*%\nD10*\nX0Y0D02*\nX1000000Y0*\nD03*\nM02*\n"
    ));
    circles(&l, 0.5, &[[1.0, 0.0]]);
    // Nothing to repeat: refused with the line.
    fails_at(&format!("{MM}%ADD10C,0.5*%\nD10*\nX0Y0*\nM02*\n"), 5);
}

#[test]
fn g54_prefixes_and_a_bare_d03_after_a_move() {
    let l = layer(&format!(
        "{MM}%ADD10C,0.5*%\n%ADD11C,0.3*%\nG54D10*\nX1000000Y1000000D03*\nG54D11*\nX3000000Y1000000D02*\nD03*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 2);
    let want = [(0.5, [1.0, 1.0]), (0.3, [3.0, 1.0])];
    for (p, (d, w)) in l.pads.iter().zip(want) {
        let Outline::Circle { centre, diameter } = p.outline else {
            panic!("{:?}", p.outline)
        };
        close(diameter, d, 1e-12);
        close(centre[0], w[0], 1e-12);
        close(centre[1], w[1], 1e-12);
    }
}

#[test]
fn signed_coordinates_are_read_with_their_sign() {
    let l = layer(&format!(
        "{MM}%ADD10C,0.5*%\nD10*\nX+1000000Y+1000000D03*\nX-1000000Y+1000000D03*\nX+1000000Y-1000000D03*\nX+2000000Y+2000000D03*\nM02*\n"
    ));
    circles(&l, 0.5, &[[1.0, 1.0], [-1.0, 1.0], [1.0, -1.0], [2.0, 2.0]]);
}

#[test]
fn decimal_and_non_numeric_coordinates_are_refused_with_the_line() {
    for bad in [
        "X1.5Y2.0D03*",
        "XNaNY0D03*",
        "X0YNaND03*",
        "XinfY0D03*",
        "X1e9Y0D03*",
        "X-Y0D03*",
        "X1000000Y0I0.5J0D01*",
    ] {
        let text = format!("{MM}%ADD10C,0.5*%\nD10*\nX0Y0D03*\n{bad}\nM02*\n");
        fails_at(&text, 6);
    }
}

#[test]
fn impossible_apertures_are_refused_with_the_line() {
    // A hole larger than (or as large as) its disc or rectangle.
    fails_at(&format!("{MM}%ADD10C,0.5X1.0*%\nD10*\nX0Y0D03*\nM02*\n"), 3);
    fails_at(&format!("{MM}%ADD10C,0.5X0.5*%\nD10*\nX0Y0D03*\nM02*\n"), 3);
    fails_at(&format!("{MM}\n%ADD10R,1X0.4X0.4*%\nM02*\n"), 4);
    fails_at(&format!("{MM}%ADD10O,1X2X1.5*%\nM02*\n"), 3);
    // A hole that is not a number.
    fails_at(&format!("{MM}%ADD10C,0.5XNaN*%\nM02*\n"), 3);
    // A polygon whose rotation or size is not a number.
    fails_at(&format!("{MM}%ADD10P,1X6XNaN*%\nD10*\nX0Y0D03*\nM02*\n"), 3);
    fails_at(&format!("{MM}%ADD10P,1X6Xinf*%\nM02*\n"), 3);
    // A legal hole inside its disc still reads: a ring of area pi/4 (1 - 0.25).
    let l = layer(&format!("{MM}%ADD10C,1X0.5*%\nD10*\nX0Y0D03*\nM02*\n"));
    assert_eq!(l.pads.len(), 1);
    close(l.pads[0].outline.area(), PI / 4.0 * 0.75, 2e-3 * 1.5 * PI);
}

#[test]
fn trailing_zero_format_and_modal_y_words() {
    // %FSTAX24Y24*% mm: "X015" = 01.5000, "Y02" = 02.0000, "X-015" = -01.5000.
    let l = layer(
        "%FSTAX24Y24*%\n%MOMM*%\n%ADD10C,0.5*%\nD10*\nX015Y02D03*\nX-015D03*\nY-01D03*\nM02*\n",
    );
    circles(&l, 0.5, &[[1.5, 2.0], [-1.5, 2.0], [-1.5, -1.0]]);
    // Leading-zero format: Y-only words keep the last X.
    let l = layer(&format!(
        "{MM}%ADD10C,0.5*%\nD10*\nX1000000Y1000000D03*\nY2000000D03*\nY3000000*\nM02*\n"
    ));
    circles(&l, 0.5, &[[1.0, 1.0], [1.0, 2.0], [1.0, 3.0]]);
}

#[test]
fn identity_forms_of_deprecated_statements_are_accepted() {
    let l = layer(
        "%FSLAX46Y46*%\n%MOMM*%\n%LNPASTE_TOP*%\n%IPPOS*%\n%ASAXBY*%\n%MIA0B0*%\n%SFA1B1*%\n%OFA0B0*%\n%IR0*%\n\
         %ADD10C,0.5*%\nD10*\n%SRX1Y1I0J0*%\nX1000000Y2000000D03*\n%SR*%\nX3000000Y2000000D03*\nM02*\n",
    );
    circles(&l, 0.5, &[[1.0, 2.0], [3.0, 2.0]]);
}

#[test]
fn non_identity_deprecated_transforms_are_refused_with_the_line() {
    for bad in [
        "%MIA1B0*%",
        "%MIA0B1*%",
        "%SFA2B1*%",
        "%SFA1B0.5*%",
        "%OFA1B0*%",
        "%OFA0B-0.5*%",
        "%ASAYBX*%",
        "%IPNEG*%",
        "%IR90*%",
    ] {
        let text = format!("{MM}{bad}\n%ADD10C,0.5*%\nD10*\nX0Y0D03*\nM02*\n");
        let e = fails_at(&text, 3);
        assert!(matches!(e, GerberError::Unsupported { .. }), "{bad}: {e}");
    }
}

#[test]
fn g74_single_quadrant_arc_in_a_region() {
    // A quarter disc of radius 1 mm: (0,0) -> (1,0), ccw arc about (0,0) to (0,1), back.
    // G74 gives the centre offset without signs: I1 J0 from (1,0).
    let l = layer(&format!(
        "{MM}G74*\nG36*\nX0Y0D02*\nG01X1000000Y0D01*\nG03X0Y1000000I1000000J0D01*\nG01X0Y0D01*\nG37*\nM02*\n"
    ));
    assert_eq!(l.pads.len(), 1);
    let p = &l.pads[0];
    let perimeter = 2.0 + PI / 2.0;
    close(p.outline.area(), PI / 4.0, 2e-3 * perimeter);
    let b = p.outline.bbox();
    for (v, w) in b.iter().zip([0.0, 0.0, 1.0, 1.0]) {
        close(*v, w, 1e-6);
    }
    // Centroid of a quarter disc: 4 r / (3 pi) on each axis.
    let c = p.outline.centroid();
    close(c[0], 4.0 / (3.0 * PI), 1e-3);
    close(c[1], 4.0 / (3.0 * PI), 1e-3);
}

#[test]
fn crlf_line_ends_and_a_macro_closed_on_its_own_line() {
    let text = "%FSLAX46Y46*%\r\n%MOMM*%\r\n%AMBOX*\r\n21,1,$1,$2,0,0,0*\r\n%\r\n%ADD10BOX,1X2*%\r\nD10*\r\nX1000000Y1000000D03*\r\nX4000000Y1000000D03*\r\nM02*\r\n";
    let l = layer(text);
    assert_eq!(l.pads.len(), 2);
    for (p, x) in l.pads.iter().zip([1.0, 4.0]) {
        let c = p.outline.centroid();
        close(c[0], x, 1e-9);
        close(c[1], 1.0, 1e-9);
        close(p.outline.area(), 2.0, 1e-9);
        let b = p.outline.bbox();
        close(b[2] - b[0], 1.0, 1e-9);
        close(b[3] - b[1], 2.0, 1e-9);
    }
    // An error after CRLF lines names the right line.
    fails_at(
        "%FSLAX46Y46*%\r\n%MOMM*%\r\n%ADD10C,0.5*%\r\nD10*\r\nX1.5Y0D03*\r\nM02*\r\n",
        5,
    );
}

#[test]
fn a_layer_without_its_end_is_refused_by_the_inspection_unless_allowed() {
    use dpsa_sim::inspection::program::Program;
    use dpsa_sim::inspection::run::paste_layer_pads;
    let dir = tempfile::tempdir().expect("tempdir");
    let gbr = dir.path().join("paste.gbr");
    let prog = dir.path().join("program.toml");
    // Cut at a line end: three flashes of the four survive, no M02.
    let full = format!(
        "{MM}%ADD10C,0.5*%\nD10*\nX0Y0D03*\nX1000000Y0D03*\nX2000000Y0D03*\nX3000000Y0D03*\nM02*\n"
    );
    let cut: String = full.lines().take(7).map(|l| format!("{l}\n")).collect();
    std::fs::write(&gbr, &cut).expect("write");
    // The reader says so.
    let l = read_file(&gbr).expect("reads");
    assert!(!l.complete);
    circles(&l, 0.5, &[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]);
    // The inspection refuses it, naming the file and the key.
    std::fs::write(&prog, "paste_layer = \"paste.gbr\"\n").expect("write");
    let p = Program::load(&prog).expect("program");
    let e = paste_layer_pads(&p, &prog)
        .expect_err("truncated layer")
        .to_string();
    assert!(e.contains("paste.gbr") && e.contains("M02"), "{e}");
    assert!(e.contains("allow_truncated_layer"), "{e}");
    // Allowed: the pads, and a note for the report.
    std::fs::write(
        &prog,
        "paste_layer = \"paste.gbr\"\nallow_truncated_layer = true\n",
    )
    .expect("write");
    let p = Program::load(&prog).expect("program");
    let (pads, notes) = paste_layer_pads(&p, &prog).expect("allowed");
    assert_eq!(pads.len(), 3);
    assert_eq!(notes.len(), 1);
    assert!(notes[0].contains("truncated"), "{notes:?}");
    // The whole file: complete, no note.
    std::fs::write(&gbr, &full).expect("write");
    assert!(read_file(&gbr).expect("reads").complete);
    let (pads, notes) = paste_layer_pads(&p, &prog).expect("complete");
    assert_eq!(pads.len(), 4);
    assert!(notes.is_empty());
}

/// Eagle 9 writes its X2 attributes as comments with a `%` inside (`G04 #@! %TF...*`); Mentor
/// writes the deprecated `%ICAS*%`. Both read; another input code is refused with its line.
#[test]
fn eagle9_attribute_comments_and_mentor_input_code() {
    let l = layer(&format!(
        "G04 #@! %TF.FileFunction,Paste,Top*\n%ICAS*%\n{MM}%ADD10C,0.5*%\nD10*\nX1000000Y2000000D03*\nM02*\n"
    ));
    circles(&l, 0.5, &[[1.0, 2.0]]);
    fails_at(&format!("{MM}%ICEB*%\nM02*\n"), 3);
}

/// A pin attribute without its pin number (found by the `load_gerber` fuzz target: the parser
/// crate indexed its second value and panicked) is refused with its line, in both X2 forms.
#[test]
fn a_pin_attribute_without_its_pin_is_refused_not_a_panic() {
    fails_at(&format!("{MM}%TO.P,U1*%\nM02*\n"), 3);
    fails_at(&format!("{MM}%TO.P*%\nM02*\n"), 3);
    fails_at(&format!("{MM}G04 #@! TO.P,U1*\nM02*\n"), 3);
    // Well formed: the pad is named.
    let l = layer(&format!(
        "{MM}%ADD10C,0.5*%\n%TO.P,U1,7*%\nD10*\nX0Y0D03*\nM02*\n"
    ));
    assert_eq!(l.pads[0].name(), "U1-7");
}
