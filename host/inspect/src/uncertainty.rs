//! A pad's standard uncertainty: how much its volume and height would scatter if the same
//! print were measured again, predicted from the map of this one measurement.
//!
//! The volume is the sum over the cell's `N` pixels of their height above the local surface,
//! so two independent parts add in variance (in pixel-sum units, um^2):
//!
//! - **The cell's pixel noise**: `kappa (n_paste sigma_p^2 + n_bare sigma_b^2)`, with `kappa`
//!   the map's noise correlation area ([`crate::noise`]), `sigma_b` the bare board's pixel
//!   noise about the local surface (its fit's rms, corrected for the fitted terms) and
//!   `sigma_p` the paste's, from the differences of neighbouring pixels in the opening's
//!   interior: `median(d^2) / 0.4549 / (2 (1 - rho_1))` (`0.4549` the median of a chi-square
//!   of one degree, `rho_1` the map's lag-one correlation; the bare board's where the interior
//!   has fewer than [`MIN_DIFFS`] pairs). Paste and board reflect differently, so their noise
//!   differs; `n_paste` counts the cell pixels above the area threshold.
//! - **The local surface**: every cell pixel is taken above the same fitted surface, so its
//!   error counts `N` times: `N^2 t' (X'X)^-1 t sigma_b^2 kappa_s`, with `t` the cell's mean
//!   terms (`1, dx, dy, ...`), `(X'X)^-1` the fit's inverse normal matrix and `kappa_s` the
//!   correlation of samples taken at the fit's stride.
//!
//! The height, a mean over the interior's `n` valid pixels, has `sigma_p^2 min(kappa / n, 1)`
//! plus the surface's variance at the interior's mean terms.
//!
//! Not included: the registration's error (a few um, which moves the cell by less than a
//! pixel: the cell's margin keeps the paste in it), the calibration's (the same on every
//! board of a calibration; `dpsa grr` measures it as reproducibility) and the map's
//! resampling of the deposit's walls. The prediction is checked against repeated
//! measurements of the same print (`dpsa grr`, `docs/spc.md`).

use crate::measure::SurfaceFit;
use crate::noise::NoiseModel;

/// Fewest interior pixel pairs for the paste's own noise estimate.
pub const MIN_DIFFS: usize = 16;

/// The median of a chi-square variable of one degree of freedom.
const CHI2_1_MEDIAN: f64 = 0.454_936_423_119_572_8;

/// What one pad's cell adds up to, for its uncertainty.
pub(crate) struct CellCounts<'a> {
    /// Pixels summed into the volume.
    pub cell_n: usize,
    /// Their [`crate::measure`] surface terms, summed.
    pub cell_t: [f64; 6],
    /// Of them, pixels above the area threshold (paste).
    pub paste_n: usize,
    /// Valid interior pixels (the height's mean) and their terms summed.
    pub int_n: usize,
    /// The interior's terms summed.
    pub int_t: [f64; 6],
    /// Squared differences of neighbouring interior pixels, um^2.
    pub diff2: &'a mut [f64],
    /// Squared slopes (um per pixel) summed over the cell's valid pixels.
    pub cell_g2: f64,
    /// ... and over the interior's.
    pub int_g2: f64,
    /// Over the cell's map rows, the squared sum of the row's slopes along the motion
    /// ((um per pixel)^2), summed, plus `2 rho` times the products of neighbouring rows' sums
    /// (`rho` the program's `row_correlation`): the rows' shifts' variance, per unit.
    pub cell_row_g2: f64,
    /// ... over the interior's rows.
    pub int_row_g2: f64,
    /// The cell's extent across each axis: its pixels whose next one down a column, and
    /// along a row, is not in it.
    pub cell_edges: [usize; 2],
    /// The same for the interior.
    pub int_edges: [usize; 2],
    /// The local surface's samples' shared noise with the cell (`Cell::overlap` in
    /// [`crate::measure`]): the covariance of the cell's sum and the surface's mean over it is
    /// this times the bare board's variance.
    pub overlap: f64,
    /// The machine's lateral scatter of single pixels, pixels.
    pub lateral_px: f64,
    /// The machine's scatter of whole rows along the motion, pixels.
    pub row_px: f64,
}

/// Variances of one pad's figures.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Uncertainty {
    /// The volume's variance, pixel-sum units (um^2).
    pub volume_sum: f64,
    /// Of it, the local surface's.
    pub volume_surface: f64,
    /// The rows' shifts' part of the volume's variance per px^2 of row scatter, pixel-sum
    /// units (`CellCounts::cell_row_g2`; negative where the rows' correlation is).
    pub volume_row_unit: f64,
    /// The height's variance, um^2 (NaN without interior pixels).
    pub height: f64,
    /// The paste's pixel noise, um.
    pub paste_sigma_um: f64,
}

