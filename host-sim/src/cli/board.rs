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
    let opt = |x: Option<f64>| x.map_or_else(|| "n/a".to_string(), |v| format!("{v:.3}"));
    out!(
        "board map {} x {} px at {} mm -> {}: {:.2} % valid",
        r.grid.rows,
        r.grid.width,
        r.grid.pitch_mm,
        a.out.display(),
        100.0 * r.pixels.valid_fraction
    );
    out!(
        "seams: height step max {} um, misregistration max {} um; turns per camera {:?}",
        opt(r.seams.height_step_um_max),
        opt(r.seams.lateral_um_max),
        r.unwrap.turns
    );
    if let Some(t) = &r.truth {
        out!(
            "truth: rms {} um (bias {}) over {} flat px, {} wrong-turn px",
            opt(t.rms_um),
            opt(t.bias_um),
            t.flat_pixels,
            t.wrong_turn_pixels
        );
    }
    out!(
        "time: core {:.2} s, unwrap {:.2} s, resample {:.2} s, blend {:.2} s, write {:.2} s",
        r.timing.core_s,
        r.timing.assemble.unwrap_s,
        r.timing.assemble.resample_s,
        r.timing.assemble.blend_s,
        r.timing.write_s
    );
    Ok(())
}
