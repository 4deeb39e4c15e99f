//! The map's noise: how neighbouring heights of the board map vary together, measured on the
//! bare board of the map itself.
//!
//! Each board pixel is resampled from the cameras' pixels (bilinear, then blended where
//! cameras overlap), so the noise of neighbouring board pixels is correlated: a sum over `N`
//! pixels of noise `sigma` varies by `sigma^2 N kappa`, not `sigma^2 N`, with `kappa` the sum
//! of the noise's correlation coefficients over all lags (the area, in pixels, over which one
//! pixel's noise is shared). A per-pad volume is such a sum, so its uncertainty needs `kappa`.
//!
//! [`NoiseModel::measure`] takes up to [`TILES`] tiles of [`TILE`] x [`TILE`] pixels spread
//! over the map where every pixel is valid and at least the surface guard from every opening
//! and fiducial (bare board), removes a plane from each (the warp), drops tiles whose rms is
//! more than three times the median tile's (a smear, a mark, a scratch), and estimates the
//! correlation coefficient `rho(di, dj)` at every lag up to [`LAGS`] pixels from the pairs
//! inside the tiles. Lags beyond two pixels are not counted: bilinear resampling at a board
//! pitch near the camera pitch shares noise over one pixel each way, which the lag 2 term
//! shows is all (its coefficient is reported).

use crate::map::BoardMap;
use crate::measure::Placed;
use serde::Serialize;

/// Side of a tile, pixels.
pub const TILE: usize = 16;
/// Most tiles used.
pub const TILES: usize = 600;
/// Largest lag counted along each axis, pixels.
pub const LAGS: usize = 2;
/// Lags up to this (beyond [`LAGS`]) measure the bias that removing the plane leaves.
const FAR: usize = 4;

/// How the map's noise is correlated between neighbouring pixels.
#[derive(Clone, Debug, Serialize)]
pub struct NoiseModel {
    /// Bare-board tiles used.
    pub tiles: usize,
    /// Their median rms about a plane, um (the bare board's pixel noise).
    pub board_sigma_um: f64,
    /// Correlation coefficient at lag `(di, dj)` (rows, columns) for `di` in `0..=LAGS`, `dj`
    /// in `-LAGS..=LAGS` (row-major, `2 LAGS + 1` wide); `rho(-di, -dj) = rho(di, dj)`.
    pub rho: Vec<f64>,
    /// Sum of `rho` over every lag within `LAGS` both ways: the variance of a sum over `N`
    /// pixels is `sigma^2 N kappa` (1 for uncorrelated pixels).
    pub kappa: f64,
}

impl NoiseModel {
    /// No correlation known (a map without bare board): `kappa` 1.
    pub fn uncorrelated() -> NoiseModel {
        let w = 2 * LAGS + 1;
        let mut rho = vec![0.0; (LAGS + 1) * w];
        rho[LAGS] = 1.0;
        NoiseModel {
            tiles: 0,
            board_sigma_um: f64::NAN,
            rho,
            kappa: 1.0,
        }
    }

    /// Coefficient at lag `(di, dj)`, pixels (0 beyond `LAGS`).
    pub fn at(&self, di: i64, dj: i64) -> f64 {
        let (di, dj) = if di < 0 { (-di, -dj) } else { (di, dj) };
        let l = LAGS as i64;
        if di > l || dj.abs() > l {
            return 0.0;
        }
        self.rho[(di * (2 * l + 1) + dj + l) as usize]
    }

    /// Sum of the coefficients at lags that are multiples of `stride` along both axes: the
    /// `kappa` of samples taken every `stride` pixels.
    pub fn kappa_at_stride(&self, stride: usize) -> f64 {
        let l = LAGS as i64;
        let s = stride.max(1) as i64;
        let mut k = 0.0;
        for di in -l..=l {
            for dj in -l..=l {
                if di % s == 0 && dj % s == 0 {
                    k += self.at(di, dj);
                }
            }
        }
        k.max(1.0)
    }

    /// The `kappa` of a region of `n` pixels whose extents across the two axes are `edges`
    /// (the pixels whose next one down a column, and along a row, lies outside): the sum of
    /// every pixel's coefficients with the region's other pixels, over `n`. A lag `(di, dj)`
    /// loses about `|di| edges[0] + |dj| edges[1]` of its `n` pairs at the region's border,
    /// which matters for small regions (a 0.3 mm deposit's interior is a few hundred pixels).
    pub fn kappa_within(&self, n: usize, edges: [usize; 2]) -> f64 {
        if n == 0 {
            return 1.0;
        }
        let l = LAGS as i64;
        let mut k = 0.0;
        for di in -l..=l {
            for dj in -l..=l {
                let lost = di.unsigned_abs() as f64 * edges[0] as f64
                    + dj.unsigned_abs() as f64 * edges[1] as f64;
                k += self.at(di, dj) * (n as f64 - lost).max(0.0);
            }
        }
        (k / n as f64).max(1.0)
    }

