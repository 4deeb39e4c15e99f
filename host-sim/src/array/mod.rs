//! The camera array (issue 10): array scenes in board millimetres ([`scene`]), the renderer
//! with area-integrated pixels ([`render`]), array and calibration recordings on disk
//! ([`record`]) and the compressed binary frame format ([`frames`]); generated paste layers
//! ([`layout`]) and the paste printed on their pads ([`print`](mod@print)). `docs/calibration.md`
//! documents the geometry, the directory layout and the calibration file.

pub mod frames;
pub mod layout;
pub mod print;
pub mod record;
pub mod render;
pub mod scene;
