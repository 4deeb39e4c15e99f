//! `dpsa demo`: the main job on a built-in scene: simulate, reconstruct, compare, write images.

use super::{load_scene, open, out};
use anyhow::Result;
use dpsa_sim::{
    files, images, reconstruct, reference::compare::compare_recording, simulation::simulate,
};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Working directory for the recording, stream, images and report.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Random seed.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Scene: `default` or a scene TOML file.
    #[arg(long, default_value = "default")]
    scene: String,
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    let (out, seed, scene) = (&a.out, a.seed, a.scene.as_str());
    let sc = load_scene(scene)?;
    let rec_dir = out.join("recording");
    out!(
        "1/4 simulating the {scene} scene (seed {seed}) into {}",
        rec_dir.display()
    );
    let s = simulate::simulate(&sc, seed, &rec_dir, progress)?;
    out!(
        "    {} frames of {} rows x {} px, {} solder-paste deposits, {:.0} um per fringe turn",
        s.frames,
        s.rows,
        s.width,
        s.deposits_placed,
        sc.height_per_turn_um
    );
    let rec = open(&rec_dir)?;
    out!("2/4 reconstructing with the fixed-point core (streaming, line by line)");
    let (stats, bytes, map) = reconstruct::reconstruct_map(&rec, progress)?;
    let stream = out.join("heights.dpsa");
    files::write_bytes(&stream, &bytes)?;
    out!(
        "    {} packets (stream header, rows, end), {} bytes -> {}; core state {} bytes",
        stats.packets,
        stats.bytes,
        stream.display(),
        stats.state_bytes
    );
    out!("3/4 comparing with the f64 reference, the 4-step PSP baseline and the ground truth");
    let cmp = compare_recording(&rec, progress)?;
    let report = out.join("compare.json");
    files::write_bytes(&report, serde_json::to_string_pretty(&cmp)?.as_bytes())?;
    out!("4/4 writing images");
    let png = out.join("heights.png");
    let colour = images::write_pngs(&map, &png)?;
    out!(
        "    {} (16-bit), {} (false colour)",
        png.display(),
        colour.display()
    );
    out!("");
    out!("{}", cmp.summary());
    out!("full report: {}", report.display());
    Ok(())
}
