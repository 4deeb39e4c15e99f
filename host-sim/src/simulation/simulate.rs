//! The simulator: renders a [`Scene`] into a recording directory (`docs/model.md`).
//!
//! Physics, in board coordinates (`x` = continuous board row, px; `c` = column, px):
//!
//! * **Motion.** Conveyor position `s_0 = -rows` (board row 0 just below the ROI), then
//!   `s_{k+1} = s_k + step_k` with `step_k = mean_step_px * (1 + jitter_pct/100 * U(-1, 1))`,
//!   or 0 during a stall. Latch `e_k = round(s_k * counts_per_pixel)`. Frames are taken while
//!   `s_k <= board_length + n * max_step_rows`.
//! * **Imaging.** Pixel `(r, c)` of frame `k` sees `x = r + s_k`:
//!   `I = B + C cos(2 pi r / fringe_period_px + phi_0(c) + 2 pi h / height_per_turn_um)`.
//! * **Board.** Integer board row `b` covers `x` in `[b - 1/2, b + 1/2)`. Deposits are rounded
//!   boxes of height `h = H_dep * smoothstep(clamp(-d / deposit_edge_px, 0, 1))` where `d` is the
//!   signed distance (px) to the footprint rectangle (rounded by `deposit_corner_px`). A footprint
//!   of `rows x cols` starting at board pixel `(row, col)` covers pixels `row..row+rows`,
//!   `col..col+cols`, i.e. the rectangle `[row - 1/2, row + rows - 1/2) x [col - 1/2, col + cols - 1/2)`.
//!   `B, C` are the paste values where `h > 0`, else the board values; patches override them
//!   (by board pixel); everything is scaled by the column illumination factor.
//! * **Noise.** Electrons `~ Poisson(I * gain)`, `DN = electrons / gain + Normal(0, read_noise)`,
//!   rounded and clamped to `[0, 2^bit_depth - 1]`. For `I * gain > 1000` the Poisson draw is
//!   replaced by its Gaussian approximation, and shot and read noise are drawn as one Gaussian of
//!   variance `I / gain + read_noise^2` (same distribution as two independent draws).
//!
//! Randomness: independent ChaCha8 streams for the deposit layout, the motion and the noise of
//! each frame, all derived from the seed, so changing e.g. the noise knobs does not move the
//! deposits, and frames can be rendered in parallel with identical results.

use crate::simulation::recording::{
    self, FrameEntry, Manifest, TruthInfo, FORMAT, MANIFEST_FILE, TRUTH_BACKGROUND_FILE,
    TRUTH_CONTRAST_FILE, TRUTH_HEIGHT_FILE, VERSION,
};
use crate::simulation::scene::Scene;
use crate::{At, SimError};
use indicatif::{ProgressBar, ProgressStyle};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Poisson, StandardNormal};
use std::f64::consts::PI;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

/// Margin between deposits and the board ends (first / last board row), px.
pub const END_MARGIN_PX: u32 = 8;
/// Minimum free space between deposit footprints, px.
pub const DEPOSIT_GAP_PX: u32 = 4;
/// Placement attempts per deposit before it is skipped.
pub const PLACEMENT_TRIES: u32 = 100;
/// Above this expected electron count the Poisson shot noise is drawn as a Gaussian.
pub const GAUSSIAN_ELECTRONS: f64 = 1000.0;

/// ChaCha stream of the deposit layout.
const LAYOUT_STREAM: u64 = 1;
/// ChaCha stream of the conveyor motion.
const MOTION_STREAM: u64 = 2;
/// ChaCha stream of frame `k`'s noise is `NOISE_STREAM + k`.
const NOISE_STREAM: u64 = 1 << 32;

pub(crate) fn rng(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// What [`simulate`] produced.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SimSummary {
    /// Frames written.
    pub frames: usize,
    /// Rows per frame `H`, px.
    pub rows: usize,
    /// Frame width `W`, px.
    pub width: usize,
    /// Deposits the scene asked for.
    pub deposits_requested: usize,
    /// Deposits placed (some are skipped when the board is too full).
    pub deposits_placed: usize,
    /// Bytes written (frames, truth and manifest).
    pub bytes_written: u64,
}

