//! Where a camera's rows were seen: the row places that the provenance of a board recording
//! (its latches replayed) gives, and that the resampling uses instead of the nominal placement;
//! and where, within its row, each pixel's height was seen ([`SamplePlace`], [`Settle`]).
//!
//! The core registers whole rows (`o_k = round(latch_k / cpp)`), so the board point behind
//! board row `b` lies `e_k = latch_k / cpp - o_k` rows off `b` in window frame `k`
//! (`|e_k| <= 1/2`). On a flat board that does not matter; on a deposit's wall the height
//! changes along the motion and the least squares blend the `n` points. To first order in the
//! slope the pixel's height is the height at `b + d`, with
//!
//! ```text
//! d = sum_k c_k e_k,   c_k = -(cos Phi P_3k - sin Phi P_2k) sin(Phi + theta_k),   sum_k c_k = 1
//! ```
//!
//! (`P` the window's least-squares rows, `theta_k` its shifts, `Phi` the pixel's measured
//! phase; from `dPhi = (v_2 dv_3 - v_3 dv_2) / C^2` with `di_k = -C sin(Phi + theta_k) Phi'
//! e_k`). Written out, `d = a + p cos 2 Phi + q sin 2 Phi` with three numbers per row: the
//! row's place ([`RowPlaces::along`]) takes `mean_k e_k` (what every pixel of the row shares
//! on average), the rest differs from pixel to pixel with the phase, by about `0.3 / sqrt(2n)`
//! rows rms. [`Settle`] takes that rest out of each pixel's height with the local slope along
//! the motion: `h(b + m) = h(b + d) - (d - m) dh/db`.
//!
//! **The paste's reflectance** ([`PasteReflectance`]). Paste and board reflect differently:
//! across a wall the background `B` steps too, and in frame `k` the pixel sees it `e_k` rows
//! off, `di_k = B' e_k`. Through the same least squares that bends the phase by
//!
//! ```text
//! dPhi = (B' / C) sum_k g_k e_k,   g_k = cos Phi P_3k - sin Phi P_2k
//! ```
//!
//! (`C` the fringe contrast), written out `(B' / C) (a cos Phi + b sin Phi)` with two more
//! numbers per row ([`SamplePlace::bg_cos`], [`SamplePlace::bg_sin`]). The stream carries
//! neither `B` nor `C`, so the map takes `B' / C` as the paste's background step over the
//! board's fringe contrast (a constant of the machine and the materials, from the program)
//! times the rate at which the pixel goes from board to paste, `(dh/db) / H` (`H` the paste's
//! height, the stencil's thickness): the sum of that rate over a wall is the paste's share of
//! it, about 1, whatever the wall's profile and wherever the edge falls in the pixel, and a
//! deposit's volume is such a sum. The same step in the fringe contrast bends the phase
//! through the fringe term; on the small board taking it out too gained nothing
//! (`docs/spc.md`, "Where the walls' scatter comes from"), so it is left in.

use dpsa_formats::instructions::Instructions;

/// Where a camera's rows were seen ([`crate::provenance::row_places`] makes them).
#[derive(Clone, Debug, PartialEq)]
pub struct RowPlaces {
    /// Position of row `i` along the motion, in rows (increasing: neighbours differ by
    /// `1 +- (less than 1)`).
    pub along: Vec<f64>,
    /// How far the board point of column `c` of row `i` lies from the nominal column, px:
    /// the point the placement puts at column `c` is at column `c - across[i]`.
    pub across: Vec<f64>,
    /// Where each pixel's height was seen against `along` (empty: at `along`, every row).
    pub samples: Vec<SamplePlace>,
}

