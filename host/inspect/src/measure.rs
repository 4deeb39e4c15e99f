//! Per-pad measurement on the board map, from the local board surface.
//!
//! For every pad, with the openings placed on the board by the registration:
//!
//! - **Cell**: the points nearer to this opening's edge than to any other opening's, and at
//!   most `margin` beyond it (`margin` = `cell_margin_share` of the opening's larger size
//!   plus the wall, clamped to `cell_margin_mm`). Cells never overlap, so no paste is counted
//!   twice, and a deposit printed half a pad off, along either axis, is still measured whole
//!   (up to the clamp).
//! - **Local surface**: a surface fitted to the bare board around the pad: pixels at least
//!   `surface_guard_mm` from every opening and fiducial and within `surface_reach_mm` of this
//!   one (2, 4 and 8 times that when too few qualify: the middle of a large BGA), about
//!   [`SURFACE_SCAN`] pixels of the window looked at. A quadratic where the samples pin its
//!   curvature (a plane, then a level, where they do not): the warp curves by several um
//!   over a few mm of a bowed board, which a plane through the ring would put under the pad.
//!   The fit is robust (iteratively trimmed at 3 robust sigma, at least 3 um), so smears and
//!   neighbours' stray paste on the board do not lift it. Heights are taken above it.
//! - **Volume**: the sum of heights above the surface over the cell's pixels (an invalid pixel
//!   takes the mean of its valid 3 x 3 neighbours in the cell), in um^3 and in % of opening
//!   area x stencil thickness. No threshold: the walls' paste counts.
//! - **Area**: cell pixels above `area_threshold_pct` of the stencil, mm^2 and % of the opening.
//! - **Height**: the mean over the opening's interior (the opening shrunk by the wall width,
//!   `wall_mm`, at most a quarter of its size), um and % of stencil; the maximum of the 3 x 3
//!   means there.
//! - **Offset**: the height-weighted centre of the cell's paste (above the area threshold)
//!   against the opening's centroid, in the design frame's axes, um; judged as % of the
//!   opening's size along each axis.
//! - **Shape**: paste above `shape_threshold_um` in the cell but outside the opening grown by
//!   `wall_mm`, % of the opening area (smears).
//! - **Coverage**: valid pixels of the opening / all its pixels.
//! - **Bridges**: for neighbouring openings less than `bridge_reach_mm` apart,
//!   whether paste above `bridge_height_pct` of the stencil (over the mean of the two planes)
//!   joins them (4-connected), searched in the two openings' joint box.

use crate::map::BoardMap;
use crate::noise::NoiseModel;
use crate::program::Program;
use crate::uncertainty::{CellCounts, Uncertainty};
use dpsa_gerber::pads::{norm, Outline, Pad, Point, Prepared, Rigid};
use serde::Serialize;

/// Fewest bare-board pixels for the local surface.
pub(crate) const MIN_SURFACE_PIXELS: usize = 24;

/// About this many pixels of the surface window are looked at (a stride over larger ones).
pub const SURFACE_SCAN: usize = 1000;

/// The openings on the board (board frame) with a bin index for neighbour queries.
pub struct Placed {
    /// Each opening's outline on the board (board mm), in the pads' order.
    pub outlines: Vec<Prepared>,
    /// Each outline's box `[xmin, ymin, xmax, ymax]`, board mm.
    pub bboxes: Vec<[f64; 4]>,
    /// Smaller size of each opening (its width), mm.
    pub min_size: Vec<f64>,
    /// Larger size of each opening (its length), mm.
    pub max_size: Vec<f64>,
    /// Fiducials on the board: centre and radius, mm.
    pub fiducials: Vec<(Point, f64)>,
    bins: Vec<Vec<u32>>,
    /// Each opening's first bin (lowest x, then y) of those its box covers.
    first_bin: Vec<(u32, u32)>,
    bin_origin: Point,
    bin_mm: f64,
    nx: usize,
    ny: usize,
}

impl Placed {
    /// The `pads` (design frame) put on the board by `t`, with the `fiducials` (design mm)
    /// of diameter `fid_diameter` (mm) that the local surface keeps clear of.
    pub fn new(pads: &[Pad], t: &Rigid, fiducials: &[Point], fid_diameter: f64) -> Placed {
        let outlines: Vec<Prepared> = pads
            .iter()
            .map(|p| Prepared::new(p.outline.transformed(t)))
            .collect();
        let bboxes: Vec<[f64; 4]> = outlines.iter().map(|o| o.outline.bbox()).collect();
        // The opening's smaller and larger size (its width and length), mm.
        let (min_size, max_size): (Vec<f64>, Vec<f64>) =
            pads.iter().map(|p| opening_size(&p.outline)).unzip();
        let fids: Vec<(Point, f64)> = fiducials
            .iter()
            .map(|&f| (t.apply(f), fid_diameter / 2.0))
            .collect();
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for b in &bboxes {
            lo = [lo[0].min(b[0]), lo[1].min(b[1])];
            hi = [hi[0].max(b[2]), hi[1].max(b[3])];
        }
        if bboxes.is_empty() {
            lo = [0.0, 0.0];
            hi = [1.0, 1.0];
        }
        let bin_mm = 1.0;
        let nx = (((hi[0] - lo[0]) / bin_mm).ceil() as usize + 1).min(100_000);
        let ny = (((hi[1] - lo[1]) / bin_mm).ceil() as usize + 1).min(100_000);
        let mut placed = Placed {
            outlines,
            bboxes,
            min_size,
            max_size,
            fiducials: fids,
            bins: Vec::new(),
            first_bin: Vec::new(),
            bin_origin: lo,
            bin_mm,
            nx,
            ny,
        };
        let mut bins = vec![Vec::new(); nx.saturating_mul(ny).min(50_000_000)];
        if bins.len() == nx * ny {
            for (k, b) in placed.bboxes.iter().enumerate() {
                let (x0, x1, y0, y1) = placed.bin_range(*b);
                placed.first_bin.push((x0 as u32, y0 as u32));
                for bx in x0..=x1 {
                    for by in y0..=y1 {
                        bins[bx * ny + by].push(k as u32);
                    }
                }
            }
        }
        placed.bins = bins;
        placed
    }

    fn bin_range(&self, b: [f64; 4]) -> (usize, usize, usize, usize) {
        let f = |v: f64, o: f64, n: usize| {
            (((v - o) / self.bin_mm).floor().max(0.0) as usize).min(n.saturating_sub(1))
        };
        (
            f(b[0], self.bin_origin[0], self.nx),
            f(b[2], self.bin_origin[0], self.nx),
            f(b[1], self.bin_origin[1], self.ny),
            f(b[3], self.bin_origin[1], self.ny),
        )
    }

    /// Openings whose box comes within `reach` of box `b`, except `skip`, in ascending order.
    pub fn near(&self, b: [f64; 4], reach: f64, skip: usize) -> Vec<usize> {
        let g = [b[0] - reach, b[1] - reach, b[2] + reach, b[3] + reach];
        let mut out: Vec<usize> = Vec::new();
        if self.bins.len() == self.nx * self.ny && !self.bins.is_empty() {
            let (x0, x1, y0, y1) = self.bin_range(g);
            // An opening is in every bin its box covers: it is taken from the first of them
            // in the range only, so each comes once (then sorted: fewer to sort).
            for bx in x0..=x1 {
                for by in y0..=y1 {
                    out.extend(self.bins[bx * self.ny + by].iter().filter_map(|&k| {
                        let (fx, fy) = self.first_bin[k as usize];
                        let first = (fx as usize).max(x0) == bx && (fy as usize).max(y0) == by;
                        first.then_some(k as usize)
                    }));
                }
            }
            out.sort_unstable();
        } else {
            out = (0..self.outlines.len()).collect();
        }
        out.retain(|&k| {
            let o = &self.bboxes[k];
            k != skip && o[0] <= g[2] && o[2] >= g[0] && o[1] <= g[3] && o[3] >= g[1]
        });
        out
    }
}

/// Why a pad could not be judged.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Unmeasurable {
    /// The opening is not (wholly) on the map.
    OutsideMap,
    /// Too few valid pixels in the opening.
    LowCoverage,
    /// Too little bare board around the pad for its surface.
    NoSurface,
}

/// What was measured on one pad. A pad that is not measurable keeps the figures it reached
/// before the reason was found (0 where none was taken).
#[derive(Clone, Debug, Default, Serialize)]
pub struct PadMeasurement {
    /// The pad's index in the paste layer.
    pub pad: usize,
    /// `None` when judged; else why not.
    pub unmeasurable: Option<Unmeasurable>,
    /// Valid pixels of the opening / its pixels.
    pub coverage: f64,
    /// Opening area, mm^2 (design).
    pub opening_mm2: f64,
    /// Paste volume over the cell above the local surface, um^3.
    pub volume_um3: f64,
    /// The volume, % of opening area x stencil thickness.
    pub volume_pct: f64,
    /// Cell area above `area_threshold_pct` of the stencil, mm^2.
    pub area_mm2: f64,
    /// The area, % of the opening's.
    pub area_pct: f64,
    /// Mean height over the opening's interior (shrunk by the wall), um; NaN when no valid
    /// pixel lies there.
    pub height_um: f64,
    /// The height, % of the stencil thickness (NaN with it).
    pub height_pct: f64,
    /// Largest 3 x 3 mean over the interior, um (the mean height when none has 5 valid
    /// pixels).
    pub height_max_um: f64,
    /// Deposit centre minus opening centre, design-frame axes, um (NaN: no paste).
    pub offset_um: [f64; 2],
    /// The larger of `|offset| / size` over the two axes, %.
    pub offset_pct: f64,
    /// Paste above `shape_threshold_um` beyond the opening grown by the wall, % of the
    /// opening area.
    pub shape_pct: f64,
    /// Board pixels kept by the local surface's fit.
    pub surface_pixels: usize,
    /// Their rms about the surface, um.
    pub surface_rms_um: f64,
    /// Standard uncertainty of the volume, um^3 (NaN when not measured; see
    /// [`crate::uncertainty`]).
    pub volume_u_um3: f64,
    /// The volume's standard uncertainty, % of the opening volume.
    pub volume_u_pct: f64,
    /// Of it, the part from the local surface (the rest is the cell pixels' noise), % of the
    /// opening volume.
    pub volume_u_surface_pct: f64,
    /// The part of the volume's variance that the rows' shifts along the motion put in, per
    /// um^2 of the program's `measure.row_sigma_um`, (% of the opening volume)^2 per um^2
    /// (`dpsa grr`'s pad study takes it apart from the rest; not in the reports).
    #[serde(skip)]
    pub volume_var_per_row_um2: f64,
    /// Standard uncertainty of the height, um.
    pub height_u_um: f64,
    /// The height's standard uncertainty, % of the stencil thickness.
    pub height_u_pct: f64,
    /// Pixel noise on the paste (the opening's interior), um: from neighbouring pixels'
    /// differences there, or the bare board's where the interior is too small to tell.
    pub paste_sigma_um: f64,
    /// Local surface about the opening's centroid (board mm, heights um): the coefficients of
    /// `1, dx, dy, dx^2, dx dy, dy^2` of a quadratic (only the first three for a plane, the
    /// first for a level, where the bare board does not pin the curvature); empty when none
    /// was fitted.
    #[serde(skip)]
    pub surface: Vec<f64>,
    /// Openings (pad indices) this pad's paste is joined to; filled after every pad is
    /// measured ([`measure_all`]).
    pub bridged_to: Vec<usize>,
}

