//! Camera-array calibration (`dpsa calibrate`, issue 10): estimation from calibration
//! recordings ([`estimate`]), the calibration file ([`file`](mod@file)), and the figures against the
//! held-out plane and the simulator's truth ([`evaluate`](mod@evaluate)). `docs/calibration.md` documents
//! the method and the file.

pub mod estimate;
pub mod evaluate;
pub mod file;
pub mod validate;

pub use estimate::{calibrate, FX_BUDGET_UM};
pub use evaluate::{evaluate, Report};
pub use file::{CalFile, CameraCal, Lateral};
