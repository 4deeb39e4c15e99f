//! `dpsa simulate`: write a recording with ground truth.

use super::{load_scene, out};
use anyhow::Result;
use dpsa_sim::{files, simulation::simulate};
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct Args {
    /// `default` for the built-in scene, or a scene TOML file (knobs: README, "Scene files").
    #[arg(long, default_value = "default")]
    scene: String,
    /// Random seed (layout, motion and noise).
    #[arg(long)]
    seed: Option<u64>,
    /// Output recording directory: new, empty, or an earlier recording (replaced whole).
    #[arg(long)]
    out: PathBuf,
    /// Write even when the estimated size exceeds the 20 GB limit.
    #[arg(long)]
    force: bool,
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    let sc = load_scene(&a.scene)?;
    let seed = a.seed.unwrap_or(sc.seed);
    if a.scene != "default" {
        files::refuse_overwrite("--out", &a.out, &[files::Input::File(Path::new(&a.scene))])?;
    }
    let s = simulate::simulate_with(&sc, seed, &a.out, progress, a.force)?;
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
