//! `dpsa board`: an array recording and its calibration into one board map, the rows from
//! the core on every camera's recording or from the cameras' packet streams, and the map
//! compared with the simulator's board truth when the recording has one.
//!
//! The map itself is `dpsa-board`'s ([`dpsa_board::run`]): with `--streams` the rows, their
//! dead-pixel masks and places come from the streams alone (the camera recordings are read only
//! for the Cramer-Rao bound of their truth, when they are there). With the core
//! ([`Source::Core`]), per camera (one thread each) the calibration goes into the camera
//! recording's manifest ([`crate::calibration::apply()`]) and the fixed-point core runs on it:
//! the rows exactly as its packets carry them (the calibration's per-column `T_z(c)` is part
//! of the core's configuration, so its heights are already in calibrated LSB in every column).

use super::truth::{against_truth, BoardTruth, MapAccuracy};
use super::Grid;
use crate::array::record::ArrayRecording;
use crate::calibration::{calibrated, CalFile};
use crate::simulation::recording::Recording;
use crate::{At, Result, SimError};
use dpsa_board::assemble::CameraRows;
use dpsa_board::provenance::Provenance;
use dpsa_board::run::{self as map, Built, Collector, Inputs, MapLayout};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub use dpsa_board::run::{
    placement, PixelCounts, RunTiming, Seams, UnwrapStats, MIN_CAMERA_SHARE, MIN_CAMERA_VALID,
    MIN_MAP_VALID, SEAM_ALARM, SEAM_BUDGET_UM,
};

/// Where the cameras' rows come from.
#[derive(Clone, Copy, Debug)]
pub enum Source<'a> {
    /// The fixed-point core on every camera's recording with its calibration (threads): the
    /// same rows as each camera's firmware emits.
    Core,
    /// The cameras' packet streams, one per camera, in any order ([`dpsa_board::streams`]).
    Streams(&'a [PathBuf]),
}

/// `dpsa board --json`: the map's report and, with the simulator's truth, the map against it.
#[derive(Clone, Debug, Serialize)]
pub struct BoardReport {
    /// The production report ([`dpsa_board::run::MapReport`]).
    #[serde(flatten)]
    pub map: map::MapReport,
    /// Against the simulator's board truth (null without it).
    pub truth: Option<MapAccuracy>,
    /// The comparison with the truth, s (0 without it).
    pub truth_s: f64,
}

impl BoardReport {
    /// A few lines for the terminal.
    pub fn summary(&self) -> String {
        let opt = |x: Option<f64>| x.map_or_else(|| "n/a".to_string(), |v| format!("{v:.3}"));
        let mut s = self.map.summary_head();
        if let Some(t) = &self.truth {
            // The bound needs every camera's per-pixel truth (B, C, phase) and noise model;
            // scenes with `camera_truth = false` (scenes/paper-board.toml: 12 bytes per
            // camera pixel saved) have none.
            let crb = match t.crb_rms_um {
                Some(_) => format!(
                    "Cramer-Rao bound {} um (ratio {})",
                    opt(t.crb_rms_um),
                    opt(t.over_crb)
                ),
                None => "no Cramer-Rao bound (it needs the cameras' truth files, which this recording lacks: its scene sets `camera_truth = false`, or it has no noise model)".into(),
            };
            s += &format!(
                "truth: rms {} um (bias {}), {crb} over {} flat px, {} wrong-turn px\n",
                opt(t.rms_um),
                opt(t.bias_um),
                t.flat_pixels,
                t.wrong_turn_pixels
            );
        }
        s + &self.map.time_line(Some(self.truth_s))
    }
}

/// Row source 1: the core on one camera's calibrated recording (camera `i` of `cal`).
pub fn core_rows(rec: &Recording, cal: &CalFile, i: usize) -> Result<Collector> {
    core_rows_counted(rec, cal, i, &indicatif::ProgressBar::hidden())
}

/// [`core_rows`], counting every row on `bar` (its length grows by the camera's planned rows).
fn core_rows_counted(
    rec: &Recording,
    cal: &CalFile,
    i: usize,
    bar: &indicatif::ProgressBar,
) -> Result<Collector> {
    bar.inc_length(crate::reference::plan(&rec.manifest).len() as u64);
    let mut rows = Collector::new(&cal.camera[i], cal.height_lsb_um);
    crate::reconstruct::reconstruct_rows(rec, false, |r| {
        rows.push(&r);
        bar.inc(1);
        Ok(())
    })?;
    Ok(rows)
}

