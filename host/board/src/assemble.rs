//! One board map from the cameras' wrapped rows: unwrap each camera, resample it onto the
//! board grid, blend (the steps of [`super`]), each camera in its own thread, with the time
//! of every stage.

use crate::blend::{blend, Blended};
use crate::resample::{resample, BoardGrid, CameraPlacement, Layer, Source};
use crate::unwrap::{unwrap, BLOCK};
use crate::Grid;
use std::time::Instant;

/// One camera's measurement, ready for the board.
#[derive(Clone, Debug)]
pub struct CameraRows {
    /// Wrapped heights, um, in `[-T(c)/2, T(c)/2)` (NaN invalid); row `i` is board row
    /// `first_row + i`.
    pub heights: Grid,
    /// Cramer-Rao bound of each height's variance, um^2 (same layout; None without a truth
    /// and noise model).
    pub variance: Option<Grid>,
    /// Pixels masked for the calibration's dead image pixels (`dpsa_sim::board::provenance`).
    pub dead_masked: u64,
    /// Where each row was seen (`dpsa_sim::board::provenance::row_places`; `None`: nominal).
    pub places: Option<crate::places::RowPlaces>,
    /// The board row of `heights`' row 0 (the core's board-row numbering).
    pub first_row: i64,
    /// Height per turn of each column, um.
    pub period_um: Vec<f32>,
    /// Where the camera's pixels lie on the board (its lateral calibration).
    pub placement: CameraPlacement,
    /// Rows of `heights` that never arrived (a stream's missing or damaged packets, its
    /// truncated end): their board pixels stay invalid. Empty when none was lost.
    pub lost: Vec<bool>,
}

/// Seconds per stage (`timing.*` of `dpsa board --json`).
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Timing {
    /// Unwrapping, all cameras (in parallel threads), s.
    pub unwrap_s: f64,
    /// Resampling onto the board grid, all cameras (in parallel threads), s.
    pub resample_s: f64,
    /// Blending, turn alignment and seams, s.
    pub blend_s: f64,
}

/// The assembled map and what it took.
#[derive(Clone, Debug)]
pub struct Assembled {
    /// The board map, the camera of each pixel, the turns and seams.
    pub blended: Blended,
    /// Valid pixels that the unwrapping placed from an extrapolated surface, per camera.
    pub unreached: Vec<usize>,
    /// Board pixels left invalid because a camera lost the rows that would have covered them
    /// (no other camera did).
    pub lost_pixels: u64,
    /// Seconds per stage.
    pub timing: Timing,
}

/// Feather width of the overlaps, camera columns.
pub const FEATHER_PX: f64 = 16.0;

/// Board-edge band that anchors the board's turn, px of the board grid.
pub const EDGE_PX: usize = 8;

/// Unwraps, resamples and blends `cameras` (in order across the board) onto `grid`. The
/// cameras' rows are consumed: each camera's heights are freed once unwrapped, the rest once
/// resampled, so the blend holds only the layers and the map.
pub fn assemble(mut cameras: Vec<CameraRows>, grid: &BoardGrid) -> Assembled {
    let t0 = Instant::now();
    let unwrapped: Vec<_> = std::thread::scope(|s| {
        let handles: Vec<_> = cameras
            .iter()
            .map(|c| s.spawn(move || unwrap(&c.heights, &c.period_um, BLOCK)))
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("unwrap thread"))
            .collect()
    });
    for c in &mut cameras {
        c.heights = Grid::invalid(0, 0);
    }
    let t1 = Instant::now();
    // Each thread owns its camera's unwrapped heights and frees them once resampled.
    let (mut layers, unreached): (Vec<Layer>, Vec<usize>) = std::thread::scope(|s| {
        let handles: Vec<_> = cameras
            .into_iter()
            .zip(unwrapped)
            .map(|(c, u)| {
                s.spawn(move || {
                    let src = Source {
                        heights: &u.heights,
                        variance: c.variance.as_ref(),
                        period_um: &u.period_um,
                        first_row: c.first_row,
                        places: c.places.as_ref(),
                        lost_rows: &c.lost,
                    };
                    (resample(&src, &c.placement, grid, FEATHER_PX), u.unreached)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("resample thread"))
            .unzip()
    });
    let t2 = Instant::now();
    let blended = blend(&mut layers, grid, EDGE_PX);
    let lost_pixels = (0..blended.heights.data.len())
        .filter(|&i| {
            !blended.heights.data[i].is_finite()
                && layers
                    .iter()
                    .any(|l| l.is_lost(i / grid.width, i % grid.width))
        })
        .count() as u64;
    let t3 = Instant::now();
    Assembled {
        blended,
        lost_pixels,
        unreached,
        timing: Timing {
            unwrap_s: (t1 - t0).as_secs_f64(),
            resample_s: (t2 - t1).as_secs_f64(),
            blend_s: (t3 - t2).as_secs_f64(),
        },
    }
}
