//! Estimating a camera's calibration from its calibration recordings (never from the truth).
//!
//! 1. **Planes.** A flat plane shows the same fringes in every frame (the fringes are fixed in
//!    the image), so each plane's frames are averaged into one mean image. Per plane and
//!    column a sinusoid `a + b cos(2 pi f r) + d sin(2 pi f r)` is fitted along the rows
//!    (Gauss-Newton in `f`); the per-column frequencies become one weighted quadratic
//!    `f_x(u)` across the field; with it fixed, the per-column phase `psi_p(c)` of every
//!    plane is refitted linearly. Per column, `psi_p = phi_0 + 2 pi h_p / T_z` (unwrapped
//!    with the nominal `T_z`) is a straight line in the known plane heights: slope `T_z(c)`,
//!    intercept `phi_0(c)`. Flat field and modulation come from the same fits; per pixel, a
//!    fit across the planes finds dead and low-modulation pixels.
//! 2. **Lateral target.** With the fringe model known, each target frame is divided by the
//!    plane model at height 0, leaving the printed reflectance; marks are local dips, located
//!    by their weighted centroid, identified on the known grid from the design position and
//!    fitted (linear least squares) to `Y = y0 + A c + B r`, `X = x0 + e / cpm + A r - B c`:
//!    pitch `hypot(A, B)`, rotation `atan2(B, A)`, encoder scale `cpm`, and the core's
//!    `counts_per_pixel = pitch * cpm / cos(rotation)`.
//! 3. **Core tables.** The core keeps one `f_x` per camera (the field mean). Its reference
//!    phase table is measured the way the core measures: the f64 reference D-PSA runs on the
//!    plane recordings with the calibrated encoder scale and `f_x`, and `phi_core(c)` is the
//!    circular mean of `D - 2 pi h_p / T_z(c)`. The height error the field variation of
//!    `f_x` still causes (it depends on the phase and the entry row) is computed for the
//!    nominal window and reported against the budget.

use crate::array::record::{ArrayRecording, Kind, PassKind};
use crate::calibration::file::{CalFile, CameraCal, Lateral, CAL_FORMAT, CAL_VERSION};
use crate::reference::{self, LazyFrames, PhaseFit};
use crate::simulation::recording::Recording;
use crate::simulation::scene::round_counts_per_pixel;
use crate::{At, Result, SimError};
use dpsa_formats::calibration::wrap_phase;
use nalgebra::{DMatrix, DVector, Matrix3, Matrix4, Vector3, Vector4};
use std::f64::consts::TAU;

/// Default budget of the height error caused by the field variation of `f_x`, um.
pub const FX_BUDGET_UM: f64 = 0.5;
/// Smallest height difference between two calibration planes, um.
pub const MIN_PLANE_SPACING_UM: f64 = 5.0;

/// `n` copies of `v` for the image-sized buffers (`rows x width` of a camera, up to
/// 4096 x 8192): reserved with `try_reserve_exact`, so that a size the machine cannot hold
/// is an error naming the buffer instead of an abort without a message.
fn filled<T: Clone>(n: usize, v: T, what: &str) -> Result<Vec<T>> {
    let mut out = Vec::new();
    out.try_reserve_exact(n).map_err(|e| {
        SimError::Refused(format!(
            "cannot allocate the {what} ({n} values of {} bytes, {:.0} MB): {e}",
            size_of::<T>(),
            n as f64 * size_of::<T>() as f64 / 1e6
        ))
    })?;
    out.resize(n, v);
    Ok(out)
}

/// Mean image of a recording, row-major `rows x width`, and the frame count.
fn mean_image(rec: &Recording) -> Result<Vec<f64>> {
    let (h, w) = (rec.rows(), rec.width());
    let mut sum = filled(
        h.saturating_mul(w),
        0f64,
        "mean image of a calibration plane",
    )?;
    for k in 0..rec.len() {
        let f = rec.frame(k)?;
        for (s, &v) in sum.iter_mut().zip(&f.data) {
            *s += f64::from(v);
        }
    }
    let n = rec.len().max(1) as f64;
    sum.iter_mut().for_each(|s| *s /= n);
    Ok(sum)
}

/// A sinusoid along the rows of one column.
#[derive(Clone, Copy, Debug)]
struct Sine {
    a: f64,
    b: f64,
    d: f64,
    f: f64,
    var_f: f64,
    resid_var: f64,
}

impl Sine {
    fn value(&self, r: f64) -> f64 {
        let (s, c) = (TAU * self.f * r).sin_cos();
        self.a + self.b * c + self.d * s
    }
    /// Phase `psi` with `b cos + d sin = A cos(2 pi f r + psi)`.
    fn phase(&self) -> f64 {
        (-self.d).atan2(self.b)
    }
    fn amplitude(&self) -> f64 {
        self.b.hypot(self.d)
    }
}