/// The Cramer-Rao bound of camera `rec`'s rows (its truth and noise model), as
/// [`dpsa_board::run::Variance`].
fn crb_of(
    rec: &Recording,
    tz: Vec<f64>,
    camera: u8,
) -> impl FnMut(
    &Provenance,
    i64,
    &Grid,
) -> std::result::Result<Option<Grid>, Box<dyn std::error::Error + Send + Sync>>
       + '_ {
    move |prov, first, g| {
        super::provenance::crb_variance(rec, prov, &tz, first, g)
            .at(|| format!("camera {camera}"))
            .map_err(Into::into)
    }
}

/// An array board recording opened and checked against its calibration.
pub(crate) struct Opened {
    pub arr: ArrayRecording,
    /// Every camera's recording (without the calibration applied).
    pub recs: Vec<Recording>,
    /// The board map's grid and identity.
    pub layout: MapLayout,
}

/// Opens the array board recording `dir` with its cameras' recordings, checks it against `cal`
/// and lays out its board grid.
pub(crate) fn open(dir: &Path, cal: &CalFile) -> Result<Opened> {
    let layout = map::layout(dir, cal)?;
    let arr = ArrayRecording::open(dir)?;
    let recs: Vec<Recording> = (0..arr.manifest.cameras.len())
        .map(|i| {
            let d = arr.camera_dir(i, None);
            Recording::open(&d).at(|| format!("camera {i}: {}", d.display()))
        })
        .collect::<Result<_>>()?;
    crate::array::record::check_camera_ids(&recs, &arr.dir)?;
    arr.board_id(&recs)?;
    Ok(Opened { arr, recs, layout })
}

/// [`map::check_latch_steps`] on a recording's manifest.
fn check_recording_steps(rec: &Recording, cal: &CalFile, i: usize) -> Result<()> {
    let t: Vec<dpsa_core::Trigger> = rec.manifest.frames.iter().map(|f| f.trigger()).collect();
    map::check_latch_steps(
        &t,
        cal.processing.max_step_rows,
        &cal.camera[i],
        i,
        &rec.dir.join(crate::simulation::recording::MANIFEST_FILE),
    )?;
    Ok(())
}

/// Builds the board map of the array recording `dir` with `cal` into `out`, the core on
/// every camera.
pub fn run(dir: &Path, cal: &CalFile, out: &Path) -> Result<BoardReport> {
    run_from(dir, cal, out, Source::Core)
}

/// Builds the board map of the array recording `dir` with `cal` into `out`, the rows from
/// `source`. Every check (recording, calibration, streams) comes before any file is written.
pub fn run_from(dir: &Path, cal: &CalFile, out: &Path, source: Source<'_>) -> Result<BoardReport> {
    run_shown(dir, cal, out, source, &Options::default())
}

/// How [`run_shown`] runs besides its inputs.
#[derive(Clone, Copy, Debug)]
pub struct Options {
    /// Progress bars on stderr.
    pub progress: bool,
    /// What to write besides the cheap default files.
    pub outputs: dpsa_board::output::Outputs,
    /// Compare the map with the recording's board truth when it has one (the simulator's
    /// check; about 35 s on the paper board). `false`: `truth` is null.
    pub truth: bool,
    /// The paste's reflectance taken out of the walls (the program's; the default: none).
    pub paste: dpsa_board::places::PasteReflectance,
}

impl Default for Options {
    fn default() -> Self {
        Options {
            progress: false,
            outputs: Default::default(),
            truth: true,
            paste: Default::default(),
        }
    }
}

