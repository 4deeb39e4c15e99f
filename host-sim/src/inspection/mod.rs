//! Paste inspection: the board's paste layer (Gerber) as pads, the inspection program, and the
//! per-pad measurement and verdict on a board map (`dpsa pads`, `dpsa inspect`, `dpsa grr`).
//!
//! | file | what |
//! | --- | --- |
//! The production inspection is its own crate, `dpsa-inspect` (on the board map's format and
//! the paste layer only), re-exported here at its old paths with the paste layer
//! (`dpsa-gerber`): [`program`], [`teach`], [`map`], [`register`], [`register_paste`],
//! [`measure`], [`verdict`], [`run`], [`report`], [`gerber`], [`pads`]. What stays here is the
//! simulator's side:
//!
//! | file | what |
//! | --- | --- |
//! | [`evaluate`] | a production inspection against the print the simulator made: accuracy, detection, the report's `truth` and `detection` keys |
//! | [`truth`] | a simulated board's truth by the measurement's own definitions; accuracy and detection figures |
//! | [`simulated`] | a simulated board's print (`print.json`) as the truth |
//! | [`grr`] | `dpsa grr`: the gauge repeatability study on simulated boards |

pub mod evaluate;
pub mod grr;
pub mod simulated;
pub mod truth;

#[cfg(test)]
mod tests;

// The production inspection (crate `dpsa-inspect`) and the paste layer with the pad geometry
// (crate `dpsa-gerber`), at their old paths.
pub use dpsa_gerber as gerber;
pub use dpsa_gerber::pads;
pub use dpsa_inspect::{
    map, measure, program, register, register_paste, report, run, teach, verdict,
};