impl PadMeasurement {
    /// Pad `pad` of opening area `opening_mm2` before anything is measured: no offset and no
    /// uncertainty (NaN), every other figure 0.
    pub fn new(pad: usize, opening_mm2: f64) -> PadMeasurement {
        PadMeasurement {
            pad,
            opening_mm2,
            offset_um: [f64::NAN; 2],
            volume_u_um3: f64::NAN,
            volume_u_pct: f64::NAN,
            volume_u_surface_pct: f64::NAN,
            volume_var_per_row_um2: f64::NAN,
            height_u_um: f64::NAN,
            height_u_pct: f64::NAN,
            paste_sigma_um: f64::NAN,
            ..Default::default()
        }
    }
}

/// The terms of a surface at `(dx, dy)`: `1, dx, dy` and, for a quadratic, `dx^2, dx dy, dy^2`.
#[inline]
fn terms(dx: f64, dy: f64) -> [f64; 6] {
    [1.0, dx, dy, dx * dx, dx * dy, dy * dy]
}

/// A robust plane or quadratic surface (coefficients in `terms` order) through samples,
/// iteratively trimmed at `max(3 robust sigma, 3 um)`; its value at `(dx, dy)` is
/// [`surface_at`]. A quadratic whose samples do not pin its curvature (a thin or one-sided
/// region) falls back to a plane, and a plane to the level alone.
pub(crate) fn robust_surface(s: &[[f64; 3]], quadratic: bool) -> Option<SurfaceFit> {
    // Paste lies above the board, never below: start from the lower half (a plane through
    // the samples below their median) and keep what lies within START_BAND_UM above it, so
    // that paste covering much of the region (an offset deposit, a smear) cannot lift the
    // first fit and hide in the trimming.
    let mut keep: Vec<bool> = vec![true; s.len()];
    if s.len() >= 12 {
        let mut zs: Vec<f64> = s.iter().map(|p| p[2]).collect();
        let mid = zs.len() / 2;
        let (_, med, _) = zs.select_nth_unstable_by(mid, f64::total_cmp);
        let med = *med;
        let low: Vec<[f64; 3]> = s.iter().copied().filter(|p| p[2] <= med).collect();
        if let Some(f) = robust_surface_from(&low, false, vec![true; low.len()]) {
            for (k, p) in keep.iter_mut().zip(s) {
                let r = p[2] - surface_at(&f.coef, p[0], p[1]);
                *k = r <= START_BAND_UM;
            }
        }
    }
    robust_surface_from(s, quadratic, keep)
}

/// Above the lower half's plane, samples within this are the board's at the start, um.
pub(crate) const START_BAND_UM: f64 = 15.0;

/// A fitted local surface.
#[derive(Clone, Debug)]
pub(crate) struct SurfaceFit {
    /// Coefficients of [`terms`] (1, 3 or 6).
    pub coef: Vec<f64>,
    /// Rms of the kept samples about it, um.
    pub rms: f64,
    /// Samples kept by the trimming.
    pub kept: usize,
    /// The inverse of the final fit's normal matrix (`coef.len()` squared, row-major): the
    /// coefficients' covariance is this times the samples' noise variance (uncorrelated).
    pub inv: Vec<f64>,
    /// Which samples the final fit kept.
    pub keep: Vec<bool>,
}

impl SurfaceFit {
    /// Variance of the surface's mean over points whose mean [`terms`] are `t`, per unit
    /// noise variance: `t' inv t`.
    pub fn mean_variance(&self, t: &[f64; 6]) -> f64 {
        self.weight(t, t).max(0.0)
    }

    /// The weight of a sample with terms `x` in the surface's mean over points whose mean
    /// terms are `t`: `t' inv x` (the mean is the sum of the kept samples' heights times
    /// their weights).
    pub fn weight(&self, t: &[f64; 6], x: &[f64; 6]) -> f64 {
        let n = self.coef.len();
        self.inv
            .chunks_exact(n)
            .zip(t)
            .map(|(row, ti)| ti * row.iter().zip(x).map(|(a, xj)| a * xj).sum::<f64>())
            .sum()
    }
}

/// [`robust_surface`] from a given first selection.
fn robust_surface_from(s: &[[f64; 3]], quadratic: bool, keep: Vec<bool>) -> Option<SurfaceFit> {
    trimmed_fit(s, quadratic, keep, true)
}

/// The trimming rounds of [`robust_surface_from`]; `early`: a round whose selection did not
/// change ends the rounds at its step (they would repeat it), else all four run (the tests'
/// reference).
fn trimmed_fit(
    s: &[[f64; 3]],
    quadratic: bool,
    mut keep: Vec<bool>,
    early: bool,
) -> Option<SurfaceFit> {
    let mut nt = if quadratic { 6 } else { 3 };
    let mut coef = vec![0.0; nt];
    let mut inv_final: Vec<f64> = Vec::new();
    let mut rms = 0.0;
    let mut kept = 0;
    let mut res: Vec<f64> = vec![0.0; s.len()];
    // The kept samples' residuals' magnitudes, as their bits: for values whose sign bit is
    // clear (magnitudes, NaN's too) the bits' order as integers is `f64::total_cmp`'s, so
    // the median is found with integer comparisons and is the same value.
    let mut kept_res: Vec<u64> = Vec::with_capacity(s.len());
    // The trimming rounds look at every `sub`-th sample (about 500); the last fit at all.
    let sub = (s.len() / 500).max(1);
    let mut round = 0;
    while round < 4 {
        let step = if round < 3 { sub } else { 1 };
        let sol = loop {
            let (mut m, v, n) = match nt {
                6 => normal_equations::<6>(s, &keep, step),
                3 => normal_equations::<3>(s, &keep, step),
                _ => normal_equations::<1>(s, &keep, step),
            };
            if n < 2 * nt.max(3) {
                if nt == 1 || n < 3 {
                    return None;
                }
                nt = if nt == 6 { 3 } else { 1 };
                continue;
            }
            for i in 0..nt {
                for j in 0..i {
                    m[(i, j)] = m[(j, i)];
                }
            }
            let solved = match nt {
                6 => solve::<6>(&m, &v),
                3 => solve::<3>(&m, &v),
                _ => solve::<1>(&m, &v),
            };
            match solved {
                Some((inv, sol)) => {
                    inv_final = inv;
                    break sol;
                }
                None if nt > 1 => nt = if nt == 6 { 3 } else { 1 },
                None => return None,
            }
        };
        coef = sol;
        for (r, p) in res.iter_mut().zip(s) {
            *r = p[2] - surface_at(&coef, p[0], p[1]);
        }
        kept_res.clear();
        kept_res.extend(
            res.iter()
                .zip(&keep)
                .step_by(step)
                .filter(|(_, k)| **k)
                .map(|(r, _)| r.abs().to_bits()),
        );
        kept = kept_res.len();
        rms = (kept_res
            .iter()
            .map(|&r| f64::from_bits(r) * f64::from_bits(r))
            .sum::<f64>()
            / kept as f64)
            .sqrt();
        if round == 3 {
            break;
        }
        let mid = kept_res.len() / 2;
        let (_, med, _) = kept_res.select_nth_unstable(mid);
        let med = f64::from_bits(*med);
        let limit = (3.0 * 1.4826 * med).max(3.0);
        let mut changed = false;
        for (k, r) in keep.iter_mut().zip(&res) {
            let now = r.abs() <= limit;
            changed |= now != *k;
            *k = now;
        }
        // The same selection gives the same fit: the rounds left at this step would repeat
        // this one to the bit. At every sample already (`sub` 1), this one is the last;
        // otherwise the last round, at every sample, comes next.
        if early && !changed {
            if step == 1 {
                break;
            }
            round = 3;
            continue;
        }
        round += 1;
    }
    Some(SurfaceFit {
        coef,
        rms,
        kept,
        inv: inv_final,
        keep,
    })
}

/// The upper-left `N x N` block of the normal equations `m` (mirrored already) solved for the
/// first `N` entries of `v`: the block's inverse (row-major, as [`SurfaceFit::inv`]) and the
/// coefficients; None when the block is singular or ill conditioned (the terms are mm-scaled,
/// so a determinant far below the diagonal's product means a direction the samples do not
/// see). A fixed size, so nothing is allocated but the two results; nalgebra picks its
/// inverse and determinant by the size, whatever the storage, so the values are those of a
/// block of run-time size.
fn solve<const N: usize>(
    m: &nalgebra::SMatrix<f64, 6, 6>,
    v: &nalgebra::SVector<f64, 6>,
) -> Option<(Vec<f64>, Vec<f64>)>
where
    nalgebra::Const<N>: nalgebra::DimMin<nalgebra::Const<N>, Output = nalgebra::Const<N>>,
{
    let sub: nalgebra::SMatrix<f64, N, N> = m.fixed_view::<N, N>(0, 0).into_owned();
    let diag: f64 = (0..N).map(|i| sub[(i, i)]).product();
    match sub.try_inverse() {
        Some(inv) if sub.determinant().abs() > 1e-9 * diag => {
            let sol = inv * v.fixed_rows::<N>(0);
            Some((
                inv.transpose().iter().copied().collect(),
                sol.iter().copied().collect(),
            ))
        }
        _ => None,
    }
}

/// The normal equations of the first `NT` terms over the kept samples (every `step`-th):
/// the upper triangle of the `NT x NT` block of the matrix, the first `NT` entries of the
/// right-hand side, and the samples summed. Each entry is summed over the samples in their
/// order; `NT` fixed lets the compiler unroll the terms.
fn normal_equations<const NT: usize>(
    s: &[[f64; 3]],
    keep: &[bool],
    step: usize,
) -> (
    nalgebra::SMatrix<f64, 6, 6>,
    nalgebra::SVector<f64, 6>,
    usize,
) {
    let mut a = [[0.0f64; NT]; NT];
    let mut b = [0.0f64; NT];
    let mut n = 0usize;
    for (p, k) in s.iter().zip(keep).step_by(step) {
        if !*k {
            continue;
        }
        let t = terms(p[0], p[1]);
        // Whole rows (the lower triangle is worked out and not used): each entry the same
        // products added in the same order as over the upper triangle alone, in a few wide
        // operations instead of one per entry.
        for i in 0..NT {
            b[i] += t[i] * p[2];
            let ti = t[i];
            for (acc, tj) in a[i].iter_mut().zip(&t[..NT]) {
                *acc += ti * tj;
            }
        }
        n += 1;
    }
    let mut m = nalgebra::SMatrix::<f64, 6, 6>::zeros();
    let mut v = nalgebra::SVector::<f64, 6>::zeros();
    for i in 0..NT {
        v[i] = b[i];
        for j in i..NT {
            m[(i, j)] = a[i][j];
        }
    }
    (m, v, n)
}

/// A [`robust_surface`]'s value at `(dx, dy)`: the coefficients times their [`terms`],
/// summed in order.
///
/// The level, plane and quadratic are written out (the inner loops of the fits, the cells
/// and the bridges' floods call this per pixel): the same products added in the same order
/// as the general sum, whose start (`-0.0`) leaves the first product as it is, so the same
/// value to the bit.
#[inline]
pub(crate) fn surface_at(c: &[f64], dx: f64, dy: f64) -> f64 {
    let t = terms(dx, dy);
    match *c {
        [a] => a * t[0],
        [a, b, e] => a * t[0] + b * t[1] + e * t[2],
        [a, b, e, f, g, h] => a * t[0] + b * t[1] + e * t[2] + f * t[3] + g * t[4] + h * t[5],
        _ => c.iter().zip(t).map(|(a, b)| a * b).sum(),
    }
}