/// One solder-paste deposit: a rounded box on the board.
#[derive(Clone, Debug, PartialEq)]
pub struct Deposit {
    /// First board row of the footprint, px.
    pub row: i64,
    /// First column of the footprint, px.
    pub col: i64,
    /// Footprint rows (along the motion), px.
    pub rows: u32,
    /// Footprint columns, px.
    pub cols: u32,
    /// Height of the flat top, um.
    pub height_um: f64,
}

fn smoothstep(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

impl Deposit {
    /// Height at board point (`x`, `c`), um (`x`: continuous board row, `c`: column).
    pub fn height(&self, x: f64, c: f64, corner_px: f64, edge_px: f64) -> f64 {
        let d = self.signed_distance(x, c, corner_px);
        if d >= 0.0 {
            0.0
        } else if edge_px > 0.0 {
            self.height_um * smoothstep((-d / edge_px).min(1.0))
        } else {
            self.height_um
        }
    }

    /// Signed distance from (`x`, `c`) to the rounded footprint rectangle, px (negative inside).
    pub fn signed_distance(&self, x: f64, c: f64, corner_px: f64) -> f64 {
        let (hy, hx) = (f64::from(self.rows) / 2.0, f64::from(self.cols) / 2.0);
        let (cy, cx) = (self.row as f64 - 0.5 + hy, self.col as f64 - 0.5 + hx);
        let radius = corner_px.min(hy).min(hx);
        let qy = (x - cy).abs() - (hy - radius);
        let qx = (c - cx).abs() - (hx - radius);
        let outside = qy.max(0.0).hypot(qx.max(0.0));
        outside + qy.max(qx).min(0.0) - radius
    }

    /// `true` if the footprints, each grown by `gap` px, overlap.
    fn too_close(&self, other: &Deposit, gap: i64) -> bool {
        let rows = (
            self.row,
            self.row + i64::from(self.rows),
            other.row,
            other.row + i64::from(other.rows),
        );
        let cols = (
            self.col,
            self.col + i64::from(self.cols),
            other.col,
            other.col + i64::from(other.cols),
        );
        rows.0 < rows.3 + gap
            && rows.2 < rows.1 + gap
            && cols.0 < cols.3 + gap
            && cols.2 < cols.1 + gap
    }
}

/// Places `scene.deposits` deposits at random without overlap (see the module docs).
/// Deposits that do not fit after [`PLACEMENT_TRIES`] attempts are skipped.
pub fn place_deposits(scene: &Scene, seed: u64) -> Vec<Deposit> {
    const BIN: i64 = 64;
    let mut rng = rng(seed, LAYOUT_STREAM);
    let length = i64::from(scene.board_length);
    let width = i64::from(scene.width);
    let margin = i64::from(END_MARGIN_PX);
    let gap = i64::from(DEPOSIT_GAP_PX);
    let [lo, hi] = scene.deposit_height_um;
    let mut placed: Vec<Deposit> = Vec::new();
    // Deposits indexed by 64-row bins of the board, for the overlap test.
    let mut bins: Vec<Vec<usize>> = vec![Vec::new(); (length / BIN + 1) as usize];
    if scene.deposit_sizes.is_empty() {
        return placed;
    }
    for _ in 0..scene.deposits {
        for _ in 0..PLACEMENT_TRIES {
            let [rows, cols] = scene.deposit_sizes[rng.random_range(0..scene.deposit_sizes.len())];
            let row_max = length - margin - i64::from(rows);
            let col_max = width - i64::from(cols);
            // Draw everything before testing so every attempt consumes the same randomness.
            let (u_row, u_col, u_height): (f64, f64, f64) =
                (rng.random(), rng.random(), rng.random());
            if row_max < margin || col_max < 0 {
                continue;
            }
            let pick = |u: f64, lo: i64, hi: i64| (lo + (u * (hi - lo + 1) as f64) as i64).min(hi);
            let d = Deposit {
                row: pick(u_row, margin, row_max),
                col: pick(u_col, 0, col_max),
                rows,
                cols,
                height_um: lo + (hi - lo) * u_height,
            };
            let first_bin = ((d.row - gap).max(0) / BIN) as usize;
            let last_bin = (((d.row + i64::from(rows) + gap) / BIN) as usize).min(bins.len() - 1);
            let clash = bins[first_bin..=last_bin]
                .iter()
                .flatten()
                .any(|&i| placed[i].too_close(&d, gap));
            if !clash {
                let bin_range =
                    (d.row / BIN) as usize..=((d.row + i64::from(rows) - 1) / BIN) as usize;
                for bin in &mut bins[bin_range] {
                    bin.push(placed.len());
                }
                placed.push(d);
                break;
            }
        }
    }
    placed
}

/// Conveyor positions `s_k` of every frame, px (see the module docs).
pub fn conveyor_positions(scene: &Scene, seed: u64) -> Vec<f64> {
    let limit = f64::from(scene.board_length) + scene.travel_beyond_board();
    travel(
        &mut rng(seed, MOTION_STREAM),
        -f64::from(scene.rows),
        limit,
        scene.mean_step_px,
        scene.jitter_pct,
        &scene.stalls,
        crate::simulation::scene::MAX_FRAMES as usize + 1,
    )
}

/// The conveyor position of every frame from `start` while it is `<= end` (at most
/// `max_frames` frames): steps of `step (1 + jitter u)` with `u` uniform in `[-1, 1)` and
/// `jitter = jitter_pct / 100`, none during a stall. Any length unit; shared by the
/// single-camera and the array simulators.
pub fn travel(
    rng: &mut ChaCha8Rng,
    start: f64,
    end: f64,
    step: f64,
    jitter_pct: f64,
    stalls: &[crate::simulation::scene::Stall],
    max_frames: usize,
) -> Vec<f64> {
    let jitter = jitter_pct / 100.0;
    let stalled = |k: u64| {
        stalls
            .iter()
            .any(|s| k >= u64::from(s.frame) && k < u64::from(s.frame) + u64::from(s.frames))
    };
    let mut s = start;
    let mut positions = Vec::new();
    while s <= end && positions.len() < max_frames {
        positions.push(s);
        if !stalled(positions.len() as u64 - 1) {
            let u: f64 = rng.random_range(-1.0..1.0);
            s += step * (1.0 + jitter * u);
        }
    }
    positions
}

/// Encoder latch at conveyor position `s` (px): `round(s * counts_per_pixel)`, counts.
pub fn latch(s: f64, counts_per_pixel: f64) -> i64 {
    (s * counts_per_pixel).round() as i64
}

/// The rendered world: board, deposits, optics and camera of a scene. Renders frames and truth.
pub struct Simulator<'a> {
    scene: &'a Scene,
    seed: u64,
    deposits: Vec<Deposit>,
    /// Deposit indices per board row (deposits whose footprint covers that row).
    row_deposits: Vec<Vec<u32>>,
    /// `phi_0(c)`, rad.
    phi0: Vec<f64>,
    cos_phi0: Vec<f64>,
    sin_phi0: Vec<f64>,
    /// Column illumination factor.
    illumination: Vec<f64>,
    positions: Vec<f64>,
}