/// How far the pixels of one row were seen from the row's place, rows: `offset + cos2 cos 2
/// Phi + sin2 sin 2 Phi`, with `Phi = fringe_rad + ref(c) + 2 pi h / T(c)` the pixel's
/// measured phase (`ref` the core's reference phase of column `c`, `h` the height, `T` the
/// height per turn). All zero for a row whose window is unknown.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SamplePlace {
    /// The fringe's phase at the row in its window's first frame, `2 pi (b - o_0) / period`,
    /// rad.
    pub fringe_rad: f32,
    /// `a - mean_k e_k` (see the module docs), rows.
    pub offset: f32,
    /// `p`, rows.
    pub cos2: f32,
    /// `q`, rows.
    pub sin2: f32,
    /// `sum_k P_3k e_k`: the background's bend of the phase is `(B' / C) (bg_cos cos Phi +
    /// bg_sin sin Phi)` (see the module docs), rows.
    pub bg_cos: f32,
    /// `-sum_k P_2k e_k`, rows.
    pub bg_sin: f32,
}

/// How the paste's reflectance differs from the board's, for taking its bend of the phase
/// out of the walls (see the module docs): a constant of the machine (its illumination and
/// optics) and of the materials (the paste, the solder mask), from the program.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct PasteReflectance {
    /// The paste's background above the board's, over the board's fringe contrast as the
    /// cameras see it, `(B_paste - B_board) / C_board`; 0: nothing is corrected.
    pub background_step: f32,
    /// The paste's height, um (the stencil's thickness): a pixel whose height rises by `dh`
    /// has gone `dh / paste_um` of the way from board to paste.
    pub paste_um: f32,
}

impl PasteReflectance {
    /// The program's background step over the board's contrast and the stencil's thickness
    /// (um).
    pub fn new(background_step: f64, paste_um: f64) -> PasteReflectance {
        PasteReflectance {
            background_step: background_step as f32,
            paste_um: paste_um as f32,
        }
    }

    /// `background_step / paste_um`, or `None` when nothing is to be corrected (a zero step;
    /// a height or step that is not finite, or a height that is not positive).
    fn per_um(&self) -> Option<f32> {
        let k = self.background_step / self.paste_um;
        (self.background_step != 0.0 && self.paste_um > 0.0 && k.is_finite()).then_some(k)
    }
}

impl SamplePlace {
    /// The place of a window with shifts from the row offsets `o` (its frames'), sub-row
    /// travels `e` (as many) and the core's fringe period `period_px`; board row `b`. `None`
    /// when the shifts do not determine a phase (fewer than three, or all alike).
    pub fn of_window(b: i64, o: &[i64], e: &[f64], period_px: f64) -> Option<SamplePlace> {
        let n = o.len().min(e.len());
        if n < 3 || !(period_px.is_finite() && period_px > 0.0) {
            return None;
        }
        let turn = std::f64::consts::TAU / period_px;
        let (mut cs, mut sn) = (vec![0.0; n], vec![0.0; n]);
        for k in 0..n {
            let th = -((o[k] - o[0]) as f64) * turn;
            (sn[k], cs[k]) = th.sin_cos();
        }
        // The centred least squares (core/src/solve.rs): u = cos - mean, w = -(sin - mean).
        let mean = |v: &[f64]| v.iter().sum::<f64>() / n as f64;
        let (mc, ms) = (mean(&cs), mean(&sn));
        let u: Vec<f64> = cs.iter().map(|c| c - mc).collect();
        let w: Vec<f64> = sn.iter().map(|s| -(s - ms)).collect();
        let (suu, suw, sww) = (0..n).fold((0.0, 0.0, 0.0), |(a, b, c), k| {
            (a + u[k] * u[k], b + u[k] * w[k], c + w[k] * w[k])
        });
        let det = suu * sww - suw * suw;
        let singular = det.abs() <= 1e-9 * (suu * sww).max(1e-300);
        if singular || !det.is_finite() {
            return None;
        }
        let (mut a, mut bb, mut c, mut d) = (0.0, 0.0, 0.0, 0.0);
        let (mut e3, mut e2) = (0.0, 0.0);
        for k in 0..n {
            let p2 = (sww * u[k] - suw * w[k]) / det;
            let p3 = (suu * w[k] - suw * u[k]) / det;
            e3 += p3 * e[k];
            e2 += p2 * e[k];
            a += p3 * cs[k] * e[k];
            bb += p3 * sn[k] * e[k];
            c += p2 * cs[k] * e[k];
            d += p2 * sn[k] * e[k];
        }
        let m = mean(&e[..n]);
        Some(SamplePlace {
            fringe_rad: (((b - o[0]) as f64 * turn) % std::f64::consts::TAU) as f32,
            offset: ((c - bb) / 2.0 - m) as f32,
            cos2: (-(bb + c) / 2.0) as f32,
            sin2: (-(a - d) / 2.0) as f32,
            bg_cos: e3 as f32,
            bg_sin: (-e2) as f32,
        })
    }

