//! The board map of one board: every camera's rows (from its packet stream, [`from_streams`],
//! or from any other source through a [`Collector`]) placed, masked, unwrapped, resampled,
//! blended ([`crate::assemble`]) and written ([`crate::output`]), with the report of
//! `dpsa board --json`.
//!
//! What it needs: the array's `array.json` (board size, pixel pitch, the cameras' design
//! positions, the board identity), the calibration file, and the rows. [`from_streams`] needs
//! no camera recording and no frame: the dead-pixel masks and row places come from the
//! registration replayed on each stream's trigger log ([`crate::provenance`]).
//!
//! Placement of a core board row `b` (`docs/calibration.md`): its window's first frame saw it
//! at image row `r_w = H - (max_step_rows + 1) / 2`, so column `c` lies at
//! `X = x0 + (p / cos a) b - p sin a (c + r_w tan a)`, `Y = y0 + p (c cos a + r_w sin a)`.

use crate::assemble::{assemble, Assembled, CameraRows, Timing};
use crate::blend::Blended;
use crate::output::BoardError;
use crate::provenance::Provenance;
use crate::resample::{BoardGrid, CameraPlacement};
use crate::streams::{self, StreamsReport};
use crate::Grid;
use dpsa_formats::array::{ArrayManifest, Kind, ARRAY_FILE};
use dpsa_formats::calibration::{CalFile, CameraCal};
use dpsa_formats::heightmap::HeightRow;
use dpsa_formats::BoardId;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

type Result<T> = std::result::Result<T, BoardError>;

/// A camera's per-pixel variance of its rows as they stand (`(provenance, first board row,
/// wrapped heights)` -> um^2 in the same layout, or `None`): the simulator's Cramer-Rao
/// bound. [`no_variance`] for none.
pub type Variance<'a> = dyn FnMut(
        &Provenance,
        i64,
        &Grid,
    ) -> std::result::Result<Option<Grid>, Box<dyn std::error::Error + Send + Sync>>
    + 'a;

/// No per-pixel variance (a production map).
pub fn no_variance(
    _: &Provenance,
    _: i64,
    _: &Grid,
) -> std::result::Result<Option<Grid>, Box<dyn std::error::Error + Send + Sync>> {
    Ok(None)
}

/// `dpsa board --json`.
#[derive(Clone, Debug, Serialize)]
pub struct MapReport {
    /// Cameras in the map.
    pub cameras: usize,
    /// The evidence that the map is wrong or useless (empty when none), one sentence each:
    /// `dpsa board` prints each as `warning: ...` and exits with status 2.
    pub warnings: Vec<String>,
    /// The board map's grid.
    pub grid: BoardGrid,
    /// How the cameras agree where they overlap.
    pub seams: Seams,
    /// Pixel counts.
    pub pixels: PixelCounts,
    /// The turns the unwrapping chose.
    pub unwrap: UnwrapStats,
    /// Seconds per step.
    pub timing: RunTiming,
    /// `--streams`: what each camera's stream held and lost.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub streams: Option<StreamsReport>,
    /// The paste's reflectance taken out of the walls (a zero step: none).
    pub paste_reflectance: crate::places::PasteReflectance,
}

#[derive(Clone, Debug, Serialize)]
/// `seams.*`: the cameras' agreement in their overlaps.
pub struct Seams {
    /// Largest |mean height difference| between neighbouring cameras over their shared flat
    /// valid pixels, um.
    pub height_step_um_max: Option<f64>,
    /// Largest misregistration between neighbouring cameras in their overlap, um.
    pub lateral_um_max: Option<f64>,
    /// Every pair of neighbouring cameras.
    pub per_seam: Vec<crate::blend::Seam>,
}

#[derive(Clone, Debug, Serialize)]
/// `pixels.*`.
pub struct PixelCounts {
    /// Board-map pixels.
    pub total: u64,
    /// Valid board-map pixels.
    pub valid: u64,
    /// `valid / total`.
    pub valid_fraction: f64,
    /// Camera pixels masked because a dead or weak image pixel of the calibration fed them,
    /// per camera (before resampling).
    pub dead_masked: Vec<u64>,
    /// Valid rows whose window the registration replay on the trigger log did not confirm (a
    /// lost trigger record), per camera: without it their dead-pixel mask and place are
    /// unknown, so they are left invalid ([`crate::provenance::Provenance::confirms`]).
    pub unplaced_rows: Vec<u64>,
}

