//! `dpsa phase`: an ordinary phase-shifting stack through the fixed-point kernel, f64 beside it.

use super::out;
use anyhow::Result;
use dpsa_sim::{files, images, stack};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// An image of the stack (repeat, 3 to 8 images, in step order).
    #[arg(long = "image", required = true)]
    images: Vec<PathBuf>,
    /// Phase step of the matching image in degrees (repeat, one per --image):
    /// I = B + C cos(phase + step).
    /// Finite, within +/-36000 degrees; negative steps are fine.
    #[arg(long = "step", required = true, allow_hyphen_values = true, value_parser = super::step_deg)]
    steps: Vec<f64>,
    /// Minimum fringe modulation C of a valid pixel, DN (default: 4% of full scale; >= 0).
    #[arg(long, allow_hyphen_values = true, value_parser = super::non_negative)]
    min_modulation: Option<f64>,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
    /// Write the fixed-point wrapped phase as an 8-bit PNG (0 = invalid).
    #[arg(long)]
    png: Option<PathBuf>,
}

pub fn run(a: Args) -> Result<()> {
    if let Some(png) = &a.png {
        files::require_png("--png", png)?;
        let inputs: Vec<_> = a.images.iter().map(|p| files::Input::File(p)).collect();
        files::refuse_overwrite("--png", png, &inputs)?;
    }
    let st = stack::Stack::load(&a.images, &a.steps)?;
    let full = if st.bit_depth == 8 { 255.0 } else { 65535.0 };
    let (ph, rep) = stack::run(&st, a.min_modulation.unwrap_or(0.04 * full))?;
    if let Some(png) = a.png {
        images::write_phase_png(&ph.fixed, st.width, &png)?;
    }
    if a.json {
        out!("{}", serde_json::to_string_pretty(&rep)?);
    } else {
        out!(
            "{}x{}: {} valid pixels of {} ({} differ in validity); fixed vs f64 phase: rms {:.2e} rad, max {:.2e} rad",
            rep.width, rep.height, rep.valid_pixels, rep.total_pixels, rep.valid_mismatch,
            rep.fixed_vs_ref_rms_rad, rep.fixed_vs_ref_max_rad
        );
    }
    Ok(())
}
