//! Camera-array calibration (`dpsa calibrate`, issue 10): estimation from calibration
//! recordings ([`estimate`]), the calibration file ([`file`](mod@file)), and the figures against the
//! held-out plane and the simulator's truth ([`evaluate`](mod@evaluate)). `docs/calibration.md` documents
//! the method and the file.

pub mod apply;
pub mod estimate;
pub mod evaluate;
/// The calibration file (crate `dpsa-formats`), at its old path.
pub use dpsa_formats::calibration as file;
pub use dpsa_formats::calibration::validate;

pub use apply::{apply, calibrated};
pub use estimate::{calibrate, FX_BUDGET_UM};
pub use evaluate::{evaluate, CalibrationReport};
pub use file::{CalFile, CameraCal, Lateral};