#[derive(Clone, Debug, Serialize)]
/// `unwrap.*`.
pub struct UnwrapStats {
    /// Whole turns each camera was moved by.
    pub turns: Vec<i32>,
    /// Median height of the board edge pixels that chose the board's turn, before it, um.
    pub edge_median_um: Option<f64>,
    /// Bands whose edge pixels put the board on another turn than the one chosen (0 on a
    /// good map; a warning otherwise).
    pub edge_off_bands: u64,
}

#[derive(Clone, Debug, Serialize)]
/// `timing.*`, s.
pub struct RunTiming {
    /// The rows: the fixed-point core on every camera (threads), or decoding and checking the
    /// streams, s.
    pub core_s: f64,
    /// Unwrap, resample, blend.
    #[serde(flatten)]
    pub assemble: Timing,
    /// Writing the files, s.
    pub write_s: f64,
    /// Of `write_s`, each file (rendering, encoding and writing), by name, s.
    pub files_s: std::collections::BTreeMap<&'static str, f64>,
    /// Opening and checking the inputs (before the rows), s.
    pub open_s: f64,
    /// The whole run, s: the sum of the steps above and what lies between them.
    pub total_s: f64,
}

impl MapReport {
    /// A few lines for the terminal: [`MapReport::summary_head`] and [`MapReport::time_line`].
    pub fn summary(&self) -> String {
        self.summary_head() + &self.time_line(None)
    }

    /// The map's and the seams' lines (each ending in a newline).
    pub fn summary_head(&self) -> String {
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
        s
    }

