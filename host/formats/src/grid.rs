//! The board map's grids: heights in board millimetres as `dpsa board` writes them and
//! `dpsa inspect` reads them.

/// A row-major grid of heights, um; NaN is invalid. Row `r` is along the motion (board `x`),
/// column `c` across it (board `y`).
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    /// Columns, px.
    pub width: usize,
    /// Rows, px.
    pub rows: usize,
    /// `rows x width` heights, um, row after row (NaN: invalid); its length is
    /// `rows * width`.
    pub data: Vec<f32>,
}

impl Grid {
    /// A grid of invalid pixels.
    pub fn invalid(width: usize, rows: usize) -> Grid {
        Grid {
            width,
            rows,
            data: vec![f32::NAN; width * rows],
        }
    }

    /// Height at row `r`, column `c` (NaN when invalid or outside).
    pub fn at(&self, r: usize, c: usize) -> f32 {
        if r < self.rows && c < self.width {
            self.data[r * self.width + c]
        } else {
            f32::NAN
        }
    }

    /// Mutable height at row `r`, column `c`. Panics outside the grid.
    pub fn at_mut(&mut self, r: usize, c: usize) -> &mut f32 {
        &mut self.data[r * self.width + c]
    }

    /// Valid (finite) pixels.
    pub fn valid(&self) -> usize {
        self.data.iter().filter(|v| v.is_finite()).count()
    }
}

/// The board grid: `rows` along the motion from `x0_mm`, `width` across from `y0_mm`, square
/// pixels of `pitch_mm`. Pixel `(i, j)` is centred at `(x0 + (i + 1/2) p, y0 + (j + 1/2) p)`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BoardGrid {
    /// Board `x` of the first row's edge, mm.
    pub x0_mm: f64,
    /// Board `y` of the first column's edge, mm.
    pub y0_mm: f64,
    /// Pixel size, mm (square pixels).
    pub pitch_mm: f64,
    /// Rows, along the motion (board `x`).
    pub rows: usize,
    /// Columns, across the motion (board `y`).
    pub width: usize,
}

impl BoardGrid {
    /// Centre of pixel `(i, j)`, mm.
    pub fn centre(&self, i: usize, j: usize) -> (f64, f64) {
        // Through i64: `usize as f64` is several instructions on x86-64 (it has no unsigned
        // conversion), `i64 as f64` one; a grid index (far below 2^53) is the same value.
        (
            self.x0_mm + (i as i64 as f64 + 0.5) * self.pitch_mm,
            self.y0_mm + (j as i64 as f64 + 0.5) * self.pitch_mm,
        )
    }
}
