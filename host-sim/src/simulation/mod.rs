//! Simulation: scene files ([`scene`]), the conveyor simulator with ground truth
//! ([`simulate`]) and the recording format on disk ([`recording`]) that every other command
//! reads, simulated or real.

pub use dpsa_formats::recording::checks;
pub mod recording;
pub mod scene;
pub mod simulate;