/// A surface's values ([`surface_at`]) over a window's pixels, a row at a time: each product
/// of its terms worked out once per column or per row, and added per pixel in
/// [`surface_at`]'s order, so the same values to the bit.
struct SurfaceColumns<'a> {
    /// The coefficients (1, 3 or 6).
    coef: &'a [f64],
    /// Per column: `dy`, `e dy` and `h dy^2` (the coefficients of `dy` and `dy^2`).
    cols: Vec<[f64; 3]>,
}

/// [`SurfaceColumns`] along one row.
struct SurfaceRow<'a> {
    columns: &'a SurfaceColumns<'a>,
    dx: f64,
    /// `a + b dx` (the level alone for a level) and `f dx^2`.
    head: f64,
    fx2: f64,
}

impl<'a> SurfaceColumns<'a> {
    /// For the surface `coef` over columns at `dys` (about the surface's origin, mm).
    fn new(coef: &'a [f64], dys: impl Iterator<Item = f64>) -> SurfaceColumns<'a> {
        let (e, h) = match *coef {
            [_, _, e] => (e, 0.0),
            [_, _, e, _, _, h] => (e, h),
            _ => (0.0, 0.0),
        };
        SurfaceColumns {
            coef,
            cols: dys.map(|dy| [dy, e * dy, h * (dy * dy)]).collect(),
        }
    }

    /// Along the row at `dx`.
    fn row(&self, dx: f64) -> SurfaceRow<'_> {
        let t = terms(dx, 0.0);
        let (head, fx2) = match *self.coef {
            [a] => (a * t[0], 0.0),
            [a, b, _] => (a * t[0] + b * t[1], 0.0),
            [a, b, _, f, _, _] => (a * t[0] + b * t[1], f * t[3]),
            _ => (f64::NAN, f64::NAN),
        };
        SurfaceRow {
            columns: self,
            dx,
            head,
            fx2,
        }
    }
}

impl SurfaceRow<'_> {
    /// The surface at this row's column `b`: `surface_at(coef, dx, dy)`.
    #[inline]
    fn at(&self, b: usize) -> f64 {
        let [dy, ey, hy2] = self.columns.cols[b];
        match *self.columns.coef {
            [_] => self.head,
            [_, _, _] => self.head + ey,
            [_, _, _, _, g, _] => self.head + ey + self.fx2 + g * (self.dx * dy) + hy2,
            _ => surface_at(self.columns.coef, self.dx, dy),
        }
    }
}

/// Sum and count of the finite values of the 3 x 3 block around `(a, b)` of a row-major
/// grid `width` wide.
fn mean3x3(r: &[f64], width: usize, a: usize, b: usize) -> (f64, u32) {
    let rows = r.len() / width.max(1);
    let (mut s, mut n) = (0.0, 0);
    if a >= 1 && b >= 1 && a + 1 < rows && b + 1 < width {
        // Away from the grid's edges (a pad's interior): three slices of three. An invalid
        // value adds 0 instead of being passed over: the sum starts at +0 and so is never
        // -0, and `s + 0.0 == s` to the bit otherwise: the same sum.
        for aa in a - 1..=a + 1 {
            let at = aa * width + b - 1;
            for &v in &r[at..at + 3] {
                let valid = v.is_finite();
                s += if valid { v } else { 0.0 };
                n += u32::from(valid);
            }
        }
        return (s, n);
    }
    for aa in a.saturating_sub(1)..=(a + 1).min(rows.saturating_sub(1)) {
        for bb in b.saturating_sub(1)..=(b + 1).min(width.saturating_sub(1)) {
            let v = r[aa * width + bb];
            if v.is_finite() {
                s += v;
                n += 1;
            }
        }
    }
    (s, n)
}

/// `f(k)` for `k` in `0..n`, in order, on the machine's threads (at most 8).
///
/// The threads take runs of `PER_PAD_RUN` (16) pads in turn from a shared counter, so a thread
/// that drew large pads does not hold the others up; the results are put back in pad order.
pub fn per_pad<T: Send>(n: usize, f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let threads = std::thread::available_parallelism()
        .map(|v| v.get())
        .unwrap_or(1)
        .clamp(1, 8)
        .min(n.div_ceil(PER_PAD_RUN).max(1));
    let next = std::sync::atomic::AtomicUsize::new(0);
    let (f, next) = (&f, &next);
    let work = move || {
        let mut runs: Vec<(usize, Vec<T>)> = Vec::new();
        loop {
            let start = next.fetch_add(PER_PAD_RUN, std::sync::atomic::Ordering::Relaxed);
            if start >= n {
                break runs;
            }
            runs.push((
                start,
                (start..(start + PER_PAD_RUN).min(n)).map(f).collect(),
            ));
        }
    };
    let mut runs: Vec<(usize, Vec<T>)> = std::thread::scope(|sc| {
        let handles: Vec<_> = (1..threads).map(|_| sc.spawn(work)).collect();
        let mut runs = work();
        for h in handles {
            match h.join() {
                Ok(v) => runs.extend(v),
                Err(e) => std::panic::resume_unwind(e),
            }
        }
        runs
    });
    runs.sort_unstable_by_key(|(start, _)| *start);
    let mut out = Vec::with_capacity(n);
    for (_, v) in runs {
        out.extend(v);
    }
    out
}

/// Pads a thread of [`per_pad`] takes at a time.
const PER_PAD_RUN: usize = 16;

/// The instructions the per-pad work's entry ([`measure_all`]) is built for; the values are
/// the same on either (`docs/board.md`, issue 22's seventeenth and nineteenth parts: what
/// the compiler keeps inside the AVX2 build has changed with the code).
pub use dpsa_formats::instructions::Instructions;

/// Measures every pad (on the machine's threads), then the bridges between them.
///
/// A pad's bridge search (its flood fill) follows its measurement in the same pass, while
/// the map's rows around it are still in the caches (a second pass over the pads after all
/// were measured waited on the map's memory: about a tenth of `dpsa inspect`'s processor
/// time on the paper board went to one load there).
///
/// `instructions`: [`Instructions::best`] but in the test that compares them (AVX2 only
/// where this processor has it: else the baseline).
pub fn measure_all(
    instructions: Instructions,
    map: &BoardMap,
    pads: &[Pad],
    placed: &Placed,
    t: &Rigid,
    program: &Program,
    noise: &NoiseModel,
) -> Vec<PadMeasurement> {
    let avx2 = instructions.avx2();
    let board = Board {
        map,
        pads,
        placed,
        t,
        program,
        noise,
    };
    let measured = per_pad(pads.len(), |k| {
        #[cfg(target_arch = "x86_64")]
        if avx2 {
            #[allow(unsafe_code)]
            // SAFETY: `Instructions::avx2` found AVX2 and FMA on this processor.
            return unsafe { board.pad_on_avx2(k) };
        }
        let _ = avx2;
        board.pad(k)
    });
    let (mut out, reached): (Vec<_>, Vec<_>) = measured.into_iter().unzip();
    join_bridges(&mut out, reached);
    out
}

/// What every pad's measurement reads.
struct Board<'a> {
    map: &'a BoardMap,
    pads: &'a [Pad],
    placed: &'a Placed,
    t: &'a Rigid,
    program: &'a Program,
    noise: &'a NoiseModel,
}

impl Board<'_> {
    /// Pad `k`'s measurement and the openings its paste reaches.
    #[inline(always)]
    fn pad(&self, k: usize) -> (PadMeasurement, Vec<usize>) {
        let (map, placed, program) = (self.map, self.placed, self.program);
        let (m, cell) = measure_pad(map, self.pads, placed, self.t, program, self.noise, k);
        let reached = reached(map, placed, program, &m, k, cell.as_ref());
        (m, reached)
    }

    /// [`Board::pad`] compiled for AVX2 (and the instructions that come with it): the same
    /// arithmetic in the same order (Rust neither fuses nor reorders floating-point
    /// operations, whatever the instructions), so the same values to the bit.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    fn pad_on_avx2(&self, k: usize) -> (PadMeasurement, Vec<usize>) {
        self.pad(k)
    }
}

/// An opening's smaller and larger size (its width and length), mm: a circle's diameter, a
/// rectangle's sides, a polygon's bounding box. Offsets are judged against the smaller.
pub fn opening_size(outline: &Outline) -> (f64, f64) {
    match outline {
        Outline::Circle { diameter, .. } => (*diameter, *diameter),
        Outline::RoundRect { size, .. } => (size[0].min(size[1]), size[0].max(size[1])),
        Outline::Polygon { .. } => {
            let b = outline.bbox();
            let (w, h) = (b[2] - b[0], b[3] - b[1]);
            (w.min(h), w.max(h))
        }
    }
}

/// How far inside the opening's edge its height is taken, mm: the wall width, at most a
/// quarter of the opening's smaller size `min_size` (mm).
pub fn height_inset(program: &Program, min_size: f64) -> f64 {
    program.measure.wall_mm.min(0.25 * min_size)
}

/// How far pad `k`'s cell reaches: along each of the opening's own axes, `cell_margin_share`
/// of its size there plus the wall (clamped to `cell_margin_mm`), so a long pad's cell is long
/// and narrow; a disc's by its diameter, a polygon's by its larger size.
#[derive(Clone, Copy, Debug)]
pub struct Reach {
    /// Largest distance beyond the edge, mm.
    pub max: f64,
    /// Box of the reach, board mm.
    pub bbox: [f64; 4],
    /// For a rounded rectangle: its centre, rotation (sin, cos) and half-extents with reach.
    rect: Option<(Point, f64, f64, f64, f64)>,
}

impl Reach {
    /// Pad `k`'s reach, by the program's `cell_margin_share`, `wall_mm` and `cell_margin_mm`.
    pub fn new(placed: &Placed, k: usize, program: &Program) -> Reach {
        let m = &program.measure;
        let grow = |size: f64| {
            (m.cell_margin_share * size + m.wall_mm).clamp(m.cell_margin_mm[0], m.cell_margin_mm[1])
        };
        let o = &placed.outlines[k];
        let bb = placed.bboxes[k];
        match &o.outline {
            Outline::RoundRect {
                centre,
                size,
                rotation_deg,
                ..
            } => {
                let (gu, gv) = (grow(size[0]), grow(size[1]));
                let (hu, hv) = (size[0] / 2.0 + gu, size[1] / 2.0 + gv);
                let (sn, cs) = rotation_deg.to_radians().sin_cos();
                let ex = (cs * hu).abs() + (sn * hv).abs();
                let ey = (sn * hu).abs() + (cs * hv).abs();
                Reach {
                    max: gu.max(gv),
                    bbox: [
                        centre[0] - ex,
                        centre[1] - ey,
                        centre[0] + ex,
                        centre[1] + ey,
                    ],
                    rect: Some((*centre, sn, cs, hu, hv)),
                }
            }
            _ => {
                let g = grow(placed.max_size[k]);
                Reach {
                    max: g,
                    bbox: [bb[0] - g, bb[1] - g, bb[2] + g, bb[3] + g],
                    rect: None,
                }
            }
        }
    }

    /// Whether board point `q` (mm), at signed distance `d` (mm, negative inside) from the
    /// opening, is within reach.
    #[inline]
    pub fn contains(&self, q: Point, d: f64) -> bool {
        if d > self.max {
            return false;
        }
        match self.rect {
            Some((c, sn, cs, hu, hv)) => {
                let (dx, dy) = (q[0] - c[0], q[1] - c[1]);
                (cs * dx + sn * dy).abs() <= hu && (-sn * dx + cs * dy).abs() <= hv
            }
            None => true,
        }
    }
}

