//! `dpsa grr`: gauge repeatability of the inspection on a simulated board.

use super::out;
use anyhow::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Array scene with a paste layer (e.g. `scenes/array-paste.toml`); give it a
    /// `[print] seed` so that every repeat sees the same printed board (without one the
    /// study uses the scene's `seed`).
    #[arg(long)]
    scene: PathBuf,
    /// Runs of the same board (10 or more for a study).
    #[arg(long, default_value_t = 10)]
    repeats: u32,
    /// Seed of the calibration and the first run (run `r` uses `seed + 1 + r`).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Working directory for the recordings (removed as the study goes; default: a new
    /// temporary directory, removed at the end and on SIGINT/SIGTERM).
    #[arg(long)]
    work: Option<PathBuf>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let tmp;
    let work = match &a.work {
        Some(w) => w.clone(),
        None => {
            // 50-130 MB of recordings: removed on drop and by the interrupt handler.
            tmp = dpsa_sim::files::TempDir::new("dpsa-grr-")?;
            tmp.path().to_path_buf()
        }
    };
    let r = dpsa_sim::inspection::grr::grr(&a.scene, a.repeats, a.seed, &work)?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        out!(
            "{} pads x {} repeats: volume sigma median {:.3} %, p95 {:.3} %, pooled {:.3} % of the opening volume; %GR&R {:.2} % of the {:.0} % volume window (6 sigma); height sigma median {:.3} um; {} of {} pads called the same every time ({:.0} s)",
            r.pads,
            r.repeats,
            r.volume_sigma_pct_median,
            r.volume_sigma_pct_p95,
            r.volume_sigma_pct_pooled,
            r.grr_pct,
            r.tolerance_pct,
            r.height_sigma_um_median,
            r.calls_consistent,
            r.pads,
            r.seconds
        );
    }
    Ok(())
}
