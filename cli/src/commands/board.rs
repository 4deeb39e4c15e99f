//! `dpsa board`: an array recording and its calibration into one board height map. The
//! production build takes the rows from the cameras' streams (`--streams`: `dpsa_board::run`,
//! reading only `array.json` of the recording); the simulator's (feature `sim`) can also run
//! the core on the recording and compares the map with the simulated board's truth.

use super::out;
use anyhow::{Context, Result};
use dpsa_formats::calibration::CalFile;
use dpsa_formats::{files, kind};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Array board recording (`dpsa simulate --scene ARRAY.toml --out DIR`, or a camera
    /// array's, docs/recording.md). With --streams only its array.json is read.
    dir: PathBuf,
    /// Calibration file of the array (`dpsa calibrate`).
    #[arg(long)]
    cal: PathBuf,
    /// Output directory: heights.png, heights_um.tiff, heights.colour.png, camera.png,
    /// board.json. New, empty or an earlier board map (replaced whole); it may not be, hold
    /// or lie inside an input.
    #[arg(long)]
    out: PathBuf,
    /// Print the figures as JSON.
    #[arg(long)]
    json: bool,
    /// Take the rows from the cameras' packet streams (one per camera, any order; matched by
    /// the camera id in their headers), e.g. `dpsa reconstruct` or `dpsa target-run` with
    /// `--cal CAL --camera I`, instead of running the core (the production build has no core
    /// on recordings: it needs them). Rows a stream lost stay invalid in the map and are
    /// reported (exit status 2).
    #[arg(long, num_args = 1.., value_name = "STREAM")]
    streams: Vec<PathBuf>,
    /// Write `heights.colour.png` at the map's full size (about 2 s more on the paper board)
    /// instead of a preview at most 2048 px on its longer side.
    #[arg(long)]
    full_colour: bool,
    /// The board's inspection program (`program.toml`): the map takes the paste's
    /// reflectance (its `[reflectance]`, with its stencil thickness) out of the deposits'
    /// walls. Default: the recording's own `DIR/program.toml` when it has one; without either
    /// nothing is taken out (the map says which in `paste_reflectance`).
    #[arg(long)]
    program: Option<PathBuf>,
    /// Draw `heights.colour.png` of the absolute heights (the board's bow and warp in it)
    /// instead of the height above the local board surface.
    #[arg(long)]
    absolute_colour: bool,
    /// Skip the comparison with the simulator's board truth (about 35 s on the paper board;
    /// `truth` is then null).
    #[cfg(feature = "sim")]
    #[arg(long)]
    no_truth: bool,
}

/// Builds the map; returns the exit status: 0, or 2 when a stream was damaged or incomplete
/// (the map is written with the rows it lost invalid), as `dpsa decode`, or when the map
/// itself shows it is wrong or useless (`MapReport::warnings`).
pub fn run(a: Args, progress: bool) -> Result<i32> {
    #[cfg(not(feature = "sim"))]
    if a.streams.is_empty() {
        anyhow::bail!(
            "this build has no core on recordings (it is built without the feature `sim`): \
             give the cameras' packet streams with --streams"
        );
    }
    kind::expect(&a.dir, "DIR", kind::Kind::ArrayBoardRecording, &[])?;
    kind::expect(&a.cal, "--cal", kind::Kind::Calibration, &[])?;
    for s in &a.streams {
        kind::expect(s, "--streams", kind::Kind::Stream, &[])?;
    }
    if let Some(p) = &a.program {
        kind::expect(p, "--program", kind::Kind::Program, &[])?;
    }
    let mut inputs = vec![files::Input::Dir(&a.dir), files::Input::File(&a.cal)];
    inputs.extend(a.streams.iter().map(|p| files::Input::File(p)));
    inputs.extend(a.program.iter().map(|p| files::Input::File(p)));
    // The map directory may not be, hold or lie inside an input; it replaces only an
    // earlier map (checked again when it is swapped in).
    files::refuse_overwrite_dir("--out", &a.out, &inputs)?;
    dpsa_board::output::check_destination(&a.out)?;
    let cal = CalFile::load(&a.cal)?;
    // The program given, else the recording's own (the simulator writes one beside its
    // frames), else none.
    let paste = match &a.program {
        Some(p) => paste_of(p)?,
        None => {
            let own = a.dir.join("program.toml");
            if own.is_file() {
                paste_of(&own).context(
                    "the recording's own program (the map takes the paste's reflectance \
                     from it; name another with --program)",
                )?
            } else {
                Default::default()
            }
        }
    };
    let outputs = dpsa_board::output::Outputs {
        full_colour: a.full_colour,
        absolute_colour: a.absolute_colour,
    };
    #[cfg(feature = "sim")]
    let (r, json, summary) = {
        use dpsa_sim::board::run::Source;
        let source = if a.streams.is_empty() {
            Source::Core
        } else {
            Source::Streams(&a.streams)
        };
        let opts = dpsa_sim::board::run::Options {
            progress,
            outputs,
            truth: !a.no_truth,
            paste,
        };
        let r = dpsa_sim::board::run::run_shown(&a.dir, &cal, &a.out, source, &opts)?;
        let json = a
            .json
            .then(|| serde_json::to_string_pretty(&r))
            .transpose()?;
        (r.map.clone(), json, r.summary())
    };
    #[cfg(not(feature = "sim"))]
    let (r, json, summary) = {
        let r = dpsa_board::run::from_streams(
            &a.dir, &cal, &a.streams, &a.out, progress, outputs, paste,
        )?
        .report;
        let json = a
            .json
            .then(|| serde_json::to_string_pretty(&r))
            .transpose()?;
        let summary = r.summary();
        (r, json, summary)
    };
    let mut status = r.streams.as_ref().map_or(0, |s| s.status);
    for (i, &u) in r.pixels.unplaced_rows.iter().enumerate() {
        if u > 0 {
            eprintln!(
                "warning: camera {i}: {u} rows arrived whose frames the trigger log does not confirm (a trigger record lost); they stay invalid in the map (exit status 2)"
            );
            status = 2;
        }
    }
    for w in &r.warnings {
        eprintln!("warning: {w} (the map is written; exit status 2)");
        status = 2;
    }
    if let Some(s) = &r.streams {
        for c in s.cameras.iter().filter(|c| c.status != 0) {
            eprintln!(
                "warning: camera {} stream {}: {} board rows lost ({} damaged, {} missing packets{}); \
                 they stay invalid in the map",
                c.camera,
                c.file,
                c.missing_rows,
                c.damaged_packets,
                c.missing_packets,
                if c.end_packet {
                    ""
                } else {
                    ", no end packet: cut off"
                }
            );
        }
        if s.damaged {
            eprintln!(
                "warning: {} board pixels are invalid for lack of stream rows (exit status 2)",
                s.gap_board_pixels
            );
        }
    }
    if let Some(json) = json {
        out!("{json}");
        return Ok(status);
    }
    out!("{summary} -> {}", a.out.display());
    Ok(status)
}

/// The paste's reflectance of the program at `path` (its `[reflectance]` and stencil), which
/// the map takes out of the deposits' walls.
pub fn paste_of(path: &std::path::Path) -> Result<dpsa_board::places::PasteReflectance> {
    let p = dpsa_inspect::program::Program::load(path)?;
    Ok(dpsa_board::places::PasteReflectance::new(
        p.reflectance.background_step,
        p.stencil_um,
    ))
}