/// Whether a board point is in pad `k`'s cell, given its own and its neighbours' outlines:
/// `(in_cell, signed distance to k)`.
pub fn cell_member(
    placed: &Placed,
    k: usize,
    near: &[usize],
    reach: &Reach,
    q: Point,
) -> (bool, f64) {
    let d = placed.outlines[k].signed_distance(q);
    if !reach.contains(q, d) {
        return (false, d);
    }
    (nearest_of(placed, k, near, q, d), d)
}

/// Whether no opening of `near` is nearer to board point `q` than opening `k`, at signed
/// distance `d` from `q` (ties to the lower index): the part of [`cell_member`] after the
/// reach.
///
/// A neighbour whose box is farther than `d` along x or y alone is passed over before the
/// box distance is worked out: `norm(bx, by) >= max(bx, by)` in floating point too
/// (`sqrt(x * x) == |x|` and the rounding is monotonic), so the box test would pass it over
/// as well and the answer is the same.
#[inline]
fn nearest_of(placed: &Placed, k: usize, near: &[usize], q: Point, d: f64) -> bool {
    // Openings do not overlap: inside this one, no other is nearer.
    if d < 0.0 {
        return true;
    }
    for &j in near {
        let b = &placed.bboxes[j];
        // Box distance is a lower bound of the outline's distance.
        let bx = (b[0] - q[0]).max(q[0] - b[2]).max(0.0);
        let by = (b[1] - q[1]).max(q[1] - b[3]).max(0.0);
        // Beside the box (`bx` or `by` zero) the norm is the other one, tested already.
        if bx > d || by > d || (bx > 0.0 && by > 0.0 && norm(bx, by) > d) {
            continue;
        }
        let dj = placed.outlines[j].signed_distance(q);
        if dj < d || (dj == d && j < k) {
            return false;
        }
    }
    true
}

/// [`cell_member`] over one map row at a time, with the distances worked out a row at a
/// time ([`Prepared::signed_distances`](dpsa_gerber::pads::Prepared::signed_distances)).
///
/// Per row: the opening's distances to every pixel, the reach; then per neighbour whose box
/// comes within the reach of the row along x ([`row_near`]), its distances over the columns
/// its box comes within the reach of along y, and the pixels it is nearer to (or as near,
/// and of a lower index) leave the cell. Every pixel in reach is at most `reach.max` from
/// the opening, and a neighbour's distance is at least its box's, so the neighbours and
/// columns passed over are farther than the opening. Inside the opening no other is nearer
/// (openings do not overlap).
struct RowCells {
    /// The opening's distances over the last row, mm.
    own: Vec<f64>,
    /// A neighbour's, over its columns.
    other: Vec<f64>,
}

impl RowCells {
    /// For rows of `cols` pixels.
    fn new(cols: usize) -> RowCells {
        RowCells {
            own: vec![0.0; cols],
            other: vec![0.0; cols],
        }
    }

    /// Into `cells`, whether each pixel `(x, ys[b])` of a row is in pad `k`'s cell, of
    /// `reach`, among the row's neighbours `row` ([`row_near`] at `x` with `reach.max`);
    /// `ys` ascending. The opening's distances stay in `self.own`.
    #[allow(clippy::too_many_arguments)]
    fn run(
        &mut self,
        placed: &Placed,
        k: usize,
        reach: &Reach,
        row: &[usize],
        x: f64,
        ys: &[f64],
        cells: &mut [bool],
    ) {
        let own = &mut self.own[..ys.len()];
        placed.outlines[k].signed_distances(x, ys, own);
        for ((cell, &y), &d) in cells.iter_mut().zip(ys).zip(own.iter()) {
            *cell = reach.contains([x, y], d);
        }
        for &j in row {
            let b = &placed.bboxes[j];
            let lo = ys.partition_point(|&y| y < b[1] - reach.max);
            let hi = ys.partition_point(|&y| y <= b[3] + reach.max);
            if lo >= hi {
                continue;
            }
            let other = &mut self.other[lo..hi];
            placed.outlines[j].signed_distances(x, &ys[lo..hi], other);
            let span = cells[lo..hi].iter_mut().zip(&own[lo..hi]).zip(other.iter());
            for ((cell, &d), &dj) in span {
                if d >= 0.0 && (dj < d || (dj == d && j < k)) {
                    *cell = false;
                }
            }
        }
    }
}

/// Measures pad `k`: the measurement, and its cell when one was made (the bridges' flood
/// reads its heights and distances).
fn measure_pad(
    map: &BoardMap,
    pads: &[Pad],
    placed: &Placed,
    t: &Rigid,
    program: &Program,
    noise: &NoiseModel,
    k: usize,
) -> (PadMeasurement, Option<Cell>) {
    let bb = placed.bboxes[k];
    let stencil = program.stencil_um;
    let m = &program.measure;
    let opening_mm2 = pads[k].outline.area();
    let mut pm = PadMeasurement::new(k, opening_mm2);
    if !map.covers(bb) {
        pm.unmeasurable = Some(Unmeasurable::OutsideMap);
        return (pm, None);
    }
    let c = placed.outlines[k].centroid();
    let p = map.grid.pitch_mm;
    let px_area = p * p;
    let reach = Reach::new(placed, k, program);
    let inset = height_inset(program, placed.min_size[k]);
    let Some((fit, stride, samples)) = local_surface(map, placed, program, k, c) else {
        pm.unmeasurable = Some(Unmeasurable::NoSurface);
        return (pm, None);
    };
    pm.surface = fit.coef.clone();
    pm.surface_rms_um = fit.rms;
    pm.surface_pixels = fit.kept;
    let cell = Cell::new(map, placed, k, &reach, &fit.coef, c);
    let thr_area = stencil * m.area_threshold_pct / 100.0;
    let s = cell.sums(map, thr_area, m.shape_threshold_um, m.wall_mm, inset, c);
    pm.coverage = if s.open_n > 0 {
        s.open_valid as f64 / s.open_n as f64
    } else {
        0.0
    };
    let opening_volume = opening_mm2 * stencil; // um * mm^2
    pm.volume_um3 = s.vol * px_area * 1e6;
    pm.volume_pct = 100.0 * s.vol * px_area / opening_volume;
    pm.area_mm2 = s.area_n as f64 * px_area;
    pm.area_pct = 100.0 * pm.area_mm2 / opening_mm2;
    pm.height_um = if s.hn > 0 {
        s.hsum / s.hn as f64
    } else {
        f64::NAN
    };
    pm.height_pct = 100.0 * pm.height_um / stencil;
    pm.height_max_um = if s.hmax.is_finite() {
        s.hmax
    } else {
        pm.height_um
    };
    pm.shape_pct = 100.0 * s.shape_n as f64 * px_area / opening_mm2;
    let mut s = s;
    let overlap = cell.overlap(map, &samples, &fit, c, &s, noise);
    let u = Uncertainty::of(
        &fit,
        stride,
        CellCounts {
            cell_n: s.cell_n,
            cell_t: s.cell_t,
            paste_n: s.area_n,
            int_n: s.hn,
            int_t: s.int_t,
            diff2: &mut s.diff2,
            cell_g2: s.cell_g2,
            int_g2: s.int_g2,
            cell_row_g2: s.cell_row_g2 + 2.0 * m.row_correlation * s.cell_row_g1,
            int_row_g2: s.int_row_g2 + 2.0 * m.row_correlation * s.int_row_g1,
            cell_edges: s.cell_edges,
            int_edges: s.int_edges,
            overlap,
            lateral_px: m.lateral_sigma_um / (p * 1000.0),
            row_px: m.row_sigma_um / (p * 1000.0),
        },
        noise,
    );
    pm.paste_sigma_um = u.paste_sigma_um;
    pm.volume_u_um3 = u.volume_sum.sqrt() * px_area * 1e6;
    pm.volume_u_pct = 100.0 * u.volume_sum.sqrt() * px_area / opening_volume;
    pm.volume_u_surface_pct = 100.0 * u.volume_surface.sqrt() * px_area / opening_volume;
    pm.volume_var_per_row_um2 =
        (100.0 * px_area / opening_volume).powi(2) * u.volume_row_unit / (p * 1000.0).powi(2);
    pm.height_u_um = u.height.sqrt();
    scratch::give(std::mem::take(&mut s.diff2));

    pm.height_u_pct = 100.0 * pm.height_u_um / stencil;

    if s.sw > 0.0 {
        let (dx, dy) = (s.sx / s.sw - c[0], s.sy / s.sw - c[1]);
        // Into the design frame's axes.
        let (sn, co) = t.rotation_rad.sin_cos();
        let (ux, uy) = (co * dx + sn * dy, -sn * dx + co * dy);
        pm.offset_um = [ux * 1000.0, uy * 1000.0];
        // Against the opening's width (its smaller size), along either axis.
        pm.offset_pct = 100.0 * ux.abs().max(uy.abs()) / placed.min_size[k];
    }
    if s.open_n == 0 || pm.coverage < m.min_coverage {
        pm.unmeasurable = Some(Unmeasurable::LowCoverage);
    }
    (pm, Some(cell))
}

/// Pad `k`'s local surface about its centroid `c` (board mm): a robust quadratic through the
/// bare board around it (at least `surface_guard_mm` from every opening and fiducial, within
/// `surface_reach_mm` of this one, grown to 2, 4 and 8 times that until at least
/// [`MIN_SURFACE_PIXELS`] qualify): the fit, the stride of its samples (pixels) and the
/// samples (about `c`, mm, and the height), or None.
fn local_surface(
    map: &BoardMap,
    placed: &Placed,
    program: &Program,
    k: usize,
    c: Point,
) -> Option<(SurfaceFit, usize, Vec<[f64; 3]>)> {
    let m = &program.measure;
    let o = &placed.outlines[k];
    let bb = placed.bboxes[k];
    for grow in [1.0, 2.0, 4.0, 8.0] {
        let reach = m.surface_reach_mm * grow;
        let near = placed.near(bb, reach + m.surface_guard_mm, k);
        let win = [bb[0] - reach, bb[1] - reach, bb[2] + reach, bb[3] + reach];
        let (ri, rj) = map.window(win);
        // Every pixel of a small window, every 2nd (3rd, ...) of a large one: about
        // SURFACE_SCAN pixels are looked at, which pins a quadratic to a few hundredths of
        // a um.
        let stride = ((ri.len() * rj.len()) as f64 / SURFACE_SCAN as f64)
            .sqrt()
            .ceil()
            .max(1.0) as usize;
        let mut samples: Vec<[f64; 3]> =
            Vec::with_capacity(ri.len().div_ceil(stride) * rj.len().div_ceil(stride));
        let mut row: Vec<usize> = Vec::with_capacity(near.len());
        // A pixel's y is its column's, its x its row's (`grid.centre`): the columns' once,
        // and the opening's distances a row at a time.
        let cols: Vec<usize> = rj.clone().step_by(stride).collect();
        let ys: Vec<f64> = cols.iter().map(|&j| map.grid.centre(0, j).1).collect();
        let mut ds = vec![0.0; ys.len()];
        for i in ri.clone().step_by(stride) {
            map.prefetch_row(i + 2 * stride, rj.clone());
            let x = map.grid.centre(i, 0).0;
            // The openings whose box comes within the guard of this row (one x) along x:
            // every other one passes `bare`'s box test on every pixel of the row.
            row_near(placed, &near, x, m.surface_guard_mm, &mut row);
            o.signed_distances(x, &ys, &mut ds);
            for ((&j, &y), &d) in cols.iter().zip(&ys).zip(&ds) {
                let h = map.heights.data[i * map.grid.width + j];
                if !h.is_finite() {
                    continue;
                }
                let q = [x, y];
                if d < m.surface_guard_mm || d > reach {
                    continue;
                }
                if bare(placed, &row, q, m.surface_guard_mm) {
                    samples.push([x - c[0], y - c[1], f64::from(h)]);
                }
            }
        }
        if samples.len() >= MIN_SURFACE_PIXELS {
            if let Some(fit) = robust_surface(&samples, true) {
                return Some((fit, stride, samples));
            }
        }
    }
    None
}