/// Linear fit of `a + b cos + d sin` at a known frequency.
fn fit_linear(y: &[f64], keep: &[bool], f: f64) -> Option<Sine> {
    let mut ata = Matrix3::<f64>::zeros();
    let mut aty = Vector3::<f64>::zeros();
    let mut n = 0usize;
    for (r, (&v, &k)) in y.iter().zip(keep).enumerate() {
        if !k {
            continue;
        }
        let (s, c) = (TAU * f * r as f64).sin_cos();
        let row = Vector3::new(1.0, c, s);
        ata += row * row.transpose();
        aty += row * v;
        n += 1;
    }
    let p = ata.try_inverse()? * aty;
    let mut sine = Sine {
        a: p[0],
        b: p[1],
        d: p[2],
        f,
        var_f: f64::INFINITY,
        resid_var: 0.0,
    };
    let rss: f64 = y
        .iter()
        .zip(keep)
        .enumerate()
        .filter(|(_, (_, &k))| k)
        .map(|(r, (&v, _))| (v - sine.value(r as f64)).powi(2))
        .sum();
    sine.resid_var = rss / (n.saturating_sub(3).max(1)) as f64;
    Some(sine)
}

/// Gauss-Newton fit of `a + b cos(2 pi f r) + d sin(2 pi f r)` starting at `f0`.
fn fit_sine(y: &[f64], keep: &[bool], f0: f64) -> Option<Sine> {
    let mut s = fit_linear(y, keep, f0)?;
    let mut info = Matrix4::<f64>::zeros();
    for _ in 0..12 {
        let mut jtj = Matrix4::<f64>::zeros();
        let mut jtr = Vector4::<f64>::zeros();
        for (r, (&v, &k)) in y.iter().zip(keep).enumerate() {
            if !k {
                continue;
            }
            let rf = r as f64;
            let (sn, cs) = (TAU * s.f * rf).sin_cos();
            let j = Vector4::new(1.0, cs, sn, TAU * rf * (-s.b * sn + s.d * cs));
            jtj += j * j.transpose();
            jtr += j * (v - s.value(rf));
        }
        let step = jtj.try_inverse()? * jtr;
        s.a += step[0];
        s.b += step[1];
        s.d += step[2];
        s.f += step[3];
        info = jtj;
        if step[3].abs() < 1e-13 {
            break;
        }
    }
    let mut fin = fit_linear(y, keep, s.f)?;
    let cov = info.try_inverse()?;
    fin.var_f = cov[(3, 3)] * fin.resid_var;
    Some(fin)
}

/// What the plane fits of one camera found.
struct PlaneFit {
    poly: [f64; 3],
    phi0: Vec<f64>,
    tz: Vec<f64>,
    background: Vec<f64>,
    modulation: Vec<f64>,
    /// Per-pixel model at height 0: `a(r,c)` and amplitude `A(r,c)`.
    pix_a: Vec<f64>,
    pix_amp: Vec<f64>,
    dead: Vec<[u32; 2]>,
}

fn poly_at(poly: &[f64; 3], u: f64) -> f64 {
    poly[0] + poly[1] * u + poly[2] * u * u
}

