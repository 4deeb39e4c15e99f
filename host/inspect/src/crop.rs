//! A pad's heights above its local surface, cut out of the map: what a person looks at to
//! judge a call (the line keeps one per pad that warned or failed; `dpsa serve` draws it).
//!
//! The crop is the map's own samples (no resampling) over the opening's bounding box on the
//! board and [`MARGIN_MM`] around it, each minus the pad's fitted local surface
//! ([`PadMeasurement::surface`]) at that sample: the warp of the board is gone, what is left is
//! the paste (and the bare board around it near 0). A pad without a fitted surface has no crop.

use crate::map::BoardMap;
use crate::measure::{surface_at, PadMeasurement};
use dpsa_gerber::pads::{Outline, Pad, Rigid};

/// Board around the opening's bounding box, mm.
pub const MARGIN_MM: f64 = 0.6;

/// Most samples of a crop along either axis: a bigger opening is cut to the window of this
/// size about its centre.
pub const MAX_SIDE: usize = 256;

/// A pad's heights above its local surface (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct PadCrop {
    /// Board `x` of the first sample's centre, mm.
    pub x0_mm: f64,
    /// Board `y` of the first sample's centre, mm.
    pub y0_mm: f64,
    /// Sample pitch (the map's), mm.
    pub pitch_mm: f64,
    /// Samples along the board's `x` (the map's rows).
    pub nx: usize,
    /// Samples along the board's `y` (the map's columns).
    pub ny: usize,
    /// Heights above the local surface, um, `[ix * ny + iy]` at `(x0 + ix pitch, y0 + iy
    /// pitch)` (the map's layout); NaN where the map has no valid height.
    pub heights_um: Vec<f32>,
    /// The opening on the board (the design's outline through the registration), mm.
    pub outline: Outline,
}

impl PadCrop {
    /// Height above the surface at sample `(ix, iy)`, um (NaN: invalid or outside).
    pub fn at(&self, ix: usize, iy: usize) -> f32 {
        if ix < self.nx && iy < self.ny {
            self.heights_um[ix * self.ny + iy]
        } else {
            f32::NAN
        }
    }

    /// Board `(x, y)` of sample `(ix, iy)`'s centre, mm.
    pub fn centre(&self, ix: usize, iy: usize) -> (f64, f64) {
        (
            self.x0_mm + ix as f64 * self.pitch_mm,
            self.y0_mm + iy as f64 * self.pitch_mm,
        )
    }
}

