//! `dpsa reconstruct`: the core through its streaming API, into a packet stream.

use super::{open, out};
use anyhow::{Context, Result};
use dpsa_sim::{images, reconstruct, stream};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Recording directory.
    dir: PathBuf,
    /// Packet stream output file.
    #[arg(long)]
    out: PathBuf,
    /// Also write a 16-bit height PNG here (h + 32768 in LSB, 0 = invalid) and a
    /// false-colour PNG beside it (`*.colour.png`).
    #[arg(long)]
    png: Option<PathBuf>,
    /// Codec intra period: 1 (default) makes every packet decodable on its own, so a
    /// damaged packet loses only itself; K > 1 predicts rows from the previous one
    /// (smaller, but a lost packet costs up to K - 1 more rows).
    #[arg(long, default_value_t = dpsa_core::packets::STREAM_INTRA_PERIOD)]
    intra_period: u32,
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    let rec = open(&a.dir)?;
    let file =
        std::fs::File::create(&a.out).with_context(|| format!("creating {}", a.out.display()))?;
    let writer = std::io::BufWriter::new(file);
    let (stats, _) = reconstruct::run_with(&rec, writer, a.intra_period, progress)?;
    out!(
        "{} packets, {} bytes -> {}",
        stats.packets,
        stats.bytes,
        a.out.display()
    );
    if let Some(png) = a.png {
        let bytes = std::fs::read(&a.out)?;
        let (map, _) = stream::decode_stream(&bytes, rec.manifest.calibration.height_lsb_um);
        let colour = images::write_pngs(&map, &png)?;
        out!(
            "heights -> {}, false colour -> {}",
            png.display(),
            colour.display()
        );
    }
    Ok(())
}
