//! The FPGA front end of the frame grabber: the core's per-pixel stages in Verilog
//! (`fpga/rtl`), checked bit for bit against `dpsa-core` by co-simulation, and synthesised
//! for a Lattice ECP5 (`fpga/synth`). `docs/fpga.md` describes the design and its interface.
//!
//! - [`model`]: the Verilator model of the RTL, built and run as a child process.
//! - [`cosim`]: the records it speaks, the vectors, the core's answers, the comparison.
//! - [`front`]: the model as the pipeline's front end ([`dpsa_core::offload::FrontEnd`]), and the
//!   fabric log the firmware reads under QEMU.
//! - [`mod@bench`]: `dpsa fpga-bench`: synthesis figures, co-simulation counts, rates.

pub mod bench;
pub mod cosim;
pub mod front;
pub mod model;

use std::path::PathBuf;

/// The repository's `fpga/` folder.
pub fn fpga_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}
