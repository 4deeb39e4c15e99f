//! `dpsa compare`: the core against the f64 reference, the PSP baseline, the CRB and the truth.

use super::{open, out};
use anyhow::Result;
use dpsa_sim::reference::compare::compare_recording;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Recording directory.
    dir: PathBuf,
    /// Print one JSON object instead of a summary.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    dpsa_sim::kind::expect(&a.dir, "DIR", dpsa_sim::kind::Kind::Recording, &[])?;
    let rec = open(&a.dir)?;
    let cmp = compare_recording(&rec, progress)?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&cmp)?);
    } else {
        out!("{}", cmp.summary());
    }
    Ok(())
}
