//! `dpsa board-bench`: the whole board's speed with its frames in memory, as JSON.

use super::out;
use anyhow::Result;
use dpsa_sim::calibration::file::CalFile;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Array board recording (`dpsa simulate --scene ARRAY.toml --out DIR`), e.g. of
    /// `scenes/paper-board.toml`.
    dir: PathBuf,
    /// Calibration file of the array (`dpsa calibrate`).
    #[arg(long)]
    cal: PathBuf,
    /// Python interpreter for the numpy baseline (it needs numpy).
    #[arg(long, default_value = "python3")]
    python: String,
    /// Skip the numpy baseline.
    #[arg(long)]
    no_numpy: bool,
}

pub fn run(a: Args) -> Result<()> {
    dpsa_sim::kind::expect(
        &a.dir,
        "DIR",
        dpsa_sim::kind::Kind::ArrayBoardRecording,
        &[],
    )?;
    dpsa_sim::kind::expect(&a.cal, "--cal", dpsa_sim::kind::Kind::Calibration, &[])?;
    let cal = CalFile::load(&a.cal)?;
    let py = (!a.no_numpy).then_some(a.python.as_str());
    let r = dpsa_sim::benches::board::run(&a.dir, &cal, py)?;
    out!("{}", serde_json::to_string_pretty(&r)?);
    Ok(())
}
