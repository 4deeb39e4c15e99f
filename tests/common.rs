//! Shared helpers of the end-to-end tests (package `dpsa-tests`).
//!
//! Everything that judges a result here is written independently of the library: the flat
//! mask, the per-pixel noise bound and the truth check are derived from `docs/model.md` and
//! textbook least-squares facts, not from `dpsa_sim::reference` or `dpsa_sim::reference::compare`.

use dpsa_sim::heightmap::{flags, HeightMap, HeightRow};
use dpsa_sim::simulation::recording::{CameraTruth, Manifest, Recording};
use dpsa_sim::simulation::scene::Scene;
use std::f64::consts::TAU;
use std::path::{Path, PathBuf};
use tempfile::TempDir;

/// A simulated recording in a temporary directory (deleted on drop).
pub struct Sim {
    pub dir: TempDir,
    pub rec: Recording,
}

impl Sim {
    pub fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Re-opens the recording (after the manifest or frames were edited on disk).
    pub fn reopen(&self) -> Recording {
        Recording::open(self.dir.path()).expect("re-open the edited recording")
    }

    pub fn truth(&self) -> CameraTruth {
        self.rec
            .truth()
            .expect("read the truth")
            .expect("simulated recordings have truth")
    }
}

/// Simulates `scene` with `seed` into a fresh temporary directory.
pub fn simulate(scene: &Scene, seed: u64) -> Sim {
    scene.validate().expect("test scene must be valid");
    let dir = tempfile::tempdir().expect("temp dir");
    dpsa_sim::simulation::simulate::simulate(scene, seed, dir.path(), false).expect("simulate");
    let rec = Recording::open(dir.path()).expect("open the simulated recording");
    Sim { dir, rec }
}

/// A small but non-trivial scene (W = 192, 420 board rows, a few dozen deposits): fast to
/// simulate and reconstruct, large enough for row statistics.
pub fn small_scene() -> Scene {
    Scene {
        width: 192,
        board_length: 420,
        deposits: 30,
        ..Scene::default()
    }
}

/// `../shared/data/real` beside the repository. Panics with a clear message if it is
/// missing: the real-data tests are part of the CI contract and must not silently pass.
pub fn real_data_dir() -> PathBuf {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/real");
    assert!(
        dir.join("README.md").is_file(),
        "the real fringe images are missing: expected them in {} (the `shared/data/real` folder \
         beside the repository, see its README.md); these tests are part of the CI contract",
        dir.display()
    );
    dir
}

/// Loads `manifest.json` of a recording directory as a JSON value, lets `edit` change it and
/// writes it back (no validation: the point is to write bad manifests).
pub fn edit_manifest_json(dir: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let path = dir.join("manifest.json");
    let text = std::fs::read_to_string(&path).expect("read manifest.json");
    let mut v: serde_json::Value = serde_json::from_str(&text).expect("parse manifest.json");
    edit(&mut v);
    std::fs::write(&path, serde_json::to_string_pretty(&v).unwrap()).expect("write manifest.json");
}

/// Folds `d` into `[-period/2, period/2)`.
pub fn fold(d: f64, period: f64) -> f64 {
    d - period * ((d + period / 2.0) / period).floor()
}

/// Flat pixels of the truth: the pixel and its 8 neighbours have the same height (border
/// pixels are never flat). Registration rounds each frame to a whole pixel, so on deposit
/// walls an error measures lateral sampling, not phase.
pub fn flat(truth: &CameraTruth) -> Vec<bool> {
    let (rows, w) = (truth.rows, truth.width);
    let h = &truth.height_um;
    let mut out = vec![false; rows * w];
    for r in 1..rows.saturating_sub(1) {
        for c in 1..w.saturating_sub(1) {
            let v = h[r * w + c];
            out[r * w + c] =
                (r - 1..=r + 1).all(|rr| (c - 1..=c + 1).all(|cc| h[rr * w + cc] == v));
        }
    }
    out
}

