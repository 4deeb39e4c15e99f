//! `dpsa inspect`: a board map judged pad by pad against the inspection program.

use super::out;
use anyhow::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Board map directory (`dpsa board --out DIR`).
    board: PathBuf,
    /// Inspection program (`program.toml`; `dpsa simulate` writes one into a board recording).
    #[arg(long)]
    program: PathBuf,
    /// Output directory: pads.csv, report.json, cfx_units_inspected.json, overview.png,
    /// gallery/. New, empty or an earlier inspection output (replaced whole); it may not be,
    /// hold or lie inside an input.
    #[arg(long)]
    out: PathBuf,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
    /// The simulator's print truth (`print.json` of the board recording) when the program
    /// does not name it; compares every figure with it (a build with the simulator only).
    #[cfg(feature = "sim")]
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Skip the comparison with the print truth the program names (about 20 s on the paper
    /// board); the report then has no `evaluation`.
    #[cfg(feature = "sim")]
    #[arg(long, conflicts_with = "truth")]
    no_truth: bool,
    /// Inspect this many times and report the fastest (a benchmark of the inspection alone).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
    repeat: u32,
}

/// Exit status 0 whatever the verdict (it is in the report), 1 on an error.
pub fn run(a: Args, progress: bool) -> Result<()> {
    dpsa_formats::kind::expect(&a.board, "MAPDIR", dpsa_formats::kind::Kind::BoardMap, &[])?;
    dpsa_formats::kind::expect(
        &a.program,
        "--program",
        dpsa_formats::kind::Kind::Program,
        &[],
    )?;
    // The inspection refuses an `--out` that is, holds or lies inside an input (the board
    // map, the program, its paste layer, the truth) and one that is not new, empty or an
    // earlier inspection output, before it runs.
    #[cfg(feature = "sim")]
    let (r, _) = {
        if let Some(t) = &a.truth {
            dpsa_formats::kind::expect(t, "--truth", dpsa_formats::kind::Kind::PrintTruth, &[])?;
        }
        // With the simulator: the print truth the program names (or `--truth`) is evaluated.
        dpsa_sim::inspection::evaluate::inspect_dir_shown(
            &a.board,
            &a.program,
            a.truth.as_deref(),
            Some(&a.out),
            a.repeat,
            !a.no_truth,
            progress,
        )?
    };
    #[cfg(not(feature = "sim"))]
    let (r, _) = dpsa_inspect::run::inspect_dir_with(
        &a.board,
        &a.program,
        Some(&a.out),
        a.repeat,
        None,
        progress,
    )?;
    if a.json {
        out!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        out!("{}", r.summary());
        out!("  -> {}", a.out.display());
    }
    Ok(())
}
