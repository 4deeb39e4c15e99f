//! `dpsa board-bench`: the speed of the whole board, as the paper counts it ("a 220 x 168 mm
//! board in under 1 s"): every camera's frames decoded into memory first (not timed with the
//! rest), then the fixed-point core on every camera (one thread each, as `dpsa board`), the
//! provenance (dead-pixel mask, row places; not the Cramer-Rao bound, which only a simulated
//! board with its truth has), unwrap, resampling and blending, each stage timed, no files
//! written: what a line runs per board. Beside it, in the same run, the
//! numpy float64 least-squares phase of camera 0's frames ([`super::numpy`]).

use crate::board::assemble::{assemble, CameraRows};
use crate::board::run::{core_rows, open, Opened};
use crate::calibration::calibrated;
use crate::calibration::file::CalFile;
use crate::{Result, SimError};
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

/// `dpsa board-bench --json`.
#[derive(Clone, Debug, Serialize)]
pub struct BoardBench {
    /// Cameras of the board recording.
    pub cameras: usize,
    /// Hardware threads available to this process.
    pub threads: usize,
    /// Samples of every camera's frames, held in memory, MB.
    pub frames_mb: f64,
    /// Height pixels the core emitted, all cameras (rows x W).
    pub core_pixels: u64,
    /// Pixels of the board map.
    pub board_pixels: u64,
    /// Seconds per stage (wall time).
    pub seconds: Stages,
    /// `core_pixels / seconds.core` / 1e6: the core's output rate over all cameras.
    pub core_mpx_s: f64,
    /// The paper's budget for the whole board, s.
    pub budget_s: f64,
    /// `seconds.total <= budget_s`.
    pub within_budget: bool,
    /// The numpy float64 least-squares phase of camera 0 (null when it could not run: then
    /// `numpy_error` says why).
    pub numpy: Option<super::numpy::NumpyRun>,
    /// Why the numpy baseline did not run (absent when it did).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub numpy_error: Option<String>,
    /// Camera 0's core rate (its own run, one thread, frames in memory) over numpy's on the
    /// same frames.
    pub core_over_numpy: Option<f64>,
}

/// Wall time per stage, s (`seconds` in the JSON).
#[derive(Clone, Debug, Serialize)]
pub struct Stages {
    /// Decoding every frame into memory (threads per camera; not part of `total`).
    pub load: f64,
    /// The fixed-point core on every camera, one thread each.
    pub core: f64,
    /// Dead-pixel masks and row places, all cameras.
    pub provenance: f64,
    /// Unwrapping, all cameras (in parallel threads).
    pub unwrap: f64,
    /// Resampling onto the board grid, all cameras (in parallel threads).
    pub resample: f64,
    /// Blending the cameras into one map (turn alignment and seams).
    pub blend: f64,
    /// `core + provenance + unwrap + resample + blend`.
    pub total: f64,
    /// Camera 0 alone through the core (one thread), for the numpy comparison.
    pub core_camera0: f64,
}

/// The paper's board time, s.
pub const BUDGET_S: f64 = 1.0;

/// Runs the bench on the array board recording `dir` with `cal`; `python` runs the numpy
/// baseline (`None`: skipped).
pub fn run(dir: &Path, cal: &CalFile, python: Option<&str>) -> Result<BoardBench> {
    let Opened { recs, layout, .. } = open(dir, cal)?;
    let grid = layout.grid;
    let t0 = Instant::now();
    let loaded = per_camera(recs.iter().enumerate(), |(i, r)| {
        let mut r = calibrated(r, cal, i)?;
        let bytes = r.preload()?;
        Ok((r, bytes))
    })?;
    let load = t0.elapsed().as_secs_f64();

    let t1 = Instant::now();
    let collected = per_camera(loaded.iter().enumerate(), |(i, (r, _))| {
        core_rows(r, cal, i)
    })?;
    let core = t1.elapsed().as_secs_f64();
    let core_pixels: u64 = collected
        .iter()
        .map(|c| c.rows.len() as u64 * c.width as u64)
        .sum();

    let t2 = Instant::now();
    let cams: Vec<CameraRows> = per_camera(
        collected.into_iter().zip(loaded.iter().zip(&cal.camera)),
        |(col, ((r, _), c))| {
            let prov = crate::board::provenance::of_recording(r);
            let max_step = r.manifest.processing.max_step_rows;
            Ok(col
                .finish(&prov, &mut dpsa_board::run::no_variance, c, max_step, &[])?
                .0)
        },
    )?;
    let provenance = t2.elapsed().as_secs_f64();
    let a = assemble(cams, &grid);

    // Camera 0 alone, then numpy on the same frames.
    let (r0, _) = loaded
        .first()
        .ok_or_else(|| SimError::refused("no camera"))?;
    let t3 = Instant::now();
    let one = core_rows(r0, cal, 0)?;
    let core_camera0 = t3.elapsed().as_secs_f64();
    let one_px = one.rows.len() as f64 * one.width as f64;
    drop(one);
    let (numpy, numpy_error) = match python {
        None => (None, Some("skipped (--no-numpy)".to_string())),
        Some(py) => match super::numpy::run(r0, py) {
            Ok(n) => (Some(n), None),
            Err(e) => (
                None,
                Some(format!(
                    "{} (the baseline needs python3 with numpy: pip install numpy)",
                    crate::error::chain(&e)
                )),
            ),
        },
    };
    let core_over_numpy = numpy
        .as_ref()
        .map(|n| (one_px / core_camera0 / 1e6) / n.mpx_s);

    let t = &a.timing;
    let total = core + provenance + t.unwrap_s + t.resample_s + t.blend_s;
    Ok(BoardBench {
        cameras: loaded.len(),
        threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
        frames_mb: loaded.iter().map(|(_, b)| *b as f64).sum::<f64>() / 1e6,
        core_pixels,
        board_pixels: (grid.rows * grid.width) as u64,
        seconds: Stages {
            load,
            core,
            provenance,
            unwrap: t.unwrap_s,
            resample: t.resample_s,
            blend: t.blend_s,
            total,
            core_camera0,
        },
        core_mpx_s: core_pixels as f64 / core / 1e6,
        budget_s: BUDGET_S,
        within_budget: total <= BUDGET_S,
        numpy,
        numpy_error,
        core_over_numpy,
    })
}

/// `f` on every item in its own thread (one per camera), the results in order; a panicking
/// thread is an error.
fn per_camera<T: Send, R: Send>(
    items: impl IntoIterator<Item = T>,
    f: impl Fn(T) -> Result<R> + Sync,
) -> Result<Vec<R>> {
    let f = &f;
    std::thread::scope(|s| {
        let handles: Vec<_> = items.into_iter().map(|t| s.spawn(move || f(t))).collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(SimError::Internal("a thread panicked".into())))
            })
            .collect()
    })
}
