//! `dpsa grr`: a gauge repeatability study (AIAG style, one operator: the machine).
//!
//! The same printed board (the scene's print: the same deposits every time) goes through the
//! machine `repeats` times, each with fresh camera noise and a fresh placement on the conveyor
//! (offset and rotation drawn again), and is inspected each time. Per pad, the standard
//! deviation of the measured volume (percentage points of the opening volume) over the
//! repeats is its repeatability; `%GR&R = 6 sigma / (upper - lower fail limit of the volume
//! window) x 100`, per pad and for the pooled sigma (the rms of the pads' sigmas), which is
//! `grr_pct`. Only pads measured in every repeat count. The calibration is recorded and
//! computed once, as on a machine.

use crate::array::{record, record::ArrayRecording, scene::ArrayScene};
use crate::calibration;
use crate::{At, Result, SimError};
use dpsa_inspect::run::inspect_dir;
use serde::Serialize;
use std::path::Path;

/// What `dpsa grr --json` prints: the study's repeatability figures.
#[derive(Clone, Debug, Serialize)]
pub struct GrrReport {
    /// The scene file, as given.
    pub scene: String,
    /// Times the board went through the machine.
    pub repeats: u32,
    /// Pads measured in every repeat.
    pub pads: usize,
    /// Median over the pads of the volume's standard deviation, % of opening volume.
    pub volume_sigma_pct_median: f64,
    /// 95th percentile over the pads of the volume's standard deviation, % of opening
    /// volume.
    pub volume_sigma_pct_p95: f64,
    /// Largest volume standard deviation of any pad, % of opening volume.
    pub volume_sigma_pct_max: f64,
    /// Pooled (rms) sigma, % of opening volume.
    pub volume_sigma_pct_pooled: f64,
    /// Height's standard deviation, median over the pads, um.
    pub height_sigma_um_median: f64,
    /// The volume window's width (fail limits), % of opening volume.
    pub tolerance_pct: f64,
    /// 6 x pooled sigma / tolerance x 100.
    pub grr_pct: f64,
    /// Per pad %GR&R: median and 95th percentile.
    pub grr_pct_pad_median: f64,
    /// Per pad %GR&R: 95th percentile.
    pub grr_pct_pad_p95: f64,
    /// Pads whose call (level and class) was the same in every repeat.
    pub calls_consistent: usize,
    /// The placements drawn: shift (mm) and rotation (deg) the registration found.
    pub placements: Vec<([f64; 2], f64)>,
    /// Wall time of the whole study (calibration included), s.
    pub seconds: f64,
}

fn quantile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

/// Runs the study in `work` (created; its board recordings are removed as it goes).
pub fn grr(scene_path: &Path, repeats: u32, seed: u64, work: &Path) -> Result<GrrReport> {
    if !(2..=1000).contains(&repeats) {
        return Err(SimError::Refused(format!(
            "--repeats {repeats}: need 2 to 1000"
        )));
    }
    let t0 = std::time::Instant::now();
    let scene = ArrayScene::load(scene_path)?;
    if scene.paste_layer.is_none() {
        return Err(SimError::Refused(format!(
            "{}: no paste layer: a repeatability study needs a board with pads (`paste_layer`)",
            scene_path.display()
        )));
    }
    std::fs::create_dir_all(work).at(|| format!("creating {}", work.display()))?;
    let cal_dir = work.join("calibration");
    record::simulate_calibration(&scene, seed, &cal_dir)?;
    let cal = calibration::calibrate(&ArrayRecording::open(&cal_dir)?, calibration::FX_BUDGET_UM)?;
    let _ = std::fs::remove_dir_all(&cal_dir);
    let mut volumes: Vec<Vec<f64>> = Vec::new();
    let mut heights: Vec<Vec<f64>> = Vec::new();
    let mut calls: Vec<Vec<String>> = Vec::new();
    let mut placements = Vec::new();
    let mut tolerance = f64::NAN;
    for r in 0..repeats {
        let board = work.join("board");
        let map = work.join("map");
        let _ = std::fs::remove_dir_all(&board);
        let _ = std::fs::remove_dir_all(&map);
        record::simulate_board(&scene, seed + 1 + u64::from(r), &board)?;
        crate::board::run::run(&board, &cal, &map)?;
        let program_path = board.join("program.toml");
        let (report, insp) = inspect_dir(&map, &program_path, None, 1)?;
        let program = super::program::Program::load(&program_path)
            .map_err(dpsa_inspect::InspectError::from)?;
        tolerance = program.windows.volume_pct.fail[1] - program.windows.volume_pct.fail[0];
        placements.push((
            report.registration.shift_mm,
            report.registration.rotation_deg,
        ));
        if volumes.is_empty() {
            volumes = vec![Vec::new(); insp.measurements.len()];
            heights = vec![Vec::new(); insp.measurements.len()];
            calls = vec![Vec::new(); insp.measurements.len()];
        }
        if insp.measurements.len() != volumes.len() {
            return Err(SimError::refused("the pad count changed between repeats"));
        }
        for (k, m) in insp.measurements.iter().enumerate() {
            let v = if m.unmeasurable.is_none() {
                m.volume_pct
            } else {
                f64::NAN
            };
            volumes[k].push(v);
            heights[k].push(m.height_um);
            let c = &insp.calls[k];
            calls[k].push(format!("{:?}{:?}", c.level, c.class));
        }
        let _ = std::fs::remove_dir_all(&board);
        let _ = std::fs::remove_dir_all(&map);
    }
    let sd = |v: &[f64]| {
        let n = v.len() as f64;
        let m = v.iter().sum::<f64>() / n;
        (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0)).sqrt()
    };
    let mut sig = Vec::new();
    let mut hsig = Vec::new();
    for (v, h) in volumes.iter().zip(&heights) {
        if v.iter().all(|x| x.is_finite()) && h.iter().all(|x| x.is_finite()) {
            sig.push(sd(v));
            hsig.push(sd(h));
        }
    }
    if sig.is_empty() {
        return Err(SimError::refused("no pad was measured in every repeat"));
    }
    let pooled = (sig.iter().map(|s| s * s).sum::<f64>() / sig.len() as f64).sqrt();
    let per_pad: Vec<f64> = sig.iter().map(|s| 600.0 * s / tolerance).collect();
    let consistent = calls
        .iter()
        .filter(|c| c.iter().all(|x| x == &c[0]))
        .count();
    Ok(GrrReport {
        scene: scene_path.display().to_string(),
        repeats,
        pads: sig.len(),
        volume_sigma_pct_median: quantile(&sig, 0.5),
        volume_sigma_pct_p95: quantile(&sig, 0.95),
        volume_sigma_pct_max: quantile(&sig, 1.0),
        volume_sigma_pct_pooled: pooled,
        height_sigma_um_median: quantile(&hsig, 0.5),
        tolerance_pct: tolerance,
        grr_pct: 600.0 * pooled / tolerance,
        grr_pct_pad_median: quantile(&per_pad, 0.5),
        grr_pct_pad_p95: quantile(&per_pad, 0.95),
        calls_consistent: consistent,
        placements,
        seconds: t0.elapsed().as_secs_f64(),
    })
}