/// Into `out`, the openings of `near` (in their order) whose box comes within `limit` (mm)
/// of the board row at `x` (mm) along x alone: the box distance of every other one to any
/// point of the row exceeds `limit`.
fn row_near(placed: &Placed, near: &[usize], x: f64, limit: f64, out: &mut Vec<usize>) {
    out.clear();
    out.extend(near.iter().copied().filter(|&n| {
        let b = &placed.bboxes[n];
        (b[0] - x).max(x - b[2]).max(0.0) <= limit
    }));
}

/// Whether board point `q` (mm) is at least `guard` (mm) from the openings `near` and from
/// every fiducial.
fn bare(placed: &Placed, near: &[usize], q: Point, guard: f64) -> bool {
    let [x, y] = q;
    near.iter().all(|&n| {
        let b = &placed.bboxes[n];
        let bx = (b[0] - x).max(x - b[2]).max(0.0);
        let by = (b[1] - y).max(y - b[3]).max(0.0);
        // `norm(bx, by) >= max(bx, by)` in floating point too, and equal to it when the
        // other is zero: the first two tests and the zeros only spare the square root.
        bx >= guard
            || by >= guard
            || (bx > 0.0 && by > 0.0 && norm(bx, by) >= guard)
            || placed.outlines[n].signed_distance(q) >= guard
    }) && placed
        .fiducials
        .iter()
        .all(|(f, r)| norm(x - f[0], y - f[1]) >= r + guard)
}

/// Pad `k`'s cell over the window of its reach: per pixel (row-major, `cols` wide) whether
/// it is in the cell, its signed distance to the opening (mm) and its height above the
/// local surface (um; NaN outside the cell or invalid).
struct Cell {
    ri: std::ops::Range<usize>,
    rj: std::ops::Range<usize>,
    cols: usize,
    r: Vec<f64>,
    in_cell: Vec<bool>,
    dist: Vec<f64>,
}

/// Pixels of a noise lag's side: `2 LAGS + 1`.
const LAG_SIDE: usize = 2 * crate::noise::LAGS + 1;

/// Over a window's cell (row-major, `cols` wide), the sum of the noise's correlation
/// coefficients between a pixel and the cell's pixels within [`crate::noise::LAGS`] of it.
///
/// The sum walks the lags row by row ([`LagSums::walk`]). With the cell's pixels counted
/// over every box of the window from its first row and column (a summed-area table, one
/// larger each way), a pixel whose neighbourhood holds none of them gets 0 (the walk would
/// add nothing), one whose neighbourhood is all in the cell gets every coefficient summed in
/// the walk's order (`all`), both the walk's values to the bit; only pixels at the cell's
/// edge walk. On the paper board this took the overlap's lines from about 5 % of the
/// samples of a profile of `dpsa inspect --repeat 6` to under 1 %.
struct LagSums<'a> {
    in_cell: &'a [bool],
    rows: i64,
    cols: i64,
    /// The coefficients, row-major over the lags `-LAGS..=LAGS` both ways.
    co: [f64; LAG_SIDE * LAG_SIDE],
    /// Every coefficient summed in the walk's order.
    all: f64,
    /// The summed-area table, `(rows + 1) x (cols + 1)`.
    counts: Vec<u32>,
}

impl<'a> LagSums<'a> {
    /// For the cell `in_cell`, `cols` wide, and the coefficients `co`.
    fn new(in_cell: &'a [bool], cols: usize, co: [f64; LAG_SIDE * LAG_SIDE]) -> LagSums<'a> {
        let rows = in_cell.len() / cols.max(1);
        let mut counts = scratch::filled((rows + 1) * (cols + 1), 0u32);
        for a in 0..rows {
            let mut run = 0u32;
            for b in 0..cols {
                run += u32::from(in_cell[a * cols + b]);
                counts[(a + 1) * (cols + 1) + b + 1] = counts[a * (cols + 1) + b + 1] + run;
            }
        }
        LagSums {
            in_cell,
            rows: rows as i64,
            cols: cols as i64,
            co,
            all: co.iter().fold(0.0, |k, &r| k + r),
            counts,
        }
    }

    /// The cell's pixels in rows `a0..a1`, columns `b0..b1` (clipped to the window).
    fn members(&self, a0: i64, a1: i64, b0: i64, b1: i64) -> u32 {
        let (a0, a1) = (
            a0.clamp(0, self.rows) as usize,
            a1.clamp(0, self.rows) as usize,
        );
        let (b0, b1) = (
            b0.clamp(0, self.cols) as usize,
            b1.clamp(0, self.cols) as usize,
        );
        let w = self.cols as usize + 1;
        let at = |a: usize, b: usize| self.counts[a * w + b];
        at(a1, b1) + at(a0, b0) - at(a0, b1) - at(a1, b0)
    }

    /// The sum at window pixel `(a, b)` (it may lie outside the window).
    fn at(&self, a: i64, b: i64) -> f64 {
        let l = crate::noise::LAGS as i64;
        if a < -l || b < -l || a >= self.rows + l || b >= self.cols + l {
            return 0.0;
        }
        match self.members(a - l, a + l + 1, b - l, b + l + 1) {
            0 => 0.0,
            n if n as usize == LAG_SIDE * LAG_SIDE => self.all,
            _ => self.walk(a, b),
        }
    }

    /// The sum at `(a, b)` lag by lag: rows of lags in order, each row's in order, the
    /// coefficient of every lag that lands on a cell pixel added.
    fn walk(&self, a: i64, b: i64) -> f64 {
        let l = crate::noise::LAGS as i64;
        let side = LAG_SIDE as i64;
        let mut k = 0.0;
        for di in -l..=l {
            let aa = a + di;
            if aa < 0 || aa >= self.rows {
                continue;
            }
            let row = &self.in_cell[(aa * self.cols) as usize..((aa + 1) * self.cols) as usize];
            let lags = &self.co[((di + l) * side) as usize..((di + l + 1) * side) as usize];
            for (dj, &r) in (-l..=l).zip(lags) {
                let bb = b + dj;
                if bb >= 0 && bb < self.cols && row[bb as usize] {
                    k += r;
                }
            }
        }
        k
    }
}

impl Drop for LagSums<'_> {
    fn drop(&mut self) {
        scratch::give(std::mem::take(&mut self.counts));
    }
}

impl Drop for Cell {
    /// The buffers go back to this thread's [`scratch`] for the next pad.
    fn drop(&mut self) {
        scratch::give(std::mem::take(&mut self.r));
        scratch::give(std::mem::take(&mut self.in_cell));
        scratch::give(std::mem::take(&mut self.dist));
    }
}

/// Buffers kept from pad to pad on each thread: a pad's cell, sums and flood took and gave
/// back some 100 KB, and the allocator's share of the per-pad work was about 4 % (the paper
/// board's profile). A buffer comes back cleared and filled as asked; each thread keeps at
/// most [`scratch::KEPT`] of a kind, as large as the largest pad's window it served.
mod scratch {
    use std::cell::RefCell;

    /// Buffers of one kind a thread keeps.
    pub(super) const KEPT: usize = 4;

    thread_local! {
        static F64S: RefCell<Vec<Vec<f64>>> = const { RefCell::new(Vec::new()) };
        static BOOLS: RefCell<Vec<Vec<bool>>> = const { RefCell::new(Vec::new()) };
        static U32S: RefCell<Vec<Vec<u32>>> = const { RefCell::new(Vec::new()) };
    }

    /// The element types kept.
    pub(super) trait Kept: Copy + 'static {
        /// This thread's buffers of the type.
        fn with<R>(f: impl FnOnce(&mut Vec<Vec<Self>>) -> R) -> R;
    }

    macro_rules! kept {
        ($t:ty, $pool:ident) => {
            impl Kept for $t {
                fn with<R>(f: impl FnOnce(&mut Vec<Vec<Self>>) -> R) -> R {
                    $pool.with(|p| f(&mut p.borrow_mut()))
                }
            }
        };
    }
    kept!(f64, F64S);
    kept!(bool, BOOLS);
    kept!(u32, U32S);

    /// `len` copies of `value`, in a kept buffer when there is one.
    pub(super) fn filled<T: Kept>(len: usize, value: T) -> Vec<T> {
        let mut v = T::with(|p| p.pop()).unwrap_or_default();
        v.clear();
        v.resize(len, value);
        v
    }

    /// `v` kept for the next [`filled`] (dropped when enough are kept).
    pub(super) fn give<T: Kept>(v: Vec<T>) {
        T::with(|p| {
            if p.len() < KEPT {
                p.push(v);
            }
        });
    }
}

/// What the cell's pixels add up to.
struct Sums {
    /// Pixels of the opening, and of those the valid ones.
    open_n: usize,
    open_valid: usize,
    /// Heights summed over the cell (invalid pixels filled), um per pixel.
    vol: f64,
    /// Pixels above the area threshold, and above the shape threshold beyond the wall.
    area_n: usize,
    shape_n: usize,
    /// Height-weighted sums of the paste above the area threshold: weight, x, y.
    sw: f64,
    sx: f64,
    sy: f64,
    /// Heights over the opening's interior: sum, count and the largest 3 x 3 mean.
    hsum: f64,
    hn: usize,
    hmax: f64,
    /// Pixels of the cell (each adds to `vol`) and their [`terms`] summed (about the
    /// centroid).
    cell_n: usize,
    cell_t: [f64; 6],
    /// The interior's valid pixels' [`terms`] summed.
    int_t: [f64; 6],
    /// Squared differences of neighbouring valid interior pixels (along rows and columns),
    /// um^2.
    diff2: Vec<f64>,
    /// Squared slopes (um per pixel, central differences) summed over the cell's valid
    /// pixels, and over the interior's.
    cell_g2: f64,
    int_g2: f64,
    /// Over the cell's rows (map rows run across the motion), the square of the row's summed
    /// slope along the motion ((um per pixel)^2), summed; and over the interior's rows.
    cell_row_g2: f64,
    int_row_g2: f64,
    /// The products of neighbouring rows' summed slopes, summed (cell, interior).
    cell_row_g1: f64,
    int_row_g1: f64,
    /// Cell pixels whose next pixel down a column (and along a row) is not in the cell: the
    /// cell's extent across each axis, for the pairs of neighbours it holds; the same for the
    /// interior.
    cell_edges: [usize; 2],
    int_edges: [usize; 2],
}

