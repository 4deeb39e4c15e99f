//! Benchmarks the `dpsa` command runs and prints as JSON (speed and size are measured here,
//! never in timed tests).
//!
//! - [`codec`]: `dpsa codec-bench`, our lossless row codec against lz4, heatshrink, zstd and
//!   PNG-16 on the same height rows, with the entropy bound and the noise floor.
//! - [`frames`]: `dpsa frame-bench`, the recording frame formats (PNG, `.zfr`).
//! - [`board`]: `dpsa board-bench`, the whole board (core on every camera, stitching) with its
//!   frames in memory, beside the numpy float64 least-squares phase ([`numpy`]).
//! - [`gerber`]: `dpsa pads-bench`, the paste-layer reader on synthetic layers of up to 10^6
//!   objects, time and peak memory per layer.

pub mod board;
pub mod codec;
pub mod frames;
pub mod gerber;
pub mod numpy;
