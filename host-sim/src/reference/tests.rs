//! Tests of the f64 reference against closed-form cases.

use super::*;
use crate::heightmap::flags;
use crate::simulation::recording::{Calibration, Camera, FrameEntry, Noise, Processing};
use crate::simulation::recording::{CameraTruth, Frame, Manifest};
use std::f64::consts::{PI, TAU};

const F: u16 = flags::INCOMPLETE;
const S: u16 = flags::SKIPPED;
const G: u16 = flags::FRAME_GAP;
const R: u16 = flags::ENCODER_REVERSAL;

fn manifest(
    width: u32,
    h: u32,
    n: u8,
    max_step_rows: u32,
    cpp: f64,
    fr: &[(u32, i64)],
) -> Manifest {
    Manifest {
        format: crate::simulation::recording::FORMAT.into(),
        version: crate::simulation::recording::VERSION,
        camera: Camera {
            id: 0,
            width,
            rows: h,
            bit_depth: 16,
            saturation: 65535,
        },
        calibration: Calibration {
            counts_per_pixel: cpp,
            fringe_period_px: 32.0,
            reference_phase_rad: (0..width).map(|c| 0.1 * c as f64).collect(),
            height_per_turn_um: 500.0,
            height_lsb_um: 0.25,
            height_per_turn_um_per_column: None,
        },
        processing: Processing {
            n,
            max_step_rows,
            min_modulation: 60.0,
            max_noise_gain: 2.0,
        },
        frames: fr
            .iter()
            .map(|&(seq, latch)| FrameEntry {
                seq,
                latch,
                file: String::new(),
            })
            .collect(),
        noise: None,
        truth: None,
        board_id: None,
    }
}

fn seqs(latches: &[i64]) -> Vec<(u32, i64)> {
    latches
        .iter()
        .enumerate()
        .map(|(i, &l)| (i as u32, l))
        .collect()
}

/// (row, first_frame, flags) triples.
fn summary(p: &[RowPlan]) -> Vec<(i64, Option<usize>, u16)> {
    p.iter().map(|r| (r.row, r.first_frame, r.flags)).collect()
}

#[test]
fn offset_rounds_half_up() {
    assert_eq!(offset(41, 10.25), Some(4));
    assert_eq!(offset(5, 10.0), Some(1));
    assert_eq!(offset(-5, 10.0), Some(0));
    assert_eq!(offset(15, 10.0), Some(2));
    assert_eq!(offset(-15, 10.0), Some(-1));
    assert_eq!(offset(14, 10.0), Some(1));
    assert_eq!(offset(1, 0.0), None);
    assert_eq!(offset(1, f64::NAN), None);
}

#[test]
fn plan_uniform_steps() {
    let m = manifest(1, 6, 3, 4, 1.0, &seqs(&[0, 2, 4, 6, 8]));
    let expect = vec![
        (0, None, S),
        (1, None, S),
        (2, Some(0), F),
        (3, Some(0), F),
        (4, Some(0), 0),
        (5, Some(0), 0),
        (6, Some(1), 0),
        (7, Some(1), 0),
        (8, Some(2), 0),
        (9, Some(2), 0),
        (10, Some(3), F),
        (11, Some(3), F),
        (12, Some(4), F),
        (13, Some(4), F),
    ];
    assert_eq!(summary(&plan(&m)), expect);
    // Same with a fractional calibration: latches scaled by cpp.
    let m2 = manifest(1, 6, 3, 4, 10.25, &seqs(&[0, 20, 41, 62, 82]));
    assert_eq!(summary(&plan(&m2)), expect);
}