/// Per-row scratch buffers of the renderer.
struct RowBuf {
    height: Vec<f64>,
    background: Vec<f64>,
    contrast: Vec<f64>,
}

impl<'a> Simulator<'a> {
    /// Lays out the deposits and the motion of `scene` for `seed`. The scene must be valid.
    pub fn new(scene: &'a Scene, seed: u64) -> crate::Result<Simulator<'a>> {
        scene.validate()?;
        let deposits = place_deposits(scene, seed);
        let mut row_deposits = vec![Vec::new(); scene.board_length as usize];
        for (i, d) in deposits.iter().enumerate() {
            for b in d.row..d.row + i64::from(d.rows) {
                row_deposits[b as usize].push(i as u32);
            }
        }
        let phi0 = scene.reference_phase();
        Ok(Simulator {
            scene,
            seed,
            cos_phi0: phi0.iter().map(|p| p.cos()).collect(),
            sin_phi0: phi0.iter().map(|p| p.sin()).collect(),
            phi0,
            illumination: scene.illumination(),
            positions: conveyor_positions(scene, seed),
            deposits,
            row_deposits,
        })
    }

    /// The placed deposits.
    pub fn deposits(&self) -> &[Deposit] {
        &self.deposits
    }

    /// Conveyor position `s_k` of every frame, px.
    pub fn positions(&self) -> &[f64] {
        &self.positions
    }

    /// Encoder latch of frame `k`, counts. Panics if `k` is not a frame index.
    pub fn latch(&self, k: usize) -> i64 {
        latch(
            self.positions[k],
            crate::simulation::scene::round_counts_per_pixel(self.scene.counts_per_pixel),
        )
    }

    fn row_buf(&self) -> RowBuf {
        let w = self.scene.width as usize;
        RowBuf {
            height: vec![0.0; w],
            background: vec![0.0; w],
            contrast: vec![0.0; w],
        }
    }

    /// Fills `buf` with height (um) and un-illuminated `B`, `C` (DN) at continuous board row `x`.
    /// Returns `false` (buffers untouched) if the row is bare board: `h = 0`, board `B` and `C`.
    fn eval_row(&self, x: f64, buf: &mut RowBuf) -> bool {
        let s = self.scene;
        let b = (x + 0.5).floor() as i64;
        let deps: &[u32] = usize::try_from(b)
            .ok()
            .and_then(|i| self.row_deposits.get(i))
            .map_or(&[], |v| v);
        let has_patch = s.patches.iter().any(|p| p.contains_row(b));
        if deps.is_empty() && !has_patch {
            return false;
        }
        buf.height.fill(0.0);
        buf.background.fill(s.background);
        buf.contrast.fill(s.contrast);
        for &i in deps {
            let d = &self.deposits[i as usize];
            for c in d.col.max(0)..(d.col + i64::from(d.cols)).min(i64::from(s.width)) {
                let h = d.height(x, c as f64, s.deposit_corner_px, s.deposit_edge_px);
                if h > 0.0 {
                    let c = c as usize;
                    buf.height[c] = h;
                    buf.background[c] = s.paste_background;
                    buf.contrast[c] = s.paste_contrast;
                }
            }
        }
        for p in s.patches.iter().filter(|p| p.contains_row(b)) {
            let c0 = p.col.clamp(0, i64::from(s.width)) as usize;
            let c1 = (p.col + i64::from(p.cols)).clamp(0, i64::from(s.width)) as usize;
            if let Some(bg) = p.background {
                buf.background[c0..c1].fill(bg);
            }
            if let Some(ct) = p.contrast {
                buf.contrast[c0..c1].fill(ct);
            }
        }
        true
    }

    /// Renders frame `k` (row-major `rows x width`, DN) with its own noise stream.
    /// Panics if `k` is not a frame index (`k >= positions().len()`).
    pub fn render(&self, k: usize) -> Vec<u16> {
        let s = self.scene;
        let (rows, width) = (s.rows as usize, s.width as usize);
        let mut rng = rng(self.seed, NOISE_STREAM + k as u64);
        let mut buf = self.row_buf();
        let mut out = vec![0u16; rows * width];
        let max = f64::from(s.max_value());
        let (gain, read) = (s.gain_e_per_dn, s.read_noise_dn);
        let turn = 2.0 * PI / s.height_per_turn_um;
        for (r, out_row) in out.chunks_exact_mut(width).enumerate() {
            let x = r as f64 + self.positions[k];
            let row_phase = 2.0 * PI * r as f64 / s.fringe_period_px;
            let (sin_r, cos_r) = row_phase.sin_cos();
            let special = self.eval_row(x, &mut buf);
            for (c, px) in out_row.iter_mut().enumerate() {
                let (bg, ct, h) = if special {
                    (buf.background[c], buf.contrast[c], buf.height[c])
                } else {
                    (s.background, s.contrast, 0.0)
                };
                let cosine = if h == 0.0 {
                    cos_r * self.cos_phi0[c] - sin_r * self.sin_phi0[c]
                } else {
                    (row_phase + self.phi0[c] + turn * h).cos()
                };
                let intensity = self.illumination[c] * (bg + ct * cosine);
                let dn = noisy(intensity, gain, read, &mut rng);
                *px = dn.round().clamp(0.0, max) as u16;
            }
        }
        out
    }

    /// Ground truth on integer board rows `0..board_length`: height (um), `B` and `C` (DN,
    /// illumination included), each row-major `board_length x width`.
    pub fn truth(&self) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let s = self.scene;
        let (len, width) = (s.board_length as usize, s.width as usize);
        let mut height = vec![0f32; len * width];
        let mut background = vec![0f32; len * width];
        let mut contrast = vec![0f32; len * width];
        let mut buf = self.row_buf();
        for b in 0..len {
            let special = self.eval_row(b as f64, &mut buf);
            let row = b * width..(b + 1) * width;
            for (c, ((h, bg), ct)) in height[row.clone()]
                .iter_mut()
                .zip(&mut background[row.clone()])
                .zip(&mut contrast[row])
                .enumerate()
            {
                let ill = self.illumination[c];
                if special {
                    *h = buf.height[c] as f32;
                    *bg = (ill * buf.background[c]) as f32;
                    *ct = (ill * buf.contrast[c]) as f32;
                } else {
                    *bg = (ill * s.background) as f32;
                    *ct = (ill * s.contrast) as f32;
                }
            }
        }
        (height, background, contrast)
    }

