//! Host side of dpsa: recordings, simulator, f64 reference, packet decoding and images.
//!
//! Data flow (same names as `dpsa-core`): frames -> solve -> accumulate -> phase -> height ->
//! packets -> sink.

pub mod recording;
pub mod scene;
pub mod simulate;
pub mod heightmap;
pub mod reference;
pub mod compare;
pub mod packets;
pub mod reconstruct;
pub mod images;
pub mod stack;
pub mod jobs;
pub mod codec_bench;
pub mod target;