#[test]
fn plan_stall() {
    let m = manifest(1, 6, 3, 4, 1.0, &seqs(&[0, 2, 2, 4, 6, 8]));
    let expect = vec![
        (0, None, S),
        (1, None, S),
        (2, Some(0), 0),
        (3, Some(0), 0),
        (4, Some(0), 0),
        (5, Some(0), 0),
        (6, Some(1), 0),
        (7, Some(1), 0),
        (8, Some(3), 0),
        (9, Some(3), 0),
        (10, Some(4), F),
        (11, Some(4), F),
        (12, Some(5), F),
        (13, Some(5), F),
    ];
    assert_eq!(summary(&plan(&m)), expect);
}

#[test]
fn plan_reversal() {
    let m = manifest(1, 6, 3, 4, 1.0, &seqs(&[0, 2, 4, 3, 6, 8, 10]));
    let expect = vec![
        (0, None, S),
        (1, None, S),
        (2, Some(0), F),
        (3, Some(0), F),
        (4, Some(0), 0),
        (5, Some(0), 0),
        (6, Some(1), R),
        (7, Some(1), R),
        (8, Some(2), R),
        (9, Some(2), R | F),
        (10, Some(4), 0),
        (11, Some(4), 0),
        (12, Some(5), F),
        (13, Some(5), F),
        (14, Some(6), F),
        (15, Some(6), F),
    ];
    assert_eq!(summary(&plan(&m)), expect);
}

#[test]
fn plan_seq_gap() {
    let m = manifest(1, 6, 3, 4, 1.0, &[(0, 0), (1, 2), (3, 4), (4, 6), (5, 8)]);
    let expect = vec![
        (0, None, S),
        (1, None, S),
        (2, Some(0), F | G),
        (3, Some(0), F | G),
        (4, Some(0), G),
        (5, Some(0), G),
        (6, Some(1), G),
        (7, Some(1), G),
        (8, Some(2), 0),
        (9, Some(2), 0),
        (10, Some(3), F),
        (11, Some(3), F),
        (12, Some(4), F),
        (13, Some(4), F),
    ];
    assert_eq!(summary(&plan(&m)), expect);
}

#[test]
fn plan_large_step() {
    let m = manifest(1, 6, 3, 4, 1.0, &seqs(&[0, 2, 4, 12, 14, 16, 18]));
    let mut expect = vec![
        (0, None, S),
        (1, None, S),
        (2, Some(0), F),
        (3, Some(0), F),
        (4, Some(0), 0),
        (5, Some(0), 0),
        (6, Some(1), F), // frames 1,2,3: frame 3 shows rows 12..17
        (7, Some(1), F),
        (8, Some(2), F),
        (9, Some(2), F),
    ];
    expect.extend((10..14).map(|b| (b, None, S)));
    expect.extend([
        (14, Some(3), F),
        (15, Some(3), F),
        (16, Some(3), 0),
        (17, Some(3), 0),
        (18, Some(4), 0),
        (19, Some(4), 0),
        (20, Some(5), F),
        (21, Some(5), F),
        (22, Some(6), F),
        (23, Some(6), F),
    ]);
    assert_eq!(summary(&plan(&m)), expect);
}

#[test]
fn plan_degenerate_inputs() {
    assert!(plan(&manifest(1, 6, 3, 4, 1.0, &[])).is_empty());
    assert!(plan(&manifest(1, 0, 3, 4, 1.0, &seqs(&[0, 1]))).is_empty());
    assert!(plan(&manifest(1, 6, 3, 4, 0.0, &seqs(&[0, 1]))).is_empty());
    assert!(plan(&manifest(1, 6, 3, 4, 1.0, &seqs(&[0, i64::MAX]))).is_empty());
    // A single frame: everything skipped or incomplete, nothing panics.
    let p = plan(&manifest(1, 6, 3, 4, 1.0, &seqs(&[5])));
    assert_eq!(p.len(), 6);
    assert!(p.iter().all(|r| r.flags != 0));
    let out = reconstruct(&manifest(2, 6, 3, 4, 1.0, &seqs(&[5])), &[]);
    assert_eq!(out.rows.len(), 6);
    assert_eq!(out.valid_pixels(), 0);
}