    /// Rows off the row's place of a pixel of column phase `ref_rad` (the core's reference)
    /// and height `h_um` in a column of `period_um` per turn.
    #[inline]
    pub fn at(&self, ref_rad: f32, h_um: f32, period_um: f32) -> f32 {
        let turns = (self.fringe_rad + ref_rad) * (0.5 / std::f32::consts::PI) + h_um / period_um;
        self.at_turns(turns)
    }

    /// [`SamplePlace::at`] of a pixel whose phase is `turns` turns.
    #[inline(always)]
    fn at_turns(&self, turns: f32) -> f32 {
        let (c, s) = cos_sin_turns(2.0 * turns);
        self.offset + self.cos2 * c + self.sin2 * s
    }
}

/// Rounds to the nearest integer (ties to even) by adding and taking off `1.5 * 2^23`: exact
/// for `|x| < 2^22`, with no call into the maths library (SSE2 has no rounding instruction).
#[inline(always)]
fn round_near(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0;
    (x + MAGIC) - MAGIC
}

/// `cos`, `sin` of `2 pi t` for `|t| < 2^18`, to about `4e-7`: reduced to an eighth of a turn,
/// then the Taylor series to the ninth power (a pixel's place needs a few decimals; the
/// library's `sin_cos` costs several times this over a board's millions of pixels). No branch
/// and no table, so that a row's pixels go through it four or eight at a time. A non-finite or
/// larger `t` gives a value of no meaning, never a panic.
#[inline(always)]
fn cos_sin_turns(t: f32) -> (f32, f32) {
    let u = 4.0 * t;
    let q = round_near(u);
    let a = (u - q) * (0.25 * std::f32::consts::TAU);
    let a2 = a * a;
    // Horner's form with the reciprocals as constants (a division each would cost more than
    // the rest of the pixel).
    let s = a
        * (1.0
            - a2 * (1.0 / 6.0)
                * (1.0
                    - a2 * (1.0 / 20.0) * (1.0 - a2 * (1.0 / 42.0) * (1.0 - a2 * (1.0 / 72.0)))));
    let c = 1.0
        - a2 * 0.5
            * (1.0 - a2 * (1.0 / 12.0) * (1.0 - a2 * (1.0 / 30.0) * (1.0 - a2 * (1.0 / 56.0))));
    // Quadrant k: swapped for odd k; the cosine negative for k = 1, 2, the sine for k = 2, 3.
    let k = (q as i32) & 3;
    let odd = k & 1 == 1;
    let (x, y) = (if odd { s } else { c }, if odd { c } else { s });
    let cos_neg = ((k ^ (k >> 1)) & 1) as u32;
    let sin_neg = ((k >> 1) & 1) as u32;
    (
        f32::from_bits(x.to_bits() ^ (cos_neg << 31)),
        f32::from_bits(y.to_bits() ^ (sin_neg << 31)),
    )
}

/// Takes each pixel's own place out of a camera's unwrapped rows, row after row as they come
/// (see the module docs): row `i` once row `i + 1` is there (or the camera ended), from the
/// rows as they came, so that whatever the chunks the same rows give the same heights.
#[derive(Clone, Debug, Default)]
pub struct Settle {
    /// Row `settled - 1` as it came (before its own settling).
    before: Vec<f32>,
    /// Rows from the camera's first that are settled.
    pub settled: usize,
    /// Per column, the reference phase in turns and `1 / T` (um^-1), made on the first call.
    columns: Vec<(f32, f32)>,
    /// The paste's reflectance taken out of the walls (the default: nothing taken out).
    pub paste: PasteReflectance,
    /// What the settling runs on (the default: [`Instructions::best`]; the same rows on every
    /// set, to the bit).
    pub instructions: Instructions,
}

