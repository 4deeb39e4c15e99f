//! `dpsa calibrate`: per-camera calibration of an array from its calibration recording.

use super::out;
use anyhow::{Context, Result};
use dpsa_sim::array::record::ArrayRecording;
use dpsa_sim::calibration::{self, evaluate};
use dpsa_sim::files;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Calibration recording (`dpsa simulate --scene ARRAY.toml --calibration --out DIR`).
    dir: PathBuf,
    /// Calibration file to write (TOML, `docs/calibration.md`).
    #[arg(long)]
    out: PathBuf,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
    /// Budget of the height error the field variation of f_x causes with the core's single
    /// value, um; cameras above it are flagged.
    #[arg(long, default_value_t = calibration::FX_BUDGET_UM, value_parser = super::positive)]
    fx_budget_um: f64,
}

pub fn run(a: Args) -> Result<()> {
    dpsa_sim::kind::expect(
        &a.dir,
        "DIR",
        dpsa_sim::kind::Kind::ArrayCalibrationRecording,
        &[],
    )?;
    let rec = ArrayRecording::open(&a.dir)?;
    files::refuse_overwrite("--out", &a.out, &[files::Input::Dir(&a.dir)])?;
    let cal = calibration::calibrate(&rec, a.fx_budget_um)?;
    let text = cal.to_toml()?;
    files::write_bytes(&a.out, text.as_bytes())
        .with_context(|| format!("writing {}", a.out.display()))?;
    let report = evaluate(&rec, &cal)?;
    for c in &cal.camera {
        if c.fx_over_budget {
            eprintln!(
                "warning: camera {}: the field variation of the fringe frequency causes up to {:.2} um of height error with the core's single f_x (budget {} um)",
                c.id, c.fx_height_error_um, cal.fx_budget_um
            );
        }
    }
    if a.json {
        out!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    out!(
        "calibrated {} cameras into {} (encoder {:.4} counts/mm)",
        cal.camera.len(),
        a.out.display(),
        cal.counts_per_mm
    );
    for c in &cal.camera {
        out!(
            "  camera {}: fringe period {:.5} px, T_z {:.1}..{:.1} um, pitch {:.5} mm, rotation {:.4} deg, {} dead pixels, f_x field error {:.3} um{}",
            c.id,
            c.fringe_period_px,
            c.height_per_turn_um.iter().copied().fold(f64::INFINITY, f64::min),
            c.height_per_turn_um.iter().copied().fold(f64::NEG_INFINITY, f64::max),
            c.lateral.pitch_mm,
            c.lateral.rotation_rad.to_degrees(),
            c.dead_pixels.len(),
            c.fx_height_error_um,
            if c.fx_over_budget { " (OVER BUDGET)" } else { "" }
        );
    }
    if let Some(h) = &report.holdout {
        out!(
            "  held-out plane at {} um: bias {:.3} um (max |.|), rms {:.3} um",
            h.height_um,
            h.bias_um_max,
            h.rms_um
        );
    }
    if let Some(t) = &report.truth_error {
        out!(
            "  against the truth: T_z {:.2e}, f_x {:.2e}, phi0 {:.2} mrad rms, lateral {:.2} um rms",
            t.t_z_rel_max, t.f_x_rel_max, t.phi0_rms_mrad, t.lateral_rms_um
        );
    }
    Ok(())
}
