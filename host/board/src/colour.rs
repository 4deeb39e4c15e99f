//! `heights.colour.png`: the map as a person reads it.
//!
//! - **What it shows.** By default the height above the *local board surface*: a board bows by
//!   hundreds of micrometres over its length, and a false colour over the absolute heights
//!   shows that bow, with the paste a speckle on it. The surface is [`local_surface`]: a
//!   smooth surface fitted robustly to the whole map, then a low percentile of each cell of
//!   [`SURFACE_CELL_MM`] of what it misses. The absolute map is drawn on
//!   request ([`Shows::Absolute`]).
//! - **How it is turned.** As a Gerber viewer shows the design: board `x` (the conveyor's
//!   motion, the map's rows) to the right, `y` (the map's columns) up, with both axes in mm.
//! - **The colour bar** beside the map, in um, over the 0.5th to 99.7th percentile of what is
//!   drawn (the paste's tops, not the bare board's noise, set its top on a printed board);
//!   invalid pixels dark grey. Text and marks are sized to the picture
//!   (`dpsa_formats::picture`, DejaVu Sans embedded).

use crate::resample::BoardGrid;
use crate::Grid;
use dpsa_formats::images::colour;
use dpsa_formats::labels::ticks;
use dpsa_formats::picture::{draw, text, text_width};
use image::{Rgb, RgbImage};

/// What `heights.colour.png` shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Shows {
    /// The height above the local board surface (the board's bow and warp removed).
    AboveLocalSurface,
    /// The absolute height over the calibration's reference plane.
    Absolute,
}

/// Side of a cell of the local surface, mm: larger than the largest deposit a cell is mostly
/// covered by (a QFN's thermal pad), small against the bow (0.8 mm over the paper board's
/// 220 mm bends by under 0.5 um inside a cell).
pub const SURFACE_CELL_MM: f64 = 5.0;

/// Lower and upper percentiles of the colour bar.
const RANGE: (f64, f64) = (0.005, 0.997);

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

/// The `q`-quantile of the finite values of `v` (by rank; None without one).
fn quantile(v: &[f32], q: f64) -> Option<f32> {
    let mut f: Vec<f32> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if f.is_empty() {
        return None;
    }
    let k = (((f.len() - 1) as f64) * q).round() as usize;
    Some(*f.select_nth_unstable_by(k, f32::total_cmp).1)
}

/// The picture drawn and its scale.
#[derive(Clone, Debug)]
pub struct View {
    /// The image.
    pub image: RgbImage,
    /// What it shows.
    pub shows: Shows,
    /// The colour bar's range, um.
    pub range_um: (f32, f32),
    /// Where the map's own pixels lie in the image: left, top, width, height, px.
    pub plot: (u32, u32, u32, u32),
}

