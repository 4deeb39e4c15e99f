//! Paste inspection: the board's paste layer (Gerber) as pads, the inspection program, and the
//! per-pad measurement and verdict on a board map (`dpsa pads`, `dpsa inspect`, `dpsa grr`).
//!
//! | file | what |
//! | --- | --- |
//! | [`pads`] | one pad = one connected paste opening: its outline in mm, names from X2 attributes; rigid transforms |
//! | [`gerber`] | the top paste layer (Gerber RS-274X / X2) read into pads |
//! | [`program`] | the inspection program (TOML): stencil, placement, fiducials, measurement settings, tolerance windows |
//! | [`map`] | the board map (`dpsa board`) as the inspection reads it |
//! | [`register`] | fiducials found on the map, the design-to-board transform |
//! | [`measure`] | per pad: local surface, volume, area, height, offset, shape, coverage, bridges |
//! | [`verdict`] | pass / warning / fail with the defect class |
//! | [`truth`] | a simulated board's truth by the same definitions; accuracy and detection figures |
//! | [`run`] | `dpsa inspect` end to end, its JSON report |
//! | [`report`] | the files: pads.csv, IPC-CFX UnitsInspected, overview, defect gallery |
//! | [`simulated`] | a simulated board's print (`print.json`) as the truth |
//! | [`grr`] | `dpsa grr`: the gauge repeatability study |
//! | [`teach`] | `dpsa program`: the program from the design files (paste, copper, outline, pick-and-place) |

pub mod grr;
pub mod map;
pub mod measure;
pub mod program;
pub mod register;
pub mod register_paste;
pub mod report;
pub mod run;
pub mod simulated;
pub mod teach;
pub mod truth;
pub mod verdict;

#[cfg(test)]
mod tests;

// The paste layer and the pad geometry (crate `dpsa-gerber`), at their old paths.
pub use dpsa_gerber as gerber;
pub use dpsa_gerber::pads;
