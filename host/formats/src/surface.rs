//! The local board surface under a height grid (`heights.colour.png`, `overview.png`): what a
//! picture subtracts so that the paste stands on a flat board, the board's bow and warp taken
//! out. Fitted to the heights themselves (no paste layer needed); see [`local_surface`].

use crate::grid::Grid;

/// Side of a cell of the local surface, mm: larger than the largest deposit a cell is mostly
/// covered by (a QFN's thermal pad), small against the bow (0.8 mm over the paper board's
/// 220 mm bends by under 0.5 um inside a cell).
pub const SURFACE_CELL_MM: f64 = 5.0;

/// The local board surface under `h` (cells of `cell` pixels): NaN only where `h` has no
/// valid height.
///
/// Two steps. A smooth surface first: a product of cubics in the map's rows and columns (16
/// terms: a bow, a twist and their higher orders) fitted to the valid heights by least
/// squares, the paste set aside by refitting to what lies within a few robust deviations of
/// it (deposits lie only above). Then what the cubics miss: a low percentile of each cell of
/// what is left (bare board outnumbers paste in a cell), bilinear between the cells' centres.
/// A percentile of the heights alone would sit below each cell's centre by a share of the
/// board's slope across it (tens of micrometres at a bowed board's ends).
pub fn local_surface(h: &Grid, cell: usize) -> Grid {
    let smooth = smooth_surface(h);
    let rest = cell_surface(h, Some(&smooth), cell, CELL_PERCENTILE);
    Grid {
        width: h.width,
        rows: h.rows,
        data: smooth
            .data
            .iter()
            .zip(&rest.data)
            .map(|(a, b)| a + b)
            .collect(),
    }
}

/// Most samples the smooth surface is fitted to (every `k`-th row and column of the map).
const FIT_SAMPLES: usize = 250_000;

/// Chebyshev polynomials `T0..T3` at `t` in `[-1, 1]`.
fn cheb(t: f64) -> [f64; 4] {
    [1.0, t, 2.0 * t * t - 1.0, t * (4.0 * t * t - 3.0)]
}

/// The 16 products `T_i(u) T_j(v)` of map row `r` and column `c`.
fn terms(r: usize, c: usize, rows: usize, w: usize) -> [f64; 16] {
    let norm = |i: usize, n: usize| {
        if n > 1 {
            2.0 * i as f64 / (n - 1) as f64 - 1.0
        } else {
            0.0
        }
    };
    let (a, b) = (cheb(norm(r, rows)), cheb(norm(c, w)));
    let mut t = [0.0; 16];
    for i in 0..4 {
        for j in 0..4 {
            t[i * 4 + j] = a[i] * b[j];
        }
    }
    t
}

/// The smooth part of [`local_surface`] (0 everywhere when too few heights are valid).
fn smooth_surface(h: &Grid) -> Grid {
    let (w, rows) = (h.width, h.rows);
    let mut out = Grid {
        width: w,
        rows,
        data: vec![0.0; w * rows],
    };
    let k = ((w * rows) as f64 / FIT_SAMPLES as f64)
        .sqrt()
        .ceil()
        .max(1.0) as usize;
    let samples: Vec<([f64; 16], f64)> = (0..rows)
        .step_by(k)
        .flat_map(|r| (0..w).step_by(k).map(move |c| (r, c)))
        .filter_map(|(r, c)| {
            let v = h.data[r * w + c];
            v.is_finite().then(|| (terms(r, c, rows, w), f64::from(v)))
        })
        .collect();
    if samples.len() < 64 {
        return out;
    }
    let mut keep = vec![true; samples.len()];
    let mut coef = [0.0; 16];
    for _ in 0..8 {
        let Some(c) = least_squares(&samples, &keep) else {
            break;
        };
        coef = c;
        let res: Vec<f64> = samples
            .iter()
            .map(|(t, v)| v - t.iter().zip(&coef).map(|(a, b)| a * b).sum::<f64>())
            .collect();
        let m = median(res.clone());
        let mad = 1.4826 * median(res.iter().map(|r| (r - m).abs()).collect());
        let (lo, hi) = (m - 4.0 * mad.max(0.5), m + 3.0 * mad.max(0.5));
        for (k, r) in keep.iter_mut().zip(&res) {
            *k = *r >= lo && *r <= hi;
        }
    }
    for r in 0..rows {
        for c in 0..w {
            let t = terms(r, c, rows, w);
            out.data[r * w + c] = t.iter().zip(&coef).map(|(a, b)| a * b).sum::<f64>() as f32;
        }
    }
    out
}

