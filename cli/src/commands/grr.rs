//! `dpsa grr`: a gauge R&R study (AIAG, ANOVA) of the inspection on a simulated board.

use super::out;
use anyhow::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Array scene with a paste layer (e.g. `scenes/array-paste.toml`); give it a
    /// `[print] seed` so that every run sees the same printed board (without one the
    /// study uses the scene's `seed`).
    #[arg(long)]
    scene: PathBuf,
    /// Set-ups of the machine (the appraisers): each its own calibration and placement.
    #[arg(long, default_value_t = 3)]
    setups: u32,
    /// Measurements under each set-up (the trials), fresh camera noise each.
    #[arg(long, default_value_t = 3)]
    repeats: u32,
    /// Seed of the first set-up (set-up `a` uses `seed + 1000 a`, its runs the next ones).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Working directory for the recordings (removed as the study goes; default: a new
    /// temporary directory, removed at the end and on SIGINT/SIGTERM).
    #[arg(long)]
    work: Option<PathBuf>,
    /// Take the paste's reflectance out of the maps' walls with the simulated machine's own
    /// step (`[reflectance] background_step` of the scene's background and contrast, in
    /// every run's program; see docs/spc.md) even where the scene's programs leave it in (a
    /// scene without `[reflectance]`; the shipped printed boards' take it out already).
    #[arg(long)]
    reflectance: bool,
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
    let r = dpsa_sim::inspection::grr::grr(
        &a.scene,
        a.setups,
        a.repeats,
        a.seed,
        a.reflectance,
        &work,
    )?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        let v = &r.volume;
        let opt = |x: Option<f64>| x.map_or("-".to_owned(), |x| format!("{x:.1}"));
        out!(
            "{} pads x {} set-ups x {} repeats ({:.0} s)\n\
             volume, % of the opening volume: repeatability (EV) {:.3}, reproducibility (AV) {:.3} \
             (calibration and placement {:.3}, pad x set-up {:.3}), GR&R {:.3}, pads (PV) {:.2}\n\
             %GR&R {} % of the {:.0} % volume window (6 GRR), {} % of the total variation; ndc {}\n\
             per pad: volume sigma median {:.3} %, p95 {:.3} %; height sigma median {:.3} um; \
             {} of {} pads called the same every time",
            r.pads,
            r.setups,
            r.repeats,
            r.seconds,
            v.repeatability,
            v.reproducibility,
            v.appraiser,
            v.interaction,
            v.grr,
            v.part,
            opt(v.pct_tolerance),
            r.tolerance_pct,
            opt(v.pct_total),
            v.ndc.map_or("-".to_owned(), |n| n.to_string()),
            r.volume_sigma_pct_median,
            r.volume_sigma_pct_p95,
            r.height_sigma_um_median,
            r.calls_consistent,
            r.pads,
        );
        for f in &r.families {
            out!(
                "  {:<11} {:>4} pads: volume sigma {:.2} % within a set-up ({:.2} % over all), stated {:.2} % (x{:.2}); height {:.2} um ({:.2}), stated {:.2} um (x{:.2})",
                f.family,
                f.pads,
                f.volume_sigma_pct,
                f.volume_sigma_all_pct,
                f.volume_u_pct,
                f.volume_ratio,
                f.height_sigma_um,
                f.height_sigma_all_um,
                f.height_u_um,
                f.height_ratio
            );
        }
    }
    Ok(())
}