fn fit_planes(
    cam: usize,
    means: &[Vec<f64>],
    heights: &[f64],
    rows: usize,
    width: usize,
    nominal_period: f64,
    nominal_tz: f64,
) -> Result<PlaneFit> {
    let half = width as f64 / 2.0;
    let u = |c: usize| (c as f64 - half) / half;
    let column =
        |img: &[f64], c: usize| -> Vec<f64> { (0..rows).map(|r| img[r * width + c]).collect() };
    // Pass 1: all rows; pixels far off their column's sinusoid in any plane are excluded.
    let mut keep = filled(rows * width, true, "per-pixel outlier mask")?;
    for img in means {
        for c in 0..width {
            let y = column(img, c);
            let all = vec![true; rows];
            let Some(s) = fit_sine(&y, &all, 1.0 / nominal_period) else {
                continue;
            };
            let amp = s.amplitude();
            // Robust scale: median absolute residual.
            let mut res: Vec<f64> = (0..rows)
                .map(|r| (y[r] - s.value(r as f64)).abs())
                .collect();
            let mut sorted = res.clone();
            sorted.sort_by(f64::total_cmp);
            let mad = sorted[rows / 2].max(1e-9);
            for (r, e) in res.iter_mut().enumerate() {
                if *e > (8.0 * 1.4826 * mad).max(0.05 * amp) {
                    keep[r * width + c] = false;
                }
            }
        }
    }
    // Pass 2: per-plane, per-column frequency fits -> one quadratic across the field.
    let mut xs = Vec::new();
    let mut ys = Vec::new();
    let mut ws = Vec::new();
    for img in means {
        for c in 0..width {
            let k: Vec<bool> = (0..rows).map(|r| keep[r * width + c]).collect();
            if k.iter().filter(|&&x| x).count() < 8 {
                continue;
            }
            if let Some(s) = fit_sine(&column(img, c), &k, 1.0 / nominal_period) {
                if s.var_f.is_finite() && s.var_f > 0.0 {
                    xs.push(u(c));
                    ys.push(s.f);
                    ws.push(1.0 / s.var_f);
                }
            }
        }
    }
    if xs.len() < 3 {
        return Err(SimError::Refused(format!(
            "camera {cam}: the planes show no fringes (no column could be fitted)"
        )));
    }
    let degree = if width >= 16 { 3 } else { 1 };
    let a = DMatrix::from_fn(xs.len(), degree, |i, j| xs[i].powi(j as i32) * ws[i].sqrt());
    let b = DVector::from_iterator(ys.len(), ys.iter().zip(&ws).map(|(y, w)| y * w.sqrt()));
    let sol = a.svd(true, true).solve(&b, 1e-15).map_err(|e| {
        SimError::Refused(format!("camera {cam}: fringe frequency fit failed: {e}"))
    })?;
    let mut poly = [0.0; 3];
    for (j, v) in sol.iter().enumerate() {
        poly[j] = *v;
    }
    // Pass 3: phases at the fitted frequency; per column a line in the plane heights.
    let mut order: Vec<usize> = (0..heights.len()).collect();
    order.sort_by(|&i, &j| heights[i].total_cmp(&heights[j]));
    let k_nom = TAU / nominal_tz;
    let mut phi0 = vec![0.0; width];
    let mut tz = vec![0.0; width];
    let mut background = vec![0.0; width];
    let mut modulation = vec![0.0; width];
    let mut psi = vec![vec![0.0; width]; means.len()];
    for c in 0..width {
        let f = poly_at(&poly, u(c));
        let k: Vec<bool> = (0..rows).map(|r| keep[r * width + c]).collect();
        let mut fits = Vec::new();
        for img in means {
            let s = fit_linear(&column(img, c), &k, f).ok_or_else(|| {
                SimError::Refused(format!("camera {cam}, column {c}: too few good pixels"))
            })?;
            fits.push(s);
        }
        background[c] = fits.iter().map(|s| s.a).sum::<f64>() / fits.len() as f64;
        modulation[c] = fits.iter().map(|s| s.amplitude()).sum::<f64>() / fits.len() as f64;
        // Unwrap along increasing height with the nominal height per turn.
        let mut unwrapped = vec![0.0; fits.len()];
        let first = order[0];
        let base = fits[first].phase() - k_nom * heights[first];
        for &p in &order {
            let rel = fits[p].phase() - k_nom * heights[p];
            unwrapped[p] = base + wrap_phase(rel - base) + k_nom * heights[p];
            psi[p][c] = fits[p].phase();
        }
        let n = heights.len() as f64;
        let mh = heights.iter().sum::<f64>() / n;
        let mp = unwrapped.iter().sum::<f64>() / n;
        let sxx: f64 = heights.iter().map(|h| (h - mh).powi(2)).sum();
        let sxy: f64 = heights
            .iter()
            .zip(&unwrapped)
            .map(|(h, p)| (h - mh) * (p - mp))
            .sum();
        let slope = sxy / sxx;
        let intercept = mp - slope * mh;
        let worst = heights
            .iter()
            .zip(&unwrapped)
            .map(|(h, p)| (p - intercept - slope * h).abs())
            .fold(0.0, f64::max);
        if worst > 0.5 || slope <= 0.0 {
            return Err(SimError::Refused(format!(
                "camera {cam}, column {c}: the plane phases do not lie on one line in the plane heights (residual {worst:.2} rad): are the plane heights right, and within a fringe turn of what the nominal height per turn ({nominal_tz} um) predicts?"
            )));
        }
        tz[c] = TAU / slope;
        phi0[c] = wrap_phase(intercept);
    }
    // Per pixel: background and amplitude across the planes (their phases differ).
    let mut pix_a = filled(rows * width, 0.0, "per-pixel background")?;
    let mut pix_amp = filled(rows * width, 0.0, "per-pixel amplitude")?;
    let mut dead = Vec::new();
    for r in 0..rows {
        for c in 0..width {
            let f = poly_at(&poly, u(c));
            let mut ata = Matrix3::<f64>::zeros();
            let mut aty = Vector3::<f64>::zeros();
            for (p, img) in means.iter().enumerate() {
                let ph = TAU * f * r as f64 + psi[p][c];
                let row = Vector3::new(1.0, ph.cos(), ph.sin());
                ata += row * row.transpose();
                aty += row * img[r * width + c];
            }
            let i = r * width + c;
            let (a, amp) = match ata.try_inverse() {
                Some(inv) if means.len() >= 3 => {
                    let p = inv * aty;
                    (p[0], p[1].hypot(p[2]))
                }
                _ => (background[c], modulation[c]),
            };
            pix_a[i] = a;
            pix_amp[i] = amp;
            if amp < 0.5 * modulation[c] || a < 0.5 * background[c] {
                dead.push([r as u32, c as u32]);
            }
        }
    }
    Ok(PlaneFit {
        poly,
        phi0,
        tz,
        background,
        modulation,
        pix_a,
        pix_amp,
        dead,
    })
}