impl Cell {
    /// The cell of pad `k` with its `reach`, heights above `plane` (about `c`, board mm).
    fn new(
        map: &BoardMap,
        placed: &Placed,
        k: usize,
        reach: &Reach,
        plane: &[f64],
        c: Point,
    ) -> Cell {
        let near = placed.near(placed.bboxes[k], 2.0 * reach.max, k);
        let (ri, rj) = map.window(reach.bbox);
        let (h_w, w_w) = (ri.len(), rj.len());
        let mut cell = Cell {
            ri: ri.clone(),
            rj: rj.clone(),
            cols: w_w,
            r: scratch::filled(h_w * w_w, f64::NAN),
            in_cell: scratch::filled(h_w * w_w, false),
            dist: scratch::filled(h_w * w_w, f64::INFINITY),
        };
        // The neighbours of one row (one x): those whose box is within the reach along x.
        // Every pixel in reach is at most `reach.max` from the opening, so the others are
        // farther from every pixel of the row than the opening is.
        let mut row: Vec<usize> = Vec::with_capacity(near.len());
        // A pixel's y is its column's, its x its row's (`grid.centre`): the columns' once,
        // and the distances a row at a time.
        let ys: Vec<f64> = rj.clone().map(|j| map.grid.centre(0, j).1).collect();
        let columns = SurfaceColumns::new(plane, ys.iter().map(|&y| y - c[1]));
        let mut rows = RowCells::new(w_w);
        for (a, i) in ri.enumerate() {
            map.prefetch_row(i + 2, rj.clone());
            let x = map.grid.centre(i, 0).0;
            let surface = columns.row(x - c[0]);
            row_near(placed, &near, x, reach.max, &mut row);
            let at = a * w_w..(a + 1) * w_w;
            rows.run(
                placed,
                k,
                reach,
                &row,
                x,
                &ys,
                &mut cell.in_cell[at.clone()],
            );
            let cells = cell.in_cell[at.clone()].iter();
            let out = cell.dist[at.clone()].iter_mut().zip(&mut cell.r[at]);
            for (b, ((j, &inside), (dist, r))) in rj.clone().zip(cells).zip(out).enumerate() {
                if !inside {
                    continue;
                }
                *dist = rows.own[b];
                let h = map.heights.data[i * map.grid.width + j];
                if h.is_finite() {
                    *r = f64::from(h) - surface.at(b);
                }
            }
        }
        cell
    }

    /// How the local surface's samples share noise with the cell: over the fit's kept
    /// samples, each one's weight in the surface's mean over the cell times the sum of its
    /// noise's correlation coefficients with the cell's pixels (samples within the cell's
    /// reach of the bare board count; farther ones have none).
    fn overlap(
        &self,
        map: &BoardMap,
        samples: &[[f64; 3]],
        fit: &SurfaceFit,
        c: Point,
        s: &Sums,
        noise: &NoiseModel,
    ) -> f64 {
        let mut t = s.cell_t;
        for v in &mut t {
            *v /= s.cell_n.max(1) as f64;
        }
        // The coefficients at every lag, looked up once (`noise.at`, in `LagSums::at`'s order).
        let l = crate::noise::LAGS as i64;
        let co: [f64; LAG_SIDE * LAG_SIDE] = std::array::from_fn(|n| {
            let side = LAG_SIDE as i64;
            noise.at(n as i64 / side - l, n as i64 % side - l)
        });
        let lags = LagSums::new(&self.in_cell, self.cols, co);
        let mut sum = 0.0;
        for (p, keep) in samples.iter().zip(&fit.keep) {
            if !keep {
                continue;
            }
            let (i, j) = map.pixel_of([p[0] + c[0], p[1] + c[1]]);
            let (a, b) = (i - self.ri.start as i64, j - self.rj.start as i64);
            let k = lags.at(a, b);
            if k != 0.0 {
                sum += fit.weight(&t, &terms(p[0], p[1])) * k;
            }
        }
        sum
    }

    /// The sums over the cell: paste above `thr_area` (um) for area and offset, above
    /// `thr_shape` (um) beyond `wall` (mm) for the shape, the interior `inset` (mm) inside
    /// the edge for the height.
    fn sums(
        &self,
        map: &BoardMap,
        thr_area: f64,
        thr_shape: f64,
        wall: f64,
        inset: f64,
        c: Point,
    ) -> Sums {
        let (h_w, w_w) = (self.ri.len(), self.cols);
        let r = &self.r;
        let mut s = Sums {
            open_n: 0,
            open_valid: 0,
            vol: 0.0,
            area_n: 0,
            shape_n: 0,
            sw: 0.0,
            sx: 0.0,
            sy: 0.0,
            hsum: 0.0,
            hn: 0,
            hmax: f64::NEG_INFINITY,
            cell_n: 0,
            cell_t: [0.0; 6],
            int_t: [0.0; 6],
            diff2: scratch::filled(0, 0.0),
            cell_g2: 0.0,
            int_g2: 0.0,
            cell_row_g2: 0.0,
            int_row_g2: 0.0,
            cell_row_g1: 0.0,
            int_row_g1: 0.0,
            cell_edges: [0; 2],
            int_edges: [0; 2],
        };
        // The slopes of a row's pixels, a row at a time.
        let mut slopes = RowSlopes::new(w_w);
        let interior = |idx: usize| self.dist[idx] <= -inset && r[idx].is_finite();
        // A pixel's x is its row's, its y its column's (`grid.centre`), and their terms'
        // factors the same products: the columns' once, the row's once per row.
        let ys: Vec<f64> = self.rj.clone().map(|j| map.grid.centre(0, j).1).collect();
        let dys: Vec<(f64, f64)> = ys
            .iter()
            .map(|&y| (y - c[1], (y - c[1]) * (y - c[1])))
            .collect();
        let (mut prev_gx, mut prev_int_gx) = (0.0, 0.0);
        for a in 0..h_w {
            let (mut row_gx, mut int_row_gx) = (0.0, 0.0);
            let x = map.grid.centre(self.ri.start + a, 0).0;
            let (dx, dx2) = (x - c[0], (x - c[0]) * (x - c[0]));
            slopes.of_row(r, a);
            for b in 0..w_w {
                let idx = a * w_w + b;
                if !self.in_cell[idx] {
                    continue;
                }
                let d = self.dist[idx];
                if d <= 0.0 {
                    s.open_n += 1;
                    if r[idx].is_finite() {
                        s.open_valid += 1;
                    }
                }
                let v = if r[idx].is_finite() {
                    r[idx]
                } else {
                    // The mean of the valid 3 x 3 neighbours; none: 0 (counted as bare board,
                    // and the coverage says how much of the opening was seen).
                    let (sum, n) = mean3x3(r, w_w, a, b);
                    if n > 0 {
                        sum / f64::from(n)
                    } else {
                        0.0
                    }
                };
                s.vol += v;
                let (y, (dy, dy2)) = (ys[b], dys[b]);
                // `terms(dx, dy)`.
                let t = [1.0, dx, dy, dx2, dx * dy, dy2];
                s.cell_n += 1;
                for (acc, t) in s.cell_t.iter_mut().zip(t) {
                    *acc += t;
                }
                let (gx, gy) = if r[idx].is_finite() {
                    (slopes.down[b], slopes.along[b])
                } else {
                    (0.0, 0.0)
                };
                let g2 = gx * gx + gy * gy;
                s.cell_g2 += g2;
                row_gx += gx;
                if a + 1 >= h_w || !self.in_cell[idx + w_w] {
                    s.cell_edges[0] += 1;
                }
                if b + 1 >= w_w || !self.in_cell[idx + 1] {
                    s.cell_edges[1] += 1;
                }
                if v > thr_area {
                    s.area_n += 1;
                    s.sw += v;
                    s.sx += v * x;
                    s.sy += v * y;
                }
                if v > thr_shape && d > wall {
                    s.shape_n += 1;
                }
                if interior(idx) {
                    s.hsum += r[idx];
                    s.hn += 1;
                    s.int_g2 += g2;
                    int_row_gx += gx;
                    let down = a + 1 < h_w && interior(idx + w_w);
                    let right = b + 1 < w_w && interior(idx + 1);
                    if !down {
                        s.int_edges[0] += 1;
                    }
                    if !right {
                        s.int_edges[1] += 1;
                    }
                    for (acc, t) in s.int_t.iter_mut().zip(t) {
                        *acc += t;
                    }
                    if right {
                        s.diff2.push((r[idx + 1] - r[idx]).powi(2));
                    }
                    if down {
                        s.diff2.push((r[idx + w_w] - r[idx]).powi(2));
                    }
                    // 3 x 3 mean for the maximum.
                    let (sum, n) = mean3x3(r, w_w, a, b);
                    if n >= 5 {
                        s.hmax = s.hmax.max(sum / f64::from(n));
                    }
                }
            }
            s.cell_row_g2 += row_gx * row_gx;
            s.int_row_g2 += int_row_gx * int_row_gx;
            s.cell_row_g1 += row_gx * prev_gx;
            s.int_row_g1 += int_row_gx * prev_int_gx;
            (prev_gx, prev_int_gx) = (row_gx, int_row_gx);
        }
        s
    }
}

/// The slopes of a row of heights (um per pixel): per pixel, down the column and along the
/// row; for rows `w` wide.
struct RowSlopes {
    down: Vec<f64>,
    along: Vec<f64>,
    /// `w` NaN: the rows above the first and below the last (nothing valid).
    outside: Vec<f64>,
}

/// A slope between the neighbours `lo` and `hi` of a valid value `mid` (um per pixel): the
/// central difference where both are valid, else one-sided, else 0.
///
/// Written without branches (each case's value is worked out and one is picked), so the
/// compiler can take a row of pixels a few at a time: the same operations on the same
/// values in each case as the reference's (the tests' `slope_at`): the same values to the bit.
#[inline(always)]
fn slope_between(lo: f64, mid: f64, hi: f64) -> f64 {
    // All ones where `v` is finite, else zero: the test on the bits (the magnitude below
    // infinity's), so the compiler keeps it in vector registers.
    let finite = |v: f64| 0u64.wrapping_sub(u64::from((v.to_bits() << 1) < (0x7ff << 53)));
    let pick =
        |mask: u64, a: f64, b: f64| f64::from_bits((a.to_bits() & mask) | (b.to_bits() & !mask));
    let (l, h) = (finite(lo), finite(hi));
    let one_sided = pick(l, mid - lo, hi - mid);
    let sided = pick(l & h, 0.5 * (hi - lo), one_sided);
    // Neither valid: +0.
    f64::from_bits(sided.to_bits() & (l | h))
}

impl RowSlopes {
    /// For rows `w` wide, its buffers from this thread's [`scratch`].
    fn new(w: usize) -> RowSlopes {
        RowSlopes {
            down: scratch::filled(w, 0.0),
            along: scratch::filled(w, 0.0),
            outside: scratch::filled(w, f64::NAN),
        }
    }

    /// The slopes of each pixel of row `a` of the row-major grid `r` (as wide as these rows;
    /// valid or not: an invalid pixel's are not used), as the reference (the tests'
    /// `slope_at`) gives them.
    fn of_row(&mut self, r: &[f64], a: usize) {
        let w = self.outside.len();
        let row_at = |aa: usize| &r[aa * w..(aa + 1) * w];
        let rows = r.len() / w.max(1);
        let up = if a > 0 { row_at(a - 1) } else { &self.outside };
        let down = if a + 1 < rows {
            row_at(a + 1)
        } else {
            &self.outside
        };
        let row = row_at(a);
        let (gx, gy) = (&mut self.down[..w], &mut self.along[..w]);
        for (g, ((&u, &m), &d)) in gx.iter_mut().zip(up.iter().zip(row).zip(down)) {
            *g = slope_between(u, m, d);
        }
        match w {
            0 => {}
            1 => gy[0] = 0.0,
            _ => {
                gy[0] = slope_between(f64::NAN, row[0], row[1]);
                for (g, t) in gy[1..w - 1].iter_mut().zip(row.windows(3)) {
                    *g = slope_between(t[0], t[1], t[2]);
                }
                gy[w - 1] = slope_between(row[w - 2], row[w - 1], f64::NAN);
            }
        }
    }
}

