//! Real fringe images (captured by others with real cameras; `../shared/data/real`, see its
//! README.md): the fixed-point kernel against the f64 least squares and against the textbook
//! closed-form N-step formulas, and the dark background must come out invalid.
//!
//! The folder is part of the CI contract: if it is missing these tests fail (with a message
//! saying where it was expected), they do not pass silently.

use dpsa_sim::reference::wrap_phase;
use dpsa_sim::stack::{self, PhaseReport, Stack, StackPhase};
use dpsa_tests::real_data_dir;
use std::path::{Path, PathBuf};

/// `dpsa phase`'s default threshold: 4 % of the 8-bit full scale.
const MIN_MOD_8BIT: f64 = 0.04 * 255.0;

fn run(paths: &[PathBuf], steps_deg: &[f64]) -> (Stack, StackPhase, PhaseReport) {
    for p in paths {
        assert!(p.is_file(), "missing real image {}", p.display());
    }
    let st = Stack::load(paths, steps_deg).expect("load the stack");
    assert_eq!(st.bit_depth, 8);
    let (ph, rep) = stack::run(&st, MIN_MOD_8BIT).expect("phase");
    (st, ph, rep)
}

/// Fixed vs f64 least squares on the same pixels, and the validity sets.
#[track_caller]
fn assert_fixed_matches_f64(rep: &PhaseReport, what: &str) {
    assert_eq!(rep.total_pixels, rep.width * rep.height);
    assert!(rep.fixed_vs_ref_rms_rad <= 1e-3, "{what}: {rep:?}");
    // The integer atan2 and Q7.24 solve are good to ~1e-5 rad; the max bounds a bad pixel.
    assert!(rep.fixed_vs_ref_max_rad <= 1e-2, "{what}: {rep:?}");
    assert_eq!(rep.valid_mismatch, 0, "{what}: {rep:?}");
    assert!(
        rep.valid_pixels * 10 >= rep.total_pixels * 4,
        "{what}: only {} of {} pixels valid",
        rep.valid_pixels,
        rep.total_pixels
    );
}

/// RMS and max of `fixed - textbook` (wrapped) over the pixels valid in the fixed result.
fn vs_textbook(st: &Stack, ph: &StackPhase, textbook: impl Fn(&[f64]) -> f64) -> (f64, f64, usize) {
    let (mut s2, mut max, mut n) = (0.0, 0.0f64, 0usize);
    let mut samples = vec![0.0; st.images.len()];
    for (i, f) in ph.fixed.iter().enumerate() {
        let Some(f) = f else { continue };
        for (s, img) in samples.iter_mut().zip(&st.images) {
            *s = f64::from(img[i]);
        }
        let d = wrap_phase(f - textbook(&samples));
        s2 += d * d;
        max = max.max(d.abs());
        n += 1;
    }
    ((s2 / n.max(1) as f64).sqrt(), max, n)
}

/// Fraction of valid pixels (fixed result) in the rectangle rows `r0..r1`, columns `c0..c1`.
fn valid_fraction(
    st: &Stack,
    ph: &StackPhase,
    (r0, r1): (usize, usize),
    (c0, c1): (usize, usize),
) -> f64 {
    let mut valid = 0;
    for r in r0..r1 {
        for c in c0..c1 {
            valid += usize::from(ph.fixed[r * st.width + c].is_some());
        }
    }
    valid as f64 / ((r1 - r0) * (c1 - c0)) as f64
}

fn lens_paths(dir: &Path) -> Vec<PathBuf> {
    ["000", "090", "180", "270"]
        .iter()
        .map(|s| dir.join(format!("fpp_tools_lens/lens_orig_{s}.jpg")))
        .collect()
}

#[test]
fn lens_four_step() {
    let dir = real_data_dir();
    let (st, ph, rep) = run(&lens_paths(&dir), &[0.0, 90.0, 180.0, 270.0]);
    assert_eq!((st.width, st.height), (933, 862));
    assert_fixed_matches_f64(&rep, "lens");
    assert!(
        (rep.noise_gain - 1.0).abs() < 1e-9,
        "equal 4-step set has gain 1: {rep:?}"
    );

    // Textbook 4-step formula for I_j = B + C cos(Phi + j 90deg):
    // I_0 - I_2 = 2 C cos Phi, I_3 - I_1 = 2 C sin Phi.
    let (rms, max, n) = vs_textbook(&st, &ph, |i| (i[3] - i[1]).atan2(i[0] - i[2]));
    assert!(n > 0);
    assert!(
        rms <= 1e-3 && max <= 1e-2,
        "fixed vs 4-step formula: rms {rms} max {max} rad"
    );

    // Background: the black top-left corner, and the lit board right of the projected
    // pattern (bright, but no fringes) carry no phase.
    assert_eq!(
        valid_fraction(&st, &ph, (0, 60), (0, 60)),
        0.0,
        "black corner"
    );
    let lit = valid_fraction(&st, &ph, (300, 600), (770, 880));
    assert!(lit <= 0.01, "lit board without fringes: {lit} valid");
    // The fringe area (board and lens) is mostly valid.
    let fringes = valid_fraction(&st, &ph, (250, 650), (100, 700));
    assert!(fringes >= 0.85, "fringe area: {fringes} valid");
}

