//! Accuracy: the fixed-point core against the f64 reference (written independently from the
//! paper), against the simulator's ground truth and against the Cramer-Rao bound.

use dpsa_sim::reference::compare::compare_recording;
use dpsa_sim::reference::compare::Comparison;
use dpsa_sim::simulation::scene::Scene;
use dpsa_tests::{check_vs_truth, simulate};

/// The fixed-point invariants every recording must satisfy: within one LSB of the f64
/// reference on every pixel valid in both, and exactly the same valid pixels.
#[track_caller]
fn assert_matches_reference(cmp: &Comparison, what: &str) {
    let f = &cmp.fixed_vs_ref;
    assert!(f.pixels_compared > 0, "{what}: no pixel compared: {f:?}");
    let max = f.max_abs_lsb.expect("pixels were compared");
    assert!(
        max <= 1.0,
        "{what}: fixed vs reference differ by {max} LSB: {f:?}"
    );
    assert_eq!(f.pixels_over_1_lsb, 0, "{what}: {f:?}");
    assert_eq!(f.valid_mismatch, 0, "{what}: validity differs: {f:?}");
    assert_eq!(
        (f.rows_only_fixed, f.rows_only_ref),
        (0, 0),
        "{what}: row sets differ: {f:?}"
    );
    assert_eq!(f.row_flags_mismatch, 0, "{what}: row flags differ: {f:?}");
}

/// The built-in default scene (2048 x 2048 board, n = 4, 90-degree mean steps with 10 %
/// jitter): the core is within 1 LSB of the reference, statistically efficient (RMS error
/// within 5 % of the Cramer-Rao bound, and not below it) and at least 3 times better than the
/// conventional 4-step PSP that assumes the nominal steps.
#[test]
fn default_scene_reaches_the_cramer_rao_bound() {
    let sim = simulate(&Scene::default(), 1);
    let cmp = compare_recording(&sim.rec, false).expect("compare");
    let (_, _, fixed) = dpsa_sim::reconstruct::reconstruct_map(&sim.rec, false).expect("core");
    let s = cmp.summary();
    assert_matches_reference(&cmp, "default scene");

    let t = &cmp.truth;
    let pixels = t.pixels.expect("truth pixels");
    // Enough samples for the RMS estimate to be good to ~0.1 % (relative sd 1/sqrt(2N)).
    assert!(
        pixels >= 1_000_000,
        "only {pixels} flat pixels compared\n{s}"
    );
    let fixed_rms = t.fixed_rms_um.unwrap();
    let crb = t.crb_rms_um.unwrap();
    let psp = t.psp_rms_um.unwrap();
    assert!(
        fixed_rms <= 1.05 * crb,
        "fixed rms {fixed_rms} um above 1.05 x CRB {crb} um\n{s}"
    );
    assert!(
        fixed_rms >= 0.98 * crb,
        "fixed rms {fixed_rms} um below the CRB {crb} um: the bound or the noise model is wrong\n{s}"
    );
    assert!(
        psp >= 3.0 * fixed_rms,
        "PSP rms {psp} um is not 3x the fixed rms {fixed_rms} um\n{s}"
    );
    assert!(t.psp_pixels.unwrap() >= 1_000_000, "{s}");
    // The reference itself is efficient too (the fixed point adds at most the LSB rounding).
    let ref_rms = t.ref_rms_um.unwrap();
    assert!(ref_rms <= 1.05 * crb && ref_rms >= 0.98 * crb, "{s}");

    // Independent check of every valid flat pixel and every valid row against the truth.
    let truth = sim.truth();
    let check = check_vs_truth(&sim.rec.manifest, &truth, &fixed, |_| true);
    check.assert_ok("default scene");
    assert!(check.pixels as u64 >= pixels, "{check:?}");
    // Most of the board is reconstructed.
    let board = 2048u64 * 2048;
    assert!(cmp.pixels.valid >= board * 9 / 10, "{s}");
}

/// One cell of the scene matrix.
struct Case {
    n: u8,
    jitter_pct: f64,
    period: f64,
    step: f64,
    bit_depth: u8,
}

/// A small scene for a case, with illumination, noise and thresholds scaled to the bit depth
/// (the 12-bit defaults times `2^(bits - 12)`; 8-bit keeps a read noise of 1 DN so that the
/// rounding to whole DN stays a small additive term, as the noise model assumes).
fn scene(c: &Case) -> Scene {
    let base = Scene::default();
    let k = 2f64.powi(i32::from(c.bit_depth) - 12);
    let (read, gain) = match c.bit_depth {
        8 => (1.0, 10.0),
        _ => (3.0 * k, 3.0 / k),
    };
    Scene {
        width: 256,
        board_length: 480,
        // A row entering at the top of the admitted band must stay in view for n - 1 more
        // steps: n steps of up to step * (1 + jitter) must fit in the ROI.
        rows: (40.0f64).max((f64::from(c.n) * c.step * (1.0 + c.jitter_pct / 100.0)).ceil() + 2.0)
            as u32,
        n: c.n,
        deposits: 30,
        jitter_pct: c.jitter_pct,
        fringe_period_px: c.period,
        mean_step_px: c.step,
        bit_depth: c.bit_depth,
        background: base.background * k,
        contrast: base.contrast * k,
        paste_background: base.paste_background * k,
        paste_contrast: base.paste_contrast * k,
        read_noise_dn: read,
        gain_e_per_dn: gain,
        min_modulation: base.min_modulation * k,
        ..base
    }
}