    /// The manifest of the recording this simulator writes.
    pub fn manifest(&self) -> Manifest {
        let s = self.scene;
        Manifest {
            format: FORMAT.into(),
            version: VERSION,
            camera: s.camera(),
            calibration: s.calibration(),
            processing: s.processing(),
            frames: (0..self.positions.len())
                .map(|k| FrameEntry {
                    seq: k as u32,
                    latch: self.latch(k),
                    file: frame_file(k),
                })
                .collect(),
            noise: Some(s.noise()),
            truth: Some(TruthInfo {
                first_row: 0,
                rows: s.board_length,
            }),
            board_id: None,
        }
    }
}

/// Relative path of frame `k`: `frames/000000.png`, ...
pub fn frame_file(k: usize) -> String {
    format!("frames/{k:06}.png")
}

/// One noisy sample of mean `intensity` (DN), before rounding (see the module docs).
pub(crate) fn noisy(intensity: f64, gain: f64, read_noise: f64, rng: &mut ChaCha8Rng) -> f64 {
    let i = intensity.max(0.0);
    let electrons = i * gain;
    if electrons > GAUSSIAN_ELECTRONS {
        let z: f64 = StandardNormal.sample(rng);
        i + (i / gain + read_noise * read_noise).sqrt() * z
    } else {
        let shot = match Poisson::new(electrons) {
            Ok(p) => p.sample(rng) / gain,
            Err(_) => 0.0, // electrons == 0
        };
        let z: f64 = StandardNormal.sample(rng);
        shot + read_noise * z
    }
}