/// Upper bound of the standard deviation (um) of a valid pixel's height, from the noise model
/// and the least-squares algebra: a valid window has noise gain `g <= max_noise_gain`, and
/// then `sd(Phi) <= g sqrt(2/n) sigma_I / C` (the covariance of `(v_2, v_3)` is
/// `sigma_I^2 A^-1`, whose largest eigenvalue is `sigma_I^2 / lambda_min(A) = sigma_I^2
/// 2 g^2 / n`). `sigma_I^2 = read^2 + (B + C) / gain + 1/12` (largest sample, plus rounding).
pub fn height_sd_bound_um(m: &Manifest, bg: f64, ct: f64) -> f64 {
    let noise = m
        .noise
        .as_ref()
        .expect("simulated recording has a noise model");
    let var_i = noise.read_noise_dn.powi(2) + (bg + ct).max(0.0) / noise.gain_e_per_dn + 1.0 / 12.0;
    let g = m.processing.max_noise_gain;
    let n = f64::from(m.processing.n);
    let sd_phi = g * (2.0 / n).sqrt() * var_i.sqrt() / ct;
    sd_phi * m.calibration.height_per_turn_um / TAU
}

/// Result of [`check_vs_truth`].
#[derive(Debug, Default, Clone)]
pub struct TruthCheck {
    /// Valid rows with at least one flat valid pixel.
    pub rows: usize,
    /// Flat valid pixels checked.
    pub pixels: usize,
    /// Largest `(|fixed - truth| - 1 LSB) / sd_bound` over the pixels.
    pub worst_pixel_z: f64,
    /// Where it happened (board row, column, error um).
    pub worst_pixel: Option<(i64, usize, f64)>,
    /// Largest `(|row mean error| - 1 LSB) / sd_bound_of_the_mean` over rows with >= 32 flat
    /// valid pixels. A registration error of one row shifts the whole row's phase by
    /// `2 pi / period`, i.e. a bias of `T_z / period` (15.6 um by default), far above this.
    pub worst_row_z: f64,
    pub worst_row: Option<(i64, f64)>,
}

impl TruthCheck {
    /// Asserts that every checked pixel and row is consistent with noise.
    #[track_caller]
    pub fn assert_ok(&self, what: &str) {
        assert!(
            self.worst_pixel_z < 6.0,
            "{what}: a valid pixel is wrong: {self:?}"
        );
        assert!(
            self.worst_row_z < 6.0,
            "{what}: a valid row is biased: {self:?}"
        );
    }
}

/// Compares every valid pixel of `map` on a flat truth pixel (in rows selected by `select`)
/// with the ground truth. See [`TruthCheck`].
pub fn check_vs_truth(
    m: &Manifest,
    truth: &CameraTruth,
    map: &HeightMap,
    select: impl Fn(&HeightRow) -> bool,
) -> TruthCheck {
    let flat = flat(truth);
    let lsb = m.calibration.height_lsb_um;
    let t_z = m.calibration.height_per_turn_um;
    let mut out = TruthCheck::default();
    for row in map.rows.iter().filter(|r| r.is_valid() && select(r)) {
        let Some(ti) = row
            .row
            .checked_sub(truth.first_row)
            .filter(|&i| i >= 0 && (i as usize) < truth.rows)
        else {
            continue;
        };
        let ti = ti as usize;
        let (mut sum, mut var, mut count) = (0.0, 0.0, 0usize);
        for c in 0..truth.width {
            let i = ti * truth.width + c;
            if !flat[i] || !row.pixel_valid(c) {
                continue;
            }
            let err = fold(
                f64::from(row.heights[c]) * lsb - f64::from(truth.height_um[i]),
                t_z,
            );
            let sd = height_sd_bound_um(
                m,
                f64::from(truth.background[i]),
                f64::from(truth.contrast[i]),
            );
            let z = (err.abs() - lsb).max(0.0) / sd;
            if z > out.worst_pixel_z || out.worst_pixel.is_none() {
                out.worst_pixel_z = z;
                out.worst_pixel = Some((row.row, c, err));
            }
            sum += err;
            var += sd * sd;
            count += 1;
        }
        out.pixels += count;
        if count > 0 {
            out.rows += 1;
        }
        if count >= 32 {
            let mean = sum / count as f64;
            let sd_mean = var.sqrt() / count as f64;
            let z = (mean.abs() - lsb).max(0.0) / sd_mean;
            if z > out.worst_row_z || out.worst_row.is_none() {
                out.worst_row_z = z;
                out.worst_row = Some((row.row, mean));
            }
        }
    }
    out
}

