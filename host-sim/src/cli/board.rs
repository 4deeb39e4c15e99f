//! `dpsa board`: an array recording and its calibration into one board height map.

use super::out;
use anyhow::Result;
use dpsa_sim::calibration::file::CalFile;
use dpsa_sim::files;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Array board recording (`dpsa simulate --scene ARRAY.toml --out DIR`).
    dir: PathBuf,
    /// Calibration file of the array (`dpsa calibrate`).
    #[arg(long)]
    cal: PathBuf,
    /// Output directory: heights.png, heights_um.tiff, heights.colour.png, camera.png,
    /// board.json (may not be inside the recording).
    #[arg(long)]
    out: PathBuf,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let inputs = [files::Input::Dir(&a.dir), files::Input::File(&a.cal)];
    files::refuse_overwrite("--out", &a.out, &inputs)?;
    let cal = CalFile::load(&a.cal)?;
    let r = dpsa_sim::board::run::run(&a.dir, &cal, &a.out)?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    out!("{} -> {}", r.summary(), a.out.display());
    Ok(())
}
