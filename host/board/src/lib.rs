//! # dpsa-board: the board height map
//!
//! Every camera's rows placed in board millimetres, unwrapped into absolute heights and
//! blended where cameras overlap (`docs/board.md`). The data flow, one file per step:
//!
//! - [`provenance`]: which frames fed each of a camera's board rows, the registration replayed
//!   on the frames' triggers (a recording's latches or a stream's trigger log): the dead-pixel
//!   masks and the row [`places`].
//! - [`unwrap`]: a camera's wrapped heights (known modulo one fringe turn `T_z`) into absolute
//!   heights, referenced to the smooth local board surface (paste stays within half a turn of
//!   it; the board's bow does not), and anchored by the board's clamped edges.
//! - [`resample`]: a camera's pixel grid (board row along the motion, column across) into the
//!   board grid in millimetres through its [`resample::CameraPlacement`], or the row
//!   [`places`] its frames were seen at.
//! - [`blend`]: the cameras' board grids into one, feathered across the overlaps, with the
//!   camera each pixel came from and the seam statistics.
//! - [`assemble`]: the three band by band of board rows as the cameras' rows arrive
//!   ([`assemble::Stitcher`]), the cameras in parallel threads, timed.
//! - [`output`]: the 16-bit PNG, the float TIFF in micrometres, the false-colour PNG with its
//!   scale bar, and the JSON metadata.
//! - [`streams`]: the cameras' packet streams read, matched to the cameras and checked
//!   against the calibration file, with what each lost.
//! - [`run`]: one board from the streams, `array.json` and the calibration file
//!   ([`run::from_streams`], `dpsa board --streams`), or from any rows ([`run::build`]).
//!
//! On `dpsa-formats` (array manifest, calibration file, heights), `dpsa-stream` (the stream
//! decoder, the core's configuration of a camera) and `dpsa-core` (the frame trigger). The core
//! run on a recording's frames, the Cramer-Rao bound per pixel and the comparison with a
//! simulated board's truth are the simulator crate's (`board::run`,
//! `board::provenance::crb_variance`, `board::truth`).
//!
//! Heights are `f32` micrometres; NaN marks an invalid pixel everywhere in this crate.

pub mod assemble;
pub mod blend;
pub mod colour;
pub mod output;
pub mod places;
pub mod pool;
pub mod provenance;
pub mod resample;
pub mod run;
pub mod streams;
#[cfg(test)]
mod test_rng;
pub mod unwrap;

pub use dpsa_formats::grid::{BoardGrid, Grid};
pub use output::BoardError;
