//! # dpsa-inspect: paste inspection on a board map
//!
//! From a board map (`dpsa board`) and the board's program to a verdict per pad (`dpsa
//! program`, `dpsa inspect`, `docs/inspection.md`). On the bottom layer (`dpsa-formats`) and the
//! paste layer (`dpsa-gerber`) only: no simulator, no reference. What the simulator adds (its
//! print truth, the accuracy and detection figures, the gauge study) is in `dpsa-sim`, through
//! [`run::Evaluate`].
//!
//! | module | what |
//! | --- | --- |
//! | [`teach`] | `dpsa program`: the program from the design files (paste, copper, outline, pick-and-place) |
//! | [`program`] | the inspection program (TOML): stencil, placement, fiducials, measurement settings, tolerance windows |
//! | [`map`] | the board map as the inspection reads it |
//! | [`register`] | fiducials found on the map, the design-to-board transform |
//! | [`register_paste`] | the transform from the paste pattern itself, for boards without fiducials |
//! | [`measure`] | per pad: local surface, volume, area, height, offset, shape, coverage, bridges |
//! | [`noise`] | the map's pixel noise and its correlation between neighbours, from the bare board |
//! | [`mod@print`] | the print's placement on the board (shift, turn, stretch) from every pad's offset |
//! | [`uncertainty`] | per pad: the standard uncertainty of the volume and height |
//! | [`verdict`] | pass / warning / fail with the defect class |
//! | [`run`] | `dpsa inspect` end to end, its JSON report |
//! | [`crop`] | a pad's heights above its local surface, cut out for a person to look at |
//! | [`report`] | the files: pads.csv, IPC-CFX UnitsInspected, overview, defect gallery |
//! | [`error`] | [`InspectError`]: why an inspection failed |

pub mod crop;
pub mod error;
pub mod map;
pub mod measure;
pub mod noise;
pub mod print;
pub mod program;
pub mod register;
pub mod register_paste;
pub mod report;
pub mod run;
pub mod teach;
pub mod uncertainty;
pub mod verdict;

pub use error::InspectError;