impl Settle {
    /// Settles the rows of `held` (camera rows from `held0`, `width` columns) that can be:
    /// every one before the last, and the last too when `ended`. `places` gives every row's
    /// place (rows past its end, or without samples, are left as they came); `reference_rad`
    /// and `period_um` are per column (an empty `reference_rad`: nothing is changed).
    pub fn rows(
        &mut self,
        held: &mut crate::Grid,
        held0: usize,
        places: Option<&RowPlaces>,
        reference_rad: &[f32],
        period_um: &[f32],
        ended: bool,
    ) {
        let w = held.width;
        let end = held0 + held.rows;
        let last = if ended { end } else { end.saturating_sub(1) };
        let usable = places.filter(|p| !p.samples.is_empty() && reference_rad.len() == w);
        let Some(pl) = usable.filter(|_| period_um.len() == w) else {
            self.settled = self.settled.max(last);
            return;
        };
        if self.columns.len() != w {
            self.columns = reference_rad
                .iter()
                .zip(period_um)
                .map(|(&r, &t)| (r * (0.5 / std::f32::consts::PI), 1.0 / t))
                .collect();
        }
        let mut this = Vec::with_capacity(w);
        let avx2 = self.instructions.avx2();
        while self.settled < last {
            let i = self.settled;
            let Some(k) = i.checked_sub(held0) else {
                // Rows dropped unsettled (never the case in the stitcher): left as they are.
                self.settled = held0;
                self.before.clear();
                continue;
            };
            this.clear();
            this.extend_from_slice(&held.data[k * w..(k + 1) * w]);
            let sp = pl.samples.get(i).copied().unwrap_or_default();
            if sp != SamplePlace::default() {
                let at = |j: usize| pl.along.get(j).copied();
                let here = at(i).unwrap_or(i as f64);
                let prev = (i > 0 && self.before.len() == w)
                    .then(|| at(i - 1))
                    .flatten()
                    .map(|a| (&self.before[..], a));
                let (upto, after) = held.data.split_at_mut((k + 1) * w);
                let next = (i + 1 < end)
                    .then(|| at(i + 1))
                    .flatten()
                    .map(|a| (&after[..w], a));
                let rows = (&mut upto[k * w..], &this[..]);
                let args = (rows, prev, next, here, &sp, &self.columns[..]);
                match self.paste.per_um() {
                    Some(per_um) => settle_row_on::<true>(avx2, args, per_um),
                    None => settle_row_on::<false>(avx2, args, 0.0),
                }
            }
            std::mem::swap(&mut self.before, &mut this);
            self.settled = i + 1;
        }
    }
}

/// [`settle_row`]'s arguments but the reflectance's `per_um`.
type SettleArgs<'a> = (
    (&'a mut [f32], &'a [f32]),
    Option<(&'a [f32], f64)>,
    Option<(&'a [f32], f64)>,
    f64,
    &'a SamplePlace,
    &'a [(f32, f32)],
);

/// [`settle_row`] built for AVX2 where `avx2` (x86-64, detected: eight pixels at a time
/// instead of the baseline's four; the same operations, so the same values to the bit), else
/// for the baseline.
fn settle_row_on<const PASTE: bool>(avx2: bool, args: SettleArgs<'_>, per_um: f32) {
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        /// [`settle_row`] in AVX2.
        #[target_feature(enable = "avx2")]
        fn on_avx2<const PASTE: bool>(args: SettleArgs<'_>, per_um: f32) {
            settle_row::<PASTE>(args, per_um);
        }
        #[allow(unsafe_code)]
        // SAFETY: `avx2` holds only where run-time detection found AVX2.
        unsafe {
            on_avx2::<PASTE>(args, per_um);
        }
        return;
    }
    let _ = avx2;
    settle_row::<PASTE>(args, per_um);
}

