//! The `dpsa` command line: one file per subcommand, each with its arguments (clap) and its
//! printing. The work itself is in the library crates; nothing here computes a figure.
//!
//! The production commands (`program`, `pads`, `inspect`, `decode`) need the production crates
//! only (`dpsa-formats`, `dpsa-gerber`, `dpsa-inspect`, `dpsa-stream`); the others come with the
//! feature `sim` (on by default): the simulator, the reference, calibration, the board map,
//! benches and the firmware tooling, all still in `dpsa-sim`.

pub mod board;
#[cfg(feature = "sim")]
pub mod board_bench;
#[cfg(feature = "sim")]
pub mod calibrate;
#[cfg(feature = "sim")]
pub mod codec_bench;
#[cfg(feature = "sim")]
pub mod compare;
pub mod decode;
#[cfg(feature = "sim")]
pub mod demo;
#[cfg(feature = "sim")]
pub mod fpga_bench;
#[cfg(feature = "sim")]
pub mod frame_bench;
#[cfg(feature = "sim")]
pub mod grr;
pub mod inspect;
#[cfg(feature = "sim")]
pub mod layout;
pub mod line;
pub mod pads;
#[cfg(feature = "sim")]
pub mod pads_bench;
#[cfg(feature = "sim")]
pub mod phase;
#[cfg(feature = "sim")]
pub mod print_process;
pub mod program;
#[cfg(feature = "sim")]
pub mod reconstruct;
pub mod serve;
#[cfg(feature = "sim")]
pub mod simulate;
pub mod spc;
#[cfg(feature = "sim")]
pub mod target_run;

#[cfg(feature = "sim")]
use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
#[cfg(feature = "sim")]
use dpsa_sim::simulation::{recording::Recording, scene::Scene};
#[cfg(feature = "sim")]
use std::path::Path;

#[derive(Parser)]
#[command(
    name = "dpsa",
    version,
    about = "3D solder-paste measurement with the dynamic phase-shift algorithm (D-PSA)"
)]
#[cfg_attr(
    feature = "sim",
    command(
        long_about = "Simulates conveyor recordings with ground truth, runs the same fixed-point core as the \
frame-grabber firmware on them, and compares it with an independent f64 reference, a conventional \
4-step PSP baseline and the Cramer-Rao bound.\n\nStart with `dpsa demo`."
    )
)]
#[cfg_attr(
    not(feature = "sim"),
    command(
        long_about = "The production host (built without the simulator): the inspection program \
from a board's design files (`program`), its paste layer as pads (`pads`), a board map judged pad by \
pad (`inspect`) and the frame grabbers' packet streams decoded (`decode`)."
    )
)]
pub struct Cli {
    /// Hide progress bars.
    #[arg(long, global = true)]
    pub quiet: bool,
    #[command(subcommand)]
    pub cmd: Cmd,
}

