//! The jobs behind the `dpsa` subcommands, as library functions (the tests call them too).

use crate::compare::{self, Comparison};
use crate::heightmap::HeightMap;
use crate::recording::{Frame, Recording};
use crate::{images, packets, reconstruct, reference};
use anyhow::{Context, Result};
use std::path::{Path, PathBuf};

/// Runs the fixed-point core on a recording and returns the packet stream bytes.
pub fn reconstruct_bytes(rec: &Recording, progress: bool) -> Result<(reconstruct::RunStats, Vec<u8>)> {
    reconstruct::run(rec, Vec::new(), progress)
}

/// Runs the fixed-point core and decodes its own stream into a height map.
pub fn reconstruct_map(rec: &Recording, progress: bool) -> Result<(reconstruct::RunStats, Vec<u8>, HeightMap)> {
    let (stats, bytes) = reconstruct_bytes(rec, progress)?;
    let (map, rep) = packets::decode_stream(&bytes, rec.manifest.calibration.height_lsb_um);
    anyhow::ensure!(rep.corrupt == 0, "internal error: the core's own stream has {} bad packets", rep.corrupt);
    Ok((stats, bytes, map))
}

/// Writes `FILE` (16-bit heights) and `FILE` with `.colour.png` (false colour, 0..250 um).
pub fn write_pngs(map: &HeightMap, png: &Path) -> Result<PathBuf> {
    images::write_height_png(map, png)?;
    let colour = png.with_extension("colour.png");
    images::write_false_colour_png(map, -20.0, 230.0, &colour)?;
    Ok(colour)
}

/// Loads every frame of a recording (the f64 reference needs them all at once).
pub fn load_frames(rec: &Recording, progress: bool) -> Result<Vec<Frame>> {
    let bar = reconstruct::progress_bar(progress, rec.manifest.frames.len() as u64, "load frames");
    let mut frames = Vec::with_capacity(rec.manifest.frames.len());
    for k in 0..rec.manifest.frames.len() {
        frames.push(rec.frame(k)?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(frames)
}

/// Fixed-point core vs f64 reference vs PSP baseline vs ground truth on one recording.
pub fn compare(rec: &Recording, progress: bool) -> Result<(Comparison, HeightMap)> {
    let (_, _, fixed) = reconstruct_map(rec, progress)?;
    Ok((compare_map(rec, &fixed, progress)?, fixed))
}

/// [`compare`] for a fixed-point height map the caller already has (from the same recording).
pub fn compare_map(rec: &Recording, fixed: &HeightMap, progress: bool) -> Result<Comparison> {
    let frames = load_frames(rec, progress)?;
    let m = &rec.manifest;
    let r = reference::reconstruct(m, &frames);
    let psp = reference::psp(m, &frames);
    let truth = rec.truth().context("reading the ground truth")?;
    Ok(compare::compare(m, fixed, &r, Some(&psp), truth.as_ref()))
}
