//! `dpsa codec-bench`: the row codec against general-purpose compressors, as a table or JSON.

use super::out;
use anyhow::Result;
use dpsa_sim::benches::codec::{self, Source};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// A recording directory (run through the fixed-point core) or a packet stream file.
    input: PathBuf,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    dpsa_sim::kind::expect(
        &a.input,
        "INPUT",
        dpsa_sim::kind::Kind::Recording,
        &[dpsa_sim::kind::Kind::Stream],
    )?;
    let (rows, source) = codec::load(&a.input, progress)?;
    if let Source::Stream { ok, corrupt } = source {
        if corrupt > 0 {
            eprintln!("warning: {corrupt} damaged packets left out ({ok} decoded)");
        }
    }
    let report = codec::run(&rows, progress)?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        out!("{}", report.table());
    }
    Ok(())
}
