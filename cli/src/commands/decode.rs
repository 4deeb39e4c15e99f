//! `dpsa decode`: a packet stream back into a height map, with its damage report.

use super::out;
use anyhow::{bail, Context, Result};
use dpsa_formats::images;
use dpsa_stream as stream;
use dpsa_stream::DecodeOutcome;
use std::path::PathBuf;

/// Exit status: 0 clean; 2 damage, missing / duplicated / reordered packets or a truncated
/// stream; 3 nothing decodable (1: the command failed, e.g. the file cannot be read).
#[derive(clap::Args)]
#[command(
    after_help = "Exit status: 0 clean (a version 2 stream ended with matching totals); 2 damage, missing, duplicated or reordered packets, or a truncated stream (no end packet, or totals that disagree); 3 nothing decodable; 1 the command failed."
)]
pub struct Args {
    /// Packet stream file (a regular file, read in 64 KiB chunks, any size; heights are held
    /// only for --png).
    stream: PathBuf,
    /// Write a 16-bit height PNG (and a false-colour PNG beside it); rows sit at their board
    /// row, missing rows are invalid.
    #[arg(long)]
    png: Option<PathBuf>,
    /// Height LSB in um, for the false-colour scale (finite, > 0).
    #[arg(long, default_value_t = 0.25, value_parser = super::positive, allow_hyphen_values = true)]
    lsb_um: f64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

/// Decodes; returns the exit status.
pub fn run(a: Args) -> Result<i32> {
    dpsa_formats::kind::expect(&a.stream, "STREAM", dpsa_formats::kind::Kind::Stream, &[])?;
    if let Some(png) = &a.png {
        dpsa_formats::files::require_png("--png", png)?;
        let inputs = [dpsa_formats::files::Input::File(&a.stream)];
        dpsa_formats::files::refuse_overwrite("--png", png, &inputs)?;
        dpsa_formats::files::refuse_overwrite("--png", &images::colour_path(png), &inputs)?;
    }
    let file = dpsa_formats::files::open_regular(&a.stream, "packet stream")?;
    // Heights are kept only for the PNG; otherwise each row leaves only its counts behind.
    let keep = stream::Keep {
        rows: a.png.is_some(),
        max_pixels: stream::MAX_MAP_PIXELS,
    };
    let decoded = stream::decode_reader_with(std::io::BufReader::new(file), a.lsb_um, keep)
        .with_context(|| format!("cannot read {}", a.stream.display()))?;
    let (rows, rep) = (decoded.rows, decoded.report);
    let verdict = rep.verdict_rows(rows.decoded);
    if let Some(png) = a.png {
        if decoded.over_limit {
            bail!(
                "the stream holds more than {} Mpx of heights, the most a PNG is drawn from \
                 (decode without --png for its report)",
                stream::MAX_MAP_PIXELS >> 20
            );
        }
        match decoded.map {
            Some(map) if !map.rows.is_empty() => {
                images::write_pngs(&map, &png)?;
            }
            _ => bail!("no decodable rows: nothing to draw"),
        }
    }
    let s = &rep.stream;
    if a.json {
        let v = serde_json::json!({
            "packets": { "ok": rep.ok, "corrupt": rep.corrupt, "resynced": rep.resynced },
            "rows": { "decoded": rows.decoded, "valid": rows.valid },
            "pixels": { "valid": rows.valid_pixels, "total": rows.total_pixels },
            "damage": rep.damage,
            "damage_listed_max": stream::MAX_DAMAGE_ENTRIES,
            "stream": s,
            "bytes": rep.bytes,
            "status": verdict as i32,
        });
        out!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        out!(
            "{} packets ok, {} corrupt ({} resyncs); {} rows, {} valid pixels",
            rep.ok,
            rep.corrupt,
            rep.resynced,
            rows.decoded,
            rows.valid_pixels
        );
        if s.version >= 2 {
            out!(
                "stream v{}: {} missing, {} duplicated, {} reordered packets, {} of another camera, {} rows missing, {} gap records ({} rows){}",
                s.version,
                s.missing,
                s.duplicated,
                s.reordered,
                s.other_camera,
                s.rows_missing,
                s.gap_records,
                s.gap_rows,
                if s.truncated {
                    "; TRUNCATED (no end packet or totals disagree)"
                } else {
                    ""
                }
            );
        }
        match verdict {
            DecodeOutcome::Clean => {}
            DecodeOutcome::Damaged => out!("the stream is damaged or incomplete (exit status 2)"),
            DecodeOutcome::Nothing => out!("nothing decodable (exit status 3)"),
        }
    }
    Ok(verdict as i32)
}
