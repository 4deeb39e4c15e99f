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
    ///
    /// Counted in eight lanes of 32-bit counters over blocks of 2^16 values (no lane can
    /// overflow), summed per block: the compiler keeps the lanes in vector registers, where
    /// `filter(..).count()` made one dependent count. On a paper board's map (47.8 Mpx,
    /// which `dpsa board` counts three times) its `perf` samples fell from 361 - 371 to
    /// 299 - 311 (two alternating pairs): the pass is mostly the memory's.
    pub fn valid(&self) -> usize {
        self.data
            .chunks(1 << 16)
            .map(|block| {
                let mut lanes = [0u32; 8];
                let eights = block.chunks_exact(8);
                let rest = eights.remainder();
                for e in eights {
                    for (n, v) in lanes.iter_mut().zip(e) {
                        *n += u32::from(v.is_finite());
                    }
                }
                let rest = rest.iter().filter(|v| v.is_finite()).count();
                lanes.iter().map(|&n| n as usize).sum::<usize>() + rest
            })
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The count is the finite values', over lengths about the lanes and the blocks and
    /// every kind of value that is not finite.
    #[test]
    fn valid_counts_the_finite_values() {
        let mut seed = 7u64;
        for len in [0, 1, 7, 8, 9, 65_535, 65_536, 65_537, 200_003] {
            let data: Vec<f32> = (0..len)
                .map(|_| {
                    seed = seed
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    match (seed >> 60) % 5 {
                        0 => f32::NAN,
                        1 => f32::INFINITY,
                        2 => f32::NEG_INFINITY,
                        _ => f32::from_bits((seed >> 16) as u32 & 0x7F7F_FFFF),
                    }
                })
                .collect();
            let want = data.iter().filter(|v| v.is_finite()).count();
            let g = Grid {
                width: 1,
                rows: len,
                data,
            };
            assert_eq!(g.valid(), want, "len {len}");
        }
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