impl Drop for RowSlopes {
    /// The buffers go back to this thread's [`scratch`] for the next pad.
    fn drop(&mut self) {
        scratch::give(std::mem::take(&mut self.down));
        scratch::give(std::mem::take(&mut self.along));
        scratch::give(std::mem::take(&mut self.outside));
    }
}

/// The bridges: per pad, a flood fill (4-connected) from its paste inside its opening over
/// pixels above the bridge height (over its local surface), within its box grown by
/// `bridge_reach_mm`; a pixel inside another opening is a bridge to it. Each flood visits
/// about the pad's own deposit, so the search costs little more than the deposit's area.
///
/// The openings measured pad `k`'s paste reaches ([`flood`], with the pad's `cell`; none when
/// it is unmeasurable).
fn reached(
    map: &BoardMap,
    placed: &Placed,
    program: &Program,
    m: &PadMeasurement,
    k: usize,
    cell: Option<&Cell>,
) -> Vec<usize> {
    let (None, Some(cell)) = (m.unmeasurable, cell) else {
        return Vec::new();
    };
    let reach = program.measure.bridge_reach_mm;
    let thr = program.stencil_um * program.windows.bridge_height_pct / 100.0;
    flood(map, placed, m, k, reach, thr, cell)
}

/// Fills `bridged_to` of both pads of each pair that one's paste reaches (`reached[k]`, the
/// openings pad `k`'s paste reaches), both measurable, in pad order.
fn join_bridges(pm: &mut [PadMeasurement], reached: Vec<Vec<usize>>) {
    let mut found: Vec<(usize, usize)> = reached
        .into_iter()
        .enumerate()
        .flat_map(|(k, hit)| hit.into_iter().map(move |j| (k, j)))
        .filter(|&(_, j)| pm[j].unmeasurable.is_none())
        .map(|(k, j)| (k.min(j), k.max(j)))
        .collect();
    found.sort_unstable();
    found.dedup();
    for (k, j) in found {
        pm[k].bridged_to.push(j);
        pm[j].bridged_to.push(k);
    }
}