#[derive(Subcommand)]
pub enum Cmd {
    /// Simulate a recording (frames, manifest, ground truth) of a scene.
    #[cfg(feature = "sim")]
    Simulate(simulate::Args),
    /// Calibrate a camera array from its calibration recording; write the calibration file.
    #[cfg(feature = "sim")]
    Calibrate(calibrate::Args),
    /// One board height map in mm from an array recording and its calibration.
    Board(board::Args),
    /// Write a generated paste layer (Gerber X2): the paper's board or the small test board.
    #[cfg(feature = "sim")]
    Layout(layout::Args),
    /// Run the fixed-point core on a recording through its streaming API; write the packet stream.
    #[cfg(feature = "sim")]
    Reconstruct(reconstruct::Args),
    /// Compare the fixed-point core with the f64 reference, the PSP baseline, the CRB and the truth.
    #[cfg(feature = "sim")]
    Compare(compare::Args),
    /// A board's top paste layer (Gerber RS-274X / X2) as pads: count, bounding box, area
    /// histogram, aperture classes, X2 names.
    Pads(pads::Args),
    /// Inspect a board map pad by pad against an inspection program (the paste layer, windows,
    /// fiducials): volume, area, height, offset, bridges, shape; pass / warn / fail per pad;
    /// pads.csv, report.json, an IPC-CFX UnitsInspected message, an overview and a defect
    /// gallery.
    Inspect(inspect::Args),
    /// Teach: an inspection program from the design files: the top paste layer, the copper
    /// layer (fiducials), the outline (board corner) and a pick-and-place file (pad names);
    /// per-family default windows; prints what it found.
    Program(Box<program::Args>),
    /// Gauge R&R of the inspection in the AIAG form: the same printed board under several
    /// set-ups of the simulated machine (calibration and placement), several times each;
    /// repeatability, reproducibility, %GR&R, ndc, and each pad's stated uncertainty against
    /// the scatter.
    #[cfg(feature = "sim")]
    Grr(grr::Args),
    /// Phase of an ordinary phase-shifting image stack (PNG, JPEG, TIFF; 8 or 16 bit), fixed-point
    /// core and f64 reference side by side.
    #[cfg(feature = "sim")]
    Phase(phase::Args),
    /// Decode a packet stream: report good/corrupt packets and optionally write images.
    Decode(decode::Args),
    /// The line: boards one after another, live from the frame grabbers, stitched, inspected
    /// and stored (`run`); its configuration (`init`); simulated frame grabbers (`send`); the
    /// boards stored (`boards`); the store's benchmark (`store-bench`).
    Line(line::Args),
    /// Statistical process control of the print from the line's store: per pad, component,
    /// package family and board the capability (Cp, Cpk, Pp, Ppk), I-MR and X-bar/S charts,
    /// Western Electric and Nelson rules, alarms; tables (CSV) and charts (SVG, PNG).
    Spc(spc::Args),
    /// The operator's web pages over the line's store (read-only; loopback unless --bind):
    /// the line's newest boards, a board's failures and print, a pad's values and history.
    Serve(serve::Args),
    /// A simulated print process over a run of boards (in-control scatter, steps, drift,
    /// clogging and cleans, viscosity) written into a new line store, for trying `dpsa spc`
    /// on a process whose changes are known.
    #[cfg(feature = "sim")]
    PrintProcess(print_process::Args),
    /// Benchmark the row codec against lz4, zstd, heatshrink and PNG on the same height rows,
    /// with the entropy of its predictor's residuals and the noise floor.
    #[cfg(feature = "sim")]
    CodecBench(codec_bench::Args),
    /// Synthesise the FPGA front end for a Lattice ECP5 LFE5U-85F (yosys, nextpnr-ecp5;
    /// installs them if missing), co-simulate it against the core, and print fmax,
    /// resources and the rates they give; as JSON with --json.
    #[cfg(feature = "sim")]
    FpgaBench(fpga_bench::Args),
    /// Benchmark the recording frame formats (16-bit PNG, compressed .zfr) on a recording's
    /// frames: size and encode/decode speed, as JSON.
    #[cfg(feature = "sim")]
    FrameBench(frame_bench::Args),
    /// Benchmark the whole board: every camera's frames in memory, the core on every camera,
    /// provenance, unwrap, resampling, blending and every pad of the recording's program
    /// judged, timed per stage, beside a numpy float64 least-squares phase of the same frames;
    /// then the rows paced at the conveyor rate (as the frame grabbers send them, and again
    /// with the core on this host) and the latency from the last row to the last verdict; as
    /// JSON.
    #[cfg(feature = "sim")]
    BoardBench(board_bench::Args),
    /// Benchmark the paste-layer reader on synthetic layers of up to 10^6 objects (flashes,
    /// apertures, arcs, strokes, regions), each read in a child process: time, peak memory,
    /// pads or the refusal; as JSON.
    #[cfg(feature = "sim")]
    PadsBench(pads_bench::Args),
    /// Run the firmware under QEMU (Cortex-M7, mps2-an500) on a recording: the same core on the
    /// target, writing the packet stream it emitted; `--bench` adds its measured figures.
    #[cfg(feature = "sim")]
    TargetRun(target_run::Args),
    /// The main job: simulate the default scene, reconstruct, compare, write images, summarise.
    #[cfg(feature = "sim")]
    Demo(demo::Args),
}