fn file_size(path: &Path) -> u64 {
    std::fs::metadata(path).map(|m| m.len()).unwrap_or(0)
}

/// Renders `scene` with `seed` into the recording directory `out` (created if needed) and
/// returns a summary. Frames are rendered and encoded in parallel; the result does not depend
/// on the number of threads. `manifest.json` is written last, so an interrupted run leaves no
/// readable recording.
///
/// Refuses an output that would exceed [`MAX_OUTPUT_BYTES`] (see [`simulate_with`] to force
/// it) and an output directory that is neither new, empty nor a recording (see
/// [`prepare_out_dir`]).
pub fn simulate(scene: &Scene, seed: u64, out: &Path, progress: bool) -> crate::Result<SimSummary> {
    simulate_with(scene, seed, out, progress, false)
}

/// Largest recording `simulate` writes without `force`, bytes (20 GB, estimated by
/// [`output_size_estimate`]).
pub const MAX_OUTPUT_BYTES: u64 = 20_000_000_000;

/// Upper bound of a recording's size on disk, bytes: `frames` 16-bit PNGs of `rows x width`
/// (raw size plus filter bytes and framing; the PNGs are usually smaller), the three truth
/// files (12 bytes per board pixel) and the manifest.
pub fn output_size_estimate(scene: &Scene, frames: u64) -> u64 {
    let (rows, width) = (u64::from(scene.rows), u64::from(scene.width));
    let png = rows * width * 2 + rows + 1024;
    let truth = 12 * u64::from(scene.board_length) * width;
    let manifest = frames * 100 + width * 25 + 4096;
    frames * png + truth + manifest
}

/// Whether `dir` holds a dpsa recording (a `manifest.json` of format `dpsa-recording`, or only
/// the `frames/` and `truth/` of a run interrupted before the marker existed).
pub fn is_recording_dir(dir: &Path) -> bool {
    let ours =
        crate::files::read_capped_io(&dir.join(MANIFEST_FILE), crate::files::MAX_MANIFEST_BYTES)
            .ok()
            .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
            .is_some_and(|v| v.get("format").and_then(|f| f.as_str()) == Some(FORMAT));
    ours || std::fs::read_dir(dir).is_ok_and(|d| {
        d.flatten()
            .all(|e| e.file_name() == "frames" || e.file_name() == "truth")
    })
}

