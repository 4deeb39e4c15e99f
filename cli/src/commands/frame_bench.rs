//! `dpsa frame-bench`: frame formats (PNG, .zfr) on a recording's frames, as JSON.

use super::out;
use anyhow::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// A recording directory (e.g. one camera of an array recording, `DIR/cam0`).
    dir: PathBuf,
    /// Frames to use (the first ones).
    #[arg(long, default_value_t = 200)]
    frames: usize,
}

pub fn run(a: Args) -> Result<()> {
    dpsa_sim::kind::expect(&a.dir, "DIR", dpsa_sim::kind::Kind::Recording, &[])?;
    let rec = super::open(&a.dir)?;
    let r = dpsa_sim::benches::frames::run(&rec, a.frames)?;
    out!("{}", serde_json::to_string_pretty(&r)?);
    Ok(())
}
