//! Ill-conditioned windows: a stalled conveyor and steps of whole fringe periods must give
//! flagged rows without heights, never plausible wrong heights.

use dpsa_sim::heightmap::{flags, HeightMap};
use dpsa_sim::reconstruct;
use dpsa_sim::reference::{self, RefOutput};
use dpsa_sim::simulation::recording::Manifest;
use dpsa_sim::simulation::recording::{load_frames, Recording};
use dpsa_sim::simulation::scene::{Scene, Stall};
use dpsa_tests::{
    assert_flags_agree, check_vs_truth, flag_names, noise_gain, row_is_empty, simulate, small_scene,
};
use std::f64::consts::TAU;

/// Runs the fixed-point core and the f64 reference on a recording.
fn both(rec: &Recording) -> (HeightMap, RefOutput) {
    let (_, _, fixed) = reconstruct::reconstruct_map(rec, false).expect("reconstruct");
    let frames = load_frames(rec, false).expect("frames");
    (fixed, reference::reconstruct(&rec.manifest, &frames))
}

/// Offset of a latch per `docs/model.md` step 1, `floor(e / cpp + 1/2)`.
fn offset(m: &Manifest, latch: i64) -> i64 {
    (latch as f64 / m.calibration.counts_per_pixel + 0.5).floor() as i64
}

/// Noise gain of the window made of manifest frames `frames` (shifts from the latches).
fn window_gain(m: &Manifest, frames: &[usize]) -> f64 {
    let o: Vec<i64> = frames
        .iter()
        .map(|&k| offset(m, m.frames[k].latch))
        .collect();
    let shifts: Vec<f64> = o
        .iter()
        .map(|&ok| -TAU * (ok - o[0]) as f64 / m.calibration.fringe_period_px)
        .collect();
    noise_gain(&shifts)
}

#[test]
fn stalled_conveyor_flags_rows_and_keeps_the_rest_accurate() {
    let scene = Scene {
        stalls: vec![
            Stall {
                frame: 15,
                frames: 3,
            },
            Stall {
                frame: 35,
                frames: 1,
            },
            Stall {
                frame: 45,
                frames: 6,
            },
        ],
        ..small_scene()
    };
    let stalled: Vec<usize> = vec![16, 17, 18, 36, 46, 47, 48, 49, 50, 51];
    let sim = simulate(&scene, 5);
    let m = &sim.rec.manifest;
    // The simulator does what the scene says: stalled frames repeat the latch.
    for &k in &stalled {
        assert_eq!(m.frames[k].latch, m.frames[k - 1].latch, "frame {k}");
    }
    let (fixed, r) = both(&sim.rec);
    assert_flags_agree(&fixed, &r);
    // Here no row has two reasons to be invalid, so the flags are identical row by row.
    for (a, b) in fixed.rows.iter().zip(&r.rows) {
        assert_eq!(
            a.flags,
            b.flags,
            "board row {}: {} vs {}",
            a.row,
            flag_names(a.flags),
            flag_names(b.flags)
        );
    }

    let ill: Vec<i64> = fixed
        .rows
        .iter()
        .filter(|x| x.flags & flags::ILL_CONDITIONED != 0)
        .map(|x| x.row)
        .collect();
    assert!(
        ill.len() >= 3 * 8,
        "expected ill-conditioned rows around the 3- and 6-frame stalls, got {ill:?}"
    );
    for row in fixed
        .rows
        .iter()
        .filter(|x| x.flags & flags::ILL_CONDITIONED != 0)
    {
        assert!(!row.is_valid());
        assert!(
            row_is_empty(row),
            "ill-conditioned row {} carries heights",
            row.row
        );
    }

    // Every flagged window is one that a stall made degenerate, and every window whose gain
    // (computed here from the latches) exceeds the limit is flagged.
    let max_gain = m.processing.max_noise_gain;
    let mut checked = 0;
    for rr in &r.rows {
        let Some(w) = &rr.window else { continue };
        let g = window_gain(m, &w.frames);
        if (g - max_gain).abs() < 1e-3 {
            continue; // too close to the limit to judge in f64
        }
        let is_ill = rr.flags & flags::ILL_CONDITIONED != 0;
        assert_eq!(
            is_ill,
            g > max_gain,
            "row {}: gain {g}, flags {}",
            rr.row,
            flag_names(rr.flags)
        );
        if is_ill {
            assert!(
                w.frames.iter().any(|k| stalled.contains(k)),
                "row {} is ill-conditioned but its window {:?} has no stalled frame",
                rr.row,
                w.frames
            );
        }
        checked += 1;
    }
    assert!(checked > 300, "{checked}");

    // Rows near the flagged ones (within 60 board rows) that are valid are still accurate.
    let near = |b: i64| ill.iter().any(|&x| (x - b).abs() <= 60);
    let truth = sim.truth();
    let check = check_vs_truth(m, &truth, &fixed, |row| near(row.row));
    check.assert_ok("rows around the stalls");
    assert!(check.rows >= 100, "{check:?}");
    // And there are many valid rows overall.
    assert!(fixed.valid_rows() >= 300, "{}", fixed.valid_rows());
}