proptest::proptest! {
    #[test]
    fn plan_covers_each_row_once(steps in proptest::collection::vec(-3i64..9, 0..30),
                                 h in 1u32..12, max_step_rows in 0u32..10) {
        let mut latches = vec![0i64];
        for s in steps { latches.push(latches.last().unwrap() + s); }
        let m = manifest(1, h, 3, max_step_rows, 1.0, &seqs(&latches));
        let p = plan(&m);
        let lo = &latches[0];
        let end = latches.iter().max().unwrap() + i64::from(h);
        let rows: Vec<i64> = p.iter().map(|r| r.row).collect();
        proptest::prop_assert_eq!(rows, (*lo..end).collect::<Vec<_>>());
        for r in &p {
            match r.first_frame {
                None => proptest::prop_assert_eq!(r.flags, S),
                Some(w) => {
                    proptest::prop_assert!(r.flags & S == 0);
                    // A valid row is visible in all window frames.
                    if r.flags == 0 {
                        for &o in &latches[w..w + 3] {
                            proptest::prop_assert!(o <= r.row && r.row < o + i64::from(h));
                        }
                    }
                }
            }
        }
    }
}

#[test]
fn noise_gain_values() {
    let four: Vec<f64> = (0..4).map(|j| -(j as f64) * PI / 2.0).collect();
    assert!((noise_gain(&four) - 1.0).abs() < 1e-12);
    let five: Vec<f64> = (0..5).map(|j| -(j as f64) * TAU / 5.0).collect();
    assert!((noise_gain(&five) - 1.0).abs() < 1e-12);
    assert_eq!(noise_gain(&[0.0; 4]), f64::INFINITY);
    assert_eq!(noise_gain(&[0.0, 0.0, -0.5, -0.5]), f64::INFINITY);
    assert_eq!(noise_gain(&[]), f64::INFINITY);
    // Uneven: worse than ideal.
    assert!(noise_gain(&[0.0, -0.3, -2.0, -3.5]) > 1.0);
    assert!(PhaseFit::new(&[0.0; 4]).is_none());
}

#[test]
fn wrap_phase_range() {
    for x in [-10.0, -PI, -PI + 1e-9, 0.0, PI - 1e-9, PI, 3.0 * PI, 100.0] {
        let d = wrap_phase(x);
        assert!((-PI..PI).contains(&d), "{x} -> {d}");
        let k = (x - d) / TAU;
        assert!((k - k.round()).abs() < 1e-9);
    }
    assert_eq!(wrap_phase(PI), -PI);
    // A phase already in range comes back exactly.
    for x in [1e-12, -0.5, 2.0, PI - 1e-6, -PI] {
        assert_eq!(wrap_phase(x).to_bits(), f64::to_bits(x), "{x}");
    }
    // Within an ulp of the host's wrap.
    for x in [-10.0, -1e-9, 0.7, 3.0 * PI, 100.0] {
        let host = dpsa_formats::calibration::wrap_phase(x);
        assert!(
            (wrap_phase(x) - host).abs() <= 4.0 * f64::EPSILON * 100.0,
            "{x}"
        );
    }
}

#[test]
fn phase_fit_exact_on_nonuniform_shifts() {
    // Arbitrary non-uniform shifts, noiseless f64 samples.
    let shifts = [0.0, -1.1, -2.9, -4.0, -5.3];
    let (b, c, t_z, h_true, phi_r) = (1000.0, 400.0, 500.0, 37.125, 2.2);
    let phi = phi_r + TAU * h_true / t_z;
    let samples: Vec<f64> = shifts.iter().map(|t| b + c * (phi + t).cos()).collect();
    let fit = PhaseFit::new(&shifts).unwrap();
    let (p, m) = fit.fit(&samples);
    assert!((m - c).abs() < 1e-9);
    let h = wrap_phase(p - phi_r) / TAU * t_z;
    assert!((h - h_true).abs() < 1e-6, "{h}");
}

