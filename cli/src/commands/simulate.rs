//! `dpsa simulate`: write a recording with ground truth.

use super::{load_scene, out};
use anyhow::Result;
use dpsa_sim::{array, files, simulation::simulate};
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
    /// Array scenes only: write the calibration recordings (planes at known heights, a
    /// held-out plane, the lateral target) instead of the board.
    #[arg(long)]
    calibration: bool,
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    if a.scene != "default" {
        dpsa_sim::kind::expect(
            Path::new(&a.scene),
            "--scene",
            dpsa_sim::kind::Kind::Scene,
            &[dpsa_sim::kind::Kind::ArrayScene],
        )?;
    }
    if a.scene != "default" {
        let text = files::read_capped(Path::new(&a.scene), files::MAX_SCENE_BYTES, "scene")?;
        if array::scene::is_array_scene(&String::from_utf8_lossy(&text)) {
            return run_array(a);
        }
    }
    anyhow::ensure!(
        !a.calibration,
        "--calibration needs an array scene (a scene file with [[cameras]], e.g. scenes/array-small.toml)"
    );
    let sc = load_scene(&a.scene)?;
    let seed = a.seed.unwrap_or(sc.seed);
    if a.scene != "default" {
        files::refuse_overwrite_dir("--out", &a.out, &[files::Input::File(Path::new(&a.scene))])?;
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

fn run_array(a: Args) -> Result<()> {
    let sc = array::scene::ArrayScene::load(Path::new(&a.scene))?;
    super::warn(&sc.warnings());
    let seed = a.seed.unwrap_or(sc.seed);
    files::refuse_overwrite_dir("--out", &a.out, &[files::Input::File(Path::new(&a.scene))])?;
    let s = if a.calibration {
        array::record::simulate_calibration(&sc, seed, &a.out)?
    } else {
        array::record::simulate_board(&sc, seed, &a.out)?
    };
    out!(
        "simulated {} {} of {} cameras ({} frames, {:.1} Mpx) into {}: {:.1} MB on disk in {:.1} s",
        if a.calibration {
            "calibration recordings"
        } else {
            "the board"
        },
        if a.calibration {
            "(planes, held-out plane, lateral target)"
        } else {
            "recording"
        },
        s.cameras,
        s.frames,
        s.pixels as f64 / 1e6,
        a.out.display(),
        s.bytes as f64 / 1e6,
        s.seconds
    );
    Ok(())
}
