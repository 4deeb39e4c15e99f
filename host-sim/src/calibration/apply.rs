//! A calibration file's camera put into a recording's manifest: what the core runs with when
//! the frames come from a recording (`reconstruct --cal`, `target-run --cal`, `board` with the
//! core). The manifest's camera, calibration and processing blocks become the calibration
//! file's ([`CalFile::core_blocks`]), so the core's configuration of the calibrated recording
//! is exactly the one a frame grabber configured with the file runs, and the one whose hash
//! `board --streams` checks (`dpsa_stream::config::of_calibration`).

use crate::calibration::CalFile;
use crate::simulation::recording::{Manifest, Recording};
use crate::{Result, SimError};

/// Puts camera `i` of `cal` into `manifest`. Refuses a manifest of another camera (id), frame
/// size or sample range: its frames measured with that calibration would give wrong heights
/// and positions.
pub fn apply(cal: &CalFile, i: usize, manifest: &mut Manifest) -> Result<()> {
    let Some((camera, calibration, processing)) = cal.core_blocks(i) else {
        return Err(SimError::Refused(format!(
            "the calibration has no camera {i} (it has {})",
            cal.camera.len()
        )));
    };
    let have = &manifest.camera;
    if have.id != camera.id {
        return Err(SimError::Refused(format!(
            "the recording is camera {}'s (its manifest says camera.id = {}), the calibration given is camera {}'s: a camera's frames measured with another camera's calibration give wrong heights and positions",
            have.id,
            have.id,
            camera.id
        )));
    }
    if (have.width, have.rows) != (camera.width, camera.rows) {
        return Err(SimError::Refused(format!(
            "calibration of camera {} is for {} x {} px frames, the recording has {} x {}",
            camera.id, camera.rows, camera.width, have.rows, have.width
        )));
    }
    if have.bit_depth != camera.bit_depth {
        return Err(SimError::Refused(format!(
            "calibration of camera {} is for {}-bit samples, the recording has {}-bit samples",
            camera.id, camera.bit_depth, have.bit_depth
        )));
    }
    manifest.camera = camera;
    manifest.calibration = calibration;
    manifest.processing = processing;
    Ok(())
}

/// A camera's recording with camera `i` of `cal` applied (what its frame grabber runs with).
pub fn calibrated(rec: &Recording, cal: &CalFile, i: usize) -> Result<Recording> {
    let mut rec = rec.clone();
    apply(cal, i, &mut rec.manifest)?;
    Ok(rec)
}
