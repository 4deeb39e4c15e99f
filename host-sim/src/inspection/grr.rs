//! `dpsa grr`: a gauge R&R study of the inspection in the AIAG form (ANOVA method).
//!
//! The same printed board (the scene's print: the same deposits every time) is measured
//! under `setups` set-ups of the machine, `repeats` times each. A set-up is what changes
//! between one loading of a machine and another: its own calibration (a calibration recording
//! simulated and computed afresh) and the board's own placement on the conveyor (offset and
//! rotation drawn afresh). Within a set-up only the camera noise is fresh. So, in AIAG terms,
//! the parts are the pads, the appraisers the set-ups and the trials the repeats:
//! repeatability is the scatter of one set-up, reproducibility the scatter across
//! calibrations and placements ([`dpsa_spc::msa`]).
//!
//! The volume is in % of the opening volume; `%GR&R = 6 GRR / (upper - lower fail limit of
//! the default volume window) x 100`. Only pads measured in every run count. Per pad, the
//! standard deviation of its volume over all runs (its own GR&R) gives the median and the
//! quantiles of `volume_sigma_pct_*`. Per package family, the observed scatter is set
//! against the standard uncertainty each single measurement stated (`docs/spc.md`,
//! "Uncertainty").

use crate::array::{record, record::ArrayRecording, scene::ArrayScene};
use crate::calibration;
use crate::{At, Result, SimError};
use dpsa_inspect::run::inspect_dir;
use dpsa_spc::msa::{gauge_rr, Gauge};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::Path;

/// What `dpsa grr --json` prints.
#[derive(Clone, Debug, Serialize)]
pub struct GrrReport {
    /// The scene file, as given.
    pub scene: String,
    /// Set-ups of the machine (a calibration and a placement each): the appraisers.
    pub setups: u32,
    /// Measurements under each set-up: the trials.
    pub repeats: u32,
    /// Pads measured in every run: the parts.
    pub pads: usize,
    /// The paste's background step over the board's contrast that the maps took out of the
    /// walls (`--reflectance`: the scene's; else the programs'; 0: nothing taken out).
    pub paste_background_step: f64,
    /// The volume's gauge study, % of the opening volume.
    pub volume: Gauge,
    /// The height's gauge study, um (no tolerance: `pct_tolerance` null).
    pub height: Gauge,
    /// `volume.pct_tolerance`: 6 GRR over the volume window's fail width, %.
    pub grr_pct: f64,
    /// The volume window's fail width, % of the opening volume.
    pub tolerance_pct: f64,
    /// Per pad, the standard deviation of its volume over every run (% of the opening
    /// volume): the median over the pads.
    pub volume_sigma_pct_median: f64,
    /// ... its 95th percentile.
    pub volume_sigma_pct_p95: f64,
    /// ... its largest.
    pub volume_sigma_pct_max: f64,
    /// Per pad %GR&R (6 x its sigma over the tolerance): median.
    pub grr_pct_pad_median: f64,
    /// ... and 95th percentile.
    pub grr_pct_pad_p95: f64,
    /// Height's standard deviation per pad over every run, median over the pads, um.
    pub height_sigma_um_median: f64,
    /// Pads whose call (level and class) was the same in every run.
    pub calls_consistent: usize,
    /// Per package family: the observed scatter against the stated uncertainty.
    pub families: Vec<FamilyCheck>,
    /// The machine's pixel scatter, from the first set-up's first two maps.
    pub pixels: PixelStudy,
    /// The row scatter the pads' volumes see, from the same two maps.
    pub pad_study: PadStudy,
    /// Every run's placement as the registration found it: shift (mm), rotation (deg).
    pub placements: Vec<([f64; 2], f64)>,
    /// Wall time of the whole study (calibrations included), s.
    pub seconds: f64,
}