/// Renders frames of a board with known height from the model formula.
fn render(m: &Manifest, height: impl Fn(i64, usize) -> f64, bg: f64, ct: f64) -> Vec<Frame> {
    let w = m.camera.width as usize;
    let h = m.camera.rows as usize;
    let cal = &m.calibration;
    let f_x = 1.0 / cal.fringe_period_px;
    m.frames
        .iter()
        .map(|fe| {
            let o = offset(fe.latch, cal.counts_per_pixel).unwrap();
            let mut data = Vec::with_capacity(w * h);
            for r in 0..h {
                for c in 0..w {
                    let hb = height(r as i64 + o, c);
                    let ph = TAU * f_x * r as f64
                        + cal.reference_phase_rad[c]
                        + TAU * hb / cal.height_per_turn_um;
                    data.push((bg + ct * ph.cos()).round().clamp(0.0, 65535.0) as u16);
                }
            }
            Frame {
                trigger: fe.trigger(),
                rows: h,
                width: w,
                data,
            }
        })
        .collect()
}

fn board_height(b: i64, c: usize) -> f64 {
    -200.0 + 7.3 * b as f64 + 11.9 * c as f64
}

#[test]
fn reconstruct_nonuniform_motion() {
    // Steps 7, 9, 5, 8, 6, 10, ... rows: non-uniform shifts (period 32 px).
    let steps = [7, 9, 5, 8, 6, 10, 7, 9];
    let mut lat = vec![0i64];
    for s in steps {
        lat.push(lat.last().unwrap() + s);
    }
    let m = manifest(5, 40, 4, 10, 1.0, &seqs(&lat));
    let frames = render(&m, board_height, 30000.0, 20000.0);
    let out = reconstruct(&m, &frames);
    assert_eq!(out.width, 5);
    let mut checked = 0;
    for r in &out.rows {
        if !r.is_valid() {
            assert!(r.valid.iter().all(|&v| !v));
            continue;
        }
        let win = r.window.as_ref().unwrap();
        assert!(win.noise_gain < 2.0);
        for c in 0..5 {
            assert!(r.valid[c]);
            let truth = board_height(r.row, c);
            // Heights are defined modulo T_z = 500 um.
            let err = wrap_phase(TAU * (r.height_um[c] - truth) / 500.0) / TAU * 500.0;
            // Only u16 rounding of the rendered samples limits the accuracy here.
            assert!(err.abs() < 0.01, "{} {}", r.height_um[c], truth);
            assert!((-250.0..250.0).contains(&r.height_um[c]));
            assert!((r.modulation[c] - 20000.0).abs() < 1.0);
            assert_eq!(r.height_lsb[c], (r.height_um[c] / 0.25).round() as i32);
            checked += 1;
        }
    }
    assert!(checked >= 5 * 40);
}