/// One detected target mark.
#[derive(Clone, Copy, Debug)]
struct Mark {
    r: f64,
    c: f64,
    latch: i64,
}

/// Finds the marks of the lateral target in every frame.
fn detect_marks(rec: &Recording, pf: &PlaneFit, pitch_px: f64) -> Result<Vec<Mark>> {
    let (rows, width) = (rec.rows(), rec.width());
    let half = width as f64 / 2.0;
    let mut model = filled(rows * width, 0.0, "target's fringe model")?;
    let mut dead = filled(rows * width, false, "dead-pixel mask")?;
    for &[r, c] in &pf.dead {
        dead[r as usize * width + c as usize] = true;
    }
    for r in 0..rows {
        for c in 0..width {
            let f = poly_at(&pf.poly, (c as f64 - half) / half);
            let i = r * width + c;
            model[i] = pf.pix_a[i] + pf.pix_amp[i] * (TAU * f * r as f64 + pf.phi0[c]).cos();
        }
    }
    let rad = ((pitch_px * 0.2).round() as usize).clamp(2, 40);
    let mut out = Vec::new();
    let mut dark = filled(rows * width, 0.0, "target's darkness image")?;
    for k in 0..rec.len() {
        let fr = rec.frame(k)?;
        for i in 0..rows * width {
            dark[i] = if dead[i] || model[i] <= 1.0 {
                0.0
            } else {
                1.0 - f64::from(fr.data[i]) / model[i]
            };
        }
        if rows < 2 * rad + 1 || width < 2 * rad + 1 {
            continue;
        }
        for r in rad..rows - rad {
            for c in rad..width - rad {
                let v = dark[r * width + c];
                if v < 0.2 {
                    continue;
                }
                let mut is_max = true;
                'n: for dr in -1i64..=1 {
                    for dc in -1i64..=1 {
                        let j = (r as i64 + dr) as usize * width + (c as i64 + dc) as usize;
                        if (dr, dc) != (0, 0)
                            && (dark[j] > v || (dark[j] == v && (dr, dc) < (0, 0)))
                        {
                            is_max = false;
                            break 'n;
                        }
                    }
                }
                if !is_max {
                    continue;
                }
                let (mut sw, mut sr, mut sc) = (0.0, 0.0, 0.0);
                for rr in r - rad..=r + rad {
                    for cc in c - rad..=c + rad {
                        let w = (dark[rr * width + cc] - 0.05).max(0.0);
                        sw += w;
                        sr += w * rr as f64;
                        sc += w * cc as f64;
                    }
                }
                if sw > 0.0 {
                    out.push(Mark {
                        r: sr / sw,
                        c: sc / sw,
                        latch: fr.trigger.latch,
                    });
                }
            }
        }
    }
    Ok(out)
}

