//! `dpsa layout`: write a generated paste layer (Gerber X2).

use super::out;
use anyhow::{Context, Result};
use dpsa_sim::array::layout::{generate, LayoutBoard};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Which board: `paper` (220 x 168 mm) or `small` (20 x 13.9 mm, scenes/array-small.toml).
    #[arg(long)]
    board: String,
    /// Output Gerber file (replaced if it exists).
    #[arg(long)]
    out: PathBuf,
}

pub fn run(a: Args) -> Result<()> {
    let board = LayoutBoard::parse(&a.board)?;
    let layout = generate(board);
    let bytes = layout.gerber()?;
    dpsa_sim::files::write_bytes(&a.out, &bytes)
        .with_context(|| format!("writing {}", a.out.display()))?;
    out!(
        "{} board, {} x {} mm: {} openings of {} components into {} ({} bytes)",
        board.name(),
        layout.length_mm,
        layout.width_mm,
        layout.pads.len(),
        layout.components.len(),
        a.out.display(),
        bytes.len()
    );
    for c in layout.family_counts() {
        out!(
            "  {:<14} {:>5} components {:>6} openings",
            c.family,
            c.components,
            c.pads
        );
    }
    let fids: Vec<String> = layout
        .fiducials
        .iter()
        .map(|f| format!("[{}, {}]", f[0], f[1]))
        .collect();
    out!("fiducials = [{}]", fids.join(", "));
    Ok(())
}