/// The crop of pad `p` measured as `m` on `map` (design to board by `t`); `None` when the pad
/// has no fitted surface or its window misses the map.
pub fn pad_crop(map: &BoardMap, p: &Pad, m: &PadMeasurement, t: &Rigid) -> Option<PadCrop> {
    if m.surface.is_empty() {
        return None;
    }
    let outline = p.outline.transformed(t);
    let c = outline.centroid();
    let b = outline.bbox();
    let (ri, rj) = map.window([
        b[0] - MARGIN_MM,
        b[1] - MARGIN_MM,
        b[2] + MARGIN_MM,
        b[3] + MARGIN_MM,
    ]);
    let cut = |r: std::ops::Range<usize>| {
        if r.len() <= MAX_SIDE {
            r
        } else {
            let s = r.start + (r.len() - MAX_SIDE) / 2;
            s..s + MAX_SIDE
        }
    };
    let (ri, rj) = (cut(ri), cut(rj));
    if ri.is_empty() || rj.is_empty() {
        return None;
    }
    let g = &map.grid;
    let mut heights_um = Vec::with_capacity(ri.len() * rj.len());
    for i in ri.clone() {
        for j in rj.clone() {
            let v = map.heights.data[i * g.width + j];
            let (x, y) = g.centre(i, j);
            heights_um.push(if v.is_finite() {
                (f64::from(v) - surface_at(&m.surface, x - c[0], y - c[1])) as f32
            } else {
                f32::NAN
            });
        }
    }
    let (x0_mm, y0_mm) = g.centre(ri.start, rj.start);
    Some(PadCrop {
        x0_mm,
        y0_mm,
        pitch_mm: g.pitch_mm,
        nx: ri.len(),
        ny: rj.len(),
        heights_um,
        outline,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use dpsa_formats::grid::BoardGrid;
    use dpsa_formats::grid::Grid;

    fn pad(outline: Outline) -> Pad {
        Pad {
            index: 0,
            outline,
            component: None,
            pin: None,
            aperture: None,
        }
    }

    /// A tilted, bowed board with a 120 um block of paste on a 0.5 x 0.3 mm opening: the crop
    /// is the paste above the surface the measurement fitted, sample for sample.
    #[test]
    fn the_crop_is_the_paste_above_the_surface() {
        let g = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.02,
            rows: 200,
            width: 150,
        };
        let board = |x: f64, y: f64| 40.0 + 3.0 * x - 2.0 * y + 0.8 * (x - 2.0) * (x - 2.0);
        let opening = Outline::RoundRect {
            centre: [2.0, 1.5],
            size: [0.5, 0.3],
            radius: 0.0,
            rotation_deg: 0.0,
        };
        let mut data = vec![0.0f32; g.rows * g.width];
        for i in 0..g.rows {
            for j in 0..g.width {
                let (x, y) = g.centre(i, j);
                let paste = if (x - 2.0).abs() < 0.25 && (y - 1.5).abs() < 0.15 {
                    120.0
                } else {
                    0.0
                };
                data[i * g.width + j] = (board(x, y) + paste) as f32;
            }
        }
        data[100 * g.width + 75] = f32::NAN;
        let map = BoardMap {
            board_id: None,
            grid: g,
            heights: Grid {
                width: g.width,
                rows: g.rows,
                data,
            },
        };
        let pad = pad(opening.clone());
        // The surface as the measurement states it: about the opening's centroid.
        let mut m = PadMeasurement::new(0, 0.15);
        m.surface = vec![board(2.0, 1.5), 3.0, -2.0, 0.8, 0.0, 0.0];
        let c = pad_crop(&map, &pad, &m, &Rigid::IDENTITY).expect("a crop");
        // The window: the bbox and the margin, in whole samples.
        assert!(c.nx >= ((0.5 + 2.0 * MARGIN_MM) / 0.02) as usize);
        assert!(c.ny >= ((0.3 + 2.0 * MARGIN_MM) / 0.02) as usize);
        assert_eq!(c.heights_um.len(), c.nx * c.ny);
        let (mut paste, mut bare, mut nan) = (0, 0, 0);
        for ix in 0..c.nx {
            for iy in 0..c.ny {
                let (x, y) = c.centre(ix, iy);
                let v = c.at(ix, iy);
                let i = ((x - g.x0_mm) / g.pitch_mm - 0.5).round() as usize;
                let j = ((y - g.y0_mm) / g.pitch_mm - 0.5).round() as usize;
                if (i, j) == (100, 75) {
                    assert!(v.is_nan());
                    nan += 1;
                    continue;
                }
                let (x, y) = g.centre(i, j);
                let want = if (x - 2.0).abs() < 0.25 && (y - 1.5).abs() < 0.15 {
                    paste += 1;
                    120.0
                } else {
                    bare += 1;
                    0.0
                };
                assert!((f64::from(v) - want).abs() < 1e-3, "({x}, {y}): {v}");
            }
        }
        assert_eq!(nan, 1);
        assert!(paste > 300 && bare > paste);
        assert_eq!(c.outline, opening);
        assert!(c.at(c.nx, 0).is_nan());
    }

    /// No surface, no crop; a huge opening is cut to the largest window about its centre.
    #[test]
    fn no_surface_no_crop_and_big_openings_are_cut() {
        let g = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.02,
            rows: 600,
            width: 600,
        };
        let map = BoardMap {
            board_id: None,
            grid: g,
            heights: Grid {
                width: g.width,
                rows: g.rows,
                data: vec![5.0; g.rows * g.width],
            },
        };
        let pad = pad(Outline::Circle {
            centre: [6.0, 6.0],
            diameter: 8.0,
        });
        let mut m = PadMeasurement::new(0, 50.0);
        assert!(pad_crop(&map, &pad, &m, &Rigid::IDENTITY).is_none());
        m.surface = vec![5.0];
        let c = pad_crop(&map, &pad, &m, &Rigid::IDENTITY).expect("a crop");
        assert_eq!((c.nx, c.ny), (MAX_SIDE, MAX_SIDE));
        let (x, y) = c.centre(MAX_SIDE / 2, MAX_SIDE / 2);
        assert!((x - 6.0).abs() < 0.05 && (y - 6.0).abs() < 0.05, "{x} {y}");
        assert!(c.heights_um.iter().all(|&v| v == 0.0));
    }
}