fn run_case(c: Case) {
    let sc = scene(&c);
    let what = format!(
        "n {} jitter {}% period {} step {} ({:.1} deg) {}-bit",
        c.n,
        c.jitter_pct,
        c.period,
        c.step,
        360.0 * c.step / c.period,
        c.bit_depth
    );
    assert!(
        (360.0 * c.step / c.period - 90.0).abs() > 5.0,
        "{what}: the matrix is meant to use non-90-degree steps"
    );
    let sim = simulate(&sc, 11);
    let cmp = compare_recording(&sim.rec, false).expect("compare");
    let (_, _, fixed) = dpsa_sim::reconstruct::reconstruct_map(&sim.rec, false).expect("core");
    let s = cmp.summary();
    assert_matches_reference(&cmp, &what);

    let board = u64::from(sc.width) * u64::from(sc.board_length);
    assert!(cmp.pixels.valid > 0, "{what}: no valid pixel\n{s}");
    assert!(
        cmp.pixels.valid >= board * 3 / 4,
        "{what}: only {} valid pixels of {board}\n{s}",
        cmp.pixels.valid
    );

    let t = &cmp.truth;
    let pixels = t.pixels.unwrap();
    let (fixed_rms, crb) = (t.fixed_rms_um.unwrap(), t.crb_rms_um.unwrap());
    if pixels > 50_000 {
        assert!(
            fixed_rms <= 1.05 * crb,
            "{what}: fixed rms {fixed_rms} um vs CRB {crb} um\n{s}"
        );
        assert!(
            fixed_rms >= 0.95 * crb,
            "{what}: fixed rms {fixed_rms} um below the CRB {crb} um\n{s}"
        );
    } else {
        assert!(
            fixed_rms <= 1.3 * crb && fixed_rms >= 0.7 * crb,
            "{what}: {pixels} px\n{s}"
        );
    }

    let truth = sim.truth();
    let check = check_vs_truth(&sim.rec.manifest, &truth, &fixed, |_| true);
    check.assert_ok(&what);
    assert!(check.pixels as u64 >= pixels, "{what}: {check:?}");
}

macro_rules! cases {
    ($($name:ident: $n:expr, $jitter:expr, $period:expr, $step:expr, $bits:expr;)*) => {$(
        #[test]
        fn $name() {
            run_case(Case { n: $n, jitter_pct: $jitter, period: $period, step: $step, bit_depth: $bits });
        }
    )*};
}

// Every n, jitter, period and bit depth appears at least twice; no case uses 90-degree steps.
cases! {
    n3_jitter0_p24_8bit:   3,  0.0, 24.0,  7.0,  8;
    n3_jitter10_p32_16bit: 3, 10.0, 32.0, 10.0, 16;
    n3_jitter20_p40_12bit: 3, 20.0, 40.0, 13.0, 12;
    n5_jitter0_p32_16bit:  5,  0.0, 32.0,  5.0, 16;
    n5_jitter10_p40_8bit:  5, 10.0, 40.0,  7.0,  8;
    n5_jitter20_p24_12bit: 5, 20.0, 24.0,  4.0, 12;
    n8_jitter0_p40_12bit:  8,  0.0, 40.0,  4.5, 12;
    n8_jitter10_p24_8bit:  8, 10.0, 24.0,  3.5,  8;
    n8_jitter20_p32_16bit: 8, 20.0, 32.0,  4.0, 16;
    n4_jitter20_p40_8bit:  4, 20.0, 40.0,  7.5,  8;
    n4_jitter0_p24_16bit:  4,  0.0, 24.0,  5.0, 16;
}

/// A per-column height per turn (`height_per_turn_um_per_column`, +-2 % over the field, as the
/// non-telecentric optics make it): the core scales each column itself, and stays within one
/// LSB of the f64 reference, which uses the same `T_z(c)` in floating point.
#[test]
fn per_column_height_scale_matches_the_reference() {
    let mut sim = simulate(&dpsa_tests::small_scene(), 9);
    let w = sim.rec.width();
    let tz: Vec<f64> = (0..w)
        .map(|c| 500.0 * (1.0 + 0.02 * (c as f64 * 0.05 + 0.3).sin()))
        .collect();
    sim.rec.manifest.calibration.height_per_turn_um_per_column = Some(tz);
    sim.rec
        .manifest
        .validate()
        .expect("a valid per-column table");
    let cmp = compare_recording(&sim.rec, false).expect("compare");
    assert_matches_reference(&cmp, "per-column T_z");
    assert!(cmp.fixed_vs_ref.pixels_compared > 50_000);
}