/// A recording directory, for [`crate::files::OutputDir`].
pub const DIR_KIND: crate::files::DirKind = crate::files::DirKind {
    format: FORMAT,
    noun: "recording",
    ours: is_recording_dir,
};

/// Checks `out` before anything is rendered: new, empty, or an earlier recording (replaced
/// whole when the new one is complete, see [`crate::files::OutputDir`]); anything else is
/// refused.
pub fn prepare_out_dir(out: &Path) -> crate::Result<()> {
    Ok(crate::files::check_output_dir(out, DIR_KIND)?)
}

/// [`simulate`]; `force` lifts the [`MAX_OUTPUT_BYTES`] limit.
pub fn simulate_with(
    scene: &Scene,
    seed: u64,
    out: &Path,
    progress: bool,
    force: bool,
) -> crate::Result<SimSummary> {
    let sim = Simulator::new(scene, seed).at(|| "invalid scene")?;
    let manifest = sim.manifest();
    manifest
        .validate()
        .at(|| "internal error: simulated manifest is invalid")?;
    let estimate = output_size_estimate(scene, manifest.frames.len() as u64);
    if !(force || estimate <= MAX_OUTPUT_BYTES) {
        return Err(SimError::Refused(format!(
            "the recording would take up to {:.1} GB ({} frames of {} x {} px as 16-bit PNG, plus ground truth), more than the {} GB limit; pass --force to write it anyway",
            estimate as f64 / 1e9,
            manifest.frames.len(),
            scene.rows,
            scene.width,
            MAX_OUTPUT_BYTES / 1_000_000_000
        )));
    }
    // Built in a hidden directory beside `out` and swapped in whole at the end: an earlier
    // recording stays as it was until then, and none of its frames survives.
    let staging = crate::files::OutputDir::create(out, DIR_KIND)?;
    let out = staging.path();
    for dir in [out.to_path_buf(), out.join("frames"), out.join("truth")] {
        std::fs::create_dir_all(&dir).map_err(|e| {
            SimError::Refused(format!(
                "cannot create {}: it {}",
                dir.display(),
                crate::files::io_cause(&e)
            ))
        })?;
    }
    let manifest_path = out.join(MANIFEST_FILE);

    let frames = manifest.frames.len();
    let bar = if progress {
        let style = ProgressStyle::with_template(
            "{elapsed_precise} [{wide_bar}] {pos}/{len} frames (eta {eta})",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar());
        ProgressBar::new(frames as u64).with_style(style)
    } else {
        ProgressBar::hidden()
    };

    let (rows, width) = (scene.rows as usize, scene.width as usize);
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let first_error: Mutex<Option<(usize, recording::RecordingError)>> = Mutex::new(None);
    let bytes = AtomicUsize::new(0);
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(frames)
        .max(1);
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(|| {
                while !failed.load(Ordering::Relaxed) {
                    let k = next.fetch_add(1, Ordering::Relaxed);
                    if k >= frames {
                        break;
                    }
                    let path = out.join(&manifest.frames[k].file);
                    match recording::write_frame_png(&path, rows, width, &sim.render(k)) {
                        Ok(()) => {
                            bytes.fetch_add(file_size(&path) as usize, Ordering::Relaxed);
                            bar.inc(1);
                        }
                        Err(e) => {
                            failed.store(true, Ordering::Relaxed);
                            let mut slot = first_error.lock().unwrap_or_else(|p| p.into_inner());
                            if slot.as_ref().is_none_or(|(j, _)| k < *j) {
                                *slot = Some((k, e));
                            }
                        }
                    }
                }
            });
        }
    });
    bar.finish_and_clear();
    if let Some((k, e)) = first_error.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(e).at(|| format!("writing frame {k}"));
    }
    let mut bytes_written = bytes.into_inner() as u64;

    let (height, background, contrast) = sim.truth();
    for (name, data) in [
        (TRUTH_HEIGHT_FILE, height),
        (TRUTH_BACKGROUND_FILE, background),
        (TRUTH_CONTRAST_FILE, contrast),
    ] {
        let path = out.join(name);
        recording::write_f32(&path, &data)?;
        bytes_written += file_size(&path);
    }
    manifest.save(out)?;
    bytes_written += file_size(&manifest_path);
    staging.commit()?;

    Ok(SimSummary {
        frames,
        rows,
        width,
        deposits_requested: scene.deposits as usize,
        deposits_placed: sim.deposits().len(),
        bytes_written,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulation::recording::Recording;
    use crate::simulation::scene::{Patch, Stall};

    fn small() -> Scene {
        Scene {
            width: 64,
            board_length: 200,
            deposits: 6,
            ..Scene::default()
        }
    }

    #[test]
    fn deterministic_for_a_seed() {
        let scene = small();
        let (a, b, c) = (
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
            tempfile::tempdir().unwrap(),
        );
        let sa = simulate(&scene, 7, a.path(), false).unwrap();
        let sb = simulate(&scene, 7, b.path(), false).unwrap();
        simulate(&scene, 8, c.path(), false).unwrap();
        assert_eq!(sa, sb);
        assert!(sa.deposits_placed > 0 && sa.deposits_placed <= 6);
        let (ra, rb, rc) = (
            Recording::open(a.path()).unwrap(),
            Recording::open(b.path()).unwrap(),
            Recording::open(c.path()).unwrap(),
        );
        assert_eq!(ra.manifest, rb.manifest);
        assert_eq!(ra.len(), sa.frames);
        for k in 0..ra.len() {
            assert_eq!(ra.frame(k).unwrap().data, rb.frame(k).unwrap().data);
        }
        assert_ne!(ra.frame(3).unwrap().data, rc.frame(3).unwrap().data);
        let (ta, tb) = (ra.truth().unwrap().unwrap(), rb.truth().unwrap().unwrap());
        assert_eq!(ta.height_um, tb.height_um);
        assert_eq!(ta.rows, 200);
        assert!(ta.height_um.iter().any(|&h| h > 50.0));
    }

    #[test]
    fn every_board_row_seen_n_times() {
        let scene = small();
        let pos = conveyor_positions(&scene, 3);
        assert_eq!(pos[0], -40.0);
        let limit = 200.0 + 4.0 * 10.0;
        assert!(*pos.last().unwrap() <= limit);
        assert!(pos.last().unwrap() + 8.0 * 1.1 > limit);
        for w in pos.windows(2) {
            let step = w[1] - w[0];
            assert!((8.0 * 0.9..8.0 * 1.1).contains(&step), "{step}");
        }
    }

    #[test]
    fn latches_monotonic_and_stall() {
        let scene = small();
        let sim = Simulator::new(&scene, 5).unwrap();
        let latches: Vec<i64> = (0..sim.positions().len()).map(|k| sim.latch(k)).collect();
        assert!(latches.windows(2).all(|w| w[1] > w[0]), "{latches:?}");
        assert_eq!(latches[0], (-40.0f64 * 10.25).round() as i64);

        let stalled = Scene {
            stalls: vec![Stall {
                frame: 5,
                frames: 3,
            }],
            ..small()
        };
        let sim2 = Simulator::new(&stalled, 5).unwrap();
        let l2: Vec<i64> = (0..sim2.positions().len()).map(|k| sim2.latch(k)).collect();
        assert_eq!(&l2[..6], &latches[..6]);
        assert_eq!([l2[6], l2[7], l2[8]], [l2[5]; 3]);
        // After the stall the motion resumes with the same steps.
        assert_eq!(&l2[9..], &latches[6..l2.len() - 3]);
        // Same layout: the stall does not move the deposits.
        assert_eq!(sim.deposits(), sim2.deposits());
    }

    #[test]
    fn flat_board_mean_matches_model() {
        // Bare board, slow motion: many frames of the same image row, averaged.
        let scene = Scene {
            width: 64,
            board_length: 400,
            deposits: 0,
            mean_step_px: 2.0,
            ..Scene::default()
        };
        let sim = Simulator::new(&scene, 11).unwrap();
        let frames = sim.positions().len();
        assert!(frames > 200);
        let r = 13;
        let mut sum = vec![0f64; 64];
        for k in 0..frames {
            let f = sim.render(k);
            for (acc, &v) in sum.iter_mut().zip(&f[r * 64..(r + 1) * 64]) {
                *acc += f64::from(v);
            }
        }
        let mut worst = 0f64;
        for (c, total) in sum.iter().enumerate() {
            // Written out from the scene knobs, independently of the simulator code.
            let phi0 = 0.5 + 2.0 * PI * 1.5 * c as f64 / 64.0;
            let u = (c as f64 - 32.0) / 32.0;
            let ill = 1.0 - 0.15 * u * u;
            let expected = ill * (1800.0 + 700.0 * (2.0 * PI * r as f64 / 32.0 + phi0).cos());
            let sigma = (expected / 3.0 + 9.0 + 1.0 / 12.0).sqrt() / (frames as f64).sqrt();
            let z = (total / frames as f64 - expected) / sigma;
            worst = worst.max(z.abs());
        }
        assert!(worst < 4.5, "worst z {worst}");
    }

    #[test]
    fn deposit_truth_shape() {
        let scene = Scene {
            width: 64,
            board_length: 200,
            deposits: 1,
            deposit_sizes: vec![[20, 30]],
            ..Scene::default()
        };
        let sim = Simulator::new(&scene, 2).unwrap();
        let d = sim.deposits()[0].clone();
        let (h, bg, ct) = sim.truth();
        let at = |b: i64, c: i64| (b * 64 + c) as usize;
        let (mr, mc) = (d.row + 10, d.col + 15);
        assert!((f64::from(h[at(mr, mc)]) - d.height_um).abs() < 1e-3);
        assert_eq!(h[at(d.row - 1, mc)], 0.0);
        assert_eq!(h[at(mr, d.col + 30)], 0.0);
        assert!(h[at(d.row, mc)] > 0.0 && f64::from(h[at(d.row, mc)]) < d.height_um);
        let ill = 1.0 - 0.15 * ((mc as f64 - 32.0) / 32.0).powi(2);
        assert!((f64::from(bg[at(mr, mc)]) - 2000.0 * ill).abs() < 1e-2);
        assert!((f64::from(ct[at(d.row - 1, mc)]) - 700.0 * ill).abs() < 1e-2);
    }

    #[test]
    fn saturation_patch_clamps() {
        // Lowest intensity in the patch: 0.85 * (6000 - 700) DN, well above 4095.
        let patch = Patch {
            row: 50,
            col: 10,
            rows: 20,
            cols: 8,
            background: Some(6000.0),
            contrast: None,
        };
        let zero = Patch {
            row: 100,
            col: 30,
            rows: 20,
            cols: 8,
            background: None,
            contrast: Some(0.0),
        };
        let scene = Scene {
            patches: vec![patch, zero],
            deposits: 0,
            ..small()
        };
        let dir = tempfile::tempdir().unwrap();
        simulate(&scene, 1, dir.path(), false).unwrap();
        let rec = Recording::open(dir.path()).unwrap();
        assert_eq!(rec.manifest.camera.saturation, 4095);
        let mut saturated = 0;
        for k in 0..rec.len() {
            let f = rec.frame(k).unwrap();
            let o = (f.trigger.latch as f64 / rec.manifest.calibration.counts_per_pixel + 0.5)
                .floor() as i64;
            for r in 0..f.rows {
                let b = r as i64 + o;
                // Stay one row clear of the patch border (sub-pixel motion).
                if (51..69).contains(&b) {
                    for c in 10..18 {
                        assert_eq!(f.row(r)[c], 4095, "frame {k} row {r} col {c}");
                        saturated += 1;
                    }
                }
            }
        }
        assert!(saturated > 100);
        let truth = rec.truth().unwrap().unwrap();
        assert!(truth.contrast[truth.index(110, 33).unwrap()] == 0.0);
        assert!(truth.background[truth.index(60, 12).unwrap()] > 4000.0);
    }

    #[test]
    fn unknown_scene_key() {
        let err = Scene::from_toml_str("deposits = 3\njiter_pct = 5.0\n").unwrap_err();
        assert!(err.to_string().contains("jiter_pct"), "{err}");
    }

    #[test]
    fn noise_statistics() {
        let mut rng = rng(0, 99);
        for (i, gain, read) in [(2000.0, 3.0, 3.0), (100.0, 3.0, 0.0), (5.0, 1.0, 2.0)] {
            let n = 20000;
            let v: Vec<f64> = (0..n).map(|_| noisy(i, gain, read, &mut rng)).collect();
            let mean = v.iter().sum::<f64>() / n as f64;
            let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
            let expected_var = i / gain + read * read;
            assert!(
                (mean - i).abs() < 5.0 * (expected_var / n as f64).sqrt(),
                "{i}: mean {mean}"
            );
            assert!(
                (var / expected_var - 1.0).abs() < 0.05,
                "{i}: var {var} vs {expected_var}"
            );
        }
    }
}