/// The rows of every camera from the core on its calibrated recording (threads).
fn rows_from_core(
    recs: &[Recording],
    cal: &CalFile,
    progress: bool,
) -> Result<Vec<(CameraRows, u64)>> {
    for (i, r) in recs.iter().enumerate() {
        check_recording_steps(r, cal, i)?;
    }
    let bar = crate::progress::progress_bar(progress, 0, "board core");
    let bar = &bar;
    let cams = std::thread::scope(|s| {
        let handles: Vec<_> = recs
            .iter()
            .enumerate()
            .map(|(i, r)| {
                s.spawn(move || {
                    let c = &cal.camera[i];
                    let r = calibrated(r, cal, i)?;
                    let prov = super::provenance::of_recording(&r);
                    let mut crb = crb_of(&r, c.height_per_turn_um.clone(), c.id);
                    let rows = core_rows_counted(&r, cal, i, bar)?;
                    Ok(rows.finish(&prov, &mut crb, c, cal.processing.max_step_rows, &[])?)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(SimError::Internal("a core thread panicked".into())))
            })
            .collect::<Result<Vec<_>>>()
    })?;
    bar.finish_and_clear();
    Ok(cams)
}

/// The blended map of `built` against the simulated board's truth, when the recording has one
/// (`with_crb`: every camera had its per-pixel Cramer-Rao bound).
fn against_board_truth(
    arr: &ArrayRecording,
    cal: &CalFile,
    built: &Built,
    grid: &dpsa_board::BoardGrid,
    with_crb: bool,
    progress: bool,
) -> Result<Option<MapAccuracy>> {
    Ok(match arr.truth()? {
        Some(t) => match t.board {
            Some(b) => {
                let path = arr.dir.join(&b.file);
                let data = crate::simulation::recording::read_f32(
                    &path,
                    b.rows as usize * b.cols as usize,
                )?;
                let raster = BoardTruth {
                    x0_mm: 0.0,
                    y0_mm: 0.0,
                    pitch_mm: b.pitch_mm,
                    heights: Grid {
                        width: b.cols as usize,
                        rows: b.rows as usize,
                        data,
                    },
                };
                let t_mean = cal
                    .camera
                    .iter()
                    .map(|c| c.core_height_per_turn_um())
                    .sum::<f64>()
                    / cal.camera.len().max(1) as f64;
                let rows_done =
                    crate::progress::progress_bar(progress, grid.rows as u64, "board truth");
                let st = against_truth(
                    &built.blended.heights,
                    built.blended.variance.as_ref().filter(|_| with_crb),
                    |_, _| t_mean as f32,
                    grid,
                    &raster,
                    &rows_done,
                );
                rows_done.finish_and_clear();
                Some(st)
            }
            None => None,
        },
        None => None,
    })
}

/// Every camera's recording directory is there (`camI/manifest.json`).
fn camera_recordings_present(arr: &ArrayRecording) -> bool {
    (0..arr.manifest.cameras.len()).all(|i| {
        arr.camera_dir(i, None)
            .join(crate::simulation::recording::MANIFEST_FILE)
            .is_file()
    })
}

/// [`run_from`] with [`Options`]: progress bars on stderr (the core's rows over every camera,
/// then the assembly's steps), the outputs, the comparison with the truth.
pub fn run_shown(
    dir: &Path,
    cal: &CalFile,
    out: &Path,
    source: Source<'_>,
    opts: &Options,
) -> Result<BoardReport> {
    let Options {
        progress,
        outputs,
        truth: compare,
        paste,
    } = *opts;
    let started = Instant::now();
    if let Source::Streams(paths) = source {
        let arr = ArrayRecording::open(dir)?;
        if !camera_recordings_present(&arr) {
            // The streams alone, as the production build runs them: no camera recording, so
            // no Cramer-Rao bound; the board truth (`truth/array.json`) is still compared.
            let built = map::from_streams(dir, cal, paths, out, progress, outputs, paste)?;
            let t2 = Instant::now();
            let truth = if compare {
                against_board_truth(&arr, cal, &built, &built.report.grid, false, progress)?
            } else {
                None
            };
            return Ok(BoardReport {
                map: built.report,
                truth,
                truth_s: t2.elapsed().as_secs_f64(),
            });
        }
    }
    let Opened { arr, recs, layout } = open(dir, cal)?;
    let open_s = started.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let (cams, streams) = match source {
        Source::Core => (rows_from_core(&recs, cal, progress)?, None),
        Source::Streams(paths) => {
            // The recordings only for the simulator's truth (the Cramer-Rao bound); the rows,
            // their masks and places are the streams' alone.
            let calibrated: Vec<Recording> = recs
                .iter()
                .enumerate()
                .map(|(i, r)| calibrated(r, cal, i))
                .collect::<Result<_>>()?;
            let (cams, report) = map::rows_from_streams(
                paths,
                cal,
                &layout,
                &arr.dir.join(crate::array::record::ARRAY_FILE),
                &mut |i| {
                    let c = &cal.camera[i];
                    Box::new(crb_of(&calibrated[i], c.height_per_turn_um.clone(), c.id))
                },
            )?;
            (cams, Some(report))
        }
    };
    let rows_s = t0.elapsed().as_secs_f64();
    let with_crb = cams.iter().all(|(c, _)| c.variance.is_some());
    let built = map::build(
        cams,
        Inputs {
            layout: &layout,
            streams,
            started,
            open_s,
            rows_s,
            progress,
            outputs,
            paste,
        },
        out,
    )?;
    let t2 = Instant::now();
    let truth = if compare {
        against_board_truth(&arr, cal, &built, &layout.grid, with_crb, progress)?
    } else {
        None
    };
    let truth_s = t2.elapsed().as_secs_f64();
    let Built { report, .. } = built;
    Ok(BoardReport {
        map: report,
        truth,
        truth_s,
    })
}
