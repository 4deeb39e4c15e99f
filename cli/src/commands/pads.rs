//! `dpsa pads`: a board's top paste layer (Gerber) as pads: count, box, areas, classes.

use super::{out, warn};
use anyhow::Result;
use dpsa_gerber::{read_file, PadSummary, PasteLayer};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// The paste layer (Gerber RS-274X / X2), e.g. `board-F_Paste.gbr` or `board.GTP`.
    file: PathBuf,
    /// Print one JSON object instead of a summary.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    dpsa_formats::kind::expect(&a.file, "FILE", dpsa_formats::kind::Kind::Gerber, &[])?;
    let layer = read_file(&a.file).map_err(|e| anyhow::anyhow!("{}", e.in_file(&a.file)))?;
    let s = layer.summary();
    if a.json {
        out!("{}", serde_json::to_string_pretty(&json(&a, &layer, &s))?);
    } else {
        warn(&layer.warnings);
        print_summary(&a, &layer, &s)?;
    }
    Ok(())
}

fn json(a: &Args, layer: &PasteLayer, s: &PadSummary) -> serde_json::Value {
    let classes: serde_json::Map<String, serde_json::Value> = s
        .classes
        .iter()
        .map(|(k, v)| (k.clone(), serde_json::Value::from(*v)))
        .collect();
    serde_json::json!({
        "file": a.file.display().to_string(),
        "units": layer.units,
        "generator": layer.generator,
        "pads": {
            "count": s.count,
            "bbox_mm": s.bbox_mm,
            "total_area_mm2": s.total_area_mm2,
            "area_histogram": s.area_histogram,
            "classes": classes,
            "named": s.named,
        },
        "warnings": layer.warnings,
    })
}

fn print_summary(a: &Args, layer: &PasteLayer, s: &PadSummary) -> Result<()> {
    let b = s.bbox_mm;
    out!(
        "{}: {} pads, units {}, generator {}",
        a.file.display(),
        s.count,
        layer.units,
        layer.generator.as_deref().unwrap_or("(not given)")
    );
    out!(
        "box: x {:.3} .. {:.3}, y {:.3} .. {:.3} mm ({:.3} x {:.3} mm); paste area {:.3} mm^2",
        b[0],
        b[2],
        b[1],
        b[3],
        b[2] - b[0],
        b[3] - b[1],
        s.total_area_mm2
    );
    out!("named (X2 component/pin): {} of {}", s.named, s.count);
    out!("area histogram (mm^2):");
    let peak = s
        .area_histogram
        .iter()
        .map(|b| b.count)
        .max()
        .unwrap_or(0)
        .max(1);
    for bin in s.area_histogram.iter().filter(|b| b.count > 0) {
        let bar = "#".repeat((bin.count * 40).div_ceil(peak));
        out!(
            "  {:>8} .. {:<8} {:>6} {bar}",
            bin.from_mm2,
            bin.to_mm2,
            bin.count
        );
    }
    out!("aperture classes:");
    for (class, n) in &s.classes {
        out!("  {n:>6}  {class}");
    }
    Ok(())
}