/// `h` (the map, or a preview of it whose pixels are `k x k` blocks of the map on `grid`)
/// as a picture: see the module docs.
pub fn view(h: &Grid, grid: &BoardGrid, k: usize, shows: Shows) -> View {
    let k = k.max(1);
    let block_mm = grid.pitch_mm * k as f64;
    let drawn = match shows {
        Shows::Absolute => h.clone(),
        Shows::AboveLocalSurface => {
            let cell = ((SURFACE_CELL_MM / block_mm).round() as usize).max(2);
            let s = local_surface(h, cell);
            Grid {
                width: h.width,
                rows: h.rows,
                data: h.data.iter().zip(&s.data).map(|(a, b)| a - b).collect(),
            }
        }
    };
    let lo = quantile(&drawn.data, RANGE.0).unwrap_or(0.0);
    let hi = quantile(&drawn.data, RANGE.1).unwrap_or(1.0).max(lo + 1.0);
    // x to the right (the map's rows), y up (its columns, the last at the top).
    let (pw, ph) = (h.rows as u32, h.width as u32);
    let fs = (f64::from(pw.max(ph)) / 80.0).clamp(12.0, 32.0);
    let left = (4.0 * fs) as u32;
    let top = (2.4 * fs) as u32;
    let bottom = (3.4 * fs) as u32;
    let bar = (1.2 * fs) as u32;
    let right = bar + (6.0 * fs) as u32;
    let (iw, ih) = (left + pw + right, top + ph + bottom);
    let mut img = RgbImage::from_pixel(iw.max(1), ih.max(1), Rgb([255; 3]));
    let scale = |v: f32| f64::from((v - lo) / (hi - lo)).clamp(0.0, 1.0);
    for r in 0..h.rows {
        for c in 0..h.width {
            let v = drawn.data[r * h.width + c];
            let px = if v.is_finite() {
                Rgb(colour(scale(v)))
            } else {
                Rgb([40, 40, 40])
            };
            img.put_pixel(left + r as u32, top + ph - 1 - c as u32, px);
        }
    }
    // The colour bar, lo at the bottom.
    let bx = left + pw + (fs * 0.8) as u32;
    for y in 0..ph {
        let t = 1.0 - f64::from(y) / f64::from(ph.saturating_sub(1).max(1));
        for x in bx..(bx + bar).min(iw) {
            img.put_pixel(x, top + y, Rgb(colour(t)));
        }
    }
    let black = Rgb([0u8; 3]);
    let line = |img: &mut RgbImage, (x0, y0): (u32, u32), (x1, y1): (u32, u32)| {
        for x in x0.min(x1)..=x0.max(x1) {
            for y in y0.min(y1)..=y0.max(y1) {
                if x < iw && y < ih {
                    img.put_pixel(x, y, black);
                }
            }
        }
    };
    // The plot's frame.
    line(&mut img, (left - 1, top - 1), (left + pw, top - 1));
    line(&mut img, (left - 1, top + ph), (left + pw, top + ph));
    line(&mut img, (left - 1, top - 1), (left - 1, top + ph));
    line(&mut img, (left + pw, top - 1), (left + pw, top + ph));
    let tick = (0.4 * fs) as u32;
    // Board mm of the image's columns and rows (block centres).
    let x_of = |px: f64| grid.x0_mm + (px + 0.5) * block_mm;
    let y_of = |py: f64| grid.y0_mm + (f64::from(ph) - py - 0.5) * block_mm;
    let n_ticks = |len: u32, per: f64, least: usize| {
        ((f64::from(len) / (per * fs)) as usize).clamp(least, 12)
    };
    let mut labels: Vec<((i32, i32), String)> = Vec::new();
    let (x_lo, x_hi) = (x_of(0.0), x_of(f64::from(pw) - 1.0));
    for v in ticks(x_lo, x_hi, n_ticks(pw, 5.0, 3)) {
        let px = ((v - grid.x0_mm) / block_mm - 0.5).round();
        if px < 0.0 || px >= f64::from(pw) {
            continue;
        }
        let x = left + px as u32;
        line(&mut img, (x, top + ph), (x, top + ph + tick));
        let s = format!("{v}");
        let tw = text_width(&s, fs);
        labels.push((
            (
                x as i32 - (tw / 2.0) as i32,
                (top + ph + tick) as i32 + fs as i32 + 2,
            ),
            s,
        ));
    }
    let (y_lo, y_hi) = (y_of(f64::from(ph) - 1.0), y_of(0.0));
    for v in ticks(y_lo, y_hi, n_ticks(ph, 4.0, 3)) {
        let py = (f64::from(ph) - 0.5 - (v - grid.y0_mm) / block_mm).round();
        if py < 0.0 || py >= f64::from(ph) {
            continue;
        }
        let y = top + py as u32;
        line(&mut img, (left - 1 - tick, y), (left - 1, y));
        let s = format!("{v}");
        let tw = text_width(&s, fs);
        labels.push((
            (
                left as i32 - tick as i32 - 4 - tw as i32,
                y as i32 + (fs * 0.35) as i32,
            ),
            s,
        ));
    }
    for v in ticks(f64::from(lo), f64::from(hi), n_ticks(ph, 3.0, 5)) {
        let t = (v - f64::from(lo)) / f64::from(hi - lo);
        let y = top + ((1.0 - t) * f64::from(ph.saturating_sub(1))).round() as u32;
        line(&mut img, (bx + bar, y), (bx + bar + tick / 2, y));
        labels.push((
            (
                (bx + bar + tick / 2 + 4) as i32,
                y as i32 + (fs * 0.35) as i32,
            ),
            format!("{v}"),
        ));
    }
    let title = match shows {
        Shows::AboveLocalSurface => "Height above the local board surface (bow and warp removed)",
        Shows::Absolute => "Height over the reference plane (absolute)",
    };
    labels.push(((left as i32, (top as f64 - 0.7 * fs) as i32), title.into()));
    labels.push((
        (
            (left + pw / 2) as i32 - (text_width("x, mm (conveyor motion)", fs) / 2.0) as i32,
            (ih as f64 - 0.3 * fs) as i32,
        ),
        "x, mm (conveyor motion)".into(),
    ));
    labels.push((
        (2, (top as f64 - 0.7 * fs) as i32 + (1.3 * fs) as i32),
        "y, mm".into(),
    ));
    labels.push(((bx as i32, (top as f64 - 0.3 * fs) as i32), "um".into()));
    draw(&mut img, |root| {
        for ((x, y), s) in &labels {
            text(root, (*x, *y), fs, [0; 3], [255; 3], s)?;
        }
        Ok(())
    });
    View {
        image: img,
        shows,
        range_um: (lo, hi),
        plot: (left, top, pw, ph),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A board bowed by 800 um with 100 um deposits on it: above the local surface the
    /// deposits are 100 um and the bare board 0 wherever it is, and the picture is turned as
    /// a Gerber viewer shows it (x right, y up).
    #[test]
    fn the_view_removes_the_bow_and_is_turned_as_the_design() {
        let (w, rows, pitch) = (200usize, 300usize, 0.1);
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: pitch,
            rows,
            width: w,
        };
        let deposit = |r: usize, c: usize| (r % 40) < 8 && (c % 40) < 8;
        let mut h = Grid::invalid(w, rows);
        for r in 0..rows {
            for c in 0..w {
                // The paper board's last 30 mm: 800 um of bow over 110 mm either side of
                // the middle, at its steepest here (14 um/mm), and tilted across.
                let (x, y) = (80.0 + r as f64 * pitch, c as f64 * pitch);
                let bow = 800.0 * (1.0 - (x / 110.0).powi(2)) + 2.0 * y;
                let paste = if deposit(r, c) { 100.0 } else { 0.0 };
                h.data[r * w + c] = (bow + paste) as f32;
            }
        }
        // A hole with no height.
        for r in 100..110 {
            for c in 150..160 {
                h.data[r * w + c] = f32::NAN;
            }
        }
        let s = local_surface(&h, (SURFACE_CELL_MM / pitch) as usize);
        let (mut bare, mut paste) = (Vec::new(), Vec::new());
        for r in 0..rows {
            for c in 0..w {
                let v = h.data[r * w + c] - s.data[r * w + c];
                if !v.is_finite() {
                    continue;
                }
                if deposit(r, c) {
                    paste.push(v);
                } else {
                    bare.push(v);
                }
            }
        }
        let worst =
            |v: &[f32], target: f32| v.iter().map(|x| (x - target).abs()).fold(0.0, f32::max);
        assert!(worst(&bare, 0.0) < 3.0, "bare board {}", worst(&bare, 0.0));
        assert!(worst(&paste, 100.0) < 3.0, "paste {}", worst(&paste, 100.0));
        // The small scene's board: 300 um of warp over 20 x 14 mm (`(1 - xi^2)(1 - eta^2)`),
        // a quarter of it paste in 1 mm squares, and noise.
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

        let v = view(&h, &grid, 1, Shows::AboveLocalSurface);
        let (left, top, pw, ph) = v.plot;
        assert_eq!((pw, ph), (rows as u32, w as u32));
        assert!(
            v.range_um.0 > -5.0 && v.range_um.0 < 5.0,
            "{:?}",
            v.range_um
        );
        assert!(
            v.range_um.1 > 90.0 && v.range_um.1 < 105.0,
            "{:?}",
            v.range_um
        );
        // Map pixel (r, c) at image (left + r, top + ph - 1 - c): a deposit's centre in the
        // top colour, the bare board beside it in the bottom one, whatever the bow.
        let at = |r: usize, c: usize| *v.image.get_pixel(left + r as u32, top + ph - 1 - c as u32);
        for (r, c) in [(4usize, 4usize), (164, 84), (244, 164)] {
            assert!(deposit(r, c));
            let p = at(r, c).0;
            assert!(p[0] > 180 && p[2] < 60, "deposit ({r}, {c}) drawn {p:?}");
            let q = at(r + 20, c + 20).0;
            assert!(q[2] > 120 && q[0] < 80, "bare ({r}, {c}) drawn {q:?}");
        }
        assert_eq!(at(105, 155).0, [40, 40, 40]);
        // The absolute view shows the bow (377 um down to 0 over these 30 mm).
        let a = view(&h, &grid, 1, Shows::Absolute);
        assert!(a.range_um.1 - a.range_um.0 > 350.0, "{:?}", a.range_um);
        // Text was drawn in the margins (the title above the plot).
        let dark = (0..v.image.width())
            .flat_map(|x| (0..top.saturating_sub(2)).map(move |y| (x, y)))
            .filter(|&(x, y)| v.image.get_pixel(x, y).0[0] < 100)
            .count();
        assert!(dark > 50, "no title drawn");
    }
}