/// One package family's stated uncertainty against its observed scatter, pooled (rms) over
/// the family's pads measured in every run. The stated one is the rms of every single
/// measurement's standard uncertainty; the observed ones are the scatter within a set-up
/// (repeatability: what the stated uncertainty predicts) and over every run (with the
/// set-ups' calibrations and placements, which it does not claim to cover).
#[derive(Clone, Debug, Serialize)]
pub struct FamilyCheck {
    /// The family (`dpsa program`'s families).
    pub family: String,
    /// Its pads measured in every run.
    pub pads: usize,
    /// Volume: observed within a set-up, % of the opening volume.
    pub volume_sigma_pct: f64,
    /// Volume: observed over every run.
    pub volume_sigma_all_pct: f64,
    /// Volume: stated.
    pub volume_u_pct: f64,
    /// `volume_u_pct / volume_sigma_pct`.
    pub volume_ratio: f64,
    /// Of the stated volume variance, the local surface's share.
    pub volume_u_surface_share: f64,
    /// ... and the rows' shifts' share (the program's `measure.row_sigma_um`).
    pub volume_u_row_share: f64,
    /// Height: observed within a set-up, um.
    pub height_sigma_um: f64,
    /// Height: observed over every run, um.
    pub height_sigma_all_um: f64,
    /// Height: stated, um.
    pub height_u_um: f64,
    /// `height_u_um / height_sigma_um`.
    pub height_ratio: f64,
}

/// The machine's pixel scatter from two maps of the same board under one set-up (the same
/// calibration and placement, so the same pixels): their difference over `sqrt 2` is one
/// map's error. Per map row segment (the row's pixels of one camera in both maps, in pieces
/// of at most [`SEGMENT`] columns), the common shift along the motion that best explains the
/// difference on the walls (slope over 5 um a pixel along the motion) is fitted; the rest is
/// modelled pixel by pixel as noise
/// plus a lateral scatter times the slope, `e^2 = noise^2 + (lateral g)^2`, by least squares
/// on the squares (three rounds, each refitting the shifts). The shifts' own variance is
/// theirs minus what the noise puts in their fit. The four figures are the program's
/// `measure.lateral_sigma_um`, `row_sigma_um` and `row_correlation` (`docs/spc.md`,
/// "Uncertainty"), and the bare pixel noise.
#[derive(Clone, Debug, Default, Serialize)]
pub struct PixelStudy {
    /// Pixels compared.
    pub pixels: usize,
    /// Row segments whose shift was fitted.
    pub rows: usize,
    /// A pixel's noise where the board is flat, um.
    pub noise_um: f64,
    /// A pixel's lateral scatter (both axes), um.
    pub lateral_sigma_um: f64,
    /// The scatter of a whole row segment's place along the motion, um.
    pub row_sigma_um: f64,
    /// The correlation of neighbouring rows' shifts.
    pub row_correlation: f64,
}

/// The row scatter along the motion that the pads' volumes see, from the same two maps as
/// the [`PixelStudy`] (one set-up, so the difference of a pad's two volumes over `sqrt 2` is
/// one measurement's error).
///
/// Each pad's stated volume variance is the rest (noise, lateral scatter, local surface)
/// plus `row^2` times its rows' part per um^2 (`volume_var_per_row_um2`, which the row
/// correlation the program gives is in). The row scatter here is the one that makes the
/// stated variances, summed over the pads, equal the pads' squared errors summed:
/// `row^2 = sum (d^2 - rest) / sum per` (the moments' estimate; the rest with the program's
/// other constants). The pixel study fits a shift to each row's pixels; a volume sums a
/// wall over several rows, so the two differ where a row's pixels are moved by more than
/// their sum is (`docs/spc.md`, "The pad study").
#[derive(Clone, Debug, Default, Serialize)]
pub struct PadStudy {
    /// Pads measured on both maps.
    pub pads: usize,
    /// The row scatter, um; null when the pads' errors are within the rest of their stated
    /// variance (nothing left for the rows) or no pad has a rows' part.
    pub row_sigma_um: Option<f64>,
    /// Its standard error, um, from the pads' scatter about the fit.
    pub row_sigma_se_um: Option<f64>,
    /// The program's `measure.row_sigma_um` the maps were inspected with, um.
    pub program_row_sigma_um: f64,
}

/// The moments' fit of [`PadStudy`]: per pad its squared error `d2`, the rest of its stated
/// variance `rest` and its rows' part per unit `per`; returns the row scatter and its
/// standard error (`None` where the fit has no positive value).
fn pad_row_fit(d2: &[f64], rest: &[f64], per: &[f64]) -> (Option<f64>, Option<f64>) {
    let den: f64 = per.iter().sum();
    let num: f64 = d2.iter().zip(rest).map(|(d, r)| d - r).sum();
    if !(den > 0.0 && num > 0.0 && num.is_finite() && den.is_finite()) {
        return (None, None);
    }
    let r2 = num / den;
    let resid: f64 = d2
        .iter()
        .zip(rest)
        .zip(per)
        .map(|((d, r), p)| (d - r - r2 * p).powi(2))
        .sum();
    let se_r2 = resid.sqrt() / den;
    let r = r2.sqrt();
    (Some(r), Some(se_r2 / (2.0 * r)))
}

