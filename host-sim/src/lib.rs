//! # dpsa-sim: the simulator's side of the host, and what is not split out yet
//!
//! The fixed-point measurement itself is `dpsa-core` (frames -> solve -> accumulate -> phase ->
//! height -> packets -> sink); the production host is the crates of `host/` (`dpsa-formats`,
//! `dpsa-gerber`, `dpsa-stream`, `dpsa-inspect`), re-exported here at their old paths. This
//! crate simulates what the core sees, checks it against an independent reference and holds
//! what the production crates do not have yet (board map, calibration, recording format):
//!
//! | module | what |
//! | --- | --- |
//! | [`simulation`] | scenes, the simulator with ground truth, recordings on disk (the input of everything) |
//! | [`reconstruct`] | runs `dpsa-core` on a recording through its streaming API, as the frame grabber does |
//! | [`stream`] | packet streams back into height maps, with the damage report (crate `dpsa-stream`) |
//! | [`reference`](mod@reference) | the independent f64 D-PSA, the PSP baseline, the Cramer-Rao bound, truth statistics, and `compare` on top |
//! | [`array`](mod@array) | the camera array: array scenes in board mm, the area-integrating renderer, array and calibration recordings, `.zfr` frames |
//! | [`calibration`] | `dpsa calibrate`: per-camera fringe frequency, reference phase, height per turn, flat field, lateral mapping and encoder scale from flat planes and a target |
//! | [`board`] | the board map: cameras' rows unwrapped, placed in millimetres and blended |
//! | [`inspection`] | the production inspection (crate `dpsa-inspect`) and the simulator's evaluation of it against the print truth |
//! | [`process`] | the print process over a run of boards (drift, step, clogging and cleans, viscosity), written into a line's store |
//! | [`target`] | the firmware: feed export, build, ELF sizes, QEMU with its defmt log, its bench figures |
//! | [`benches`] | `codec-bench`: our row codec against general-purpose compressors and the entropy bound |
//! | [`stack`] | ordinary phase-shifting image stacks (real camera images) through the same kernel |
//! | [`error`] | [`SimError`]: the one error of this crate's API (the production crates' errors inside it, typed); [`At`] says where |
//! | [`files`], [`heightmap`], [`images`], [`kind`], [`progress`] | the bottom layer (crate `dpsa-formats`) |
//!
//! The `dpsa` binary is its own package (`cli/`): it only parses arguments and prints, one file
//! per subcommand.

pub mod array;
pub mod benches;
pub mod board;
pub mod calibration;
pub mod error;
pub mod inspection;
pub mod process;
pub mod reconstruct;
pub mod reference;
pub mod simulation;
pub mod stack;
pub mod target;

// The bottom layer, re-exported at its old paths.
pub use dpsa_formats::{files, heightmap, images, kind, progress};
pub use dpsa_stream as stream;
pub use error::{At, Result, SimError};
