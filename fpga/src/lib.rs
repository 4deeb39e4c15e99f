//! The FPGA front end of the frame grabber: the core's per-pixel stages in Verilog
//! (`fpga/rtl`), checked bit for bit against `dpsa-core` by co-simulation, and synthesised
//! for a Lattice ECP5 (`fpga/synth`). `docs/fpga.md` describes the design and its interface.
//!
//! - [`model`]: the Verilator models of the RTL, built and run as child processes.
//! - [`cosim`]: the pixel pipeline's records, vectors, the core's answers, the comparison.
//! - [`codec`]: the row codec's encoder (`dpsa_codec`) against the core's `Encoder`, payload
//!   for payload.
//! - [`front`]: the models as the pipeline's front end ([`dpsa_core::offload::FrontEnd`]), and
//!   the fabric log the firmware reads under QEMU.
//! - [`mod@bench`]: `dpsa fpga-bench`: synthesis figures, co-simulation counts, rates.

pub mod bench;
pub mod codec;
pub mod cosim;
pub mod front;
pub mod model;

use std::path::PathBuf;

/// The repository's `fpga/` folder.
pub fn fpga_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}
