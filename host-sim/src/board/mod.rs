//! The board height map: every camera's rows placed in board millimetres, unwrapped into
//! absolute heights and blended where cameras overlap (issue 10, "The board map").
//!
//! The data flow, one file per step:
//!
//! - [`unwrap`]: a camera's wrapped heights (known modulo one fringe turn `T_z`) into absolute
//!   heights, referenced to the smooth local board surface (paste stays within half a turn of
//!   it; the board's bow does not), and anchored by the board's clamped edges.
//! - [`resample`]: a camera's pixel grid (board row along the motion, column across) into the
//!   board grid in millimetres through its lateral mapping (offset, pitch, rotation).
//! - [`blend`]: the cameras' board grids into one, feathered across the overlaps, with the
//!   camera each pixel came from and the seam statistics.
//! - [`streams`]: the rows from the cameras' packet streams instead of the core
//!   (`dpsa board --streams`), matched to the cameras and checked, with what they lost.
//! - [`output`]: the 16-bit PNG, the float TIFF in micrometres, the false-colour PNG with its
//!   scale bar, and the JSON metadata.
//!
//! Heights are `f32` micrometres; NaN marks an invalid pixel everywhere in this module.

pub mod assemble;
pub mod blend;
pub mod output;
pub mod provenance;
pub mod resample;
pub mod run;
pub mod streams;
pub mod unwrap;

/// A row-major grid of heights, um; NaN is invalid. Row `r` is along the motion (board `x`),
/// column `c` across it (board `y`).
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    pub width: usize,
    pub rows: usize,
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
