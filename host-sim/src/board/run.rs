//! `dpsa board`: an array recording and its calibration into one board map.
//!
//! Per camera (one thread each): the calibration goes into the camera recording's manifest
//! (`CameraCal::apply`), the fixed-point core runs on it (the rows exactly as its packets carry
//! them; the calibration's per-column height per turn `T_z(c)` is part of the core's
//! configuration, so its heights are already in calibrated LSB in every column, as a frame
//! grabber's packets carry them), and its board rows are placed with the lateral calibration. Then [`super::assemble`] unwraps, resamples and blends, and
//! [`super::output`] writes the files.
//!
//! Placement of a core board row `b` (`docs/calibration.md`): its window's first frame saw it
//! at image row `r_w = H - (max_step_rows + 1) / 2`, so column `c` lies at
//! `X = x0 + (p / cos a) b - p sin a (c + r_w tan a)`, `Y = y0 + p (c cos a + r_w sin a)`.

use super::assemble::{against_truth, assemble, CameraRows, Timing, TruthRaster, TruthStats};
use super::resample::{BoardGrid, Placement};
use super::Grid;
use crate::array::record::{ArrayRecording, Kind};
use crate::calibration::file::{CalFile, CameraCal};
use crate::simulation::recording::Recording;
use anyhow::{bail, Context, Result};
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

/// `dpsa board --json`.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub cameras: usize,
    pub grid: BoardGrid,
    pub seams: Seams,
    pub pixels: PixelCounts,
    /// Against the simulator's board truth (null without it).
    pub truth: Option<TruthStats>,
    pub unwrap: UnwrapStats,
    pub timing: RunTiming,
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
    /// The fixed-point core on every camera (threads), s.
    pub core_s: f64,
    #[serde(flatten)]
    pub assemble: Timing,
    /// Writing the files, s.
    pub write_s: f64,
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
            s += &format!(
                "truth: rms {} um (bias {}), Cramer-Rao bound {} um (ratio {}) over {} flat px, {} wrong-turn px\n",
                opt(t.rms_um),
                opt(t.bias_um),
                opt(t.crb_rms_um),
                opt(t.over_crb),
                t.flat_pixels,
                t.wrong_turn_pixels
            );
        }
        s += &format!(
            "time: core {:.2} s, unwrap {:.2} s, resample {:.2} s, blend {:.2} s, write {:.2} s",
            self.timing.core_s,
            self.timing.assemble.unwrap_s,
            self.timing.assemble.resample_s,
            self.timing.assemble.blend_s,
            self.timing.write_s
        );
        s
    }
}

/// The board row's image row in its window's first frame (see the module docs).
fn entry_row(cal: &CameraCal, max_step_rows: u32) -> f64 {
    f64::from(cal.rows) - f64::from(max_step_rows + 1) / 2.0
}

/// A camera's [`Placement`] from its lateral calibration.
pub fn placement(cal: &CameraCal, max_step_rows: u32) -> Placement {
    let l = &cal.lateral;
    let (s, c) = l.rotation_rad.sin_cos();
    let r_w = entry_row(cal, max_step_rows);
    Placement {
        x0_mm: l.x0_mm - l.pitch_mm * s * r_w * s / c,
        y0_mm: l.y0_mm + l.pitch_mm * r_w * s,
        row_mm: l.pitch_mm / c,
        pitch_mm: l.pitch_mm,
        rotation_rad: -l.rotation_rad,
    }
}

/// Runs the core on one camera with its calibration; returns the wrapped heights in um.
fn camera_rows(rec: &Recording, cal: &CameraCal, lsb_um: f64) -> Result<CameraRows> {
    let mut rec = rec.clone();
    cal.apply(&mut rec.manifest, lsb_um)?;
    let w = rec.manifest.camera.width as usize;
    let max_step = rec.manifest.processing.max_step_rows;
    let mut rows: Vec<(i64, Vec<f32>)> = Vec::new();
    crate::reconstruct::reconstruct_rows(&rec, false, |r| {
        let h = (0..w)
            .map(|c| {
                if r.pixel_valid(c) {
                    f32::from(r.heights[c]) * lsb_um as f32
                } else {
                    f32::NAN
                }
            })
            .collect();
        rows.push((r.row, h));
        Ok(())
    })?;
    let (Some(first), Some(last)) = (rows.first().map(|r| r.0), rows.last().map(|r| r.0)) else {
        bail!("camera {}: the core produced no rows", cal.id);
    };
    let span = usize::try_from(last - first + 1).unwrap_or(usize::MAX);
    if span > rows.len() + (1 << 16) {
        bail!(
            "camera {}: its rows span {span} board rows but only {} are present (an encoder fault?)",
            cal.id,
            rows.len()
        );
    }
    let mut g = Grid::invalid(w, span);
    for (b, h) in rows {
        let i = (b - first) as usize;
        g.data[i * w..(i + 1) * w].copy_from_slice(&h);
    }
    let dead_masked = super::provenance::mask_dead_pixels(&rec, &cal.dead_pixels, first, &mut g);
    let variance = super::provenance::crb_variance(&rec, &cal.height_per_turn_um, first, &g)
        .with_context(|| format!("camera {}", cal.id))?;
    let places = super::provenance::row_places(
        &rec,
        first,
        g.rows,
        entry_row(cal, max_step),
        cal.lateral.rotation_rad,
    );
    Ok(CameraRows {
        heights: g,
        variance,
        dead_masked,
        places: Some(places),
        first_row: first,
        period_um: cal.height_per_turn_um.iter().map(|&t| t as f32).collect(),
        placement: placement(cal, max_step),
    })
}

/// Builds the board map of the array recording `dir` with `cal` into `out`.
pub fn run(dir: &Path, cal: &CalFile, out: &Path) -> Result<Report> {
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
    let recs: Vec<Recording> = (0..dims.len())
        .map(|i| {
            let d = arr.camera_dir(i, None);
            Recording::open(&d).with_context(|| format!("camera {i}: {}", d.display()))
        })
        .collect::<Result<_>>()?;

    let t0 = Instant::now();
    let cams: Vec<CameraRows> = std::thread::scope(|s| {
        let handles: Vec<_> = recs
            .iter()
            .zip(&cal.camera)
            .map(|(r, c)| s.spawn(move || camera_rows(r, c, cal.height_lsb_um)))
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
    let core_s = t0.elapsed().as_secs_f64();

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
    let a = assemble(&cams, &grid);
    let t1 = Instant::now();
    super::output::write(out, &grid, &a.blended, cams.len())?;
    let write_s = t1.elapsed().as_secs_f64();

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
                Some(against_truth(
                    &a.blended.heights,
                    with_crb.then_some(&a.blended.variance),
                    |_, _| t_mean as f32,
                    &grid,
                    &raster,
                ))
            }
            None => None,
        },
        None => None,
    };

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
    Ok(Report {
        cameras: cams.len(),
        grid,
        seams: Seams {
            height_step_um_max: fold(|s| s.height_step_um),
            lateral_um_max: fold(|s| s.lateral_um()),
            per_seam: b.seams.clone(),
        },
        pixels: PixelCounts {
            total,
            valid,
            valid_fraction: if total > 0 {
                valid as f64 / total as f64
            } else {
                0.0
            },
            dead_masked: cams.iter().map(|c| c.dead_masked).collect(),
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
        },
    })
}