/// Fits the lateral mapping and the encoder scale to the identified marks.
fn fit_lateral(
    cam: usize,
    marks: &[Mark],
    design: (f64, f64),
    pixel_mm: f64,
    nominal_cpm: f64,
    target: &crate::array::record::TargetInfo,
) -> Result<(Lateral, f64)> {
    if marks.len() < 12 {
        return Err(SimError::Refused(format!(
            "camera {cam}: lateral target not found ({} marks detected, at least 12 needed): is the target pass recorded, lit and in focus?",
            marks.len()
        )));
    }
    let p = target.pitch_mm;
    let [ox, oy] = target.origin_mm;
    // Parameters: y0, x0, A, B, mu.
    let mut par = [design.1, design.0, pixel_mm, 0.0, 1.0 / nominal_cpm];
    let mut rms = f64::INFINITY;
    let mut used = 0;
    for _ in 0..4 {
        let mut rows_a: Vec<[f64; 5]> = Vec::new();
        let mut rhs = Vec::new();
        for m in marks {
            let [y0, x0, a, b, mu] = par;
            let y = y0 + a * m.c + b * m.r;
            let x = x0 + mu * m.latch as f64 + a * m.r - b * m.c;
            let (i, j) = (((x - ox) / p).round(), ((y - oy) / p).round());
            if i < 0.0 || j < 0.0 {
                continue;
            }
            let (xt, yt) = (ox + i * p, oy + j * p);
            if (x - xt).abs() > 0.3 * p || (y - yt).abs() > 0.3 * p {
                continue;
            }
            rows_a.push([1.0, 0.0, m.c, m.r, 0.0]);
            rhs.push(yt);
            rows_a.push([0.0, 1.0, m.r, -m.c, m.latch as f64]);
            rhs.push(xt);
        }
        used = rows_a.len() / 2;
        if used < 12 {
            return Err(SimError::Refused(format!(
                "camera {cam}: lateral target not found ({used} marks lie on the expected {p} mm grid, at least 12 needed): check the design camera positions and the target pitch"
            )));
        }
        // Scale the latch column for conditioning.
        let scale = rows_a.iter().map(|r| r[4].abs()).fold(1.0, f64::max);
        let a = DMatrix::from_fn(rows_a.len(), 5, |i, j| {
            if j == 4 {
                rows_a[i][j] / scale
            } else {
                rows_a[i][j]
            }
        });
        let b = DVector::from_vec(rhs.clone());
        let sol = a
            .clone()
            .svd(true, true)
            .solve(&b, 1e-14)
            .map_err(|e| SimError::Refused(format!("camera {cam}: lateral fit failed: {e}")))?;
        par = [sol[0], sol[1], sol[2], sol[3], sol[4] / scale];
        let res = &a * &sol - &b;
        rms = (res.norm_squared() / res.len() as f64).sqrt();
    }
    if rms > 0.05 * p {
        return Err(SimError::Refused(format!("camera {cam}: lateral target not found: the marks do not fit a {p} mm grid (residual {:.0} um rms)", rms * 1e3)));
    }
    let [y0, x0, a, b, mu] = par;
    let pitch = a.hypot(b);
    let rot = b.atan2(a);
    let cpm = 1.0 / mu;
    Ok((
        Lateral {
            x0_mm: x0,
            y0_mm: y0,
            pitch_mm: pitch,
            rotation_rad: rot,
            row_pitch_mm: pitch / rot.cos(),
            fit_rms_um: rms * 1e3,
            marks: used as u32,
        },
        cpm,
    ))
}

/// Runs the f64 reference D-PSA with the calibrated encoder scale and `f_x` and a zero
/// reference-phase table and hands every valid pixel whose samples avoid dead pixels to
/// `each(column, D, sample rows)`, with `D = wrap_phase(Phi - 2 pi f (b - o_w))` (no
/// reference-phase table) and the image rows of the pixel's `n` window samples.
///
/// Streaming, row by row: memory is one window of frames and one row, whatever the plane's
/// length (collecting the rows and pixels of a 150 mm plane held about 100 MB per camera).
pub fn plane_phases(
    rec: &Recording,
    cal: &CameraCal,
    mut each: impl FnMut(usize, f64, &[i64]),
) -> Result<()> {
    let mut m = rec.manifest.clone();
    m.calibration.counts_per_pixel = round_counts_per_pixel(cal.counts_per_pixel);
    m.calibration.fringe_period_px = cal.fringe_period_px;
    m.calibration.reference_phase_rad = vec![0.0; rec.width()];
    m.calibration.height_per_turn_um = TAU * 1000.0;
    // Phase in mrad in every column: no per-column height scale.
    m.calibration.height_per_turn_um_per_column = None;
    let mut src = LazyFrames::new(rec);
    let mut eval = reference::RowEval::dpsa(&m);
    let width = rec.width();
    let mut dead = filled(rec.rows() * width, false, "dead-pixel mask")?;
    for &[r, c] in &cal.dead_pixels {
        if let Some(d) = dead.get_mut(r as usize * width + c as usize) {
            *d = true;
        }
    }
    let mut rows: Vec<i64> = Vec::new();
    while let Some(row) = eval.next_row(&mut src) {
        let row = row?;
        let Some(win) = row.window.as_ref().filter(|_| row.is_valid()) else {
            continue;
        };
        rows.clear();
        rows.extend(win.offsets.iter().map(|o| row.row - o));
        for c in 0..width {
            if !row.valid[c] {
                continue;
            }
            if rows
                .iter()
                .any(|&r| r < 0 || r as usize >= rec.rows() || dead[r as usize * width + c])
            {
                continue;
            }
            each(c, row.phase_rad[c], &rows);
        }
    }
    Ok(())
}

