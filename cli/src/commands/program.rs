//! `dpsa program`: the teach step: an inspection program from the board's design files.

use super::{out, warn};
use anyhow::Result;
use dpsa_inspect::teach::{self, placement};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// The top paste layer (Gerber).
    #[arg(long)]
    paste: PathBuf,
    /// The top copper layer (Gerber), to find the fiducials.
    #[arg(long)]
    copper: Option<PathBuf>,
    /// The board outline (Gerber profile, KiCad Edge.Cuts), for the board corner.
    #[arg(long)]
    outline: Option<PathBuf>,
    /// Pick-and-place (centroid) file: names every pad `REF-PIN`.
    #[arg(long)]
    placement: Option<PathBuf>,
    /// Its format: kicad (.pos), kicad-csv, altium (Pick Place), csv (with --columns).
    #[arg(long, default_value = "kicad", requires = "placement")]
    placement_format: placement::Format,
    /// Generic CSV: its columns, `ref=..,x=..,y=..[,rot=..][,side=..][,package=..]` (header names).
    #[arg(long, requires = "placement")]
    columns: Option<placement::Columns>,
    /// Generic CSV: the unit of its coordinates, mm, mil or inch.
    #[arg(long, requires = "columns")]
    units: Option<String>,
    /// A pad goes to the nearest component centre within this distance, mm.
    #[arg(long, default_value_t = placement::default_max_distance(), value_parser = super::positive)]
    max_distance_mm: f64,
    /// Stencil thickness, um.
    #[arg(long, default_value_t = 100.0, value_parser = super::positive)]
    stencil_um: f64,
    /// The program's (recipe's) name.
    #[arg(long)]
    name: Option<String>,
    /// The program file to write (TOML; may not be an input).
    #[arg(long)]
    out: PathBuf,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: Args) -> Result<()> {
    use dpsa_formats::files::Input;
    use dpsa_formats::kind::{expect, Kind};
    expect(&a.paste, "--paste", Kind::Gerber, &[])?;
    for (p, what) in [(&a.copper, "--copper"), (&a.outline, "--outline")] {
        if let Some(p) = p {
            expect(p, what, Kind::Gerber, &[])?;
        }
    }
    let mut inputs = vec![Input::File(&a.paste)];
    for p in [&a.copper, &a.outline, &a.placement].into_iter().flatten() {
        inputs.push(Input::File(p));
    }
    dpsa_formats::files::refuse_overwrite("--out", &a.out, &inputs)?;
    dpsa_formats::files::refuse_fifo_output("--out", &a.out)?;
    if a.placement_format == placement::Format::Csv && a.columns.is_none() {
        anyhow::bail!("--placement-format csv needs --columns ref=..,x=..,y=..");
    }
    if a.placement_format != placement::Format::Csv && a.columns.is_some() {
        anyhow::bail!("--columns is for --placement-format csv only");
    }
    let components = match &a.placement {
        Some(p) => Some(placement::ComponentsFile {
            file: p
                .to_str()
                .ok_or_else(|| anyhow::anyhow!("--placement {}: not UTF-8", p.display()))?
                .to_string(),
            format: a.placement_format,
            columns: a.columns.clone(),
            units: a.units.clone(),
            max_distance_mm: a.max_distance_mm,
        }),
        None => None,
    };
    let inp = teach::Inputs {
        paste: a.paste.clone(),
        copper: a.copper.clone(),
        outline: a.outline.clone(),
        components,
        stencil_um: a.stencil_um,
        name: a.name.clone(),
        out: a.out.clone(),
    };
    let t = teach::teach(&inp)?;
    dpsa_formats::files::write_bytes(&a.out, teach::program_text(&t).as_bytes())?;
    let s = &t.summary;
    if a.json {
        out!("{}", serde_json::to_string_pretty(s)?);
        return Ok(());
    }
    warn(&s.warnings);
    out!("{} pads -> {}", s.pads, a.out.display());
    out!(
        "board corner ({:.3}, {:.3}) mm from the {}; board {:.3} x {:.3} mm",
        s.design_origin_mm[0],
        s.design_origin_mm[1],
        s.outline,
        s.board_box_mm[2] - s.board_box_mm[0],
        s.board_box_mm[3] - s.board_box_mm[1]
    );
    out!("pads per family:");
    for (f, n) in &s.families {
        out!("  {n:>6}  {f}");
    }
    out!(
        "  ({} [[override]] entries with the families' default windows)",
        s.overrides
    );
    if s.fiducials.points_mm.is_empty() {
        out!(
            "fiducials: NONE {}: dpsa inspect will register the design by its paste pattern (or fill in [fiducials] points_mm)",
            if s.copper_given {
                "found on the copper layer"
            } else {
                "(no --copper given)"
            }
        );
    } else {
        out!(
            "fiducials: {} found, diameter {:.3} mm:",
            s.fiducials.points_mm.len(),
            s.fiducials.diameter_mm
        );
        for (p, how) in s.fiducials.points_mm.iter().zip(&s.fiducials.how) {
            out!("  ({:.3}, {:.3})  {how}", p[0], p[1]);
        }
    }
    for r in &s.fiducials.rejected {
        out!("  not a fiducial: {r}");
    }
    match &s.naming {
        Some(n) => {
            out!(
                "names: {} of {} pads ({} from the layer's X2, {} from the placement file); {} without a name",
                s.named, s.pads, n.from_layer, n.from_placement, s.unnamed_count
            );
            if !n.components_without_pads.is_empty() {
                out!(
                    "  top components without paste pads: {}",
                    n.components_without_pads.join(", ")
                );
            }
        }
        None => out!(
            "names: {} of {} pads from the layer's X2; {} without a name (give --placement)",
            s.named,
            s.pads,
            s.unnamed_count
        ),
    }
    for u in &s.unnamed {
        out!("  without a name: {u}");
    }
    Ok(())
}
