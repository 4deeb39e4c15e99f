//! `dpsa`: simulate recordings, run the fixed-point D-PSA core on them, compare it with an f64
//! reference and the ground truth, and decode packet streams.

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use dpsa_sim::{jobs, packets, recording::Recording, scene::Scene, simulate, stack};
use std::path::{Path, PathBuf};

#[derive(Parser)]
#[command(name = "dpsa", version, about = "3D solder-paste measurement with the dynamic phase-shift algorithm (D-PSA)",
    long_about = "Simulates conveyor recordings with ground truth, runs the same fixed-point core as the \
frame-grabber firmware on them, and compares it with an independent f64 reference, a conventional \
4-step PSP baseline and the Cramer-Rao bound.\n\nStart with `dpsa demo`.")]
struct Cli {
    /// Hide progress bars.
    #[arg(long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Simulate a recording (frames, manifest, ground truth) of a scene.
    Simulate {
        /// `default` for the built-in scene, or a scene TOML file (knobs: README, "Scene files").
        #[arg(long, default_value = "default")]
        scene: String,
        /// Random seed (layout, motion and noise).
        #[arg(long)]
        seed: Option<u64>,
        /// Output recording directory.
        #[arg(long)]
        out: PathBuf,
    },
    /// Run the fixed-point core on a recording through its streaming API; write the packet stream.
    Reconstruct {
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
    },
    /// Compare the fixed-point core with the f64 reference, the PSP baseline, the CRB and the truth.
    Compare {
        /// Recording directory.
        dir: PathBuf,
        /// Print one JSON object instead of a summary.
        #[arg(long)]
        json: bool,
    },
    /// Phase of an ordinary phase-shifting image stack (PNG, JPEG, TIFF; 8 or 16 bit), fixed-point
    /// core and f64 reference side by side.
    Phase {
        /// An image of the stack (repeat, 3 to 8 images, in step order).
        #[arg(long = "image", required = true)]
        images: Vec<PathBuf>,
        /// Phase step of the matching image in degrees (repeat, one per --image):
        /// I = B + C cos(phase + step).
        #[arg(long = "step", required = true, allow_negative_numbers = true)]
        steps: Vec<f64>,
        /// Minimum fringe modulation C of a valid pixel, DN (default: 4% of full scale).
        #[arg(long)]
        min_modulation: Option<f64>,
        /// Print one JSON object.
        #[arg(long)]
        json: bool,
        /// Write the fixed-point wrapped phase as an 8-bit PNG (0 = invalid).
        #[arg(long)]
        png: Option<PathBuf>,
    },
    /// Decode a packet stream: report good/corrupt packets and optionally write images.
    Decode {
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
    },
    /// Benchmark the row codec against lz4, zstd, heatshrink and PNG on the same height rows,
    /// with the entropy of its predictor's residuals and the noise floor.
    CodecBench {
        /// A recording directory (run through the fixed-point core) or a packet stream file.
        input: PathBuf,
        /// Print one JSON object.
        #[arg(long)]
        json: bool,
    },
    /// Run the firmware under QEMU (Cortex-M7, mps2-an500) on a recording: the same core on the
    /// target, writing the packet stream it emitted; `--bench` adds its measured figures.
    TargetRun {
        /// Recording directory.
        recording: PathBuf,
        /// Packet stream output file (required unless --bench).
        #[arg(long, required_unless_present = "bench")]
        out: Option<PathBuf>,
        /// Codec intra period of the stream (as for `dpsa reconstruct`).
        #[arg(long, default_value_t = dpsa_core::packets::STREAM_INTRA_PERIOD)]
        intra_period: u32,
        /// Firmware ELF to run; default: build it with `firmware/build.sh` if needed.
        #[arg(long)]
        elf: Option<PathBuf>,
        /// Have the firmware measure itself: instructions per pixel by stage, per window
        /// solve, flash, static RAM, state RAM and stack high-water mark.
        #[arg(long)]
        bench: bool,
        /// Print one JSON object.
        #[arg(long)]
        json: bool,
    },
    /// The main job: simulate the default scene, reconstruct, compare, write images, summarise.
    Demo {
        /// Working directory for the recording, stream, images and report.
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
        /// Random seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Scene: `default` or a scene TOML file.
        #[arg(long, default_value = "default")]
        scene: String,
    },
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

fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn load_scene(spec: &str) -> Result<Scene> {
    if spec == "default" {
        Ok(Scene::default())
    } else {
        Scene::load(spec).with_context(|| format!("scene {spec}"))
    }
}

fn open(dir: &Path) -> Result<Recording> {
    Recording::open(dir).with_context(|| format!("recording {}", dir.display()))
}

fn run(cli: Cli) -> Result<()> {
    let progress = !cli.quiet;
    match cli.cmd {
        Cmd::Simulate { scene, seed, out } => {
            let sc = load_scene(&scene)?;
            let seed = seed.unwrap_or(sc.seed);
            let s = simulate::simulate(&sc, seed, &out, progress)?;
            out!(
                "simulated {} frames of {}x{} ({} deposits) into {}",
                s.frames, s.rows, s.width, s.deposits_placed, out.display()
            );
        }
        Cmd::Reconstruct { dir, out, png, intra_period } => {
            let rec = open(&dir)?;
            let file = std::fs::File::create(&out).with_context(|| format!("creating {}", out.display()))?;
            let writer = std::io::BufWriter::new(file);
            let (stats, _) = dpsa_sim::reconstruct::run_with(&rec, writer, intra_period, progress)?;
            out!("{} packets, {} bytes -> {}", stats.packets, stats.bytes, out.display());
            if let Some(png) = png {
                let bytes = std::fs::read(&out)?;
                let (map, _) = packets::decode_stream(&bytes, rec.manifest.calibration.height_lsb_um);
                let colour = jobs::write_pngs(&map, &png)?;
                out!("heights -> {}, false colour -> {}", png.display(), colour.display());
            }
        }
        Cmd::Compare { dir, json } => {
            let rec = open(&dir)?;
            let (cmp, _) = jobs::compare(&rec, progress)?;
            if json {
                out!("{}", serde_json::to_string_pretty(&cmp)?);
            } else {
                out!("{}", cmp.summary());
            }
        }
        Cmd::Phase { images, steps, min_modulation, json, png } => {
            let st = stack::Stack::load(&images, &steps)?;
            let full = if st.bit_depth == 8 { 255.0 } else { 65535.0 };
            let (ph, rep) = stack::run(&st, min_modulation.unwrap_or(0.04 * full))?;
            if let Some(png) = png {
                dpsa_sim::images::write_phase_png(&ph.fixed, st.width, &png)?;
            }
            if json {
                out!("{}", serde_json::to_string_pretty(&rep)?);
            } else {
                out!(
                    "{}x{}: {} valid pixels of {} ({} differ in validity); fixed vs f64 phase: rms {:.2e} rad, max {:.2e} rad",
                    rep.width, rep.height, rep.valid_pixels, rep.total_pixels, rep.valid_mismatch,
                    rep.fixed_vs_ref_rms_rad, rep.fixed_vs_ref_max_rad
                );
            }
        }
        Cmd::Decode { stream, png, lsb_um, json } => {
            let bytes = std::fs::read(&stream).with_context(|| format!("reading {}", stream.display()))?;
            let (map, rep) = packets::decode_stream(&bytes, lsb_um);
            if let Some(png) = png {
                if map.rows.is_empty() {
                    bail!("no decodable rows: nothing to draw");
                }
                jobs::write_pngs(&map, &png)?;
            }
            let out = serde_json::json!({
                "packets": { "ok": rep.ok, "corrupt": rep.corrupt, "resynced": rep.resynced },
                "rows": { "decoded": map.rows.len(), "valid": map.rows.iter().filter(|r| r.is_valid()).count() },
                "pixels": { "valid": map.valid_pixels(), "total": map.total_pixels() },
                "damage": rep.damage,
            });
            if json {
                out!("{}", serde_json::to_string_pretty(&out)?);
            } else {
                out!(
                    "{} packets ok, {} corrupt ({} resyncs); {} rows, {} valid pixels",
                    rep.ok, rep.corrupt, rep.resynced, map.rows.len(), map.valid_pixels()
                );
            }
        }
        Cmd::TargetRun { recording, out, intra_period, elf, bench, json } => {
            let rec = open(&recording)?;
            let args = dpsa_sim::target::CliArgs { out: out.as_deref(), intra_period, elf, bench, json, progress };
            out!("{}", dpsa_sim::target::cli(&rec, args)?)
        }
        Cmd::Demo { out, seed, scene } => demo(&out, seed, &scene, progress)?,
        Cmd::CodecBench { input, json } => out!("{}", dpsa_sim::codec_bench::cli(&input, json, progress)?),
    }
    Ok(())
}

fn demo(out: &Path, seed: u64, scene: &str, progress: bool) -> Result<()> {
    let sc = load_scene(scene)?;
    let rec_dir = out.join("recording");
    out!("1/4 simulating the {scene} scene (seed {seed}) into {}", rec_dir.display());
    let s = simulate::simulate(&sc, seed, &rec_dir, progress)?;
    out!(
        "    {} frames of {} rows x {} px, {} solder-paste deposits, {:.0} um per fringe turn",
        s.frames, s.rows, s.width, s.deposits_placed, sc.height_per_turn_um
    );
    let rec = open(&rec_dir)?;
    out!("2/4 reconstructing with the fixed-point core (streaming, line by line)");
    let (stats, bytes, map) = jobs::reconstruct_map(&rec, progress)?;
    let stream = out.join("heights.dpsa");
    std::fs::write(&stream, &bytes).with_context(|| format!("writing {}", stream.display()))?;
    out!(
        "    {} row packets, {} bytes -> {}; core state {} bytes",
        stats.packets, stats.bytes, stream.display(), stats.state_bytes
    );
    out!("3/4 comparing with the f64 reference, the 4-step PSP baseline and the ground truth");
    let cmp = jobs::compare_map(&rec, &map, progress)?;
    let report = out.join("compare.json");
    std::fs::write(&report, serde_json::to_string_pretty(&cmp)?)?;
    out!("4/4 writing images");
    let png = out.join("heights.png");
    let colour = jobs::write_pngs(&map, &png)?;
    out!("    {} (16-bit), {} (false colour)", png.display(), colour.display());
    out!("");
    out!("{}", cmp.summary());
    out!("full report: {}", report.display());
    Ok(())
}