#[test]
fn reconstruct_flags_stall_saturation_and_gaps() {
    let mut m = manifest(3, 6, 3, 4, 1.0, &seqs(&[0, 2, 2, 4, 6, 8]));
    // 2 px steps = 120 degrees: an ideal 3-step set when the conveyor moves.
    m.calibration.fringe_period_px = 6.0;
    let mut frames = render(&m, |_, _| 10.0, 1000.0, 500.0);
    // Rows 2..5 (offsets 0,2,2) and 6,7 (2,2,4) have two-phase windows: singular.
    let out = reconstruct(&m, &frames);
    for r in &out.rows {
        let ill = r.flags & flags::ILL_CONDITIONED != 0;
        assert_eq!(ill, (2..8).contains(&r.row), "row {}", r.row);
        if (2..8).contains(&r.row) {
            assert_eq!(r.window.as_ref().unwrap().noise_gain, f64::INFINITY);
        }
    }
    assert!(out.get(8).unwrap().valid.iter().all(|&v| v));

    // Saturate one sample of board row 9 (frame 4 at o=6: image row 3), column 1.
    frames[4].data[3 * 3 + 1] = 65535;
    // Truncate frame 5 (o=8) to 1 line: board row 9 (image row 1) not delivered.
    let out = reconstruct(&m, &frames);
    let r9 = out.get(9).unwrap();
    assert_eq!(r9.flags, flags::SATURATED);
    assert_eq!(r9.valid, [true, false, true]);
    frames[5].rows = 1;
    let out = reconstruct(&m, &frames);
    let r9 = out.get(9).unwrap();
    assert!(r9.flags & flags::FRAME_GAP != 0);
    assert!(r9.valid.iter().all(|&v| !v));
    assert!(out.get(8).unwrap().valid.iter().all(|&v| v));
    // Missing frames: FRAME_GAP as well.
    let out = reconstruct(&m, &frames[..5]);
    assert!(out.get(8).unwrap().flags & flags::FRAME_GAP != 0);

    // Low modulation.
    let frames = render(&m, |_, _| 10.0, 1000.0, 30.0);
    let out = reconstruct(&m, &frames);
    let r8 = out.get(8).unwrap();
    assert_eq!(r8.flags, flags::LOW_MODULATION);
    assert!(r8.valid.iter().all(|&v| !v));
}

#[test]
fn psp_equals_reconstruct_for_nominal_motion() {
    // 8 px steps with period 32: exactly 90 degrees.
    let lat: Vec<i64> = (0..10).map(|k| 8 * k).collect();
    let m = manifest(4, 40, 4, 10, 1.0, &seqs(&lat));
    assert_eq!(nominal_step_px(&m), 8.0);
    let frames = render(&m, board_height, 2000.0, 800.0);
    let a = reconstruct(&m, &frames);
    let b = psp(&m, &frames);
    assert_eq!(a.rows.len(), b.rows.len());
    assert!(a.valid_pixels() > 0);
    for (ra, rb) in a.rows.iter().zip(&b.rows) {
        assert_eq!(ra.flags, rb.flags);
        assert_eq!(ra.valid, rb.valid);
        for c in 0..4 {
            if ra.valid[c] {
                assert!((ra.height_um[c] - rb.height_um[c]).abs() < 1e-9);
            }
        }
    }
    // Non-uniform motion: PSP is never flagged ill-conditioned but D-PSA may be.
    let m = manifest(4, 40, 4, 10, 1.0, &seqs(&[0, 8, 8, 8, 16, 24, 32, 40, 48]));
    assert_eq!(nominal_step_px(&m), 6.0);
    let frames = render(&m, board_height, 2000.0, 800.0);
    let b = psp(&m, &frames);
    assert!(b.rows.iter().all(|r| r.flags & flags::ILL_CONDITIONED == 0));
    let a = reconstruct(&m, &frames);
    assert!(a.rows.iter().any(|r| r.flags & flags::ILL_CONDITIONED != 0));
}

fn truth_for(out_rows: std::ops::Range<i64>, w: usize, h: f32, bg: f32, ct: f32) -> CameraTruth {
    let rows = (out_rows.end - out_rows.start) as usize;
    CameraTruth {
        first_row: out_rows.start,
        rows,
        width: w,
        height_um: vec![h; rows * w],
        background: vec![bg; rows * w],
        contrast: vec![ct; rows * w],
    }
}

