//! `dpsa decode`: a packet stream back into a height map, with its damage report.

use super::out;
use anyhow::{bail, Context, Result};
use dpsa_sim::{images, stream};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Packet stream file.
    stream: PathBuf,
    /// Write a 16-bit height PNG (and a false-colour PNG beside it).
    #[arg(long)]
    png: Option<PathBuf>,
    /// Height LSB in um, for the false-colour scale.
    #[arg(long, default_value_t = 0.25)]
    lsb_um: f64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    let bytes =
        std::fs::read(&a.stream).with_context(|| format!("reading {}", a.stream.display()))?;
    let (map, rep) = stream::decode_stream(&bytes, a.lsb_um);
    if let Some(png) = a.png {
        if map.rows.is_empty() {
            bail!("no decodable rows: nothing to draw");
        }
        images::write_pngs(&map, &png)?;
    }
    if a.json {
        let v = serde_json::json!({
            "packets": { "ok": rep.ok, "corrupt": rep.corrupt, "resynced": rep.resynced },
            "rows": { "decoded": map.rows.len(), "valid": map.rows.iter().filter(|r| r.is_valid()).count() },
            "pixels": { "valid": map.valid_pixels(), "total": map.total_pixels() },
            "damage": rep.damage,
        });
        out!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        out!(
            "{} packets ok, {} corrupt ({} resyncs); {} rows, {} valid pixels",
            rep.ok,
            rep.corrupt,
            rep.resynced,
            map.rows.len(),
            map.valid_pixels()
        );
    }
    Ok(())
}
