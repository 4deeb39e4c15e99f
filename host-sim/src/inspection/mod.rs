//! Paste inspection: the board's paste layer (Gerber) as pads, the inspection program, and the
//! per-pad measurement and verdict on a board map (`dpsa pads`, `dpsa inspect`, `dpsa grr`).
//!
//! | file | what |
//! | --- | --- |
//! | [`pads`] | one pad = one connected paste opening: its outline in mm, names from X2 attributes; rigid transforms |
//! | [`gerber`] | the top paste layer (Gerber RS-274X / X2) -> pads: apertures, macros, regions, strokes, step and repeat, polarity, X2 names |

pub mod gerber;
pub mod pads;
