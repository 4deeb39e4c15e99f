//! `dpsa board`: an array recording and its calibration into one board map.
//!
//! Per camera (one thread each): the calibration goes into the camera recording's manifest
//! (`CameraCal::apply`), the fixed-point core runs on it (the rows exactly as its packets carry
//! them; the calibration's per-column height per turn `T_z(c)` is part of the core's
//! configuration, so its heights are already in calibrated LSB in every column, as a frame
//! grabber's packets carry them), and its board rows are placed with the lateral calibration.
//! Or (`--streams`, [`Source::Streams`]) the rows come from the cameras' packet streams
//! ([`super::streams`]) and go through the same steps. [`super::provenance`] masks the pixels
//! fed by dead image pixels, gives each row's Cramer-Rao bound and where it was seen. Then
//! [`super::assemble`] unwraps, resamples and blends, and [`super::output`] writes the files.
//!
//! Placement of a core board row `b` (`docs/calibration.md`): its window's first frame saw it
//! at image row `r_w = H - (max_step_rows + 1) / 2`, so column `c` lies at
//! `X = x0 + (p / cos a) b - p sin a (c + r_w tan a)`, `Y = y0 + p (c cos a + r_w sin a)`.

use super::assemble::{assemble, CameraRows, Timing};
use super::provenance::Provenance;
use super::resample::{BoardGrid, CameraPlacement};
use super::streams::{self, StreamsReport};
use super::truth::{against_truth, TruthRaster, TruthStats};
use super::Grid;
use crate::array::record::{ArrayRecording, Kind};
use crate::calibration::file::{CalFile, CameraCal};
use crate::heightmap::HeightRow;
use crate::simulation::recording::Recording;
use anyhow::{bail, Context, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Where the cameras' rows come from.
#[derive(Clone, Copy, Debug)]
pub enum Source<'a> {
    /// The fixed-point core on every camera's recording with its calibration (threads): the
    /// same rows as each camera's firmware emits.
    Core,
    /// The cameras' packet streams, one per camera, in any order ([`super::streams`]).
    Streams(&'a [PathBuf]),
}

/// `dpsa board --json`.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub cameras: usize,
    /// The evidence that the map is wrong or useless (empty when none), one sentence each:
    /// `dpsa board` prints each as `warning: ...` and exits with status 2.
    pub warnings: Vec<String>,
    pub grid: BoardGrid,
    pub seams: Seams,
    pub pixels: PixelCounts,
    /// Against the simulator's board truth (null without it).
    pub truth: Option<TruthStats>,
    pub unwrap: UnwrapStats,
    pub timing: RunTiming,
    /// `--streams`: what each camera's stream held and lost.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub streams: Option<StreamsReport>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Seams {
    /// Largest |mean height difference| between neighbouring cameras over their shared flat
    /// valid pixels, um.
    pub height_step_um_max: Option<f64>,
    /// Largest misregistration between neighbouring cameras in their overlap, um.
    pub lateral_um_max: Option<f64>,
    pub per_seam: Vec<super::blend::Seam>,
}