    /// The time line: each step and the total, s; `truth_s`: a comparison after the run
    /// (the simulator's), printed before the total and added to it.
    pub fn time_line(&self, truth_s: Option<f64>) -> String {
        let truth = truth_s.map_or_else(String::new, |t| format!(", truth {t:.2} s"));
        format!(
            "time: open {:.2} s, core {:.2} s, unwrap {:.2} s, resample {:.2} s, blend {:.2} s, write {:.2} s{truth}; total {:.2} s",
            self.timing.open_s,
            self.timing.core_s,
            self.timing.assemble.unwrap_s,
            self.timing.assemble.resample_s,
            self.timing.assemble.blend_s,
            self.timing.write_s,
            self.timing.total_s + truth_s.unwrap_or(0.0)
        )
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

/// The core's reference phase of each column of camera `cal`, rad (for each pixel's place
/// within its row, [`crate::places`]).
pub fn reference_rad(cal: &CameraCal) -> Vec<f32> {
    cal.core_reference_phase_rad
        .iter()
        .map(|&r| r.rem_euclid(std::f64::consts::TAU) as f32)
        .collect()
}

/// What the stitcher needs of camera `cal` whose first row is board row `first_row` (rows
/// placed as they come, nothing lost up front, no variance): the line's and the paced bench's
/// cameras.
pub fn feed(cal: &CameraCal, first_row: i64, max_step_rows: u32) -> crate::assemble::CameraFeed {
    crate::assemble::CameraFeed {
        first_row,
        period_um: cal.height_per_turn_um.iter().map(|&t| t as f32).collect(),
        reference_rad: reference_rad(cal),
        placement: placement(cal, max_step_rows),
        places: None,
        lost: Vec::new(),
        variance: false,
    }
}

/// A camera's rows on their way to the board, whatever their source: wrapped heights in um
/// by board row.
pub struct Collector {
    id: u8,
    /// Columns.
    pub width: usize,
    lsb_um: f32,
    /// Board row of every row, in arrival order.
    rows: Vec<i64>,
    /// Wrapped heights (um, NaN invalid) of every row of `rows`, `width` each, one after
    /// another: one buffer, so that rows in order become the camera's grid without a copy
    /// ([`Collector::finish`]) and the line's chunks reuse it ([`Collector::take_chunk`]).
    heights: Vec<f32>,
    /// Per row of `rows`: the window's first latch when the row is valid (to be confirmed by
    /// the registration replay), `None` for an invalid row.
    latches: Vec<Option<i64>>,
    /// The board row after the last one [`Collector::take_chunk`] handed on.
    next_row: Option<i64>,
}

/// A camera's rows as the line hands them on ([`Collector::take_chunk`]): whole rows from
/// board row `first_row`, ready for [`crate::assemble::Stitcher::push`].
#[derive(Clone, Debug)]
pub struct Chunk {
    /// The board row of the first row.
    pub first_row: i64,
    /// Rows.
    pub rows: usize,
    /// Wrapped heights, um (NaN invalid), whole rows: dead-pixel masked, rows the replay did
    /// not confirm left invalid, a row that never came invalid.
    pub heights: Vec<f32>,
    /// Where each row was seen, row `i` at `along[i]` rows from `first_row`.
    pub places: crate::places::RowPlaces,
    /// Valid rows the registration replay did not confirm (left invalid).
    pub unplaced: u64,
    /// Pixels masked for dead image pixels.
    pub dead_masked: u64,
}

impl Collector {
    /// An empty collector for camera `cal`, heights in LSB of `lsb_um`.
    pub fn new(cal: &CameraCal, lsb_um: f64) -> Collector {
        let width = cal.width as usize;
        Collector {
            id: cal.id,
            width,
            lsb_um: lsb_um as f32,
            rows: Vec::new(),
            heights: Vec::new(),
            latches: Vec::new(),
            next_row: None,
        }
    }

    /// Rows pushed (since the last chunk taken).
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether no row is held.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Heights of held row `k` (arrival order).
    fn row(&self, k: usize) -> &[f32] {
        &self.heights[k * self.width..(k + 1) * self.width]
    }

    /// Whether the held rows are one after another from the first, each once.
    fn in_order(&self) -> bool {
        self.rows.windows(2).all(|p| p[1] == p[0] + 1)
    }

    /// The rows pushed since the last call, as a [`Chunk`] (`None`: none new). The rows are
    /// taken in board-row order from the row after the last chunk's, so chunks follow each
    /// other without a gap (a row that comes again or late is dropped; a row that never came
    /// is invalid); `prov` is the registration of
    /// the camera's frames so far (masks, places and confirmations as in
    /// [`Collector::finish`]).
    /// Refused like [`Collector::finish`] when the rows span far more board rows than came
    /// (an encoder fault).
    pub fn take_chunk(
        &mut self,
        prov: &Provenance,
        cal: &CameraCal,
        max_step: u32,
    ) -> Result<Option<Chunk>> {
        let from = self.next_row;
        let taken = |b: &i64| from.is_none_or(|f| *b >= f);
        let (Some(first), Some(last)) = (
            self.rows.iter().copied().filter(taken).min(),
            self.rows.iter().copied().max(),
        ) else {
            self.clear();
            return Ok(None);
        };
        let rows = self.rows.len();
        // Chunks follow each other without a gap: rows lost at a chunk's start are invalid
        // rows of it, so that every row stays at its board row in the stitcher.
        let first = from.unwrap_or(first);
        let span = i128::from(last) - i128::from(first) + 1;
        if span > rows as i128 + (1 << 16) {
            self.clear();
            return Err(BoardError::Refused(format!(
                "camera {}: its rows span {span} board rows but only {rows} came (an encoder fault?)",
                self.id,
            )));
        }
        let w = self.width;
        let n = span as usize;
        // Every value invalid, on rows a chunk before gave back (`pool::give_rows`) when the
        // pools are kept between boards.
        let mut data = crate::pool::ROWS.take_empty(w * n);
        data.resize(w * n, f32::NAN);
        let mut g = Grid {
            width: w,
            rows: n,
            data,
        };
        let mut unplaced = 0;
        for (k, (&b, latch)) in self.rows.iter().zip(&self.latches).enumerate() {
            if b < first {
                continue;
            }
            let i = (b - first) as usize;
            // A valid row whose window the replay does not confirm stays invalid.
            if latch.is_some_and(|l| !prov.confirms(b, l)) {
                unplaced += 1;
                g.data[i * w..(i + 1) * w].fill(f32::NAN);
                continue;
            }
            g.data[i * w..(i + 1) * w].copy_from_slice(self.row(k));
        }
        self.clear();
        let dead_masked =
            crate::provenance::mask_dead_pixels(prov, &cal.dead_pixels, first, &mut g);
        let places = crate::provenance::row_places(
            prov,
            first,
            n,
            entry_row(cal, max_step),
            cal.lateral.rotation_rad,
            cal.fringe_period_px,
        );
        self.next_row = Some(last + 1);
        Ok(Some(Chunk {
            first_row: first,
            rows: n,
            heights: g.data,
            places,
            unplaced,
            dead_masked,
        }))
    }

    /// Forgets the held rows, keeping the buffers for the next ones.
    fn clear(&mut self) {
        self.rows.clear();
        self.heights.clear();
        self.latches.clear();
    }

    /// One row as the core emitted it (the same bytes as its packet, from the core or from a
    /// stream): LSB to um (the core applied the per-column height per turn).
    pub fn push(&mut self, r: &HeightRow) {
        let lsb = self.lsb_um;
        self.heights
            .extend((0..self.width).map(|c| match r.heights.get(c) {
                Some(&v) if r.pixel_valid(c) => f32::from(v) * lsb,
                _ => f32::NAN,
            }));
        self.rows.push(r.row);
        self.latches.push(r.is_valid().then_some(r.latch));
    }

    /// The rows (in any order; a row that came twice keeps its last copy) as a grid from the
    /// first to the last row, with the `lost` board rows (inclusive ranges) inside it marked;
    /// returns it and the valid rows `prov` did not confirm (left invalid, marked lost).
    /// `prov` is the registration of the camera's frames (which frames fed each row, see
    /// [`crate::provenance`]); `variance`: each pixel's variance (um^2) of the rows as they
    /// stand (the simulator's Cramer-Rao bound), or `None`.
    pub fn finish(
        mut self,
        prov: &Provenance,
        variance: &mut Variance<'_>,
        cal: &CameraCal,
        max_step: u32,
        lost: &[(i64, i64)],
    ) -> Result<(CameraRows, u64)> {
        // A valid row whose window the replay does not confirm: its mask and place are
        // unknown, so it is not used (lost, never interpolated across).
        let mut lost = lost.to_vec();
        let mut unplaced = 0u64;
        let w = self.width;
        for (k, (&b, latch)) in self.rows.iter().zip(&self.latches).enumerate() {
            if let Some(l) = *latch {
                if !prov.confirms(b, l) {
                    self.heights[k * w..(k + 1) * w].fill(f32::NAN);
                    lost.push((b, b));
                    unplaced += 1;
                }
            }
        }
        let lost = &lost[..];
        // The rows' ends whatever their order (a stream's rows need not come sorted).
        let ends = self
            .rows
            .iter()
            .min()
            .zip(self.rows.iter().max())
            .map(|(&f, &l)| (f, l));
        let (first, last) = lost
            .iter()
            .fold(ends, |e, &(a, b)| {
                Some(e.map_or((a, b), |(f, l)| (f.min(a), l.max(b))))
            })
            .filter(|_| !self.rows.is_empty())
            .ok_or_else(|| BoardError::Refused(format!("camera {}: no rows arrived", self.id)))?;
        let lost_rows: i128 = lost
            .iter()
            .map(|&(a, b)| i128::from(b) - i128::from(a) + 1)
            .sum();
        let span = i128::from(last) - i128::from(first) + 1;
        if span > self.rows.len() as i128 + lost_rows + (1 << 16) {
            return Err(BoardError::Refused(format!(
                "camera {}: its rows span {span} board rows but only {} are present (an encoder fault?)",
                self.id,
                self.rows.len()
            )));
        }
        let span = span as usize;
        // Rows that came in order, each once, over the whole span are the grid as they are.
        let mut g = if self.rows.len() == span && self.in_order() {
            Grid {
                width: w,
                rows: span,
                data: std::mem::take(&mut self.heights),
            }
        } else {
            let mut g = Grid::invalid(w, span);
            for (k, &b) in self.rows.iter().enumerate() {
                let i = (b - first) as usize;
                g.data[i * w..(i + 1) * w].copy_from_slice(self.row(k));
            }
            g
        };
        let mut mask = Vec::new();
        if !lost.is_empty() {
            mask = vec![false; span];
            for &(a, b) in lost {
                mask[(a - first) as usize..=(b - first) as usize].fill(true);
            }
        }
        let dead_masked =
            crate::provenance::mask_dead_pixels(prov, &cal.dead_pixels, first, &mut g);
        let variance = variance(prov, first, &g).map_err(BoardError::Hook)?;
        let places = crate::provenance::row_places(
            prov,
            first,
            g.rows,
            entry_row(cal, max_step),
            cal.lateral.rotation_rad,
            cal.fringe_period_px,
        );
        Ok((
            CameraRows {
                heights: g,
                variance,
                dead_masked,
                places: Some(places),
                first_row: first,
                period_um: cal.height_per_turn_um.iter().map(|&t| t as f32).collect(),
                reference_rad: reference_rad(cal),
                placement: placement(cal, max_step),
                lost: mask,
            },
            unplaced,
        ))
    }
}

/// Refuses a camera's frames (triggers `f`, from `source`: a manifest or a stream's trigger
/// log) that advance further per frame than its core can take: the median latch step divided
/// by the calibration's `counts_per_pixel` (board rows per frame) above `max_step_rows`. The
/// simulator sets `max_step_rows` to 1.25 times the nominal step, so a good recording's median
/// step is about 0.8 of it; latches doubled (or a calibration of another encoder scale) give
/// 1.6.
pub fn check_latch_steps(
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
        return Err(BoardError::Refused(format!(
            "camera {i}: its frames advance a median {median:.1} board rows each (latch steps of {} counts over the calibration's counts_per_pixel {}), more than the {max} rows (processing.max_step_rows) its core takes: the latches of {} are scaled wrong (doubled?) or the calibration is of another encoder",
            steps[steps.len() / 2],
            cal.counts_per_pixel,
            source.display()
        )));
    }
    Ok(())
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
/// `warning: ...`, exit status 2). `own_valid`: each camera's valid and total pixels of its
/// own rows.
pub fn evidence(own_valid: &[(usize, usize)], b: &Blended, seams: &Seams) -> Vec<String> {
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
    let share = valid as f64 / own_valid.len().max(1) as f64;
    for (i, &(own_n, own_total)) in own_valid.iter().enumerate() {
        let own = own_n as f64 / own_total.max(1) as f64;
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
    for s in b.seams.iter().filter(|s| s.off_turn_bands > 0) {
        w.push(format!(
            "{} bands of the overlap of cameras {} and {} put camera {} on another fringe turn than the board's first rows did: a camera's unwrapping slipped there, heights a turn off are possible",
            s.off_turn_bands, s.cameras.0, s.cameras.1, s.cameras.1
        ));
    }
    if b.edge_off_bands > 0 {
        w.push(format!(
            "{} bands of the board's edge lie a fringe turn or more from 0 um, where the board's leading edge put them: the board is not clamped flat at its edges, or the map slipped a turn",
            b.edge_off_bands
        ));
    }
    w
}

/// The board map's grid and identity from the array's `array.json` and the calibration file,
/// both checked against each other (camera count, frame sizes, design positions, pitch).
pub struct MapLayout {
    /// The board map's grid: the board's size at the array's pixel pitch, from (0, 0).
    pub grid: BoardGrid,
    /// The board identity every camera's stream carries (`array.json`'s `board_id`).
    pub board: Option<BoardId>,
}

/// Lays out the board map of the array recording `dir` (its `array.json` only) with `cal`.
pub fn layout(dir: &Path, cal: &CalFile) -> Result<MapLayout> {
    let m = ArrayManifest::load(dir)?;
    if m.kind != Kind::Board {
        return Err(BoardError::Refused(format!(
            "{} is a calibration recording; dpsa board takes a board recording",
            dir.display()
        )));
    }
    let dims: Vec<(u32, u32)> = m.cameras.iter().map(|c| (c.width, c.rows)).collect();
    cal.check_array(&dims)?;
    cal.check_design(&m)
        .map_err(|e| BoardError::Refused(format!("{} and its calibration: {e}", dir.display())))?;
    let pitch = m.pixel_mm;
    let grid = BoardGrid {
        x0_mm: 0.0,
        y0_mm: 0.0,
        pitch_mm: pitch,
        rows: (m.board_length_mm / pitch).ceil() as usize,
        width: (m.board_width_mm / pitch).ceil() as usize,
    };
    if grid.rows.saturating_mul(grid.width) > 1 << 28 {
        return Err(BoardError::Refused(format!(
            "a {} x {} px board map is more than this tool holds (2^28 px)",
            grid.rows, grid.width
        )));
    }
    Ok(MapLayout {
        grid,
        board: m.board_id,
    })
}

/// The rows of every camera from its packet stream (`paths`, one per camera, any order;
/// [`crate::streams`]): each stream's trigger log replays the registration (dead-pixel masks,
/// row places, rows it cannot confirm left invalid), `variance` gives camera `i`'s per-pixel
/// variance. Returns the cameras' rows with each one's unplaced-row count, and the report.
pub fn rows_from_streams<'v>(
    paths: &[PathBuf],
    cal: &CalFile,
    layout: &MapLayout,
    array_file: &Path,
    variance: &mut dyn FnMut(usize) -> Box<Variance<'v>>,
) -> Result<(Vec<(CameraRows, u64)>, StreamsReport)> {
    let max_step = cal.processing.max_step_rows;
    let extents: Vec<(i64, i64)> = cal
        .camera
        .iter()
        .map(|c| streams::board_extent(&placement(c, max_step), &layout.grid, c.width))
        .collect();
    let (arrived, report) = streams::read_streams(paths, cal, layout.board, array_file, &extents)?;
    let cams = arrived
        .into_iter()
        .zip(&cal.camera)
        .enumerate()
        .map(|(i, (a, c))| {
            // Where each row came from: the registration replayed on the stream's own
            // trigger log.
            check_latch_steps(&a.triggers, a.registration.max_step_rows, c, i, &a.path)?;
            let prov = Provenance::replay(&a.triggers, &a.registration);
            let mut rows = Collector::new(c, cal.height_lsb_um);
            for row in &a.map.rows {
                rows.push(row);
            }
            let mut v = variance(i);
            rows.finish(&prov, &mut *v, c, a.registration.max_step_rows, &a.lost)
        })
        .collect::<Result<Vec<_>>>()?;
    Ok((cams, report))
}

/// A board map built and written: the report and the blended map (for a comparison after).
pub struct Built {
    /// `dpsa board --json`.
    pub report: MapReport,
    /// The blended map, its variance and turns.
    pub blended: Blended,
}

/// What [`build`] was given besides the rows.
pub struct Inputs<'a> {
    /// The board map's grid and identity.
    pub layout: &'a MapLayout,
    /// The streams' report (`--streams`), or `None` (rows from the core).
    pub streams: Option<StreamsReport>,
    /// When the run started (for `timing.total_s`).
    pub started: Instant,
    /// Opening and checking the inputs, s.
    pub open_s: f64,
    /// The rows, s.
    pub rows_s: f64,
    /// Progress bars on stderr.
    pub progress: bool,
    /// What to write besides the cheap default files.
    pub outputs: crate::output::Outputs,
    /// The paste's reflectance taken out of the walls (the program's; the default: none).
    pub paste: crate::places::PasteReflectance,
}

/// Assembles the cameras' rows `cams` (with each one's unplaced-row count) into the board map,
/// writes it into `out` and reports on it, with the evidence that it is wrong or useless.
pub fn build(cams: Vec<(CameraRows, u64)>, inputs: Inputs<'_>, out: &Path) -> Result<Built> {
    let Inputs {
        layout,
        streams: mut streams_report,
        started,
        open_s,
        rows_s,
        progress,
        outputs,
        paste,
    } = inputs;
    let grid = &layout.grid;
    let (cams, unplaced): (Vec<CameraRows>, Vec<u64>) = cams.into_iter().unzip();
    // What the report needs of the cameras' rows, taken before the assembly consumes them.
    let own_valid: Vec<(usize, usize)> = cams
        .iter()
        .map(|c| (c.heights.valid(), c.heights.data.len()))
        .collect();
    let dead_masked: Vec<u64> = cams.iter().map(|c| c.dead_masked).collect();
    let n_cams = cams.len();
    let steps = dpsa_formats::progress::progress_bar(progress, 2, "board map");
    let Assembled {
        blended,
        timing,
        lost_pixels,
        ..
    } = assemble(cams, grid, paste);
    steps.inc(1);
    if let Some(r) = &mut streams_report {
        r.gap_board_pixels = lost_pixels;
    }
    let missing: Vec<u64> = match &streams_report {
        Some(r) => r.missing_rows.clone(),
        None => vec![0; n_cams],
    };
    let t1 = Instant::now();
    let written =
        crate::output::write(out, grid, &blended, n_cams, &missing, layout.board, outputs)?;
    let write_s = t1.elapsed().as_secs_f64();
    steps.finish_and_clear();

    let b = &blended;
    let valid = b.heights.valid() as u64;
    let total = b.heights.data.len() as u64;
    let fold = |f: fn(&crate::blend::Seam) -> Option<f64>| {
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
    let warnings = evidence(&own_valid, b, &seams);
    let report = MapReport {
        cameras: n_cams,
        warnings,
        grid: *grid,
        seams,
        pixels: PixelCounts {
            total,
            valid,
            valid_fraction: crate::output::valid_fraction(valid, total),
            dead_masked,
            unplaced_rows: unplaced,
        },
        unwrap: UnwrapStats {
            turns: b.turns.clone(),
            edge_median_um: b.edge_median_um,
            edge_off_bands: b.edge_off_bands,
        },
        timing: RunTiming {
            core_s: rows_s,
            assemble: timing,
            write_s,
            files_s: written.seconds.into_iter().collect(),
            open_s,
            total_s: started.elapsed().as_secs_f64(),
        },
        streams: streams_report,
        paste_reflectance: paste,
    };
    Ok(Built { report, blended })
}

/// `dpsa board DIR --cal CAL --streams S0 S1 ... --out OUT`: the board map of the array
/// recording `dir` (its `array.json` only) from the cameras' packet streams, with the
/// calibration file `cal`. Every check (array, calibration, streams) comes before any file
/// is written. `paste`: the program's paste reflectance, taken out of the walls.
pub fn from_streams(
    dir: &Path,
    cal: &CalFile,
    paths: &[PathBuf],
    out: &Path,
    progress: bool,
    outputs: crate::output::Outputs,
    paste: crate::places::PasteReflectance,
) -> Result<Built> {
    let started = Instant::now();
    let layout = layout(dir, cal)?;
    let open_s = started.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let (cams, report) =
        rows_from_streams(paths, cal, &layout, &dir.join(ARRAY_FILE), &mut |_| {
            Box::new(no_variance)
        })?;
    let rows_s = t0.elapsed().as_secs_f64();
    build(
        cams,
        Inputs {
            layout: &layout,
            streams: Some(report),
            started,
            open_s,
            rows_s,
            progress,
            outputs,
            paste,
        },
        out,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::provenance::{plan_triggers, Registration};
    use dpsa_core::Trigger;
    use dpsa_formats::calibration::Lateral;

    const W: usize = 24;
    const LSB_UM: f64 = 0.25;

    fn cal() -> CameraCal {
        CameraCal {
            id: 0,
            width: W as u32,
            rows: 40,
            bit_depth: 12,
            saturation: 4095,
            counts_per_pixel: 10.0,
            counts_per_mm: 360.0,
            fringe_period_px: 32.0,
            fringe_frequency_poly: [1.0 / 32.0, 0.0, 0.0],
            fx_height_error_um: 0.0,
            fx_over_budget: false,
            height_per_turn_um: vec![500.0; W],
            reference_phase_rad: vec![0.0; W],
            core_reference_phase_rad: vec![0.0; W],
            background_dn: vec![1800.0; W],
            modulation_dn: vec![700.0; W],
            dead_pixels: Vec::new(),
            background_map: Vec::new(),
            modulation_map: Vec::new(),
            lateral: Lateral {
                x0_mm: 0.0,
                y0_mm: 0.0,
                pitch_mm: 0.0277,
                rotation_rad: 0.0,
                row_pitch_mm: 0.0277,
                fit_rms_um: 0.0,
                marks: 0,
            },
        }
    }

    /// Every row a steady run of 30 frames of 8 rows gives a complete window, as the core
    /// emits it: heights `(7 b + 3 c) mod 1000 - 500` LSB, every fifth pixel invalid, the
    /// window's first latch; and the registration of those frames.
    fn rows() -> (Vec<HeightRow>, Provenance) {
        let triggers: Vec<Trigger> = (0..30u32)
            .map(|k| Trigger {
                seq: k,
                latch: i64::from(k) * 80 + 3,
            })
            .collect();
        let reg = Registration {
            rows: 40,
            n: 4,
            max_step_rows: 12,
            counts_per_pixel: 10.0,
        };
        let rows = plan_triggers(&triggers, &reg)
            .into_iter()
            .filter(|p| p.flags == 0)
            .filter_map(|p| {
                let w = p.first_frame?;
                Some(HeightRow {
                    row: p.row,
                    latch: triggers[w].latch,
                    flags: 0,
                    heights: (0..W as i64)
                        .map(|c| ((7 * p.row + 3 * c).rem_euclid(1000) - 500) as i16)
                        .collect(),
                    valid: (0..W as i64).map(|c| (p.row + c) % 5 != 0).collect(),
                })
            })
            .collect();
        (rows, Provenance::replay(&triggers, &reg))
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// Rows in order become the grid as they are (no copy); shuffled, with one row twice, they
    /// are placed row by row; handed on in chunks as the line does, the same heights again.
    /// Every way gives each pixel its height in um (`LSB x 0.25`) or NaN where it was invalid.
    #[test]
    fn the_camera_grid_is_the_same_however_the_rows_come() {
        let (rows, prov) = rows();
        assert!(rows.len() > 150, "{}", rows.len());
        let c = cal();
        let whole = |order: &[usize]| {
            let mut col = Collector::new(&c, LSB_UM);
            for &k in order {
                col.push(&rows[k]);
            }
            let (cam, unplaced) = col
                .finish(&prov, &mut no_variance, &c, 12, &[])
                .expect("rows");
            assert_eq!(unplaced, 0);
            cam
        };
        let in_order: Vec<usize> = (0..rows.len()).collect();
        let a = whole(&in_order);
        assert_eq!(a.first_row, rows[0].row);
        assert_eq!(a.heights.rows, rows.len());
        for (i, r) in rows.iter().enumerate() {
            for col in 0..W {
                let want = if r.valid[col] {
                    f32::from(r.heights[col]) * LSB_UM as f32
                } else {
                    f32::NAN
                };
                assert_eq!(
                    a.heights.at(i, col).to_bits(),
                    want.to_bits(),
                    "row {i} col {col}"
                );
            }
        }
        // Reversed, with row 10 again at the end.
        let mut shuffled: Vec<usize> = (0..rows.len()).rev().collect();
        shuffled.push(10);
        let b = whole(&shuffled);
        assert_eq!(b.first_row, a.first_row);
        assert_eq!(bits(&b.heights.data), bits(&a.heights.data));

        let mut col = Collector::new(&c, LSB_UM);
        let mut chunks = Vec::new();
        for (k, r) in rows.iter().enumerate() {
            col.push(r);
            if k % 37 == 36 || k + 1 == rows.len() {
                let chunk = col.take_chunk(&prov, &c, 12).expect("chunk").expect("rows");
                assert!(col.is_empty());
                chunks.push(chunk);
            }
        }
        assert_eq!(chunks[0].first_row, a.first_row);
        let joined: Vec<f32> = chunks.iter().flat_map(|c| c.heights.clone()).collect();
        assert_eq!(bits(&joined), bits(&a.heights.data));
    }
}