/// [`PadStudy`] of two runs' volumes `v0`, `v1`, stated variances `u0`, `u1` and rows' parts
/// per um^2 `p0`, `p1` (%, per pad; NaN: not measured), inspected with `program_row` um.
fn pad_study(v: [&[f64]; 2], u: [&[f64]; 2], p: [&[f64]; 2], program_row: f64) -> PadStudy {
    let (mut d2, mut rest, mut per) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..v[0].len() {
        let (a, b) = (v[0][k], v[1][k]);
        let (ua, ub, pa, pb) = (u[0][k], u[1][k], p[0][k], p[1][k]);
        if ![a, b, ua, ub, pa, pb].iter().all(|x| x.is_finite()) {
            continue;
        }
        let pk = 0.5 * (pa + pb);
        d2.push(0.5 * (a - b).powi(2));
        rest.push(0.5 * (ua + ub) - program_row * program_row * pk);
        per.push(pk);
    }
    let (row_sigma_um, row_sigma_se_um) = pad_row_fit(&d2, &rest, &per);
    PadStudy {
        pads: d2.len(),
        row_sigma_um,
        row_sigma_se_um,
        program_row_sigma_um: program_row,
    }
}

/// Most columns of a row segment in [`PixelStudy`]: about the width of a small pad's cell
/// (0.9 mm at the arrays' 27.7 um pixels).
///
/// The pads' stated uncertainty moves each of a cell's rows by one shift, so the shift to
/// measure is the mean over a cell's width. A row's shift is not the same all along it:
/// each camera's rows move on their own (the camera's own trigger), and within a camera the
/// rows' places still vary with the pixels' phase (`dpsa_board::places`). So a segment never
/// spans two cameras, and it is as wide as a cell. On the small board (`docs/spc.md`,
/// "Where the walls' scatter comes from") segments of 16, 32, 64 and 128 columns within a
/// camera read the row scatter 4.6, 4.3, 4.0 and 3.7 um; 128 columns regardless of camera
/// read 3.5 um, and the shift they missed went into the lateral scatter (1.7 um against 1.2
/// at 32 columns).
pub const SEGMENT: usize = 32;

/// The camera key of a pixel that neither map, or not both alike, gives a camera.
pub const NO_CAMERA: u8 = 255;

/// Per pixel, the camera both maps took it from (`camera.png` of each: [`NO_CAMERA`] where
/// they differ or either is invalid). Such pixels fit no row shift; they stay in the noise
/// and lateral fit (a few columns at the seams).
pub fn camera_key(a: &[u8], b: &[u8]) -> Vec<u8> {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| if x == y { x } else { NO_CAMERA })
        .collect()
}

/// Fits `e^2 = c0 + c1 g^2` by least squares over the pairs `(g^2, e^2)`.
fn fit_squares(pairs: &[(f64, f64)]) -> (f64, f64) {
    let n = pairs.len() as f64;
    let (sx, sy) = pairs
        .iter()
        .fold((0.0, 0.0), |(a, b), (x, y)| (a + x, b + y));
    let (mx, my) = (sx / n, sy / n);
    let (mut sxx, mut sxy) = (0.0, 0.0);
    for (x, y) in pairs {
        sxx += (x - mx) * (x - mx);
        sxy += (x - mx) * (y - my);
    }
    let c1 = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    (my - c1 * mx, c1)
}

