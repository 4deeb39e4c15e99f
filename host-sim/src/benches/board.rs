//! `dpsa board-bench`: the speed of the whole board, as the paper counts it ("a 220 x 168 mm
//! board in under 1 s"): every camera's frames decoded into memory first (not timed with the
//! rest), then the fixed-point core on every camera (one thread each, as `dpsa board`), the
//! provenance (dead-pixel mask, row places; not the Cramer-Rao bound, which only a simulated
//! board with its truth has), unwrap, resampling and blending, and the inspection of every pad
//! against the recording's program (`program.toml`: registration, measurement, verdicts),
//! each stage timed, no files written: what a line runs per board. Beside it, in the same run,
//! the numpy float64 least-squares phase of camera 0's frames ([`super::numpy`]).
//!
//! Then the same board once more as the line receives it: every camera's rows paced at the
//! paper's conveyor rate ([`CONVEYOR_MM_S`]), and the time from the last row to the last
//! verdict (`latency_after_last_row_s`). The map is built once all rows are in (the banded
//! assembly that would start earlier is not built yet), so that latency is the stitching and
//! inspection of the whole board, plus any backlog of the core behind the conveyor.

use crate::board::assemble::{assemble, CameraRows};
use crate::board::run::{open, Opened};
use crate::calibration::calibrated;
use crate::calibration::file::CalFile;
use crate::simulation::recording::Recording;
use crate::{Result, SimError};
use dpsa_board::run::Collector;
use dpsa_board::BoardGrid;
use dpsa_gerber::pads::Pad;
use dpsa_inspect::map::BoardMap;
use dpsa_inspect::program::Program;
use serde::Serialize;
use std::path::Path;
use std::time::{Duration, Instant};

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
    /// Camera 0's core rate, Mpx/s (one thread; numpy's is `numpy.mpx_s`).
    pub core_camera0_mpx_s: f64,
    /// The inspection of every pad (null when the recording has no `program.toml`).
    pub inspection: Option<BenchInspection>,
    /// The board as the line receives it: rows paced at the conveyor rate, then the map and
    /// the verdicts.
    pub line: LineFeed,
}

/// The inspection stage's work (`inspection` in the JSON): `pads` and `calls` as in
/// `dpsa inspect`'s report.
#[derive(Clone, Debug, Serialize)]
pub struct BenchInspection {
    /// Pads of the layer, measured, not measurable.
    pub pads: dpsa_inspect::run::Counts,
    /// Pads per verdict, and the board's.
    pub calls: dpsa_inspect::run::Calls,
    /// Of `seconds.inspection`, the registration, s.
    pub register_s: f64,
}

/// The paced run (`line` in the JSON).
#[derive(Clone, Debug, Serialize)]
pub struct LineFeed {
    /// The conveyor speed the rows were paced at, mm/s.
    pub conveyor_mm_s: f64,
    /// Seconds over which the rows arrived (the longest camera's rows at the conveyor rate).
    pub feed_s: f64,
    /// Seconds the core fell behind the conveyor at its last row (0 when it kept up).
    pub core_backlog_s: f64,
    /// From the last row's arrival (the later of its paced time and the core's emitting it)
    /// to the last verdict (or the map, without a program), s.
    pub latency_after_last_row_s: f64,
    /// The line's budget for that latency, s.
    pub latency_budget_s: f64,
    /// `latency_after_last_row_s <= latency_budget_s`.
    pub within_latency_budget: bool,
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
    /// `provenance + unwrap + resample + blend`.
    pub stitching: f64,
    /// Registering the program on the map, measuring and judging every pad (0 without a
    /// program).
    pub inspection: f64,
    /// `core + stitching + inspection`: frames in memory to the last verdict.
    pub total: f64,
    /// Camera 0 alone through the core (one thread), for the numpy comparison.
    pub core_camera0: f64,
}

/// The paper's board time, s.
pub const BUDGET_S: f64 = 1.0;

/// The paper's conveyor speed: a 220 mm board's rows in its 1 s, mm/s.
pub const CONVEYOR_MM_S: f64 = 220.0;

/// The line's budget from a board's last row to its last verdict, s.
pub const LATENCY_BUDGET_S: f64 = 0.3;

/// The recording's program and its pads, read once per product (not timed with the board).
struct Judge {
    program: Program,
    pads: Vec<Pad>,
}

impl Judge {
    /// `program.toml` of the board recording `dir`, if it has one.
    fn of(dir: &Path) -> Result<Option<Judge>> {
        let path = dir.join(crate::array::record::PROGRAM_FILE);
        if !path.is_file() {
            return Ok(None);
        }
        let mut program = Program::load(&path).map_err(dpsa_inspect::InspectError::from)?;
        let (mut pads, _) = dpsa_inspect::run::paste_layer_pads(&program, &path)?;
        dpsa_inspect::teach::apply_components(&mut program, &path, &mut pads)
            .map_err(dpsa_inspect::InspectError::from)?;
        Ok(Some(Judge { program, pads }))
    }

    /// Registers, measures and judges every pad on `heights`.
    fn judge(&self, grid: &BoardGrid, heights: dpsa_board::Grid) -> Result<BenchInspection> {
        let map = BoardMap {
            board_id: None,
            grid: *grid,
            heights,
        };
        let i = dpsa_inspect::run::inspect(&map, &self.pads, &self.program)
            .map_err(dpsa_inspect::InspectError::from)?;
        let (pads, calls) = dpsa_inspect::run::counts(&i);
        Ok(BenchInspection {
            pads,
            calls,
            register_s: i.register_s,
        })
    }
}

