//! The conventional phase-shift baseline: the reference's registration with nominal shifts.

use super::dpsa::{infallible, offsets, run, FrameSource, RefOutput, Shifts};
use crate::simulation::recording::{Frame, Manifest};
use std::f64::consts::TAU;

/// Nominal frame-to-frame step of a recording, px: `(o_last - o_first) / (frames - 1)`, the
/// mean step a conventional system calibrated to the nominal conveyor speed would assume.
/// 0 with fewer than two frames or unusable offsets.
pub fn nominal_step_px(manifest: &Manifest) -> f64 {
    match offsets(manifest) {
        Some(o) if o.len() >= 2 => (o[o.len() - 1] - o[0]) as f64 / (o.len() - 1) as f64,
        _ => 0.0,
    }
}

/// Conventional phase-shift baseline: same registration, samples, reference phase, height and
/// validity rules as [`reconstruct`](super::reconstruct), but the shifts are the nominal uniform set
/// `theta_j = -j delta`, `delta = 2 pi f_x * nominal_step` ([`nominal_step_px`]; 90 degrees
/// for the default scene, i.e. the classic 4-step formula).
///
/// The actual motion is not used for conditioning, so rows are never flagged
/// `ILL_CONDITIONED` because of it. The noise-gain test is applied to the nominal set
/// instead (the same for every window): only when that set itself is degenerate (e.g. a
/// recording with no net motion, or a nominal step of a whole fringe period) is every
/// windowed row flagged `ILL_CONDITIONED`.
pub fn psp(manifest: &Manifest, frames: &[Frame]) -> RefOutput {
    let mut src = frames;
    infallible(psp_from(manifest, &mut src))
}

/// [`psp`] on frames read on demand (see [`super::dpsa::LazyFrames`]).
pub fn psp_from(manifest: &Manifest, frames: &mut dyn FrameSource) -> crate::Result<RefOutput> {
    let f_x = 1.0 / manifest.calibration.fringe_period_px;
    run(
        manifest,
        frames,
        Shifts::Nominal(TAU * f_x * nominal_step_px(manifest)),
    )
}