/// Steps of exactly whole fringe periods, no jitter: every window's shifts are multiples of
/// 2 pi, `M^T M` is singular, and no pixel may come out valid (a plausible but meaningless
/// height is the worst possible failure).
fn whole_period_steps(period: f64, periods_per_step: f64, n: u8, rows: u32) {
    let scene = Scene {
        fringe_period_px: period,
        mean_step_px: period * periods_per_step,
        jitter_pct: 0.0,
        n,
        rows,
        ..small_scene()
    };
    let what = format!("period {period} px, step {} px, n {n}", scene.mean_step_px);
    let sim = simulate(&scene, 3);
    let m = &sim.rec.manifest;
    let (fixed, r) = both(&sim.rec);
    assert_flags_agree(&fixed, &r);
    assert_eq!(
        fixed.valid_pixels(),
        0,
        "{what}: the fixed core output valid pixels"
    );
    assert_eq!(
        r.valid_pixels(),
        0,
        "{what}: the reference output valid pixels"
    );
    assert!(
        fixed.rows.iter().all(row_is_empty),
        "{what}: a row carries heights"
    );
    // The rows are flagged for the right reason: every row with a complete window is
    // ill-conditioned, and that is most of the board.
    let ill = fixed.rows_with(flags::ILL_CONDITIONED);
    assert!(
        ill >= scene.board_length as usize * 9 / 10,
        "{what}: {ill} ill-conditioned rows"
    );
    for rr in &r.rows {
        let Some(w) = &rr.window else { continue };
        if rr.flags & (flags::SKIPPED | flags::INCOMPLETE) == 0 {
            assert!(
                rr.flags & flags::ILL_CONDITIONED != 0,
                "{what}: row {} flags {}",
                rr.row,
                flag_names(rr.flags)
            );
            let g = window_gain(m, &w.frames);
            assert!(g > 1e3, "{what}: row {} gain {g}", rr.row);
        }
    }
}

#[test]
fn one_period_steps_binary_angle_exact() {
    // 2^32 / 8 is exact: the shifts are exactly 0 in the core's binary angles.
    whole_period_steps(8.0, 1.0, 4, 40);
}

#[test]
fn one_period_steps_binary_angle_inexact() {
    // 2^32 / 12 is not an integer: the core sees tiny nonzero shifts and must still refuse.
    whole_period_steps(12.0, 1.0, 4, 64);
}

#[test]
fn two_period_steps() {
    whole_period_steps(10.0, 2.0, 3, 64);
}

/// Half-period steps confine the shifts to two phases (0 and pi): singular too.
#[test]
fn half_period_steps_are_two_phase_and_singular() {
    whole_period_steps(16.0, 0.5, 4, 40);
}