#[test]
fn crb_matches_textbook_for_equal_steps() {
    for (n, step) in [(4u8, 8i64), (8, 4)] {
        let lat: Vec<i64> = (0..12).map(|k| step * k).collect();
        let mut m = manifest(3, 40, n, 10, 1.0, &seqs(&lat));
        let sigma = 3.0;
        m.noise = Some(Noise {
            gain_e_per_dn: 1e15,
            read_noise_dn: sigma,
        });
        let frames = render(&m, |_, _| 42.0, 1000.0, 300.0);
        let out = reconstruct(&m, &frames);
        let truth = truth_for(-50..200, 3, 42.0, 1000.0, 300.0);
        let v = crb(&m, &truth, &out);
        let var = sigma * sigma + 1.0 / 12.0;
        let var_phi = 2.0 * var / (f64::from(n) * 300.0 * 300.0);
        let expect = var_phi * (500.0 / TAU).powi(2);
        let mut seen = 0;
        for (r, vr) in out.rows.iter().zip(&v) {
            for x in vr {
                if r.is_valid() && r.window.is_some() {
                    let got = x.unwrap();
                    assert!((got / expect - 1.0).abs() < 1e-9, "{got} {expect}");
                    seen += 1;
                } else {
                    assert!(x.is_none());
                }
            }
        }
        assert!(seen > 0);
        // No noise model: nothing.
        m.noise = None;
        assert!(crb(&m, &truth, &out).iter().flatten().all(|x| x.is_none()));
    }
}

#[test]
fn flat_mask_neighbourhood() {
    let mut t = truth_for(0..4, 5, 1.0, 0.0, 0.0);
    t.height_um[3 * 5 + 4] = 2.0; // corner (border) pixel changes
    t.height_um[5 + 1] = 3.0; // interior pixel (1,1)
    let m = flat_mask(&t);
    let expect_row1 = [false, false, false, true, false];
    let expect_row2 = [false; 5]; // (2,3) sees the changed corner (3,4)
    assert_eq!(&m[5..10], &expect_row1);
    assert_eq!(&m[10..15], &expect_row2);
    assert!(m[..5].iter().all(|&v| !v));
    assert!(m[15..].iter().all(|&v| !v));
    assert!(flat_mask(&truth_for(0..2, 5, 1.0, 0.0, 0.0))
        .iter()
        .all(|&v| !v));
}

#[test]
fn to_height_map_roundtrip() {
    let lat: Vec<i64> = (0..8).map(|k| 8 * k).collect();
    let m = manifest(4, 40, 4, 10, 1.0, &seqs(&lat));
    let frames = render(&m, board_height, 2000.0, 800.0);
    let out = reconstruct(&m, &frames);
    let hm = out.to_height_map(&m);
    assert_eq!(hm.len(), out.rows.len());
    assert_eq!(hm.valid_pixels(), out.valid_pixels());
    let r = out.rows.iter().find(|r| r.is_valid()).unwrap();
    let hr = hm.get(r.row).unwrap();
    assert_eq!(
        hr.latch,
        m.frames[r.window.as_ref().unwrap().frames[0]].latch
    );
    assert_eq!(i32::from(hr.heights[2]), r.height_lsb[2]);
}

/// Timing check of a full 2048 x 2048 board (run with `--release -- --ignored`).
#[test]
#[ignore]
fn full_board_timing() {
    let steps = [8i64, 7, 9, 8, 8, 9, 7, 8];
    let mut lat = vec![0i64];
    while *lat.last().unwrap() < 2048 {
        let k = lat.len();
        lat.push(lat.last().unwrap() + steps[k % steps.len()]);
    }
    let m = manifest(2048, 40, 4, 10, 1.0, &seqs(&lat));
    let frames = render(
        &m,
        |b, c| ((b as usize / 50 + c / 50) % 2) as f64 * 80.0,
        2000.0,
        800.0,
    );
    let t0 = std::time::Instant::now();
    let out = reconstruct(&m, &frames);
    let t_ref = t0.elapsed();
    let t0 = std::time::Instant::now();
    let base = psp(&m, &frames);
    let t_psp = t0.elapsed();
    eprintln!(
        "{} rows, {} valid px: reconstruct {t_ref:?}, psp {t_psp:?} ({} valid px)",
        out.rows.len(),
        out.valid_pixels(),
        base.valid_pixels()
    );
    assert!(out.valid_pixels() > 2000 * 2000);
}
