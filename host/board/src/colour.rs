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
pub use dpsa_formats::surface::{local_surface, SURFACE_CELL_MM};
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

/// Lower and upper percentiles of the colour bar.
const RANGE: (f64, f64) = (0.005, 0.997);

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
