//! Paste inspection: the board's paste layer (Gerber) as pads, the inspection program, and the
//! per-pad measurement and verdict on a board map (`dpsa pads`, `dpsa inspect`, `dpsa grr`).
//!
//! | file | what |
//! | --- | --- |
//! | [`pads`] | one pad = one connected paste opening: its outline in mm, names from X2 attributes; rigid transforms |

pub mod map;
pub mod measure;
pub mod pads;
pub mod program;
pub mod register;
pub mod report;
pub mod run;
pub mod truth;
pub mod verdict;

#[cfg(test)]
mod tests;