/// [`PixelStudy`] of maps `a` and `b` (heights, um, the same grid) at `pitch_mm`, with the
/// pixels' [`camera_key`] (None: the whole map one camera).
pub fn pixel_study(
    a: &dpsa_formats::grid::Grid,
    b: &dpsa_formats::grid::Grid,
    cameras: Option<&[u8]>,
    pitch_mm: f64,
) -> PixelStudy {
    let (rows, w) = (a.rows, a.width);
    if b.rows != rows
        || b.width != w
        || rows < 3
        || w < 3
        || cameras.is_some_and(|c| c.len() != rows * w)
    {
        return PixelStudy::default();
    }
    let camera = |k: usize| cameras.map_or(0, |c| c[k]);
    let n_cams = cameras.map_or(1, |c| {
        c.iter()
            .filter(|&&v| v != NO_CAMERA)
            .max()
            .map_or(1, |&m| usize::from(m) + 1)
    });
    let at = |g: &dpsa_formats::grid::Grid, i: usize, j: usize| f64::from(g.data[i * w + j]);
    let mean = |i: usize, j: usize| 0.5 * (at(a, i, j) + at(b, i, j));
    // Per pixel: the difference (one map's error) and the mean map's slopes.
    let mut d = vec![f64::NAN; rows * w];
    let mut gx = vec![f64::NAN; rows * w];
    let mut gy = vec![f64::NAN; rows * w];
    for i in 1..rows - 1 {
        for j in 1..w - 1 {
            let k = i * w + j;
            d[k] = (at(a, i, j) - at(b, i, j)) / std::f64::consts::SQRT_2;
            gx[k] = 0.5 * (mean(i + 1, j) - mean(i - 1, j));
            gy[k] = 0.5 * (mean(i, j + 1) - mean(i, j - 1));
        }
    }
    let ok: Vec<bool> = (0..rows * w)
        .map(|k| d[k].is_finite() && gx[k].is_finite() && gy[k].is_finite())
        .collect();
    let g2 = |k: usize| gx[k] * gx[k] + gy[k] * gy[k];
    let pixels = ok.iter().filter(|v| **v).count();
    if pixels < 1000 {
        return PixelStudy::default();
    }
    let mut c = fit_squares(
        &(0..rows * w)
            .filter(|&k| ok[k])
            .map(|k| (g2(k), d[k] * d[k]))
            .collect::<Vec<_>>(),
    );
    // A segment: a row, a block of SEGMENT columns and a camera; row `i`'s segment of
    // block `s` and camera `cam` is `shift[i * segs + seg(s, cam)]`.
    let blocks = w.div_ceil(SEGMENT);
    let segs = blocks * n_cams;
    let seg = |s: usize, cam: usize| s * n_cams + cam;
    let mut shift = vec![f64::NAN; rows * segs];
    let mut row_var = 0.0;
    for _ in 0..3 {
        let mut r = d.clone();
        let mut noise_in_shift = Vec::new();
        shift.fill(f64::NAN);
        let mut acc = vec![(0.0, 0.0, 0.0, 0usize); n_cams];
        for i in 0..rows {
            for s in 0..blocks {
                let cols = s * SEGMENT..((s + 1) * SEGMENT).min(w);
                acc.fill((0.0, 0.0, 0.0, 0));
                for j in cols.clone() {
                    let k = i * w + j;
                    let cam = camera(k);
                    if ok[k] && cam != NO_CAMERA && gx[k].abs() > 5.0 {
                        let (gd, gg, gge, n) = &mut acc[usize::from(cam)];
                        *gd += gx[k] * d[k];
                        *gg += gx[k] * gx[k];
                        *gge += gx[k] * gx[k] * (c.0 + c.1 * g2(k)).max(0.0);
                        *n += 1;
                    }
                }
                for (cam, &(gd, gg, gge, n)) in acc.iter().enumerate() {
                    if n < 5 {
                        continue;
                    }
                    let delta = gd / gg;
                    shift[i * segs + seg(s, cam)] = delta;
                    noise_in_shift.push(gge / (gg * gg));
                    for j in cols.clone() {
                        let k = i * w + j;
                        if ok[k] && usize::from(camera(k)) == cam {
                            r[k] -= gx[k] * delta;
                        }
                    }
                }
            }
        }
        let fitted: Vec<f64> = shift.iter().copied().filter(|v| v.is_finite()).collect();
        if fitted.len() < 10 {
            break;
        }
        row_var = (var(&fitted) - noise_in_shift.iter().sum::<f64>() / noise_in_shift.len() as f64)
            .max(0.0);
        c = fit_squares(
            &(0..rows * w)
                .filter(|&k| ok[k])
                .map(|k| (g2(k), r[k] * r[k]))
                .collect::<Vec<_>>(),
        );
    }
    let fitted: Vec<f64> = shift.iter().copied().filter(|v| v.is_finite()).collect();
    let m = fitted.iter().sum::<f64>() / fitted.len().max(1) as f64;
    let (mut cov, mut n) = (0.0, 0);
    for i in 1..rows {
        for s in 0..segs {
            let (p, q) = (shift[(i - 1) * segs + s], shift[i * segs + s]);
            if p.is_finite() && q.is_finite() {
                cov += (p - m) * (q - m);
                n += 1;
            }
        }
    }
    let um = pitch_mm * 1000.0;
    PixelStudy {
        pixels,
        rows: fitted.len(),
        noise_um: c.0.max(0.0).sqrt(),
        lateral_sigma_um: c.1.max(0.0).sqrt() * um,
        row_sigma_um: row_var.sqrt() * um,
        row_correlation: if n > 0 && row_var > 0.0 {
            (cov / n as f64 / row_var).clamp(-1.0, 1.0)
        } else {
            0.0
        },
    }
}