/// The openings pad `k`'s paste reaches, with `cell` its [`Cell`]: over the cell's pixels the
/// heights above the surface and the distances to the opening are the cell's (the same
/// values: the same formulas on the same coordinates), elsewhere worked out here.
fn flood(
    map: &BoardMap,
    placed: &Placed,
    m: &PadMeasurement,
    k: usize,
    reach: f64,
    thr: f64,
    cell: &Cell,
) -> Vec<usize> {
    let o = &placed.outlines[k];
    let bb = placed.bboxes[k];
    let near = placed.near(bb, reach, k);
    if near.is_empty() {
        return Vec::new();
    }
    let (ri, rj) = map.window([bb[0] - reach, bb[1] - reach, bb[2] + reach, bb[3] + reach]);
    let (hw, ww) = (ri.len(), rj.len());
    if hw == 0 || ww == 0 {
        return Vec::new();
    }
    let c = o.centroid();
    // The cell's index of map pixel `(i, j)` when it is one of the cell's pixels.
    let of_cell = |i: usize, j: usize| -> Option<usize> {
        let (a, b) = (i.wrapping_sub(cell.ri.start), j.wrapping_sub(cell.rj.start));
        let idx = a.checked_mul(cell.cols)?.checked_add(b)?;
        (a < cell.ri.len() && b < cell.cols && cell.in_cell[idx]).then_some(idx)
    };
    let paste = |a: usize, b: usize| -> bool {
        let (i, j) = (ri.start + a, rj.start + b);
        if let Some(idx) = of_cell(i, j) {
            // NaN (an invalid pixel) is not above.
            return cell.r[idx] > thr;
        }
        let h = map.heights.data[i * map.grid.width + j];
        if !h.is_finite() {
            return false;
        }
        let (x, y) = map.grid.centre(i, j);
        f64::from(h) - surface_at(&m.surface, x - c[0], y - c[1]) > thr
    };
    // 0 unseen, 1 visited.
    let mut seen = scratch::filled(hw * ww, false);
    // Pixels to go on from, as (row, column) of the window: no division per pixel.
    let mut stack: Vec<(usize, usize)> = Vec::new();
    let (oi, oj) = map.window(bb);
    for i in oi {
        for j in oj.clone() {
            let (a, b) = (i - ri.start, j - rj.start);
            let d = match of_cell(i, j) {
                Some(idx) => cell.dist[idx],
                None => {
                    let (x, y) = map.grid.centre(i, j);
                    o.signed_distance([x, y])
                }
            };
            if d <= 0.0 && paste(a, b) {
                seen[a * ww + b] = true;
                stack.push((a, b));
            }
        }
    }
    let mut hit: Vec<usize> = Vec::new();
    while let Some((a, b)) = stack.pop() {
        let idx = a * ww + b;
        let (i, j) = (ri.start + a, rj.start + b);
        let (x, y) = map.grid.centre(i, j);
        let d = match of_cell(i, j) {
            Some(at) => cell.dist[at],
            None => o.signed_distance([x, y]),
        };
        if d > 0.0 {
            let q = [x, y];
            if let Some(&j) = near.iter().find(|&&j| {
                let bj = &placed.bboxes[j];
                q[0] >= bj[0]
                    && q[0] <= bj[2]
                    && q[1] >= bj[1]
                    && q[1] <= bj[3]
                    && placed.outlines[j].signed_distance(q) <= 0.0
            }) {
                if !hit.contains(&j) {
                    hit.push(j);
                }
                // Do not flood the neighbour's own deposit.
                continue;
            }
        }
        let mut visit = |n: usize, a2: usize, b2: usize| {
            if !seen[n] {
                seen[n] = true;
                if paste(a2, b2) {
                    stack.push((a2, b2));
                }
            }
        };
        if a > 0 {
            visit(idx - ww, a - 1, b);
        }
        if a + 1 < hw {
            visit(idx + ww, a + 1, b);
        }
        if b > 0 {
            visit(idx - 1, a, b - 1);
        }
        if b + 1 < ww {
            visit(idx + 1, a, b + 1);
        }
    }
    scratch::give(seen);
    hit
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_gerber::pads::Rigid;
    use proptest::prelude::*;

    /// A rounded rectangle or a disc from generated numbers.
    fn opening(v: (f64, f64, f64, f64, f64, bool)) -> Pad {
        let (x, y, w, h, rot, disc) = v;
        let outline = if disc {
            Outline::Circle {
                centre: [x, y],
                diameter: w,
            }
        } else {
            Outline::RoundRect {
                centre: [x, y],
                size: [w, h],
                radius: 0.2 * w.min(h),
                rotation_deg: rot,
            }
        };
        Pad {
            index: 0,
            outline,
            component: None,
            pin: None,
            aperture: None,
        }
    }

    /// Cell membership by its definition: within reach, and inside the opening or no other
    /// opening (of all) nearer, ties to the lower index.
    fn member_by_definition(placed: &Placed, k: usize, reach: &Reach, q: Point) -> bool {
        let d = placed.outlines[k].signed_distance(q);
        reach.contains(q, d)
            && (d < 0.0
                || (0..placed.outlines.len()).filter(|&j| j != k).all(|j| {
                    let dj = placed.outlines[j].signed_distance(q);
                    dj > d || (dj == d && j > k)
                }))
    }

    /// The 3 x 3 block's sum and count by their definition: rows, then columns, in order,
    /// clipped to the grid, finite values only.
    fn mean3x3_by_definition(r: &[f64], width: usize, a: usize, b: usize) -> (f64, u32) {
        let rows = r.len() / width;
        let (mut s, mut n) = (0.0, 0);
        for aa in a as i64 - 1..=a as i64 + 1 {
            for bb in b as i64 - 1..=b as i64 + 1 {
                if aa < 0 || bb < 0 || aa >= rows as i64 || bb >= width as i64 {
                    continue;
                }
                let v = r[aa as usize * width + bb as usize];
                if v.is_finite() {
                    s += v;
                    n += 1;
                }
            }
        }
        (s, n)
    }

    /// The slopes at valid pixel `(a, b)` of a row-major grid `w` wide (um per pixel, down the
    /// column and along the row): central differences where both neighbours are valid, else
    /// one-sided, else 0 along that axis: the reference of [`RowSlopes::of_row`], as the sums took them
    /// pixel by pixel before.
    fn slope_at(r: &[f64], w: usize, a: usize, b: usize) -> (f64, f64) {
        let h = r.len() / w;
        let at = |aa: usize, bb: usize| r[aa * w + bb];
        let d = |lo: f64, mid: f64, hi: f64| match (lo.is_finite(), hi.is_finite()) {
            (true, true) => 0.5 * (hi - lo),
            (true, false) => mid - lo,
            (false, true) => hi - mid,
            _ => 0.0,
        };
        let mid = at(a, b);
        let up = if a > 0 { at(a - 1, b) } else { f64::NAN };
        let down = if a + 1 < h { at(a + 1, b) } else { f64::NAN };
        let left = if b > 0 { at(a, b - 1) } else { f64::NAN };
        let right = if b + 1 < w { at(a, b + 1) } else { f64::NAN };
        (d(up, mid, down), d(left, mid, right))
    }

    /// The block's inverse and solution as the fit took them before [`solve`]: a block of
    /// run-time size (nalgebra's `DMatrix`).
    fn solve_at_run_time(
        m: &nalgebra::SMatrix<f64, 6, 6>,
        v: &nalgebra::SVector<f64, 6>,
        nt: usize,
    ) -> Option<(Vec<f64>, Vec<f64>)> {
        let sub = m.view((0, 0), (nt, nt)).clone_owned();
        let diag: f64 = (0..nt).map(|i| sub[(i, i)]).product();
        match sub.clone().try_inverse() {
            Some(inv) if sub.determinant().abs() > 1e-9 * diag => {
                let sol = inv.clone() * v.rows(0, nt);
                Some((
                    inv.transpose().iter().copied().collect(),
                    sol.iter().copied().collect(),
                ))
            }
            _ => None,
        }
    }

    #[test]
    fn a_kept_buffer_comes_back_as_asked() {
        let mut v = scratch::filled(5, 1.5f64);
        assert_eq!(v, vec![1.5; 5]);
        v[2] = f64::NAN;
        v.push(7.0);
        scratch::give(v);
        assert_eq!(scratch::filled(3, 0.25f64), vec![0.25; 3]);
        let b = scratch::filled(4, true);
        scratch::give(b);
        assert_eq!(scratch::filled(6, false), vec![false; 6]);
        // More given back than kept: the rest are dropped.
        for _ in 0..2 * scratch::KEPT {
            scratch::give(vec![9u32; 10]);
        }
        assert_eq!(scratch::filled(2, 0u32), vec![0, 0]);
    }

    proptest! {
        /// The trimming's median of the residuals' magnitudes taken on their bits is the
        /// median by `f64::total_cmp`, bit for bit: magnitudes of signed zeros, NaN, both
        /// infinities, subnormals and ordinary values, odd and even counts.
        #[test]
        fn a_median_of_magnitudes_by_their_bits_is_the_total_orders(
            v in proptest::collection::vec(prop_oneof![
                Just(0.0), Just(-0.0), Just(f64::NAN), Just(-f64::NAN), Just(f64::INFINITY),
                Just(f64::NEG_INFINITY), Just(5e-324), Just(f64::MIN_POSITIVE), -1e3..1e3f64,
            ], 1..60),
        ) {
            let mut by_order: Vec<f64> = v.iter().map(|x| x.abs()).collect();
            let mut by_bits: Vec<u64> = by_order.iter().map(|x| x.to_bits()).collect();
            let mid = v.len() / 2;
            let want = *by_order.select_nth_unstable_by(mid, f64::total_cmp).1;
            let got = *by_bits.select_nth_unstable(mid).1;
            prop_assert_eq!(got, want.to_bits());
        }

        /// A row's slopes are the pixel-by-pixel slopes to the bit, on grids of 1 to 9 rows
        /// and columns with invalid values (NaN, both infinities) anywhere and signed zeros
        /// among the heights.
        #[test]
        fn row_slopes_are_the_slopes_pixel_by_pixel(
            rows in 1..9usize,
            cols in 1..9usize,
            r in proptest::collection::vec(prop_oneof![
                Just(f64::NAN), Just(f64::INFINITY), Just(f64::NEG_INFINITY),
                Just(0.0), Just(-0.0), -80.0..120.0f64,
            ], 81),
        ) {
            let r = &r[..rows * cols];
            let mut out = RowSlopes::new(cols);
            out.down.fill(7.0);
            out.along.fill(7.0);
            for a in 0..rows {
                out.of_row(r, a);
                for b in 0..cols {
                    if !r[a * cols + b].is_finite() {
                        continue;
                    }
                    let (gx, gy) = slope_at(r, cols, a, b);
                    prop_assert_eq!(out.down[b].to_bits(), gx.to_bits());
                    prop_assert_eq!(out.along[b].to_bits(), gy.to_bits());
                }
            }
        }

        /// The lag sums' shortcuts (no cell pixel near, all of them) give the walk's value
        /// to the bit at every pixel of the window and beyond its edges, on random cells
        /// (empty, full, sparse, dense) and coefficients (zeros among them).
        #[test]
        fn lag_sums_are_the_walk(
            rows in 1..14usize,
            cols in 1..14usize,
            fill in prop_oneof![Just(0.0), Just(1.0), 0.0..1.0f64],
            co in proptest::collection::vec(prop_oneof![Just(0.0), -0.3..1.0f64], LAG_SIDE * LAG_SIDE),
            seed in any::<u64>(),
        ) {
            use rand::SeedableRng;
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let cell: Vec<bool> = (0..rows * cols).map(|_| rng.random::<f64>() < fill).collect();
            let co: [f64; LAG_SIDE * LAG_SIDE] = std::array::from_fn(|n| co[n]);
            let lags = LagSums::new(&cell, cols, co);
            let l = crate::noise::LAGS as i64 + 2;
            for a in -l..rows as i64 + l {
                for b in -l..cols as i64 + l {
                    prop_assert_eq!(lags.at(a, b).to_bits(), lags.walk(a, b).to_bits());
                }
            }
        }

        /// A surface row's values are [`surface_at`]'s to the bit, for the level, the plane
        /// and the quadratic (signed zeros among the coefficients and offsets).
        #[test]
        fn surface_rows_are_surface_at(
            c in proptest::collection::vec(prop_oneof![Just(0.0), Just(-0.0), -50.0..50.0f64], 6),
            dx in prop_oneof![Just(0.0), Just(-0.0), -3.0..3.0f64],
            dys in proptest::collection::vec(prop_oneof![Just(0.0), Just(-0.0), -3.0..3.0f64], 1..20),
        ) {
            for n in [1, 3, 6] {
                let columns = SurfaceColumns::new(&c[..n], dys.iter().copied());
                let row = columns.row(dx);
                for (b, &dy) in dys.iter().enumerate() {
                    prop_assert_eq!(row.at(b).to_bits(), surface_at(&c[..n], dx, dy).to_bits());
                }
            }
        }

        /// [`mean3x3`] (with its path away from the edges) is the block's sum and count by
        /// definition, to the bit, at every pixel of grids with invalid values.
        #[test]
        fn mean3x3_is_the_block_by_definition(
            rows in 1..9usize,
            cols in 1..9usize,
            values in proptest::collection::vec(
                prop_oneof![Just(f64::NAN), Just(0.0), Just(-0.0), -80.0..80.0f64], 64),
        ) {
            let r: Vec<f64> = (0..rows * cols).map(|n| values[n % values.len()]).collect();
            for a in 0..rows {
                for b in 0..cols {
                    let (s, n) = mean3x3(&r, cols, a, b);
                    let (s0, n0) = mean3x3_by_definition(&r, cols, a, b);
                    prop_assert_eq!((s.to_bits(), n), (s0.to_bits(), n0));
                }
            }
        }

        /// [`solve`] at a fixed size gives the run-time-size block's inverse and solution to
        /// the bit, or None with it: normal matrices of random samples (well and badly
        /// conditioned) and singular ones.
        #[test]
        fn a_fixed_size_solve_is_the_run_time_one(
            pts in proptest::collection::vec((-2.0..2.0f64, -2.0..2.0f64, -30.0..30.0f64), 0..40),
            line in any::<bool>(),
        ) {
            let s: Vec<[f64; 3]> = pts
                .iter()
                .map(|&(x, y, z)| if line { [x, 0.5 * x, z] } else { [x, y, z] })
                .collect();
            let keep = vec![true; s.len()];
            let (mut m, v, _) = normal_equations::<6>(&s, &keep, 1);
            for i in 0..6 {
                for j in 0..i {
                    m[(i, j)] = m[(j, i)];
                }
            }
            let bits = |o: Option<(Vec<f64>, Vec<f64>)>| {
                o.map(|(a, b)| {
                    let f = |v: Vec<f64>| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    (f(a), f(b))
                })
            };
            prop_assert_eq!(bits(solve::<6>(&m, &v)), bits(solve_at_run_time(&m, &v, 6)));
            prop_assert_eq!(bits(solve::<3>(&m, &v)), bits(solve_at_run_time(&m, &v, 3)));
            prop_assert_eq!(bits(solve::<1>(&m, &v)), bits(solve_at_run_time(&m, &v, 1)));
        }

        /// A fit that ends its rounds once the selection stops changing is the fit of all
        /// four rounds, to the bit (coefficients, rms, count, inverse, selection): on planes
        /// and quadratics with noise and paste-like outliers, of a few samples (every round
        /// at every sample) and of thousands (the first rounds at every few).
        #[test]
        fn a_fit_that_stops_early_is_the_fit_of_every_round(
            n in prop_oneof![20..200usize, 900..3000usize],
            c in proptest::collection::vec(-20.0..20.0f64, 6),
            noise in 0.2..4.0f64,
            paste in 0.0..0.5f64,
            quadratic in any::<bool>(),
            seed in any::<u64>(),
        ) {
            use rand::SeedableRng;
            use rand_distr::{Distribution, Uniform};
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let mut u = |a: f64, b: f64| Uniform::new(a, b).unwrap().sample(&mut rng);
            let s: Vec<[f64; 3]> = (0..n)
                .map(|_| {
                    let (x, y) = (u(-1.0, 1.0), u(-1.0, 1.0));
                    let mut z = surface_at(&c, x, y) + noise * u(-1.7, 1.7);
                    if u(0.0, 1.0) < paste {
                        z += u(20.0, 120.0);
                    }
                    [x, y, z]
                })
                .collect();
            let keep = vec![true; n];
            let a = trimmed_fit(&s, quadratic, keep.clone(), true);
            let b = trimmed_fit(&s, quadratic, keep, false);
            prop_assert_eq!(a.is_some(), b.is_some());
            if let (Some(a), Some(b)) = (a, b) {
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                prop_assert_eq!(bits(&a.coef), bits(&b.coef));
                prop_assert_eq!(bits(&a.inv), bits(&b.inv));
                prop_assert_eq!(a.rms.to_bits(), b.rms.to_bits());
                prop_assert_eq!(a.kept, b.kept);
                prop_assert_eq!(a.keep, b.keep);
            }
        }

        /// The written-out surfaces give the general sum's value to the bit (signed zeros
        /// included), for the level, the plane and the quadratic.
        #[test]
        fn surface_at_is_the_general_sum(
            c in proptest::collection::vec(prop_oneof![Just(0.0), Just(-0.0), -50.0..50.0f64], 6),
            dx in prop_oneof![Just(0.0), Just(-0.0), -3.0..3.0f64],
            dy in prop_oneof![Just(0.0), Just(-0.0), -3.0..3.0f64],
        ) {
            for n in [1, 3, 6] {
                let t = terms(dx, dy);
                let general: f64 = c[..n].iter().zip(t).map(|(a, b)| a * b).sum();
                prop_assert_eq!(surface_at(&c[..n], dx, dy).to_bits(), general.to_bits());
            }
        }

        /// The cell test over one row's neighbours ([`row_near`], then [`nearest_of`] per
        /// pixel, and [`RowCells`] a row at a time as `Cell::new` runs it) agrees with
        /// [`cell_member`] and with the definition, and
        /// `bare` over a row's neighbours with `bare` over them all, on every pixel of the
        /// pads' windows in random layouts.
        #[test]
        fn row_neighbours_keep_cells_and_bare_board(
            ops in prop::collection::vec(
                (0.0..4.0f64, 0.0..4.0f64, 0.1..1.6f64, 0.1..1.0f64, -90.0..90.0f64, any::<bool>()),
                2..9,
            ),
            pitch in 0.02..0.05f64,
            guard in 0.05..0.3f64,
        ) {
            let pads: Vec<Pad> = ops.into_iter().map(opening).collect();
            let placed = Placed::new(&pads, &Rigid::IDENTITY, &[], 0.0);
            let program = Program::new("paste.gbr");
            let mut row = Vec::new();
            for k in 0..pads.len() {
                let reach = Reach::new(&placed, k, &program);
                let near = placed.near(placed.bboxes[k], 2.0 * reach.max, k);
                let others: Vec<usize> = (0..pads.len()).filter(|&j| j != k).collect();
                let b = reach.bbox;
                let cols = ((b[3] - b[1]) / pitch).ceil() as usize + 1;
                let ys: Vec<f64> = (0..cols).map(|jj| b[1] + (jj as f64 + 0.5) * pitch).collect();
                let mut rows = RowCells::new(cols);
                let mut cells = vec![false; cols];
                for i in 0..((b[2] - b[0]) / pitch).ceil() as usize + 1 {
                    let x = b[0] + (i as f64 + 0.5) * pitch;
                    row_near(&placed, &near, x, reach.max, &mut row);
                    rows.run(&placed, k, &reach, &row, x, &ys, &mut cells);
                    for (jj, &y) in ys.iter().enumerate() {
                        let q = [x, y];
                        let d = placed.outlines[k].signed_distance(q);
                        let fast = reach.contains(q, d) && nearest_of(&placed, k, &row, q, d);
                        prop_assert_eq!(fast, cell_member(&placed, k, &near, &reach, q).0);
                        prop_assert_eq!(fast, member_by_definition(&placed, k, &reach, q));
                        prop_assert_eq!(cells[jj], fast);
                        prop_assert_eq!(rows.own[jj].to_bits(), d.to_bits());
                    }
                    row_near(&placed, &others, x, guard, &mut row);
                    for jj in 0..cols {
                        let q = [x, b[1] + (jj as f64 + 0.5) * pitch];
                        prop_assert_eq!(
                            bare(&placed, &row, q, guard),
                            bare(&placed, &others, q, guard)
                        );
                    }
                }
            }
        }
    }
}