#[derive(Clone, Debug, Serialize)]
pub struct PixelCounts {
    pub total: u64,
    pub valid: u64,
    pub valid_fraction: f64,
    /// Camera pixels masked because a dead or weak image pixel of the calibration fed them,
    /// per camera (before resampling).
    pub dead_masked: Vec<u64>,
    /// Valid rows whose window the registration replay on the trigger log did not confirm (a
    /// lost trigger record), per camera: without it their dead-pixel mask and place are
    /// unknown, so they are left invalid ([`super::provenance::Provenance::confirms`]).
    pub unplaced_rows: Vec<u64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct UnwrapStats {
    /// Valid pixels whose absolute height is off by half a turn or more (truth only).
    pub wrong_turn_pixels: Option<u64>,
    /// Whole turns each camera was moved by.
    pub turns: Vec<i32>,
    /// Median height of the board edge before the board's turn was chosen, um.
    pub edge_median_um: Option<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct RunTiming {
    /// The rows: the fixed-point core on every camera (threads), or decoding and checking the
    /// streams, s.
    pub core_s: f64,
    #[serde(flatten)]
    pub assemble: Timing,
    /// Writing the files, s.
    pub write_s: f64,
    /// Opening and checking the recording (before the core), s.
    pub open_s: f64,
    /// The comparison with the simulator's truth (0 without it), s.
    pub truth_s: f64,
    /// The whole run, s: the sum of the steps above and what lies between them.
    pub total_s: f64,
}

impl Report {
    /// A few lines for the terminal.
    pub fn summary(&self) -> String {
        let opt = |x: Option<f64>| x.map_or_else(|| "n/a".to_string(), |v| format!("{v:.3}"));
        let mut s = format!(
            "board map {} x {} px at {} mm, {} cameras: {:.2} % valid ({} camera px masked for dead image pixels)\n",
            self.grid.rows,
            self.grid.width,
            self.grid.pitch_mm,
            self.cameras,
            100.0 * self.pixels.valid_fraction,
            self.pixels.dead_masked.iter().sum::<u64>()
        );
        s += &format!(
            "seams: height step max {} um, misregistration max {} um; turns per camera {:?}\n",
            opt(self.seams.height_step_um_max),
            opt(self.seams.lateral_um_max),
            self.unwrap.turns
        );
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
        s += &format!(
            "time: open {:.2} s, core {:.2} s, unwrap {:.2} s, resample {:.2} s, blend {:.2} s, write {:.2} s, truth {:.2} s; total {:.2} s",
            self.timing.open_s,
            self.timing.core_s,
            self.timing.assemble.unwrap_s,
            self.timing.assemble.resample_s,
            self.timing.assemble.blend_s,
            self.timing.write_s,
            self.timing.truth_s,
            self.timing.total_s
        );
        s
    }
}

/// The board row's image row in its window's first frame (see the module docs).
fn entry_row(cal: &CameraCal, max_step_rows: u32) -> f64 {
    f64::from(cal.rows) - f64::from(max_step_rows + 1) / 2.0
}

/// A camera's [`CameraPlacement`] from its lateral calibration.
pub fn placement(cal: &CameraCal, max_step_rows: u32) -> CameraPlacement {
    let l = &cal.lateral;
    let (s, c) = l.rotation_rad.sin_cos();
    let r_w = entry_row(cal, max_step_rows);
    CameraPlacement {
        x0_mm: l.x0_mm - l.pitch_mm * s * r_w * s / c,
        y0_mm: l.y0_mm + l.pitch_mm * r_w * s,
        row_mm: l.pitch_mm / c,
        pitch_mm: l.pitch_mm,
        rotation_rad: -l.rotation_rad,
    }
}

/// A camera's rows on their way to the board, whatever their source: wrapped heights in um
/// by board row.
pub(crate) struct Collector {
    id: u8,
    pub(crate) width: usize,
    lsb_um: f32,
    pub(crate) rows: Vec<(i64, Vec<f32>)>,
    /// Per row of `rows`: the window's first latch when the row is valid (to be confirmed by
    /// the registration replay), `None` for an invalid row.
    latches: Vec<Option<i64>>,
}

impl Collector {
    fn new(cal: &CameraCal, lsb_um: f64) -> Collector {
        let width = cal.width as usize;
        Collector {
            id: cal.id,
            width,
            lsb_um: lsb_um as f32,
            rows: Vec::new(),
            latches: Vec::new(),
        }
    }

    /// One row as the core emitted it (the same bytes as its packet, from the core or from a
    /// stream): LSB to um (the core applied the per-column height per turn).
    fn push(&mut self, r: &HeightRow) {
        let h = (0..self.width)
            .map(|c| match r.heights.get(c) {
                Some(&v) if r.pixel_valid(c) => f32::from(v) * self.lsb_um,
                _ => f32::NAN,
            })
            .collect();
        self.rows.push((r.row, h));
        self.latches.push(r.is_valid().then_some(r.latch));
    }

    /// The rows (sorted by board row) as a grid from the first to the last row, with the
    /// `lost` board rows (inclusive ranges) inside it marked; returns it and the valid rows
    /// `prov` did not confirm (left invalid, marked lost).
    /// `prov` is the registration of the camera's frames (which frames fed each row, see
    /// [`super::provenance`]); `truth`: the camera's calibrated recording, to compute each
    /// pixel's Cramer-Rao bound when it has a truth and a noise model.
    pub(crate) fn finish(
        mut self,
        prov: &Provenance,
        truth: Option<&Recording>,
        cal: &CameraCal,
        max_step: u32,
        lost: &[(i64, i64)],
    ) -> Result<(CameraRows, u64)> {
        // A valid row whose window the replay does not confirm: its mask and place are
        // unknown, so it is not used (lost, never interpolated across).
        let mut lost = lost.to_vec();
        let mut unplaced = 0u64;
        for ((b, h), latch) in self.rows.iter_mut().zip(&self.latches) {
            if let Some(l) = *latch {
                if !prov.confirms(*b, l) {
                    h.fill(f32::NAN);
                    lost.push((*b, *b));
                    unplaced += 1;
                }
            }
        }
        let lost = &lost[..];
        let w = self.width;
        let ends = self
            .rows
            .first()
            .map(|r| (r.0, self.rows.last().map_or(r.0, |l| l.0)));
        let (first, last) = lost
            .iter()
            .fold(ends, |e, &(a, b)| {
                Some(e.map_or((a, b), |(f, l)| (f.min(a), l.max(b))))
            })
            .filter(|_| !self.rows.is_empty())
            .ok_or_else(|| anyhow::anyhow!("camera {}: no rows arrived", self.id))?;
        let lost_rows: i128 = lost
            .iter()
            .map(|&(a, b)| i128::from(b) - i128::from(a) + 1)
            .sum();
        let span = i128::from(last) - i128::from(first) + 1;
        if span > self.rows.len() as i128 + lost_rows + (1 << 16) {
            bail!(
                "camera {}: its rows span {span} board rows but only {} are present (an encoder fault?)",
                self.id,
                self.rows.len()
            );
        }
        let span = span as usize;
        let mut g = Grid::invalid(w, span);
        for (b, h) in self.rows {
            let i = (b - first) as usize;
            g.data[i * w..(i + 1) * w].copy_from_slice(&h);
        }
        let mut mask = Vec::new();
        if !lost.is_empty() {
            mask = vec![false; span];
            for &(a, b) in lost {
                mask[(a - first) as usize..=(b - first) as usize].fill(true);
            }
        }
        let dead_masked =
            super::provenance::mask_dead_pixels(prov, &cal.dead_pixels, first, &mut g);
        let variance = match truth {
            Some(rec) => {
                super::provenance::crb_variance(rec, prov, &cal.height_per_turn_um, first, &g)
                    .with_context(|| format!("camera {}", cal.id))?
            }
            None => None,
        };
        let places = super::provenance::row_places(
            prov,
            first,
            g.rows,
            entry_row(cal, max_step),
            cal.lateral.rotation_rad,
        );
        Ok((
            CameraRows {
                heights: g,
                variance,
                dead_masked,
                places: Some(places),
                first_row: first,
                period_um: cal.height_per_turn_um.iter().map(|&t| t as f32).collect(),
                placement: placement(cal, max_step),
                lost: mask,
            },
            unplaced,
        ))
    }
}

/// A camera's recording with its calibration applied (what its frame grabber runs with).
pub(crate) fn calibrated(rec: &Recording, cal: &CameraCal, lsb_um: f64) -> Result<Recording> {
    let mut rec = rec.clone();
    cal.apply(&mut rec.manifest, lsb_um)?;
    Ok(rec)
}

/// Row source 1: the core on one camera's calibrated recording.
pub(crate) fn core_rows(rec: &Recording, cal: &CameraCal, lsb_um: f64) -> Result<Collector> {
    core_rows_counted(rec, cal, lsb_um, &indicatif::ProgressBar::hidden())
}

/// [`core_rows`], counting every row on `bar` (its length grows by the camera's planned rows).
fn core_rows_counted(
    rec: &Recording,
    cal: &CameraCal,
    lsb_um: f64,
    bar: &indicatif::ProgressBar,
) -> Result<Collector> {
    bar.inc_length(crate::reference::plan(&rec.manifest).len() as u64);
    let mut rows = Collector::new(cal, lsb_um);
    crate::reconstruct::reconstruct_rows(rec, false, |r| {
        rows.push(&r);
        bar.inc(1);
        Ok(())
    })?;
    Ok(rows)
}

/// An array board recording opened and checked against its calibration.
pub(crate) struct Opened {
    pub arr: ArrayRecording,
    /// Every camera's recording (without the calibration applied).
    pub recs: Vec<Recording>,
    /// The board identity every camera's stream carries.
    pub board: Option<crate::simulation::recording::BoardId>,
    pub grid: BoardGrid,
}

/// Opens the array board recording `dir`, checks it against `cal` and lays out its board grid.
pub(crate) fn open(dir: &Path, cal: &CalFile) -> Result<Opened> {
    let arr = ArrayRecording::open(dir)?;
    if arr.manifest.kind != Kind::Board {
        bail!(
            "{} is a calibration recording; dpsa board takes a board recording",
            dir.display()
        );
    }
    let dims: Vec<(u32, u32)> = arr
        .manifest
        .cameras
        .iter()
        .map(|c| (c.width, c.rows))
        .collect();
    cal.check_array(&dims)?;
    cal.check_design(&arr.manifest)
        .with_context(|| format!("{} and its calibration", dir.display()))?;
    let recs: Vec<Recording> = (0..dims.len())
        .map(|i| {
            let d = arr.camera_dir(i, None);
            Recording::open(&d).with_context(|| format!("camera {i}: {}", d.display()))
        })
        .collect::<Result<_>>()?;
    crate::array::record::check_camera_ids(&recs, &arr.dir)?;
    let board = arr.board_id(&recs)?;

    let m = &arr.manifest;
    let pitch = m.pixel_mm;
    let grid = BoardGrid {
        x0_mm: 0.0,
        y0_mm: 0.0,
        pitch_mm: pitch,
        rows: (m.board_length_mm / pitch).ceil() as usize,
        width: (m.board_width_mm / pitch).ceil() as usize,
    };
    if grid.rows.saturating_mul(grid.width) > 1 << 28 {
        bail!(
            "a {} x {} px board map is more than this tool holds (2^28 px)",
            grid.rows,
            grid.width
        );
    }
    Ok(Opened {
        arr,
        recs,
        board,
        grid,
    })
}

/// Refuses a camera's frames (triggers `f`, from `source`: a manifest or a stream's trigger
/// log) that advance further per frame than its core can take: the median latch step divided
/// by the calibration's `counts_per_pixel` (board rows per frame) above `max_step_rows`. The
/// simulator sets `max_step_rows` to 1.25 times the nominal step, so a good recording's median
/// step is about 0.8 of it; latches doubled (or a calibration of another encoder scale) give
/// 1.6.
fn check_latch_steps(
    f: &[dpsa_core::Trigger],
    max: u32,
    cal: &CameraCal,
    i: usize,
    source: &Path,
) -> Result<()> {
    if f.len() < 3 {
        return Ok(());
    }
    let mut steps: Vec<i64> = f
        .windows(2)
        .map(|w| w[1].latch.saturating_sub(w[0].latch))
        .collect();
    steps.sort_unstable();
    let median = steps[steps.len() / 2] as f64 / cal.counts_per_pixel;
    if median > f64::from(max) {
        bail!(
            "camera {i}: its frames advance a median {median:.1} board rows each (latch steps of {} counts over the calibration's counts_per_pixel {}), more than the {max} rows (processing.max_step_rows) its core takes: the latches of {} are scaled wrong (doubled?) or the calibration is of another encoder",
            steps[steps.len() / 2],
            cal.counts_per_pixel,
            source.display()
        );
    }
    Ok(())
}

/// [`check_latch_steps`] on a recording's manifest.
fn check_recording_steps(rec: &Recording, cal: &CameraCal, i: usize) -> Result<()> {
    let t: Vec<dpsa_core::Trigger> = rec.manifest.frames.iter().map(|f| f.trigger()).collect();
    check_latch_steps(
        &t,
        rec.manifest.processing.max_step_rows,
        cal,
        i,
        &rec.dir.join(crate::simulation::recording::MANIFEST_FILE),
    )
}

/// A camera that contributes less than this fraction of an equal share (valid map pixels /
/// cameras) to the map, or whose own rows are less than [`MIN_CAMERA_VALID`] valid, is
/// reported (exit status 2). The small scene's cameras give 0.9 to 1.2 of an equal share and
/// 97 % valid rows (`docs/board.md`).
pub const MIN_CAMERA_SHARE: f64 = 0.25;
/// See [`MIN_CAMERA_SHARE`].
pub const MIN_CAMERA_VALID: f64 = 0.5;
/// A map less valid than this is reported (the shipped scenes' maps are 97 % valid or more).
pub const MIN_MAP_VALID: f64 = 0.5;
/// Seams this many times over their acceptance budgets (0.3 um height step, 5 um
/// misregistration, `docs/board.md`) are reported: 3 um and 50 um. The shipped scenes meet
/// them with 0.07 um and 1.7 um at most.
pub const SEAM_ALARM: f64 = 10.0;
/// The seams' acceptance budgets, um: height step, misregistration.
pub const SEAM_BUDGET_UM: (f64, f64) = (0.3, 5.0);

/// The evidence that a written map is wrong or useless, one sentence each (printed as
/// `warning: ...`, exit status 2).
fn evidence(cams: &[CameraRows], b: &super::blend::Blended, seams: &Seams) -> Vec<String> {
    let mut w = Vec::new();
    let total = b.heights.data.len().max(1) as f64;
    let valid = b.heights.valid();
    if (valid as f64) < MIN_MAP_VALID * total {
        w.push(format!(
            "the board map is {:.1} % valid ({valid} of {} px), less than {} %: check pixel_mm and the board size in array.json and the calibration",
            100.0 * valid as f64 / total,
            b.heights.data.len(),
            MIN_MAP_VALID * 100.0
        ));
    }
    let share = valid as f64 / cams.len().max(1) as f64;
    for (i, c) in cams.iter().enumerate() {
        let own = c.heights.valid() as f64 / c.heights.data.len().max(1) as f64;
        let src = b.camera.iter().filter(|&&k| usize::from(k) == i).count();
        if own < MIN_CAMERA_VALID {
            w.push(format!(
                "camera {i} contributes almost nothing: {:.1} % of its own pixels are valid (less than {} %): check its calibration (fringe period, height per turn) and its frames",
                own * 100.0,
                MIN_CAMERA_VALID * 100.0
            ));
        } else if (src as f64) < MIN_CAMERA_SHARE * share {
            w.push(format!(
                "camera {i} contributes almost nothing: {src} map px, less than {} % of an equal share ({share:.0} px): check its lateral calibration",
                MIN_CAMERA_SHARE * 100.0
            ));
        }
    }
    if let Some(h) = seams
        .height_step_um_max
        .filter(|&h| h > SEAM_ALARM * SEAM_BUDGET_UM.0)
    {
        w.push(format!(
            "the cameras' heights differ by up to {h:.2} um at a seam, more than {} times the 0.3 um budget: a camera's calibration is wrong or belongs to another camera",
            SEAM_ALARM
        ));
    }
    if let Some(l) = seams
        .lateral_um_max
        .filter(|&l| l > SEAM_ALARM * SEAM_BUDGET_UM.1)
    {
        w.push(format!(
            "the cameras are misregistered by up to {l:.1} um at a seam, more than {} times the 5 um budget: a camera's lateral calibration is wrong or belongs to another camera",
            SEAM_ALARM
        ));
    }
    w
}

/// Builds the board map of the array recording `dir` with `cal` into `out`, the core on
/// every camera.
pub fn run(dir: &Path, cal: &CalFile, out: &Path) -> Result<Report> {
    run_from(dir, cal, out, Source::Core)
}

/// Builds the board map of the array recording `dir` with `cal` into `out`, the rows from
/// `source`. Every check (recording, calibration, streams) comes before any file is written.
pub fn run_from(dir: &Path, cal: &CalFile, out: &Path, source: Source<'_>) -> Result<Report> {
    run_shown(dir, cal, out, source, false)
}

/// [`run_from`] with progress bars on stderr when `progress` (the core's rows over every
/// camera, then the assembly's steps).
pub fn run_shown(
    dir: &Path,
    cal: &CalFile,
    out: &Path,
    source: Source<'_>,
    progress: bool,
) -> Result<Report> {
    let t_open = Instant::now();
    let Opened {
        arr,
        recs,
        board,
        grid,
    } = open(dir, cal)?;

    let open_s = t_open.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let (cams, mut streams_report) = match source {
        Source::Core => {
            for ((r, c), i) in recs.iter().zip(&cal.camera).zip(0..) {
                check_recording_steps(r, c, i)?;
            }
            let bar = crate::progress::progress_bar(progress, 0, "board core");
            let bar = &bar;
            let cams: Vec<(CameraRows, u64)> = std::thread::scope(|s| {
                let handles: Vec<_> = recs
                    .iter()
                    .zip(&cal.camera)
                    .map(|(r, c)| {
                        s.spawn(move || {
                            let max_step = r.manifest.processing.max_step_rows;
                            let r = calibrated(r, c, cal.height_lsb_um)?;
                            let prov = super::provenance::of_recording(&r);
                            core_rows_counted(&r, c, cal.height_lsb_um, bar)?.finish(
                                &prov,
                                Some(&r),
                                c,
                                max_step,
                                &[],
                            )
                        })
                    })
                    .collect();
                handles
                    .into_iter()
                    .map(|h| {
                        h.join().unwrap_or_else(|_| {
                            Err(anyhow::anyhow!("internal error: a core thread panicked"))
                        })
                    })
                    .collect::<Result<Vec<_>>>()
            })?;
            bar.finish_and_clear();
            (cams, None)
        }
        Source::Streams(paths) => {
            let extents: Vec<(i64, i64)> = recs
                .iter()
                .zip(&cal.camera)
                .map(|(r, c)| {
                    let p = placement(c, r.manifest.processing.max_step_rows);
                    streams::board_extent(&p, &grid, c.width)
                })
                .collect();
            let (arrived, report) = streams::read_streams(paths, cal, &recs, board, dir, &extents)?;
            let cams = arrived
                .into_iter()
                .zip(recs.iter().zip(&cal.camera))
                .enumerate()
                .map(|(i, (a, (r, c)))| {
                    // Where each row came from: the registration replayed on the stream's
                    // own trigger log, not on the recording's frames.
                    check_latch_steps(&a.triggers, a.registration.max_step_rows, c, i, &a.path)?;
                    let prov = Provenance::replay(&a.triggers, &a.registration);
                    let mut rows = Collector::new(c, cal.height_lsb_um);
                    for row in &a.map.rows {
                        rows.push(row);
                    }
                    // The recording only for the simulator's truth (the Cramer-Rao bound).
                    let r = calibrated(r, c, cal.height_lsb_um)?;
                    rows.finish(&prov, Some(&r), c, a.registration.max_step_rows, &a.lost)
                })
                .collect::<Result<Vec<_>>>()?;
            (cams, Some(report))
        }
    };
    let (cams, unplaced): (Vec<CameraRows>, Vec<u64>) = cams.into_iter().unzip();
    let core_s = t0.elapsed().as_secs_f64();

    // The steps after the core, one bar position each; the truth comparison has its own bar.
    let steps = crate::progress::progress_bar(progress, 2, "board map");
    let a = assemble(&cams, &grid);
    steps.inc(1);
    if let Some(r) = &mut streams_report {
        r.gap_board_pixels = a.lost_pixels;
    }
    let missing: Vec<u64> = match &streams_report {
        Some(r) => r.missing_rows.clone(),
        None => vec![0; cams.len()],
    };
    let t1 = Instant::now();
    super::output::write(out, &grid, &a.blended, cams.len(), &missing, board)?;
    let write_s = t1.elapsed().as_secs_f64();
    steps.finish_and_clear();

    let t2 = Instant::now();
    let truth = match arr.truth()? {
        Some(t) => match t.board {
            Some(b) => {
                let path = arr.dir.join(&b.file);
                let data = crate::simulation::recording::read_f32(
                    &path,
                    b.rows as usize * b.cols as usize,
                )?;
                let raster = TruthRaster {
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
                let with_crb = cams.iter().all(|c| c.variance.is_some());
                let rows_done =
                    crate::progress::progress_bar(progress, grid.rows as u64, "board truth");
                let st = against_truth(
                    &a.blended.heights,
                    with_crb.then_some(&a.blended.variance),
                    |_, _| t_mean as f32,
                    &grid,
                    &raster,
                    &rows_done,
                );
                rows_done.finish_and_clear();
                Some(st)
            }
            None => None,
        },
        None => None,
    };
    let truth_s = t2.elapsed().as_secs_f64();

    let b = &a.blended;
    let valid = b.heights.valid() as u64;
    let total = b.heights.data.len() as u64;
    let fold = |f: fn(&super::blend::Seam) -> Option<f64>| {
        b.seams
            .iter()
            .filter_map(f)
            .map(f64::abs)
            .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))))
    };
    let seams = Seams {
        height_step_um_max: fold(|s| s.height_step_um),
        lateral_um_max: fold(|s| s.lateral_um()),
        per_seam: b.seams.clone(),
    };
    let warnings = evidence(&cams, b, &seams);
    Ok(Report {
        cameras: cams.len(),
        warnings,
        grid,
        seams,
        pixels: PixelCounts {
            total,
            valid,
            valid_fraction: if total > 0 {
                valid as f64 / total as f64
            } else {
                0.0
            },
            dead_masked: cams.iter().map(|c| c.dead_masked).collect(),
            unplaced_rows: unplaced,
        },
        unwrap: UnwrapStats {
            wrong_turn_pixels: truth.as_ref().map(|t| t.wrong_turn_pixels),
            turns: b.turns.clone(),
            edge_median_um: b.edge_median_um,
        },
        truth,
        timing: RunTiming {
            core_s,
            assemble: a.timing,
            write_s,
            open_s,
            truth_s,
            total_s: t_open.elapsed().as_secs_f64(),
        },
        streams: streams_report,
    })
}