/// The median of `v` (0 for none).
fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let k = v.len() / 2;
    *v.select_nth_unstable_by(k, f64::total_cmp).1
}

/// Least squares over the kept samples: the normal equations by Gaussian elimination with
/// partial pivoting (16 unknowns; the Chebyshev terms on `[-1, 1]` keep them well
/// conditioned). None when singular.
fn least_squares(samples: &[([f64; 16], f64)], keep: &[bool]) -> Option<[f64; 16]> {
    let mut a = [[0.0f64; 17]; 16];
    for ((t, v), _) in samples.iter().zip(keep).filter(|(_, k)| **k) {
        for i in 0..16 {
            for j in 0..16 {
                a[i][j] += t[i] * t[j];
            }
            a[i][16] += t[i] * v;
        }
    }
    for col in 0..16 {
        let p = (col..16).max_by(|&x, &y| a[x][col].abs().total_cmp(&a[y][col].abs()))?;
        if a[p][col].abs().is_nan() || a[p][col].abs() <= 1e-9 {
            return None;
        }
        a.swap(col, p);
        let pivot = a[col];
        for (r, row) in a.iter_mut().enumerate() {
            if r != col {
                let f = row[col] / pivot[col];
                for (x, p) in row.iter_mut().zip(&pivot).skip(col) {
                    *x -= f * p;
                }
            }
        }
    }
    let mut x = [0.0; 16];
    for i in 0..16 {
        x[i] = a[i][16] / a[i][i];
    }
    Some(x)
}

/// Share of a cell's valid heights (less the smooth surface) below its value: bare board is
/// the low part, and a cell can be half paste.
const CELL_PERCENTILE: f64 = 0.3;

/// A percentile `q` of each cell of `h` (less `less` where given), empty cells from their
/// nearest, bilinear between the cells' centres. (No median over the cells: on a sloped
/// board a median of the cells at the map's edge, where it has fewer of them, is pulled
/// inwards.)
fn cell_surface(h: &Grid, less: Option<&Grid>, cell: usize, q: f64) -> Grid {
    let cell = cell.max(1);
    let (cw, ch) = (h.width.div_ceil(cell).max(1), h.rows.div_ceil(cell).max(1));
    let mut low = vec![f32::NAN; cw * ch];
    let mut vals: Vec<f32> = Vec::new();
    for cr in 0..ch {
        for cc in 0..cw {
            vals.clear();
            let cols = cc * cell..((cc + 1) * cell).min(h.width);
            let rows = cr * cell..((cr + 1) * cell).min(h.rows);
            let size = cols.len() * rows.len();
            for r in rows {
                let at = r * h.width;
                let row = &h.data[at + cols.start..at + cols.end];
                match less {
                    None => vals.extend(row.iter().filter(|v| v.is_finite())),
                    Some(s) => vals.extend(
                        row.iter()
                            .zip(&s.data[at + cols.start..at + cols.end])
                            .map(|(a, b)| a - b)
                            .filter(|v| v.is_finite()),
                    ),
                }
            }
            // A cell mostly invalid says little of its surface.
            if vals.is_empty() || vals.len() * 4 < size {
                continue;
            }
            let k = ((vals.len() - 1) as f64 * q) as usize;
            low[cr * cw + cc] = *vals.select_nth_unstable_by(k, f32::total_cmp).1;
        }
    }
    let low = fill_nearest(&low, cw, ch);
    let mut out = Grid::invalid(h.width, h.rows);
    let at = |r: usize, c: usize| low[r * cw + c];
    // Between the two nearest cells' centres, and on from the last two beyond them (linear:
    // a board sloped at its ends stays sloped up to the map's edge).
    let coord = |i: usize, n: usize, len: usize| {
        let centre = |k: usize| (k * cell + ((k + 1) * cell).min(len)) as f64 / 2.0;
        if n < 2 {
            return (0, 0, 0.0f32);
        }
        let p = i as f64 + 0.5;
        let k0 = (i / cell).min(n - 2);
        let k0 = if p < centre(k0) {
            k0.saturating_sub(1)
        } else {
            k0
        };
        let f = (p - centre(k0)) / (centre(k0 + 1) - centre(k0));
        (k0, k0 + 1, f as f32)
    };
    for r in 0..h.rows {
        let (r0, r1, fr) = coord(r, ch, h.rows);
        for c in 0..h.width {
            let (c0, c1, fc) = coord(c, cw, h.width);
            let top = at(r0, c0) * (1.0 - fc) + at(r0, c1) * fc;
            let bottom = at(r1, c0) * (1.0 - fc) + at(r1, c1) * fc;
            out.data[r * h.width + c] = top * (1.0 - fr) + bottom * fr;
        }
    }
    out
}