/// One row settled: `row` (as it came: `raw`) at place `here`, its neighbours as they came
/// with their places (`None`: not there), the row's sample place, the columns' reference
/// turns and inverse periods; with `PASTE`, the paste's reflectance taken out too
/// ([`PasteReflectance`]: `per_um` its background step over its height). The slope along the
/// motion is the central difference where both neighbours are valid, else the one-sided one;
/// a pixel with neither stays as it came. Written without a branch per pixel (selects), so
/// that the compiler runs it in vectors.
#[inline(always)]
fn settle_row<const PASTE: bool>(
    ((row, raw), prev, next, here, sp, columns): SettleArgs<'_>,
    per_um: f32,
) {
    let w = row.len().min(raw.len()).min(columns.len());
    let nan_row = vec![
        f32::NAN;
        if prev.is_none() || next.is_none() {
            w
        } else {
            0
        }
    ];
    let (p_row, p_at) = prev.unwrap_or((&nan_row, here - 1.0));
    let (n_row, n_at) = next.unwrap_or((&nan_row, here + 1.0));
    let (p_row, n_row) = (&p_row[..w], &n_row[..w]);
    let inv = |d: f64| (1.0 / d) as f32;
    let (both, fwd, bwd) = (inv(n_at - p_at), inv(n_at - here), inv(here - p_at));
    let fringe = sp.fringe_rad * (0.5 / std::f32::consts::PI);
    for c in 0..w {
        let (h, p, n) = (raw[c], p_row[c], n_row[c]);
        let (pf, nf) = (p.is_finite(), n.is_finite());
        let central = (n - p) * both;
        let one_sided = if nf { (n - h) * fwd } else { (h - p) * bwd };
        let slope = if pf && nf { central } else { one_sided };
        let (ref_turns, inv_t) = columns[c];
        let turns = fringe + ref_turns + h * inv_t;
        let d = sp.at_turns(turns);
        let mut v = h - slope * d;
        if PASTE {
            // The background's bend of the phase, rad, as height: times T / (2 pi).
            let (c1, s1) = cos_sin_turns(turns);
            let bend = slope * per_um * (sp.bg_cos * c1 + sp.bg_sin * s1);
            v -= bend / (std::f32::consts::TAU * inv_t);
        }
        // NaN where the pixel or both neighbours are invalid: left as it came.
        row[c] = if v.is_finite() { v } else { h };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Grid;
    use std::f64::consts::TAU;

    use crate::test_rng::Lcg;

    /// A window of `n` frames about `step` rows apart (a step of 4 to 8 rows turns a fringe of
    /// 10.3 rows by 140 to 280 degrees: a window the core takes) (with up to a quarter row of jitter),
    /// their sub-row travels uniform in `[-1/2, 1/2)`: row offsets and travels.
    fn window(rng: &mut Lcg, n: usize, step: f64) -> (Vec<i64>, Vec<f64>) {
        let mut s = 100.0 + rng.next() * 10.0;
        let (mut o, mut e) = (Vec::new(), Vec::new());
        for _ in 0..n {
            let ok = (s + 0.5f64).floor();
            o.push(ok as i64);
            e.push(s - ok);
            s += step * (1.0 + 0.05 * (2.0 * rng.next() - 1.0));
        }
        (o, e)
    }

    /// The least-squares phase of samples `i` at shifts `th`, by the full normal equations
    /// (rows `[1, cos, -sin]`, Cramer's rule): independent of the centred form above.
    fn phase(i: &[f64], th: &[f64]) -> f64 {
        let rows: Vec<[f64; 3]> = th.iter().map(|t| [1.0, t.cos(), -t.sin()]).collect();
        let mut a = [[0.0; 3]; 3];
        let mut y = [0.0; 3];
        for (r, &v) in rows.iter().zip(i) {
            for p in 0..3 {
                y[p] += r[p] * v;
                for q in 0..3 {
                    a[p][q] += r[p] * r[q];
                }
            }
        }
        let det3 = |m: [[f64; 3]; 3]| {
            m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
                - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
                + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
        };
        let d = det3(a);
        let col = |k: usize| {
            let mut m = a;
            for p in 0..3 {
                m[p][k] = y[p];
            }
            det3(m) / d
        };
        col(2).atan2(col(1))
    }

    #[test]
    fn cos_sin_of_turns_match_the_library() {
        let mut worst = 0.0f64;
        for k in -40_000..40_000 {
            let t = k as f32 * 7.3e-5 + 0.013;
            let (c, s) = cos_sin_turns(t);
            let a = f64::from(t) * TAU;
            worst = worst.max((f64::from(c) - a.cos()).abs());
            worst = worst.max((f64::from(s) - a.sin()).abs());
        }
        assert!(worst < 1e-6, "worst {worst}");
    }

    /// On a board whose phase rises slowly along the motion, the least squares of a window's
    /// samples give the phase at the place `SamplePlace` says (plus the travels' mean), for
    /// any phase, 3 to 8 frames and steps that are not a fraction of the period.
    #[test]
    fn a_pixel_is_seen_where_its_window_says() {
        let mut rng = Lcg(7);
        let (period, slope) = (10.3, 1e-4);
        let mut worst = 0.0f64;
        let mut spread = 0.0f64;
        for case in 0..400 {
            let n = 3 + case % 6;
            let (o, e) = window(&mut rng, n, [4.0, 5.6, 8.0][case % 3]);
            let b = o[n - 1] + 2;
            let Some(sp) = SamplePlace::of_window(b, &o, &e, period) else {
                continue;
            };
            let phi0 = rng.next() * TAU;
            let th: Vec<f64> = o
                .iter()
                .map(|&k| -((k - o[0]) as f64) * TAU / period)
                .collect();
            // The board point's own phase (the height's) changes by `slope` per row; the
            // fringe's part is the row's.
            let fringe = (b - o[0]) as f64 * TAU / period;
            let i: Vec<f64> = (0..n)
                .map(|k| 900.0 + 700.0 * (fringe + phi0 + slope * e[k] + th[k]).cos())
                .collect();
            let got = phase(&i, &th);
            let seen = (got - fringe - phi0 + TAU / 2.0).rem_euclid(TAU) - TAU / 2.0;
            let seen = seen / slope;
            let mean = e.iter().sum::<f64>() / n as f64;
            let said = mean + f64::from(sp.at((got - f64::from(sp.fringe_rad)) as f32, 0.0, 1.0));
            worst = worst.max((seen - said).abs());
            spread = spread.max((seen - mean).abs());
        }
        // The first order in a slope of 1e-4 rad per row; the f32 place.
        assert!(worst < 2e-3, "worst {worst} rows");
        // ... and the place is not just the mean.
        assert!(spread > 0.05, "spread {spread} rows");
    }

    /// Rows of a ramp along the motion, each pixel seen at its own place: settled, every
    /// pixel is the ramp at its row's place (to the slope's second order), whatever chunks
    /// the rows come in; nothing changes without a reference table.
    #[test]
    fn settled_rows_are_the_ramp_at_their_place_whatever_the_chunks() {
        let mut rng = Lcg(11);
        let (w, rows, period_px, slope) = (24usize, 60usize, 10.3, 12.0f32);
        let period_um: Vec<f32> = (0..w).map(|c| 480.0 + c as f32).collect();
        let reference: Vec<f32> = (0..w).map(|c| (c as f32 * 0.7) % 6.2).collect();
        let mut along = Vec::new();
        let mut samples = Vec::new();
        for i in 0..rows {
            let (o, e) = window(&mut rng, 4, 8.0);
            let mean = e.iter().sum::<f64>() / 4.0;
            along.push(i as f64 + mean);
            samples.push(SamplePlace::of_window(i as i64 + 200, &o, &e, period_px).unwrap());
        }
        samples[30] = SamplePlace::default();
        let places = RowPlaces {
            along: along.clone(),
            across: vec![0.0; rows],
            samples,
        };
        // Each pixel's height is the ramp where it was seen (its place depends on its height:
        // a few rounds find it).
        let mut g = Grid::invalid(w, rows);
        let mut before = 0.0f64;
        for (i, &a) in along.iter().enumerate() {
            for c in 0..w {
                let mut h = slope * a as f32;
                for _ in 0..4 {
                    let d = places.samples[i].at(reference[c], h, period_um[c]);
                    h = slope * (a as f32 + d);
                }
                *g.at_mut(i, c) = h;
                before += f64::from(h - slope * a as f32).powi(2);
            }
        }
        g.data[5 * w + 3] = f32::NAN;
        let settle_in = |cuts: &[usize], instructions: Instructions| {
            let mut held = Grid::invalid(w, 0);
            let mut s = Settle {
                instructions,
                ..Settle::default()
            };
            let mut from = 0;
            for &to in cuts.iter().chain(std::iter::once(&rows)) {
                held.data.extend_from_slice(&g.data[from * w..to * w]);
                held.rows = to;
                s.rows(
                    &mut held,
                    0,
                    Some(&places),
                    &reference,
                    &period_um,
                    to == rows,
                );
                from = to;
            }
            assert_eq!(s.settled, rows);
            held
        };
        let whole = settle_in(&[], Instructions::best());
        let bits = |g: &Grid| g.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        for cuts in [&[1usize, 2, 3][..], &[17, 18, 40], &[59]] {
            let parts = settle_in(cuts, Instructions::best());
            assert_eq!(bits(&parts), bits(&whole), "cuts {cuts:?}");
        }
        // The baseline's build settles the same bits as the best this processor runs.
        for cuts in [&[][..], &[17, 18, 40]] {
            let base = settle_in(cuts, Instructions::Baseline);
            assert_eq!(bits(&base), bits(&whole), "baseline, cuts {cuts:?}");
        }
        let mut after = 0.0f64;
        for (i, &a) in along.iter().enumerate() {
            for c in 0..w {
                let v = whole.data[i * w + c];
                if i == 5 && c == 3 {
                    assert!(v.is_nan());
                    continue;
                }
                let err = f64::from(v - slope * a as f32);
                if i == 30 {
                    // No window: as it came.
                    assert_eq!(v, g.data[i * w + c]);
                    continue;
                }
                after += err * err;
            }
        }
        assert!(before > 0.5 * (rows * w) as f64, "before {before}");
        assert!(after < 0.02 * before, "after {after}, before {before}");
        // Without the columns' reference phases nothing is changed.
        let mut held = g.clone();
        let mut s = Settle::default();
        s.rows(&mut held, 0, Some(&places), &[], &period_um, true);
        assert_eq!(s.settled, rows);
        assert!(held
            .data
            .iter()
            .zip(&g.data)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
    }

    /// Columns across a deposit's wall along the motion, paste brighter than the board (its
    /// background 400 above, its contrast the board's 700): each row's window through the
    /// least squares of the full normal equations. Against the same windows over paste that
    /// reflects as the board, a column's height summed over the wall (what a volume adds up)
    /// differs, settled with the paste's reflectance, by a fraction of what it does without,
    /// wherever the edge lies in the pixel and though the background steps over a narrower
    /// band than the height rises; where the board is flat nothing changes.
    #[test]
    fn the_pastes_reflectance_is_taken_out_of_a_wall() {
        // The background steps where the height rises (the correction's own model): what is
        // left is a small part; over half that band (as a hard edge blurred by the pixel over
        // a wall that rises over two or three): still less than three quarters.
        for (band, bound) in [(3.0, 0.3), (1.5, 0.75)] {
            reflectance_across_a_wall(band, bound);
        }
    }

    fn reflectance_across_a_wall(band: f64, bound: f64) {
        let mut rng = Lcg(23);
        let (w, rows, period_px, paste_um) = (64usize, 24usize, 10.3, 100.0f64);
        let period_um: Vec<f32> = (0..w).map(|c| 480.0 + (c % 7) as f32).collect();
        let reference: Vec<f32> = (0..w).map(|c| (c as f32 * 0.9) % 6.2).collect();
        let smooth = |x: f64| {
            let t = x.clamp(0.0, 1.0);
            t * t * (3.0 - 2.0 * t)
        };
        // Each column's wall at its own sub-row place; the background steps over `band` rows
        // about it (the height rises over 3).
        let edge: Vec<f64> = (0..w).map(|_| 9.0 + 2.0 * rng.next()).collect();
        let height = |c: usize, b: f64| paste_um * smooth((b - edge[c]) / 3.0 + 0.5);
        let paste = |c: usize, b: f64| smooth((b - edge[c]) / band + 0.5);
        let (mut along, mut samples) = (Vec::new(), Vec::new());
        let (mut g, mut same) = (Grid::invalid(w, rows), Grid::invalid(w, rows));
        for i in 0..rows {
            let (o, e) = window(&mut rng, 4, 8.0);
            let b0 = i as i64 + 200;
            let sp = SamplePlace::of_window(b0, &o, &e, period_px).unwrap();
            let th: Vec<f64> = o
                .iter()
                .map(|&k| -((k - o[0]) as f64) * TAU / period_px)
                .collect();
            for c in 0..w {
                let t = f64::from(period_um[c]);
                let base = f64::from(sp.fringe_rad) + f64::from(reference[c]);
                for (step, m) in [(400.0, &mut g), (0.0, &mut same)] {
                    let i_k: Vec<f64> = (0..4)
                        .map(|k| {
                            let b = i as f64 + e[k];
                            let bg = 1800.0 + step * paste(c, b);
                            bg + 700.0 * (base + TAU * height(c, b) / t + th[k]).cos()
                        })
                        .collect();
                    let got = phase(&i_k, &th) - base;
                    let got = (got + TAU / 2.0).rem_euclid(TAU) - TAU / 2.0;
                    *m.at_mut(i, c) = (got / TAU * t) as f32;
                }
            }
            along.push(i as f64 + e.iter().sum::<f64>() / 4.0);
            samples.push(sp);
        }
        let places = RowPlaces {
            along: along.clone(),
            across: vec![0.0; rows],
            samples,
        };
        let settled_on = |g: &Grid, p: PasteReflectance, instructions: Instructions| {
            let mut held = g.clone();
            let mut s = Settle {
                paste: p,
                instructions,
                ..Settle::default()
            };
            s.rows(&mut held, 0, Some(&places), &reference, &period_um, true);
            held
        };
        let settled = |g: &Grid, p: PasteReflectance| settled_on(g, p, Instructions::best());
        let without = settled(&g, PasteReflectance::default());
        let with = settled(&g, PasteReflectance::new(400.0 / 700.0, paste_um));
        // The baseline's build gives the same bits, with the reflectance and without.
        let bits = |g: &Grid| g.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        for (p, got) in [
            (PasteReflectance::default(), &without),
            (PasteReflectance::new(400.0 / 700.0, paste_um), &with),
        ] {
            assert_eq!(bits(&settled_on(&g, p, Instructions::Baseline)), bits(got));
        }
        let reference_map = settled(&same, PasteReflectance::default());
        // Per column, the heights summed over the rows against paste reflecting as the board.
        let column_error = |m: &Grid| {
            let sq: f64 = (0..w)
                .map(|c| {
                    let d: f64 = (0..rows)
                        .map(|i| f64::from(m.data[i * w + c] - reference_map.data[i * w + c]))
                        .sum();
                    d * d
                })
                .sum();
            (sq / w as f64).sqrt()
        };
        let (e_without, e_with) = (column_error(&without), column_error(&with));
        assert!(e_without > 2.0, "without: {e_without} um rows");
        assert!(
            e_with < bound * e_without,
            "band {band}: with {e_with}, without {e_without} um rows"
        );
        // Where the board is flat (the first and last rows, the slope 0), nothing changes.
        for i in [1, rows - 2] {
            for c in 0..w {
                let (a, b) = (with.data[i * w + c], without.data[i * w + c]);
                assert!((a - b).abs() < 1e-3, "row {i} column {c}: {a} against {b}");
            }
        }
    }
}