fn kamino(first: usize) {
    let dir = real_data_dir().join("kamino410_object1");
    let paths: Vec<PathBuf> = (first..first + 3)
        .map(|i| dir.join(format!("pat{i:02}.png")))
        .collect();
    let what = format!("kamino410 pat{first:02}..{:02}", first + 2);
    let (st, ph, rep) = run(&paths, &[-120.0, 0.0, 120.0]);
    assert_eq!((st.width, st.height), (1936, 1216));
    assert_fixed_matches_f64(&rep, &what);
    assert!((rep.noise_gain - 1.0).abs() < 1e-9, "{what}: {rep:?}");

    // Textbook 3-step formula for steps -120, 0, +120 degrees:
    // I_a - I_c = sqrt(3) C sin Phi, 2 I_b - I_a - I_c = 3 C cos Phi.
    let (rms, max, n) = vs_textbook(&st, &ph, |i| {
        (3f64.sqrt() * (i[0] - i[2])).atan2(2.0 * i[1] - i[0] - i[2])
    });
    assert!(n > 0);
    assert!(
        rms <= 1e-3 && max <= 1e-2,
        "{what}: fixed vs 3-step formula: rms {rms} max {max} rad"
    );

    // pat30 is the all-white capture, pat31 the all-black one: pixels black in both receive
    // no projector light (background, shadows) and must be invalid; pixels bright in the white
    // capture see the fringes and must be valid.
    let white = Stack::load(
        &[
            dir.join("pat30.png"),
            dir.join("pat31.png"),
            dir.join("pat31.png"),
        ],
        &[0.0, 0.0, 0.0],
    )
    .expect("load pat30/pat31");
    let (w, b) = (&white.images[0], &white.images[1]);
    let (mut dark, mut dark_valid, mut bright, mut bright_valid) = (0usize, 0usize, 0usize, 0usize);
    for i in 0..w.len() {
        let valid = ph.fixed[i].is_some();
        if b[i] <= 4 && w[i] <= 20 {
            dark += 1;
            dark_valid += usize::from(valid);
        } else if w[i] >= 120 {
            bright += 1;
            bright_valid += usize::from(valid);
        }
    }
    assert!(dark >= w.len() / 5, "{what}: only {dark} dark pixels");
    assert!(
        dark_valid * 100 <= dark,
        "{what}: {dark_valid} of {dark} dark pixels valid"
    );
    assert!(bright >= 10_000, "{what}: {bright}");
    assert!(
        bright_valid * 100 >= bright * 99,
        "{what}: {bright_valid} of {bright} bright pixels valid"
    );
}

#[test]
fn kamino_three_step_period_200_3() {
    kamino(0);
}

#[test]
fn kamino_three_step_period_100() {
    kamino(3);
}

/// Fixed and f64 agree on every pixel's validity also when the steps are given in a
/// different order (same frames, permuted): the phase must be the same.
#[test]
fn lens_step_order_does_not_matter() {
    let dir = real_data_dir();
    let p = lens_paths(&dir);
    let (_, a, _) = run(&p, &[0.0, 90.0, 180.0, 270.0]);
    let perm = [p[2].clone(), p[0].clone(), p[3].clone(), p[1].clone()];
    let (_, b, rep) = run(&perm, &[180.0, 0.0, 270.0, 90.0]);
    assert_fixed_matches_f64(&rep, "lens permuted");
    let mut worst = 0.0f64;
    for (x, y) in a.fixed.iter().zip(&b.fixed) {
        assert_eq!(x.is_some(), y.is_some());
        if let (Some(x), Some(y)) = (x, y) {
            worst = worst.max(wrap_phase(x - y).abs());
        }
    }
    assert!(worst <= 1e-3, "permuted stack differs by {worst} rad");
}