/// Runs the bench on the array board recording `dir` with `cal`; `python` runs the numpy
/// baseline (`None`: skipped).
pub fn run(dir: &Path, cal: &CalFile, python: Option<&str>) -> Result<BoardBench> {
    let Opened { recs, layout, .. } = open(dir, cal)?;
    let grid = layout.grid;
    let judge = Judge::of(dir)?;
    let t0 = Instant::now();
    let loaded = per_camera(recs.iter().enumerate(), |(i, r)| {
        let mut r = calibrated(r, cal, i)?;
        let bytes = r.preload()?;
        Ok((r, bytes))
    })?;
    let load = t0.elapsed().as_secs_f64();

    let t1 = Instant::now();
    let collected = per_camera(loaded.iter().enumerate(), |(i, (r, _))| {
        core_rows_paced(r, cal, i, None)
    })?;
    let core = t1.elapsed().as_secs_f64();
    let core_pixels: u64 = collected
        .iter()
        .map(|c| c.rows.len() as u64 * c.width as u64)
        .sum();
    let (a, provenance) = stitch(collected, &loaded, cal, &grid)?;
    let t4 = Instant::now();
    let inspection = judge
        .as_ref()
        .map(|j| j.judge(&grid, a.blended.heights))
        .transpose()?;
    let inspection_s = if judge.is_some() {
        t4.elapsed().as_secs_f64()
    } else {
        0.0
    };
    let t = a.timing;

    // Camera 0 alone, then numpy on the same frames.
    let (r0, _) = loaded
        .first()
        .ok_or_else(|| SimError::refused("no camera"))?;
    let t3 = Instant::now();
    let one = core_rows_paced(r0, cal, 0, None)?;
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
    let core_camera0_mpx_s = one_px / core_camera0 / 1e6;
    let core_over_numpy = numpy.as_ref().map(|n| core_camera0_mpx_s / n.mpx_s);

    let line = line_feed(&loaded, cal, &grid, judge.as_ref())?;

    let stitching = provenance + t.unwrap_s + t.resample_s + t.blend_s;
    let total = core + stitching + inspection_s;
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
            stitching,
            inspection: inspection_s,
            total,
            core_camera0,
        },
        core_mpx_s: core_pixels as f64 / core / 1e6,
        budget_s: BUDGET_S,
        within_budget: total <= BUDGET_S,
        numpy,
        numpy_error,
        core_over_numpy,
        core_camera0_mpx_s,
        inspection,
        line,
    })
}

/// Provenance and assembly of the cameras' rows: the map, and the provenance's seconds.
fn stitch(
    collected: Vec<Collector>,
    loaded: &[(Recording, u64)],
    cal: &CalFile,
    grid: &BoardGrid,
) -> Result<(dpsa_board::assemble::Assembled, f64)> {
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
    Ok((assemble(cams, grid), provenance))
}

/// Camera `i`'s rows through the core (`rec`'s frames in memory). With `pace = Some((start,
/// row_s))`, row `k` is not taken before `start + k row_s`: the rows arrive as a conveyor
/// brings them.
fn core_rows_paced(
    rec: &Recording,
    cal: &CalFile,
    i: usize,
    pace: Option<(Instant, Duration)>,
) -> Result<Collector> {
    let mut rows = Collector::new(&cal.camera[i], cal.height_lsb_um);
    let mut k = 0u32;
    crate::reconstruct::reconstruct_rows(rec, false, |r| {
        if let Some((start, row_s)) = pace {
            let due = start + row_s * k;
            let now = Instant::now();
            if due > now {
                std::thread::sleep(due - now);
            }
        }
        k += 1;
        rows.push(&r);
        Ok(())
    })?;
    Ok(rows)
}

/// The board again as the line receives it: each camera's rows paced at [`CONVEYOR_MM_S`]
/// (board rows of `grid.pitch_mm`), then provenance, assembly and verdicts; the time from the
/// last row to the last verdict.
fn line_feed(
    loaded: &[(Recording, u64)],
    cal: &CalFile,
    grid: &BoardGrid,
    judge: Option<&Judge>,
) -> Result<LineFeed> {
    let row_s = Duration::from_secs_f64(grid.pitch_mm / CONVEYOR_MM_S);
    let most_rows = loaded
        .iter()
        .map(|(r, _)| crate::reference::plan(&r.manifest).len())
        .max()
        .unwrap_or(0);
    let start = Instant::now();
    let collected = per_camera(loaded.iter().enumerate(), |(i, (r, _))| {
        core_rows_paced(r, cal, i, Some((start, row_s)))
    })?;
    let last_row = Instant::now();
    let feed_s = row_s.as_secs_f64() * most_rows as f64;
    let core_backlog_s = ((last_row - start).as_secs_f64() - feed_s).max(0.0);
    let (a, _) = stitch(collected, loaded, cal, grid)?;
    if let Some(j) = judge {
        j.judge(grid, a.blended.heights)?;
    }
    let latency = last_row.elapsed().as_secs_f64();
    Ok(LineFeed {
        conveyor_mm_s: CONVEYOR_MM_S,
        feed_s,
        core_backlog_s,
        latency_after_last_row_s: latency,
        latency_budget_s: LATENCY_BUDGET_S,
        within_latency_budget: latency <= LATENCY_BUDGET_S,
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
