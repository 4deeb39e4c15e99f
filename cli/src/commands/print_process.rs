//! `dpsa print-process`: a simulated print process over a run of boards, into a new store.

use super::out;
use anyhow::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// The process (`docs/spc.md`, "A known process": boards, seed, in-control scatter,
    /// `[[change]]`s).
    #[arg(long)]
    process: PathBuf,
    /// The inspection program whose pads are printed (its paste layer, components, windows).
    #[arg(long)]
    program: PathBuf,
    /// The store to write: a new SQLite file (an existing one is refused).
    #[arg(long)]
    store: PathBuf,
    /// The line the boards are stored under.
    #[arg(long, default_value = "line-1")]
    line: String,
    /// Print what was written as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let spec = dpsa_sim::process::ProcessSpec::load(&a.process)?;
    let s = dpsa_sim::process::print_process(&spec, &a.program, &a.store, &a.line)?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&s)?);
    } else {
        out!(
            "{} boards of {} pads ({} fine apertures) into {}: {} failed, {} warned, {} passed",
            s.boards,
            s.pads,
            s.fine_pads,
            s.store,
            s.fail,
            s.warn,
            s.pass
        );
    }
    Ok(())
}
