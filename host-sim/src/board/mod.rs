//! The board height map: every camera's rows placed in board millimetres, unwrapped into
//! absolute heights and blended where cameras overlap (issue 10, "The board map").
//!
//! The steps are the crate `dpsa-board`, re-exported here (its `run::from_streams` is the
//! production `board --streams`); what stays here feeds them from the core on a recording
//! ([`run`]), adds the Cramer-Rao bound per pixel ([`provenance`]) and compares a map with a
//! simulated board's truth ([`truth`]). The data flow:
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

pub mod provenance;
pub mod run;
pub mod truth;

// The board map's steps (crate `dpsa-board`), at their old paths.
pub use dpsa_board::{assemble, blend, output, resample, streams, unwrap};
pub use dpsa_formats::grid::Grid;