/// Worst height error (um) the field variation of `f_x` causes when the core uses one value,
/// after the core table has absorbed its mean: noise-free LS over the nominal window, every
/// entry row of the entering band and 16 phases, max over columns.
pub fn fx_height_error(cal: &CameraCal, n: usize, step_px: f64, max_step: u32) -> f64 {
    let f_core = 1.0 / cal.fringe_period_px;
    let offs: Vec<f64> = (0..n).map(|j| (j as f64 * step_px).round()).collect();
    let shifts: Vec<f64> = offs.iter().map(|o| -TAU * f_core * o).collect();
    let Some(fit) = PhaseFit::new(&shifts) else {
        return f64::NAN;
    };
    let rows = i64::from(cal.rows);
    let band: Vec<f64> = ((rows - i64::from(max_step)).max(0)..rows)
        .map(|r| r as f64)
        .collect();
    let w = cal.width as usize;
    let stride = (w / 128).max(1);
    let mut worst: f64 = 0.0;
    for c in (0..w).step_by(stride).chain([w - 1]) {
        let f = cal.fringe_frequency(c as f64);
        let mut errs = Vec::new();
        for &r0 in &band {
            for q in 0..16 {
                let psi = TAU * q as f64 / 16.0;
                let samples: Vec<f64> = offs
                    .iter()
                    .map(|o| (psi + TAU * f * (r0 - o)).cos())
                    .collect();
                let (phi, _) = fit.fit(&samples);
                errs.push(wrap_phase(phi - TAU * f_core * r0 - psi));
            }
        }
        let (s, co) = errs
            .iter()
            .fold((0.0, 0.0), |(s, c), e| (s + e.sin(), c + e.cos()));
        let mean = s.atan2(co);
        let e = errs
            .iter()
            .map(|e| wrap_phase(e - mean).abs())
            .fold(0.0, f64::max);
        worst = worst.max(e * cal.height_per_turn_um[c] / TAU);
    }
    worst
}

/// Heights of a plane measured with the calibration, streamed: `each(column, h, sample rows)`
/// per valid pixel, `h` unwrapped to the turn nearest the known height.
pub fn measure_plane(
    rec: &Recording,
    cal: &CameraCal,
    known_um: f64,
    mut each: impl FnMut(usize, f64, &[i64]),
) -> Result<()> {
    plane_phases(rec, cal, |c, d, rows| {
        let t = cal.height_per_turn_um[c];
        let mut h = wrap_phase(d - cal.core_reference_phase_rad[c]) / TAU * t;
        h += t * ((known_um - h) / t).round();
        each(c, h, rows)
    })
}

