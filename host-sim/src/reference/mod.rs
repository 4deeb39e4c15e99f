//! The independent f64 reference and what is measured against it.
//!
//! - [`dpsa`]: D-PSA in f64, written from the measurement model (`docs/model.md`), with
//!   nalgebra's full least squares; shares no code with `dpsa-core`.
//! - [`psp`](mod@psp): the conventional phase-shift baseline (nominal uniform steps).
//! - [`crb`](mod@crb): the Cramer-Rao bound of the height variance per pixel.
//! - [`truth`]: ground-truth lookups and the flat-pixel mask.
//! - [`compare`]: the fixed-point core against all of the above.

pub mod compare;
pub mod crb;
pub mod dpsa;
pub mod psp;
#[cfg(test)]
mod tests;
pub mod truth;

pub use crb::crb;
pub use dpsa::*;
pub use psp::{nominal_step_px, psp, psp_from};
pub use truth::{flat_mask, truth_height};