/// True when the decoded row carries no height at all: no valid bit and every height 0.
pub fn row_is_empty(row: &HeightRow) -> bool {
    row.valid.iter().all(|&v| !v) && row.heights.iter().all(|&h| h == 0)
}

/// Noise gain `g = sqrt(n / (2 lambda_min(A)))` of a set of shifts (rad), with the closed-form
/// eigenvalue of the symmetric 2x2 matrix `A` of `docs/model.md`. `+inf` when singular.
pub fn noise_gain(shifts: &[f64]) -> f64 {
    let n = shifts.len() as f64;
    let mc = shifts.iter().map(|t| t.cos()).sum::<f64>() / n;
    let ms = shifts.iter().map(|t| t.sin()).sum::<f64>() / n;
    let (mut a, mut b, mut d) = (0.0, 0.0, 0.0);
    for t in shifts {
        let u = t.cos() - mc;
        let w = -(t.sin() - ms);
        a += u * u;
        b += u * w;
        d += w * w;
    }
    let lmin = 0.5 * (a + d - ((a - d).powi(2) + 4.0 * b * b).sqrt());
    if lmin > 1e-12 {
        (n / (2.0 * lmin)).sqrt()
    } else {
        f64::INFINITY
    }
}

/// Row flags by board row of a height map.
pub fn flags_by_row(map: &HeightMap) -> std::collections::BTreeMap<i64, u16> {
    map.rows.iter().map(|r| (r.row, r.flags)).collect()
}

/// Names of the flags set in `f`, for messages.
pub fn flag_names(f: u16) -> String {
    flags::names(f).join("|")
}

/// Row flags of the fixed core against the f64 reference, row by row:
///
/// - the same board rows, in the same order, with the same row validity;
/// - on valid rows, identical flags (including the `SATURATED` / `LOW_MODULATION` summaries);
/// - on invalid rows, every flag the core reports is reported by the reference too, and
///   `ILL_CONDITIONED` agrees whenever the window is otherwise complete (the reference has no
///   other invalidating flag).
///
/// The last rule is weaker than equality on purpose: the reference evaluates every reason
/// that applies to a row (and the pixel summaries whenever it has all `n` lines), while the
/// core stops at the first invalidating reason. `docs/model.md` does not say which is right.
#[track_caller]
pub fn assert_flags_agree(fixed: &HeightMap, reference: &dpsa_sim::reference::RefOutput) {
    assert_eq!(fixed.rows.len(), reference.rows.len(), "row counts differ");
    for (a, b) in fixed.rows.iter().zip(&reference.rows) {
        assert_eq!(a.row, b.row, "row sets differ");
        let ctx = || {
            format!(
                "board row {}: core {} vs reference {}",
                a.row,
                flag_names(a.flags),
                flag_names(b.flags)
            )
        };
        assert_eq!(a.is_valid(), b.is_valid(), "{}", ctx());
        if a.is_valid() {
            assert_eq!(a.flags, b.flags, "{}", ctx());
        } else {
            assert_eq!(a.flags & !b.flags, 0, "{}", ctx());
            if b.flags & flags::ROW_INVALID & !flags::ILL_CONDITIONED == 0 {
                assert_eq!(
                    a.flags & flags::ILL_CONDITIONED,
                    b.flags & flags::ILL_CONDITIONED,
                    "{}",
                    ctx()
                );
            }
        }
    }
}