    /// Measures the model on the bare board of `map`, away from the `placed` openings by
    /// `guard` (mm).
    pub fn measure(map: &BoardMap, placed: &Placed, guard: f64) -> NoiseModel {
        let g = &map.grid;
        if g.rows < TILE || g.width < TILE {
            return NoiseModel::uncorrelated();
        }
        // A lattice of candidate tiles over the whole map, about 4 TILES of them.
        let (ti, tj) = (g.rows / TILE, g.width / TILE);
        let step = (((ti * tj) as f64 / (4 * TILES) as f64).sqrt().ceil() as usize).max(1);
        let mut tiles: Vec<(f64, Vec<f64>)> = Vec::new();
        'tile: for a in (0..ti).step_by(step) {
            'b: for b in (0..tj).step_by(step) {
                if tiles.len() >= TILES {
                    break 'tile;
                }
                let (i0, j0) = (a * TILE, b * TILE);
                let (x0, y0) = g.centre(i0, j0);
                let (x1, y1) = g.centre(i0 + TILE - 1, j0 + TILE - 1);
                let bbox = [x0.min(x1), y0.min(y1), x0.max(x1), y0.max(y1)];
                if !placed.near(bbox, guard, usize::MAX).is_empty()
                    || placed.fiducials.iter().any(|(f, r)| {
                        let dx = (bbox[0] - f[0]).max(f[0] - bbox[2]).max(0.0);
                        let dy = (bbox[1] - f[1]).max(f[1] - bbox[3]).max(0.0);
                        dx.hypot(dy) < r + guard
                    })
                {
                    continue;
                }
                let mut r = Vec::with_capacity(TILE * TILE);
                for i in i0..i0 + TILE {
                    for j in j0..j0 + TILE {
                        let h = map.heights.data[i * g.width + j];
                        if !h.is_finite() {
                            continue 'b;
                        }
                        r.push(f64::from(h));
                    }
                }
                let rms = detrend(&mut r);
                tiles.push((rms, r));
            }
        }
        Self::from_tiles(tiles)
    }

    /// The model from tiles of residuals (row-major `TILE` x `TILE`) with their rms.
    fn from_tiles(mut tiles: Vec<(f64, Vec<f64>)>) -> NoiseModel {
        if tiles.len() < 4 {
            return NoiseModel::uncorrelated();
        }
        let mut rms: Vec<f64> = tiles.iter().map(|t| t.0).collect();
        rms.sort_by(f64::total_cmp);
        let med = rms[rms.len() / 2];
        tiles.retain(|t| t.0 <= 3.0 * med);
        // Sums of products at every lag up to FAR, in the half plane (di > 0, or di = 0 and
        // dj >= 0): the lags within LAGS are the model, those beyond it measure the bias.
        let far = FAR as i64;
        let w = 2 * FAR + 1;
        let mut sum = vec![0.0; (FAR + 1) * w];
        let mut cnt = vec![0usize; (FAR + 1) * w];
        let (mut ss, mut n) = (0.0, 0usize);
        for (_, r) in &tiles {
            for i in 0..TILE {
                for j in 0..TILE {
                    let v = r[i * TILE + j];
                    ss += v * v;
                    n += 1;
                    for di in 0..=FAR {
                        for dj in -far..=far {
                            let (ii, jj) = (i + di, j as i64 + dj);
                            if (di == 0 && dj < 0) || ii >= TILE || jj < 0 || jj >= TILE as i64 {
                                continue;
                            }
                            let at = di * w + (dj + far) as usize;
                            sum[at] += v * r[ii * TILE + jj as usize];
                            cnt[at] += 1;
                        }
                    }
                }
            }
        }
        let var = ss / n as f64;
        let raw = |di: i64, dj: i64| {
            let at = di as usize * w + (dj + far) as usize;
            if cnt[at] > 0 {
                sum[at] / cnt[at] as f64 / var
            } else {
                0.0
            }
        };
        // Removing each tile's plane leaves every pair's product low by about the same
        // amount (the plane takes some of the noise's own variance): the mean coefficient at
        // the far lags, where the noise itself has none, is that bias; it is taken off every
        // lag and the variance put back.
        let (mut b, mut nb) = (0.0, 0);
        for di in 0..=far {
            for dj in -far..=far {
                if (di == 0 && dj <= 0) || di.max(dj.abs()) <= LAGS as i64 {
                    continue;
                }
                b += raw(di, dj);
                nb += 1;
            }
        }
        let bias = if nb > 0 { b / nb as f64 } else { 0.0 };
        let l = LAGS as i64;
        let wl = 2 * LAGS + 1;
        let mut rho = vec![0.0; (LAGS + 1) * wl];
        for di in 0..=l {
            for dj in -l..=l {
                let (a, c) = if di == 0 && dj < 0 {
                    (0, -dj)
                } else {
                    (di, dj)
                };
                rho[di as usize * wl + (dj + l) as usize] = (raw(a, c) - bias) / (1.0 - bias);
            }
        }
        rho[LAGS] = 1.0;
        let mut model = NoiseModel {
            tiles: tiles.len(),
            board_sigma_um: med,
            rho,
            kappa: 0.0,
        };
        model.kappa = model.kappa_at_stride(1);
        model
    }
}

/// Removes the least-squares plane from a `TILE` x `TILE` tile (row-major); its rms, um.
fn detrend(r: &mut [f64]) -> f64 {
    let n = (TILE * TILE) as f64;
    let c = (TILE as f64 - 1.0) / 2.0;
    let mean = r.iter().sum::<f64>() / n;
    let (mut si, mut sj, mut sii) = (0.0, 0.0, 0.0);
    for i in 0..TILE {
        for j in 0..TILE {
            let v = r[i * TILE + j] - mean;
            si += v * (i as f64 - c);
            sj += v * (j as f64 - c);
        }
        sii += TILE as f64 * (i as f64 - c).powi(2);
    }
    // The centred indices are orthogonal, with the same sum of squares along both axes.
    let (bi, bj) = (si / sii, sj / sii);
    let mut ss = 0.0;
    for i in 0..TILE {
        for j in 0..TILE {
            let v = &mut r[i * TILE + j];
            *v -= mean + bi * (i as f64 - c) + bj * (j as f64 - c);
            ss += *v * *v;
        }
    }
    (ss / (n - 3.0)).sqrt()
}
