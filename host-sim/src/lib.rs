//! # dpsa-sim: the host side of dpsa
//!
//! The library behind the `dpsa` command, one folder per concern. The fixed-point measurement
//! itself is `dpsa-core` (frames -> solve -> accumulate -> phase -> height -> packets -> sink);
//! this crate feeds it, checks it and reads what it emits:
//!
//! | module | what |
//! | --- | --- |
//! | [`simulation`] | scenes, the simulator with ground truth, recordings on disk (the input of everything) |
//! | [`reconstruct`] | runs `dpsa-core` on a recording through its streaming API, as the frame grabber does |
//! | [`stream`] | packet streams back into height maps, with the damage report |
//! | [`reference`](mod@reference) | the independent f64 D-PSA, the PSP baseline, the Cramer-Rao bound, truth statistics, and `compare` on top |
//! | [`array`](mod@array) | the camera array: array scenes in board mm, the area-integrating renderer, array and calibration recordings, `.zfr` frames |
//! | [`calibration`] | `dpsa calibrate`: per-camera fringe frequency, reference phase, height per turn, flat field, lateral mapping and encoder scale from flat planes and a target |
//! | [`board`] | the board map: cameras' rows unwrapped, placed in millimetres and blended |
//! | [`inspection`] | the paste layer as pads (Gerber), the inspection program, per-pad measurement and verdicts |
//! | [`target`] | the firmware: feed export, build, ELF sizes, QEMU with its defmt log, its bench figures |
//! | [`benches`] | `codec-bench`: our row codec against general-purpose compressors and the entropy bound |
//! | [`stack`] | ordinary phase-shifting image stacks (real camera images) through the same kernel |
//! | [`heightmap`], [`images`], [`progress`] | the common result type, image writers, progress bars |
//!
//! The `dpsa` binary (`src/main.rs`, `src/cli/`) only parses arguments and prints: one file per
//! subcommand.

pub mod array;
pub mod benches;
pub mod board;
pub mod calibration;
pub mod inspection;
pub mod kind;
pub mod reconstruct;
pub mod reference;
pub mod simulation;
pub mod stack;
pub mod target;

// The bottom layer, re-exported at its old paths.
pub use dpsa_formats::{files, heightmap, images, progress};
pub use dpsa_stream as stream;
