//! `dpsa simulate`: write a recording with ground truth.

use super::{load_scene, out};
use anyhow::Result;
use dpsa_sim::simulation::simulate;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// `default` for the built-in scene, or a scene TOML file (knobs: README, "Scene files").
    #[arg(long, default_value = "default")]
    scene: String,
    /// Random seed (layout, motion and noise).
    #[arg(long)]
    seed: Option<u64>,
    /// Output recording directory.
    #[arg(long)]
    out: PathBuf,
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    let sc = load_scene(&a.scene)?;
    let seed = a.seed.unwrap_or(sc.seed);
    let s = simulate::simulate(&sc, seed, &a.out, progress)?;
    out!(
        "simulated {} frames of {}x{} ({} deposits) into {}",
        s.frames,
        s.rows,
        s.width,
        s.deposits_placed,
        a.out.display()
    );
    Ok(())
}