/// The array calibration of a calibration recording.
pub fn calibrate(rec: &ArrayRecording, fx_budget_um: f64) -> Result<CalFile> {
    let m = &rec.manifest;
    if m.kind != Kind::Calibration {
        return Err(SimError::Refused(format!("{} is a board recording, not a calibration recording (`dpsa simulate --calibration` writes one)", rec.dir.display())));
    }
    let planes: Vec<&crate::array::record::Pass> = m
        .passes
        .iter()
        .filter(|p| p.kind == PassKind::Plane)
        .collect();
    if planes.len() < 3 {
        return Err(SimError::Refused(format!(
            "{} calibration planes, at least 3 at different known heights are needed",
            planes.len()
        )));
    }
    let mut hs: Vec<f64> = planes.iter().map(|p| p.height_um).collect();
    if hs.iter().any(|h| !h.is_finite()) {
        return Err(SimError::refused("a plane height is not a finite number"));
    }
    hs.sort_by(f64::total_cmp);
    for w in hs.windows(2) {
        if w[1] - w[0] < MIN_PLANE_SPACING_UM {
            return Err(SimError::Refused(format!(
                "two calibration planes are at {} um and {} um: planes must differ by at least {MIN_PLANE_SPACING_UM} um (equal heights give no height scale)",
                w[0],
                w[1]
            )));
        }
    }
    let target = m
        .passes
        .iter()
        .find(|p| p.kind == PassKind::Target)
        .ok_or_else(|| SimError::refused("the calibration recording has no lateral target pass"))?;
    let tinfo = m.target.as_ref().ok_or_else(|| {
        SimError::refused(
            "array.json has no `target` block (pitch and origin of the lateral target)",
        )
    })?;
    for i in 0..m.cameras.len() {
        for p in &m.passes {
            let d = rec.camera_dir(i, Some(&p.name));
            if !d.join(crate::simulation::recording::MANIFEST_FILE).exists() {
                return Err(SimError::Refused(format!(
                    "camera {i}: its recording of pass {:?} ({}) is missing",
                    p.name,
                    d.display()
                )));
            }
        }
    }
    let planes_ref: &[&crate::array::record::Pass] = &planes;
    let holdout = m.passes.iter().find(|p| p.kind == PassKind::Holdout);
    let results: Vec<Result<CameraCal>> = std::thread::scope(|sc| {
        let handles: Vec<_> = (0..m.cameras.len())
            .map(|i| {
                sc.spawn(move || {
                    calibrate_camera(rec, i, planes_ref, target, holdout, tinfo, fx_budget_um)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join().unwrap_or_else(|_| {
                    Err(SimError::Internal("calibration thread panicked".into()))
                })
            })
            .collect()
    });
    let cams = results.into_iter().collect::<Result<Vec<_>>>()?;
    let cpm = cams.iter().map(|c| c.counts_per_mm).sum::<f64>() / cams.len() as f64;
    let first = Recording::open(rec.camera_dir(0, Some(&planes[0].name)))?.manifest;
    let lsb = first.calibration.height_lsb_um;
    // The frame grabbers' processing, one for the array: every camera's recordings must agree.
    let processing = first.processing;
    for i in 1..m.cameras.len() {
        let d = rec.camera_dir(i, Some(&planes[0].name));
        let other = Recording::open(&d)?.manifest.processing;
        if other != processing {
            return Err(SimError::Refused(format!(
                "camera {i}'s recording {} has processing {other:?}, camera 0's {processing:?}: the calibration file holds one processing for the array",
                d.display()
            )));
        }
    }
    Ok(CalFile {
        format: CAL_FORMAT.into(),
        version: CAL_VERSION,
        counts_per_mm: cpm,
        height_lsb_um: lsb,
        fx_budget_um,
        processing,
        camera: cams,
    })
}

fn calibrate_camera(
    rec: &ArrayRecording,
    i: usize,
    planes: &[&crate::array::record::Pass],
    target: &crate::array::record::Pass,
    holdout: Option<&crate::array::record::Pass>,
    tinfo: &crate::array::record::TargetInfo,
    fx_budget_um: f64,
) -> Result<CameraCal> {
    let design = &rec.manifest.cameras[i];
    let open = |name: &str| -> Result<Recording> {
        let r = Recording::open(rec.camera_dir(i, Some(name)))
            .at(|| format!("camera {i}, pass {name}"))?;
        if usize::from(r.manifest.camera.id) != i {
            return Err(SimError::Refused(format!(
                "camera {i}, pass {name}: {} holds camera {}'s frames (its manifest says camera.id = {}), not camera {i}'s: the camera directories are swapped or misnamed",
                r.dir.display(),
                r.manifest.camera.id,
                r.manifest.camera.id
            )));
        }
        if (r.manifest.camera.width, r.manifest.camera.rows) != (design.width, design.rows) {
            return Err(SimError::Refused(format!(
                "camera {i}, pass {name}: {} x {} px frames, array.json says {} x {}",
                r.manifest.camera.rows, r.manifest.camera.width, design.rows, design.width
            )));
        }
        Ok(r)
    };
    let recs: Vec<Recording> = planes
        .iter()
        .map(|p| open(&p.name))
        .collect::<Result<_>>()?;
    let (rows, width) = (recs[0].rows(), recs[0].width());
    let means: Vec<Vec<f64>> = recs.iter().map(mean_image).collect::<Result<_>>()?;
    let heights: Vec<f64> = planes.iter().map(|p| p.height_um).collect();
    let nominal = &recs[0].manifest.calibration;
    let pf = fit_planes(
        i,
        &means,
        &heights,
        rows,
        width,
        nominal.fringe_period_px,
        nominal.height_per_turn_um,
    )?;

    let trec = open(&target.name)?;
    let marks = detect_marks(&trec, &pf, tinfo.pitch_mm / rec.manifest.pixel_mm)?;
    let (lateral, cpm) = fit_lateral(
        i,
        &marks,
        (design.x_mm, design.y_mm),
        rec.manifest.pixel_mm,
        rec.manifest.nominal_counts_per_mm,
        tinfo,
    )?;
    let cpp = round_counts_per_pixel(lateral.pitch_mm * cpm / lateral.rotation_rad.cos());
    let half = width as f64 / 2.0;
    let f_mean = (0..width)
        .map(|c| poly_at(&pf.poly, (c as f64 - half) / half))
        .sum::<f64>()
        / width as f64;
    let mut cal = CameraCal {
        id: i as u8,
        width: width as u32,
        rows: rows as u32,
        bit_depth: recs[0].manifest.camera.bit_depth,
        saturation: recs[0].manifest.camera.saturation,
        counts_per_pixel: cpp,
        counts_per_mm: cpm,
        fringe_period_px: 1.0 / f_mean,
        fringe_frequency_poly: pf.poly,
        fx_height_error_um: 0.0,
        fx_over_budget: false,
        height_per_turn_um: pf.tz.clone(),
        reference_phase_rad: pf.phi0.clone(),
        core_reference_phase_rad: vec![0.0; width],
        background_dn: pf.background.clone(),
        modulation_dn: pf.modulation.clone(),
        dead_pixels: pf.dead.clone(),
        background_map: super::file::relative_map(&pf.pix_a, &pf.background, rows),
        modulation_map: super::file::relative_map(&pf.pix_amp, &pf.modulation, rows),
        lateral,
    };
    // The core's table: the f64 reference D-PSA on the planes, circular mean per column.
    let mut acc = vec![(0.0f64, 0.0f64); width];
    for (r, &h) in recs.iter().zip(&heights) {
        let tz = &cal.height_per_turn_um;
        plane_phases(r, &cal, |c, d, _| {
            let e = d - TAU * h / tz[c];
            acc[c].0 += e.sin();
            acc[c].1 += e.cos();
        })?;
    }
    for (c, &(s, co)) in acc.iter().enumerate() {
        cal.core_reference_phase_rad[c] = if s == 0.0 && co == 0.0 {
            cal.reference_phase_rad[c]
        } else {
            s.atan2(co)
        };
    }
    let proc = &recs[0].manifest.processing;
    let latches: Vec<i64> = recs[0].manifest.frames.iter().map(|f| f.latch).collect();
    let step_counts = if latches.len() > 1 {
        (latches[latches.len() - 1] - latches[0]) as f64 / (latches.len() - 1) as f64
    } else {
        0.0
    };
    cal.fx_height_error_um = fx_height_error(
        &cal,
        usize::from(proc.n),
        step_counts / cal.counts_per_pixel,
        proc.max_step_rows,
    );
    cal.fx_over_budget = cal.fx_height_error_um.is_nan() || cal.fx_height_error_um > fx_budget_um;
    if let Some(p) = holdout {
        let hr = open(&p.name)?;
        let (rms, bound, bias, px) = super::evaluate::holdout_bound(&hr, &cal, p.height_um)?;
        let limit = super::evaluate::HOLDOUT_CRB_LIMIT;
        if rms.is_nan() || bound.is_nan() || rms > limit * bound {
            return Err(SimError::Refused(format!(
                "camera {i}: the held-out plane ({} um in array.json) measures {rms:.2} um rms off with this calibration (bias {bias:+.2} um over {px} px), {:.1} times its Cramer-Rao bound of {bound:.2} um (at most {limit} allowed): a plane height in array.json is wrong, or the planes are not flat, or not the heights given",
                p.height_um,
                rms / bound
            )));
        }
    }
    Ok(cal)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibration::file::Lateral;

    fn cal(poly: [f64; 3]) -> CameraCal {
        let w = 256;
        CameraCal {
            id: 0,
            width: w,
            rows: 40,
            bit_depth: 12,
            saturation: 4095,
            counts_per_pixel: 11.0,
            counts_per_mm: 400.0,
            fringe_period_px: 32.0,
            fringe_frequency_poly: poly,
            fx_height_error_um: 0.0,
            fx_over_budget: false,
            height_per_turn_um: vec![500.0; w as usize],
            reference_phase_rad: vec![0.0; w as usize],
            core_reference_phase_rad: vec![0.0; w as usize],
            background_dn: vec![1800.0; w as usize],
            modulation_dn: vec![700.0; w as usize],
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

    #[test]
    fn field_variation_error_grows_with_the_variation() {
        let f = 1.0 / 32.0;
        let none = fx_height_error(&cal([f, 0.0, 0.0]), 4, 8.0, 10);
        assert!(none < 1e-9, "{none}");
        let small = fx_height_error(&cal([f, f * 0.0005, 0.0]), 4, 8.0, 10);
        let large = fx_height_error(&cal([f, f * 0.002, 0.0]), 4, 8.0, 10);
        assert!(small > 0.0 && large > 3.0 * small, "{small} {large}");
        // 0.2 % at the field edge: a few tenths of a micrometre at 500 um per turn.
        assert!((0.05..1.0).contains(&large), "{large}");
    }

    #[test]
    fn an_image_buffer_too_large_is_an_error_naming_it() {
        let e = filled(usize::MAX / 4, 0f64, "mean image of a calibration plane").unwrap_err();
        let msg = format!("{e}");
        assert!(
            msg.starts_with("cannot allocate the mean image of a calibration plane ("),
            "{msg}"
        );
        let v = filled(12, 7u8, "x").unwrap();
        assert_eq!(v, vec![7u8; 12]);
    }

    #[test]
    fn a_sinusoid_is_fitted_exactly() {
        let f = 1.0 / 31.7;
        let y: Vec<f64> = (0..40)
            .map(|r| 1000.0 + 600.0 * (TAU * f * r as f64 + 0.7).cos())
            .collect();
        let s = fit_sine(&y, &[true; 40], 1.0 / 32.0).unwrap();
        assert!((s.f / f - 1.0).abs() < 1e-9, "{}", s.f);
        assert!((s.phase() - 0.7).abs() < 1e-7 && (s.amplitude() - 600.0).abs() < 1e-6);
    }
}
