//! dpsa-firmware: the fixed-point core on a Cortex-M7 frame grabber.
//!
//! Placeholder until the firmware issue: this crate only proves that `dpsa-core` builds as a
//! dependency of a `no_std` crate. The board layer (`src/board/`), the QEMU runner and the
//! bit-exactness tests come with that issue.
#![no_std]

pub use dpsa_core as core_pipeline;