/// `println!` that never panics: a closed stdout (e.g. `dpsa ... | head`) ends the program
/// quietly instead of panicking.
macro_rules! out {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let mut o = std::io::stdout().lock();
        if let Err(e) = writeln!(o, $($t)*) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                std::process::exit(0);
            }
            return Err(anyhow::Error::new(e).context("writing to stdout"));
        }
    }};
}
pub(crate) use out;

#[cfg(feature = "sim")]
/// `default` for the built-in scene, or a scene TOML file. Prints the scene's warnings.
pub fn load_scene(spec: &str) -> Result<Scene> {
    let scene = if spec == "default" {
        Scene::default()
    } else {
        Scene::load(spec)? // the error names the file
    };
    warn(&scene.warnings());
    Ok(scene)
}

#[cfg(feature = "sim")]
/// Opens a recording directory, naming it in the error. Prints the manifest's warnings.
pub fn open(dir: &Path) -> Result<Recording> {
    let rec = Recording::open(dir).with_context(|| format!("recording {}", dir.display()))?;
    warn(&rec.manifest.warnings());
    Ok(rec)
}

#[cfg(feature = "sim")]
/// Puts camera `camera`'s calibration from the array calibration file `path` into `rec`'s
/// manifest (`reconstruct --cal`, `target-run --cal`: what one frame grabber of the array runs
/// with); `camera` defaults to the manifest's camera id. A missing camera or a calibration of
/// another frame size is refused.
pub fn apply_cal(rec: &mut Recording, path: &Path, camera: Option<u8>) -> Result<()> {
    let cal = dpsa_sim::calibration::CalFile::load(path)?;
    let id = camera.unwrap_or(rec.manifest.camera.id);
    if usize::from(id) >= cal.camera.len() {
        anyhow::bail!(
            "{}: no camera {id} (the calibration has {} cameras)",
            path.display(),
            cal.camera.len()
        );
    }
    dpsa_sim::calibration::apply(&cal, usize::from(id), &mut rec.manifest)?;
    rec.manifest
        .validate()
        .map_err(|e| anyhow::anyhow!("the calibrated manifest is invalid: {e}"))
}

/// The services' log (`line run`, `serve`): timestamped on stderr, `info` unless `RUST_LOG`
/// says otherwise, colour only on a terminal.
pub fn log_to_stderr() {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
}

/// Prints each warning on stderr as `warning: ...`.
pub fn warn(warnings: &[String]) {
    for w in warnings {
        eprintln!("warning: {w}");
    }
}

/// clap value parser: a finite number (no NaN or infinity).
pub fn finite(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .trim()
        .parse()
        .map_err(|_| format!("{s:?} is not a number"))?;
    if v.is_finite() {
        Ok(v)
    } else {
        Err(format!("{s} is not a finite number"))
    }
}

#[cfg(feature = "sim")]
/// clap value parser: a finite number >= 0.
pub fn non_negative(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v >= 0.0 {
        Ok(v)
    } else {
        Err(format!("{s} is negative, expected a value >= 0"))
    }
}

/// clap value parser: a finite number > 0 (e.g. for `decode --lsb-um`).
pub fn positive(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v > 0.0 {
        Ok(v)
    } else {
        Err(format!("{s}, expected a value > 0"))
    }
}

#[cfg(feature = "sim")]
/// Largest phase step `dpsa phase` takes, degrees (either sign): 100 turns.
pub const MAX_STEP_DEG: f64 = 36_000.0;

#[cfg(feature = "sim")]
/// clap value parser: a phase step in degrees, finite and within +/- [`MAX_STEP_DEG`].
pub fn step_deg(s: &str) -> Result<f64, String> {
    let v = finite(s)?;
    if v.abs() <= MAX_STEP_DEG {
        Ok(v)
    } else {
        Err(format!(
            "{s} degrees, expected -{MAX_STEP_DEG}..={MAX_STEP_DEG}"
        ))
    }
}