impl Uncertainty {
    /// The variances of a pad with local surface `fit` (samples every `stride` pixels) and
    /// cell `c`, on a map whose noise is `noise`.
    pub fn of(
        fit: &SurfaceFit,
        stride: usize,
        c: CellCounts<'_>,
        noise: &NoiseModel,
    ) -> Uncertainty {
        let p = fit.coef.len();
        let dof = fit.kept.saturating_sub(p).max(1) as f64;
        let var_b = fit.rms * fit.rms * fit.kept as f64 / dof;
        let rho1 = 0.5 * (noise.at(0, 1) + noise.at(1, 0));
        let var_p = if c.diff2.len() >= MIN_DIFFS {
            let mid = c.diff2.len() / 2;
            let (_, med, _) = c.diff2.select_nth_unstable_by(mid, f64::total_cmp);
            *med / CHI2_1_MEDIAN / (2.0 * (1.0 - rho1).max(0.05))
        } else {
            var_b
        };
        let kappa_s = noise.kappa_at_stride(stride);
        let mean = |t: &[f64; 6], n: usize| {
            let mut m = *t;
            for v in &mut m {
                *v /= n.max(1) as f64;
            }
            m
        };
        let n = c.cell_n as f64;
        let bare = c.cell_n.saturating_sub(c.paste_n) as f64;
        let lat2 = c.lateral_px * c.lateral_px;
        let row2 = c.row_px * c.row_px;
        let kappa = noise.kappa_within(c.cell_n, c.cell_edges);
        let pixels = kappa * (c.paste_n as f64 * var_p + bare * var_b + lat2 * c.cell_g2)
            + row2 * c.cell_row_g2;
        let surface = n * n * fit.mean_variance(&mean(&c.cell_t, c.cell_n)) * var_b * kappa_s;
        // The volume is the cell's sum minus n times the surface's mean; where the surface's
        // samples lie in the cell (or next to it) the two share noise, which comes off.
        let shared = 2.0 * n * var_b * c.overlap;
        let height = if c.int_n > 0 {
            (var_p + lat2 * c.int_g2 / c.int_n as f64)
                * (noise.kappa_within(c.int_n, c.int_edges) / c.int_n as f64).min(1.0)
                + row2 * c.int_row_g2 / (c.int_n as f64).powi(2)
                + fit.mean_variance(&mean(&c.int_t, c.int_n)) * var_b * kappa_s
        } else {
            f64::NAN
        };
        Uncertainty {
            volume_sum: (pixels + surface - shared).max(0.0),
            volume_surface: surface,
            volume_row_unit: c.cell_row_g2,
            height,
            paste_sigma_um: var_p.sqrt(),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::map::BoardMap;
    use crate::measure::{measure_all, Instructions, Placed};
    use crate::noise::NoiseModel;
    use crate::program::Program;
    use dpsa_formats::grid::{BoardGrid, Grid};
    use dpsa_gerber::pads::{Outline, Pad, Rigid};

    /// Standard normal draws from splitmix64 and Box-Muller (independent of the code tested).
    struct Normal(u64);
    impl Normal {
        fn uniform(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        }
        fn next(&mut self) -> f64 {
            let u = self.uniform().max(1e-300);
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * self.uniform()).cos()
        }
    }

    const N: usize = 160;
    const PITCH: f64 = 0.02;

    /// One rounded-rectangle opening, 0.6 x 0.4 mm, in the middle of the 3.2 mm map.
    fn pad() -> Pad {
        Pad {
            index: 0,
            outline: Outline::RoundRect {
                centre: [1.6, 1.6],
                size: [0.6, 0.4],
                radius: 0.05,
                rotation_deg: 0.0,
            },
            component: None,
            pin: None,
            aperture: None,
        }
    }

    /// A tilted board with a 100 um deposit filling the opening, plus noise of `sigma` um:
    /// white, or (`boxed`) white noise averaged over 2 x 2 pixels and scaled back to `sigma`
    /// (its correlation: 1/2 at one pixel along an axis, 1/4 diagonally; `kappa` 4).
    fn map(seed: u64, sigma: f64, boxed: bool) -> BoardMap {
        let mut g = Normal(seed);
        let m = N + 1;
        let white: Vec<f64> = (0..m * m).map(|_| g.next()).collect();
        let p = pad();
        let mut data = vec![0.0f32; N * N];
        for i in 0..N {
            for j in 0..N {
                let (x, y) = ((i as f64 + 0.5) * PITCH, (j as f64 + 0.5) * PITCH);
                let e = if boxed {
                    0.5 * (white[i * m + j]
                        + white[(i + 1) * m + j]
                        + white[i * m + j + 1]
                        + white[(i + 1) * m + j + 1])
                } else {
                    white[i * m + j]
                };
                let paste = if p.outline.signed_distance([x, y]) < 0.0 {
                    100.0
                } else {
                    0.0
                };
                data[i * N + j] = (200.0 + 3.0 * x - 2.0 * y + paste + sigma * e) as f32;
            }
        }
        BoardMap {
            board_id: None,
            grid: BoardGrid {
                x0_mm: 0.0,
                y0_mm: 0.0,
                pitch_mm: PITCH,
                rows: N,
                width: N,
            },
            heights: Grid {
                width: N,
                rows: N,
                data,
            },
        }
    }

    /// The program of these maps: the walls are exact steps, so no lateral term.
    fn program() -> Program {
        let mut p = Program::new("paste.gbr");
        p.measure.lateral_sigma_um = 0.0;
        p.measure.row_sigma_um = 0.0;
        p
    }

    #[test]
    fn noise_model_finds_the_correlation() {
        let pads = [pad()];
        let placed = Placed::new(&pads, &Rigid::IDENTITY, &[], 1.0);
        for (boxed, kappa, rho1) in [(false, 1.0, 0.0), (true, 4.0, 0.5)] {
            let nm = NoiseModel::measure(&map(7, 1.5, boxed), &placed, 0.1);
            assert!(nm.tiles >= 50, "{nm:?}");
            assert!((nm.board_sigma_um - 1.5).abs() < 0.08, "{nm:?}");
            assert!((nm.kappa - kappa).abs() < 0.12 * kappa, "{boxed}: {nm:?}");
            assert!((nm.at(0, 1) - rho1).abs() < 0.04, "{nm:?}");
            assert!((nm.at(1, 0) - rho1).abs() < 0.04, "{nm:?}");
            assert!((nm.at(1, -1) - rho1 * rho1).abs() < 0.04, "{nm:?}");
        }
    }

    /// The stated uncertainty against the scatter of the same deposit measured on 300 maps
    /// with fresh noise: within 12 % (three standard errors of a sigma from 300 samples), for
    /// white and correlated noise.
    #[test]
    fn stated_uncertainty_matches_repeated_measurements() {
        let pads = [pad()];
        let program = program();
        let placed = Placed::new(&pads, &Rigid::IDENTITY, &[], 1.0);
        for boxed in [false, true] {
            let (mut v, mut h, mut uv, mut uh) = (Vec::new(), Vec::new(), 0.0, 0.0);
            let runs = 300;
            for seed in 0..runs {
                let m = map(1000 + seed, 1.5, boxed);
                let noise = NoiseModel::measure(&m, &placed, 0.1);
                let pm = &measure_all(
                    Instructions::best(),
                    &m,
                    &pads,
                    &placed,
                    &Rigid::IDENTITY,
                    &program,
                    &noise,
                )[0];
                assert!(pm.unmeasurable.is_none());
                v.push(pm.volume_pct);
                h.push(pm.height_um);
                uv += pm.volume_u_pct.powi(2) / runs as f64;
                uh += pm.height_u_um.powi(2) / runs as f64;
            }
            let sd = |x: &[f64]| {
                let m = x.iter().sum::<f64>() / x.len() as f64;
                (x.iter().map(|a| (a - m).powi(2)).sum::<f64>() / (x.len() - 1) as f64).sqrt()
            };
            let (rv, rh) = (uv.sqrt() / sd(&v), uh.sqrt() / sd(&h));
            assert!(
                (rv - 1.0).abs() < 0.12,
                "{boxed}: volume stated / observed {rv:.3}"
            );
            assert!(
                (rh - 1.0).abs() < 0.12,
                "{boxed}: height stated / observed {rh:.3}"
            );
        }
    }

    /// The rows' part of a volume's variance, as `dpsa grr`'s pad study takes it apart: the
    /// stated variance with a row scatter less the one without is that scatter squared times
    /// `volume_var_per_row_um2`, whatever the rows' correlation.
    #[test]
    fn the_rows_part_of_the_volume_variance_is_taken_apart() {
        let pads = [pad()];
        let placed = Placed::new(&pads, &Rigid::IDENTITY, &[], 1.0);
        let m = map(11, 1.5, false);
        let noise = NoiseModel::measure(&m, &placed, 0.1);
        for rho in [0.0, 0.36, -0.2] {
            let at = |row: f64| {
                let mut p = program();
                p.measure.row_sigma_um = row;
                p.measure.row_correlation = rho;
                measure_all(
                    Instructions::best(),
                    &m,
                    &pads,
                    &placed,
                    &Rigid::IDENTITY,
                    &p,
                    &noise,
                )[0]
                .clone()
            };
            let (none, some) = (at(0.0), at(4.0));
            let per = some.volume_var_per_row_um2;
            assert!(
                per > 0.0 && per == none.volume_var_per_row_um2,
                "{rho}: {per}"
            );
            let rows_part = some.volume_u_pct.powi(2) - none.volume_u_pct.powi(2);
            assert!(
                (rows_part / (16.0 * per) - 1.0).abs() < 1e-9,
                "{rho}: {rows_part} against {}",
                16.0 * per
            );
        }
    }
}