/// Each NaN cell given its nearest valid cell's value (all NaN: unchanged).
fn fill_nearest(v: &[f32], w: usize, n: usize) -> Vec<f32> {
    let valid: Vec<(usize, usize, f32)> = (0..v.len())
        .filter(|&i| v[i].is_finite())
        .map(|i| (i / w, i % w, v[i]))
        .collect();
    if valid.is_empty() {
        return v.to_vec();
    }
    (0..w * n)
        .map(|i| {
            if v[i].is_finite() {
                return v[i];
            }
            let (r, c) = ((i / w) as i64, (i % w) as i64);
            valid
                .iter()
                .min_by_key(|&&(vr, vc, _)| (vr as i64 - r).pow(2) + (vc as i64 - c).pow(2))
                .map_or(f32::NAN, |t| t.2)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The small scene's board: 300 um of warp over 20 x 14 mm (`(1 - xi^2)(1 - eta^2)`), a
    /// quarter of it paste in 1 mm squares, and noise: the bare board within 5 um of the
    /// surface. (`dpsa_board::colour`'s test takes the paper board's steepest ends.)
    #[test]
    fn a_warped_board_a_quarter_paste_is_flattened() {
        let worst =
            |v: &[f32], target: f32| v.iter().map(|x| (x - target).abs()).fold(0.0, f32::max);
        let (w2, rows2, p2) = (140usize, 200usize, 0.1);
        let dense = |r: usize, c: usize| (r % 20) < 10 && (c % 20) < 10;
        let mut h2 = Grid::invalid(w2, rows2);
        for r in 0..rows2 {
            for c in 0..w2 {
                let (xi, eta) = (2.0 * r as f64 / 199.0 - 1.0, 2.0 * c as f64 / 139.0 - 1.0);
                let warp = 300.0 * (1.0 - xi * xi) * (1.0 - eta * eta);
                let paste = if dense(r, c) { 100.0 } else { 0.0 };
                let noise = 1.5 * (((r * 7919 + c * 104_729) % 1000) as f64 / 500.0 - 1.0);
                h2.data[r * w2 + c] = (warp + paste + noise) as f32;
            }
        }
        let s2 = local_surface(&h2, (SURFACE_CELL_MM / p2) as usize);
        let off: Vec<f32> = (0..w2 * rows2)
            .filter(|&i| !dense(i / w2, i % w2))
            .map(|i| h2.data[i] - s2.data[i])
            .collect();
        assert!(
            worst(&off, 0.0) < 5.0,
            "dense board's bare board {}",
            worst(&off, 0.0)
        );
    }
}
