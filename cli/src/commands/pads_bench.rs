//! `dpsa pads-bench`: the paste-layer reader on synthetic layers of up to 10^6 objects, each
//! read in a child process: wall time, peak memory and pads (or the reader's refusal), as JSON.

use super::out;
use anyhow::{Context, Result};
use dpsa_sim::benches::gerber::{self, KINDS};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Objects per layer.
    #[arg(long, default_value_t = 1_000_000)]
    objects: usize,
    /// Kinds of layer (repeatable): column, same, grid, apertures, arcs, strokes, regions;
    /// all when none is given.
    #[arg(long = "kind")]
    kinds: Vec<String>,
    /// Read this one layer file here and print its reading (what each child runs).
    #[arg(long, value_name = "FILE", hide = true)]
    one: Option<PathBuf>,
}

pub fn run(a: Args) -> Result<()> {
    if let Some(file) = &a.one {
        out!("{}", serde_json::to_string(&gerber::read_one(file))?);
        return Ok(());
    }
    let kinds: Vec<String> = if a.kinds.is_empty() {
        KINDS.iter().map(|k| k.to_string()).collect()
    } else {
        a.kinds.clone()
    };
    let exe = std::env::current_exe().context("finding the dpsa binary to run the readings")?;
    let dir = dpsa_sim::files::TempDir::new("dpsa-pads-bench")?;
    let cases = gerber::run(&exe, &kinds, a.objects, dir.path())?;
    out!(
        "{}",
        serde_json::to_string_pretty(&serde_json::json!({
            "limits": {
                "max_file_bytes": dpsa_sim::inspection::gerber::MAX_FILE_BYTES,
                "max_objects": dpsa_sim::inspection::gerber::MAX_OBJECTS,
                "max_vertices": dpsa_sim::inspection::gerber::MAX_VERTICES,
                "max_stroke_vertices": dpsa_sim::inspection::gerber::MAX_STROKE_VERTICES,
            },
            "cases": cases,
        }))?
    );
    Ok(())
}