fn quantile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

/// Sample variance (ddof 1) of `v`.
fn var(v: &[f64]) -> f64 {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0)
}

/// One run's figures per pad.
struct Run {
    volume: Vec<f64>,
    height: Vec<f64>,
    /// Stated variances: volume, its surface part, height.
    stated: Vec<[f64; 3]>,
    /// The volume variance's rows' part per um^2 of row scatter.
    row_part: Vec<f64>,
    calls: Vec<String>,
}

/// Runs the study in `work` (created; its recordings are removed as it goes); with
/// `reflectance`, every run's program takes the scene's paste reflectance out of the walls
/// ([`crate::array::render::paste_background_step`]).
pub fn grr(
    scene_path: &Path,
    setups: u32,
    repeats: u32,
    seed: u64,
    reflectance: bool,
    work: &Path,
) -> Result<GrrReport> {
    if !(2..=20).contains(&setups) {
        return Err(SimError::Refused(format!(
            "--setups {setups}: need 2 to 20"
        )));
    }
    if !(2..=100).contains(&repeats) {
        return Err(SimError::Refused(format!(
            "--repeats {repeats}: need 2 to 100"
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
    let mut runs: Vec<Run> = Vec::new();
    let mut paste_step = 0.0;
    let mut placements = Vec::new();
    let mut tolerance = f64::NAN;
    let mut family: Vec<&'static str> = Vec::new();
    let mut first_maps: Vec<dpsa_inspect::map::BoardMap> = Vec::new();
    let mut first_cameras: Vec<Vec<u8>> = Vec::new();
    let mut program_row = f64::NAN;
    for a in 0..setups {
        // The set-up: its own calibration and its own placement.
        let setup_seed = seed.wrapping_add(1000 * u64::from(a));
        let cal_dir = work.join("calibration");
        let _ = std::fs::remove_dir_all(&cal_dir);
        record::simulate_calibration(&scene, setup_seed, &cal_dir)?;
        let cal =
            calibration::calibrate(&ArrayRecording::open(&cal_dir)?, calibration::FX_BUDGET_UM)?;
        let _ = std::fs::remove_dir_all(&cal_dir);
        let mut placed = scene.clone();
        placed.placement.seed = Some(setup_seed.wrapping_add(0x5eed));
        for t in 0..repeats {
            let board = work.join("board");
            let map = work.join("map");
            let _ = std::fs::remove_dir_all(&board);
            let _ = std::fs::remove_dir_all(&map);
            record::simulate_board(&placed, setup_seed + 1 + u64::from(t), &board)?;
            let program_path = board.join("program.toml");
            let program = super::program::Program::load(&program_path)
                .map_err(dpsa_inspect::InspectError::from)?;
            paste_step = if reflectance {
                crate::array::render::paste_background_step(&scene)
            } else {
                program.reflectance.background_step
            };
            let opts = crate::board::run::Options {
                paste: dpsa_board::places::PasteReflectance::new(paste_step, program.stencil_um),
                ..Default::default()
            };
            let source = crate::board::run::Source::Core;
            crate::board::run::run_shown(&board, &cal, &map, source, &opts)?;
            let (report, insp) = inspect_dir(&map, &program_path, None, 1)?;
            if a == 0 && t < 2 {
                first_maps.push(dpsa_inspect::map::BoardMap::open(&map)?);
                let cameras = map.join("camera.png");
                let (values, _) = dpsa_formats::images::read_png_indexed(&cameras)
                    .map_err(|e| SimError::Refused(format!("{}: {e}", cameras.display())))?;
                first_cameras.push(values);
            }
            tolerance = program.windows.volume_pct.fail[1] - program.windows.volume_pct.fail[0];
            program_row = program.measure.row_sigma_um;
            placements.push((
                report.registration.shift_mm,
                report.registration.rotation_deg,
            ));
            if family.is_empty() {
                let (pads, _) = dpsa_inspect::run::paste_layer_pads(&program, &program_path)?;
                let packages = dpsa_inspect::teach::component_packages(&program, &program_path)
                    .unwrap_or_default();
                family = dpsa_inspect::teach::families::classify(&pads, &packages);
            }
            if let Some(first) = runs.first() {
                if first.volume.len() != insp.measurements.len() {
                    return Err(SimError::refused("the pad count changed between runs"));
                }
            }
            let mut run = Run {
                volume: Vec::new(),
                height: Vec::new(),
                stated: Vec::new(),
                row_part: Vec::new(),
                calls: Vec::new(),
            };
            for (m, c) in insp.measurements.iter().zip(&insp.calls) {
                let ok = m.unmeasurable.is_none();
                run.volume.push(if ok { m.volume_pct } else { f64::NAN });
                run.height.push(if ok { m.height_um } else { f64::NAN });
                run.stated.push([
                    m.volume_u_pct.powi(2),
                    m.volume_u_surface_pct.powi(2),
                    m.height_u_um.powi(2),
                ]);
                run.row_part.push(if ok {
                    m.volume_var_per_row_um2
                } else {
                    f64::NAN
                });
                run.calls.push(format!("{:?}{:?}", c.level, c.class));
            }
            runs.push(run);
            let _ = std::fs::remove_dir_all(&board);
            let _ = std::fs::remove_dir_all(&map);
        }
    }
    let n_pads = runs[0].volume.len();
    let all_finite = |k: usize| {
        runs.iter().all(|r| {
            r.volume[k].is_finite()
                && r.height[k].is_finite()
                && r.stated[k].iter().all(|v| v.is_finite())
                && r.row_part[k].is_finite()
        })
    };
    let pads: Vec<usize> = (0..n_pads).filter(|&k| all_finite(k)).collect();
    if pads.len() < 2 {
        return Err(SimError::refused(
            "fewer than 2 pads were measured in every run",
        ));
    }
    let (a_n, r_n) = (setups as usize, repeats as usize);
    // Values in the study's order: pad, set-up, trial (runs are set-up after set-up).
    let order = |f: &dyn Fn(&Run, usize) -> f64| -> Vec<f64> {
        pads.iter()
            .flat_map(|&k| runs.iter().map(move |r| (r, k)))
            .map(|(r, k)| f(r, k))
            .collect()
    };
    let msa_err = |e: dpsa_spc::msa::MsaError| SimError::Refused(format!("gauge study: {e}"));
    let volume = gauge_rr(
        &order(&|r, k| r.volume[k]),
        pads.len(),
        a_n,
        r_n,
        Some(tolerance),
    )
    .map_err(msa_err)?;
    let height =
        gauge_rr(&order(&|r, k| r.height[k]), pads.len(), a_n, r_n, None).map_err(msa_err)?;
    // Per pad: variance over every run, and within the set-ups (pooled).
    let within = |vals: &[f64]| {
        (0..a_n)
            .map(|a| var(&vals[a * r_n..(a + 1) * r_n]))
            .sum::<f64>()
            / a_n as f64
    };
    let mut sig = Vec::new();
    let mut hsig = Vec::new();
    // Per family: [volume within, volume all, height within, height all], stated sums (the
    // volume, its surface part, the height, the volume's rows' part), pads.
    let mut fam: BTreeMap<&str, ([f64; 4], [f64; 4], usize)> = BTreeMap::new();
    for &k in &pads {
        let v: Vec<f64> = runs.iter().map(|r| r.volume[k]).collect();
        let h: Vec<f64> = runs.iter().map(|r| r.height[k]).collect();
        sig.push(var(&v).sqrt());
        hsig.push(var(&h).sqrt());
        let e = fam
            .entry(family.get(k).copied().unwrap_or("?"))
            .or_default();
        e.0[0] += within(&v);
        e.0[1] += var(&v);
        e.0[2] += within(&h);
        e.0[3] += var(&h);
        for r in &runs {
            for (acc, s) in e.1.iter_mut().zip(r.stated[k]) {
                *acc += s / runs.len() as f64;
            }
            e.1[3] += program_row * program_row * r.row_part[k] / runs.len() as f64;
        }
        e.2 += 1;
    }
    let families = fam
        .into_iter()
        .map(|(f, (o, s, n))| {
            let n = n as f64;
            let o = o.map(|v| (v / n).sqrt());
            let (vs, hs) = ((s[0] / n).sqrt(), (s[2] / n).sqrt());
            FamilyCheck {
                family: f.to_owned(),
                pads: n as usize,
                volume_sigma_pct: o[0],
                volume_sigma_all_pct: o[1],
                volume_u_pct: vs,
                volume_ratio: vs / o[0],
                volume_u_surface_share: s[1] / s[0],
                volume_u_row_share: s[3] / s[0],
                height_sigma_um: o[2],
                height_sigma_all_um: o[3],
                height_u_um: hs,
                height_ratio: hs / o[2],
            }
        })
        .collect();
    let per_pad: Vec<f64> = sig.iter().map(|s| 600.0 * s / tolerance).collect();
    let consistent = pads
        .iter()
        .filter(|&&k| runs.iter().all(|r| r.calls[k] == runs[0].calls[k]))
        .count();
    Ok(GrrReport {
        paste_background_step: paste_step,
        scene: scene_path.display().to_string(),
        setups,
        repeats,
        pads: pads.len(),
        grr_pct: volume.pct_tolerance.unwrap_or(f64::NAN),
        volume,
        height,
        tolerance_pct: tolerance,
        volume_sigma_pct_median: quantile(&sig, 0.5),
        volume_sigma_pct_p95: quantile(&sig, 0.95),
        volume_sigma_pct_max: quantile(&sig, 1.0),
        grr_pct_pad_median: quantile(&per_pad, 0.5),
        grr_pct_pad_p95: quantile(&per_pad, 0.95),
        height_sigma_um_median: quantile(&hsig, 0.5),
        calls_consistent: consistent,
        families,
        pixels: pixel_study(
            &first_maps[0].heights,
            &first_maps[1].heights,
            Some(&camera_key(&first_cameras[0], &first_cameras[1])),
            first_maps[0].grid.pitch_mm,
        ),
        pad_study: {
            let stated = |r: &Run| r.stated.iter().map(|s| s[0]).collect::<Vec<f64>>();
            let (u0, u1) = (stated(&runs[0]), stated(&runs[1]));
            pad_study(
                [&runs[0].volume, &runs[1].volume],
                [&u0, &u1],
                [&runs[0].row_part, &runs[1].row_part],
                program_row,
            )
        },
        placements,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_formats::grid::Grid;

    /// Standard normal draws (rand's ChaCha8 stream and rand_distr's sampler).
    struct Normal(rand_chacha::ChaCha8Rng);
    impl Normal {
        fn new(seed: u64) -> Normal {
            Normal(rand::SeedableRng::seed_from_u64(seed))
        }
        fn next(&mut self) -> f64 {
            rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut self.0)
        }
    }

    const ROWS: usize = 1500;
    const W: usize = 192;
    const PITCH_MM: f64 = 0.0277;
    /// Three cameras' columns: their edges fall in the middle of segments.
    const EDGES: [usize; 2] = [80, 144];
    /// Each camera's row shift (px), its correlation with the row before, each pixel's own
    /// shift along the motion (px) and its noise (um).
    const ROW_PX: f64 = 0.15;
    const RHO: f64 = 0.3;
    const LATERAL_PX: f64 = 0.05;
    const NOISE_UM: f64 = 1.2;

    fn camera(j: usize) -> u8 {
        EDGES.iter().filter(|&&e| j >= e).count() as u8
    }

    /// A board of ridges across the motion (60 um sine along the rows, period 24 px: walls
    /// up to 15.7 um a pixel) measured with the shifts and noise above.
    fn map(seed: u64) -> Grid {
        let mut g = Normal::new(seed);
        let h = |x: f64| 60.0 * (std::f64::consts::TAU * x / 24.0).sin();
        let mut shift = [0.0f64; 3];
        let mut data = vec![0.0f32; ROWS * W];
        for i in 0..ROWS {
            for s in &mut shift {
                *s = RHO * *s + (1.0 - RHO * RHO).sqrt() * ROW_PX * g.next();
            }
            for j in 0..W {
                let x = i as f64 + shift[usize::from(camera(j))] + LATERAL_PX * g.next();
                data[i * W + j] = (h(x) + NOISE_UM * g.next()) as f32;
            }
        }
        Grid {
            width: W,
            rows: ROWS,
            data,
        }
    }

    /// The pad study's fit recovers the row scatter its pads' errors were drawn with (4,000
    /// pads: within 5 %, and within three of its standard errors), and states none where the
    /// errors leave nothing for the rows; `pad_study` pairs the two runs' pads and leaves out
    /// what either did not measure.
    #[test]
    fn the_pad_study_recovers_the_row_scatter() {
        let mut g = Normal::new(5);
        let mut uni = Normal::new(6);
        // Spread over (lo, hi) from a normal draw (not uniform: any spread will do).
        let mut between = |lo: f64, hi: f64| {
            let z = uni.next();
            lo + (hi - lo) * 0.5 * (1.0 + (z / std::f64::consts::SQRT_2).tanh())
        };
        let row: f64 = 2.3;
        let n = 4000;
        let per: Vec<f64> = (0..n).map(|_| between(0.01, 0.1)).collect();
        let rest: Vec<f64> = (0..n).map(|_| between(0.1, 0.5)).collect();
        let d2: Vec<f64> = (0..n)
            .map(|k| (rest[k] + row * row * per[k]) * g.next().powi(2))
            .collect();
        let (r, se) = pad_row_fit(&d2, &rest, &per);
        let (r, se) = (r.expect("a row"), se.expect("its error"));
        assert!((r / row - 1.0).abs() < 0.05, "{r} {se}");
        assert!((r - row).abs() < 3.0 * se && se < 0.1 * row, "{r} {se}");
        // Errors within the rest: no row.
        let small: Vec<f64> = rest.iter().map(|r| 0.5 * r).collect();
        assert_eq!(pad_row_fit(&small, &rest, &per), (None, None));
        assert_eq!(pad_row_fit(&[], &[], &[]), (None, None));
        // Through the runs' figures: a run's variance is the rest plus the program's row part.
        let program_row = 4.3;
        let (mut v0, mut v1, mut u) = (Vec::new(), Vec::new(), Vec::new());
        for k in 0..n {
            let e = (2.0_f64 * d2[k]).sqrt() * if k % 2 == 0 { 1.0 } else { -1.0 };
            v0.push(80.0 + e);
            v1.push(80.0);
            u.push(rest[k] + program_row * program_row * per[k]);
        }
        v1[3] = f64::NAN;
        let study = pad_study([&v0, &v1], [&u, &u], [&per, &per], program_row);
        assert_eq!(study.pads, n - 1);
        let want = {
            let keep = |x: &[f64]| -> Vec<f64> {
                x.iter()
                    .enumerate()
                    .filter(|(k, _)| *k != 3)
                    .map(|(_, v)| *v)
                    .collect()
            };
            pad_row_fit(&keep(&d2), &keep(&rest), &keep(&per))
                .0
                .expect("a row")
        };
        let got = study.row_sigma_um.expect("a row");
        assert!((got / want - 1.0).abs() < 1e-9, "{got} {want}");
    }

    /// The study recovers each camera's row scatter (within 6 %; 1 to 3 % over seeds), its
    /// correlation and the noise it was given (within 8 %: it reads about 5 % high); told
    /// nothing of the cameras, its segments that span two of them fit a mean of two shifts and
    /// read the row scatter 7 to 10 % low. The lateral scatter reads low: by about a quarter
    /// here (6 % with no row shifts: the slopes' own noise), so this test holds it within
    /// 30 %; on the boards it is the smallest of the terms (`docs/spc.md`).
    #[test]
    fn pixel_study_recovers_the_scatter_it_was_given() {
        let (a, b) = (map(1), map(2));
        let cams: Vec<u8> = (0..ROWS * W).map(|k| camera(k % W)).collect();
        let key = camera_key(&cams, &cams);
        assert_eq!(key, cams);
        let um = PITCH_MM * 1000.0;
        let p = pixel_study(&a, &b, Some(&key), PITCH_MM);
        let rel = |got: f64, want: f64| (got / want - 1.0).abs();
        assert!(rel(p.row_sigma_um, ROW_PX * um) < 0.06, "{p:?}");
        assert!((p.row_correlation - RHO).abs() < 0.08, "{p:?}");
        assert!(rel(p.lateral_sigma_um, LATERAL_PX * um) < 0.3, "{p:?}");
        assert!(rel(p.noise_um, NOISE_UM) < 0.08, "{p:?}");
        let blind = pixel_study(&a, &b, None, PITCH_MM);
        assert!(blind.row_sigma_um < 0.95 * ROW_PX * um, "{blind:?}");
        // Pixels the two maps took from different cameras are left out of the rows' shifts
        // (they stay in the noise and lateral fit).
        let mut other = cams.clone();
        other[..W * ROWS / 2].fill(0);
        let half = camera_key(&cams, &other);
        assert_eq!(
            half.iter().filter(|&&c| c == NO_CAMERA).count(),
            (W - EDGES[0]) * ROWS / 2
        );
        let p = pixel_study(&a, &b, Some(&half), PITCH_MM);
        assert!(rel(p.row_sigma_um, ROW_PX * um) < 0.08, "{p:?}");
        // A camera grid of the wrong size: no study.
        assert_eq!(pixel_study(&a, &b, Some(&key[1..]), PITCH_MM).pixels, 0);
    }
}
