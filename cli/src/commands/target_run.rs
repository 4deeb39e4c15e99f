//! `dpsa target-run`: the firmware under QEMU on a recording, its stream and its bench figures.

use super::{open, out};
use anyhow::{Context, Result};
use dpsa_sim::{files, stream, target};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Recording directory.
    recording: PathBuf,
    /// Packet stream output file (required unless --bench or --link).
    #[arg(long, required_unless_present_any = ["bench", "link"])]
    out: Option<PathBuf>,
    /// A frame grabber on the line: the stream goes out on the board's UART, which QEMU
    /// carries as a TCP connection to this address (a camera's `listen` of `dpsa line run`).
    #[arg(long, conflicts_with_all = ["out", "bench"])]
    link: Option<std::net::SocketAddr>,
    /// Codec intra period of the stream (as for `dpsa reconstruct`).
    #[arg(long, default_value_t = dpsa_core::packets::STREAM_INTRA_PERIOD,
          value_parser = super::reconstruct::intra_period)]
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
    /// Array calibration file (`dpsa calibrate`): the frame grabber runs with camera
    /// `--camera`'s encoder scale, fringe period, reference-phase table and height per turn
    /// instead of the manifest's (as `dpsa reconstruct --cal`).
    #[arg(long)]
    cal: Option<PathBuf>,
    /// Camera of `--cal` (default: the manifest's camera id).
    #[arg(long, requires = "cal")]
    camera: Option<u8>,
    /// The frame grabber with its FPGA front end (`docs/fpga.md`): the RTL's Verilator model
    /// computes every row on the host first, through the core's front-end seam, and must give
    /// the core's own stream byte for byte (else the run stops); the firmware then takes the
    /// rows from that fabric log as from the fabric's DMA, and its bench figures are the
    /// MCU's share. The rows are coded by the fabric's row codec (its model too) unless
    /// `--mcu-codec`. Needs `verilator`.
    #[arg(long, conflicts_with = "link")]
    front_end: bool,
    /// With `--front-end`: code the rows on the MCU (the core's encoder) instead of in the
    /// fabric, to measure what the codec costs the MCU.
    #[arg(long, requires = "front_end")]
    mcu_codec: bool,
}

/// What the front end's host run found.
pub(crate) struct FrontEndRun {
    /// The fabric log (in `_dir`).
    pub(crate) log: PathBuf,
    /// The payload log of the fabric's row codec (in `_dir`), unless the MCU codes.
    pub(crate) payloads: Option<PathBuf>,
    /// Rows the fabric's codec coded, their payload bytes and the codec's clocks.
    pub(crate) coded: Option<(u64, u64, u64)>,
    _dir: tempfile::TempDir,
    rows: u64,
    pixels: u64,
    /// The core's own stream of the recording (the firmware's must equal it).
    pub(crate) core_stream: Vec<u8>,
}

impl FrontEndRun {
    /// The logs for the firmware.
    pub(crate) fn logs(&self) -> target::FabricLogs<'_> {
        target::FabricLogs {
            rows: &self.log,
            payloads: self.payloads.as_deref(),
        }
    }
}

/// Runs the recording through the RTL's model as the pipeline's front end, writing the fabric
/// log, and checks its stream against the core's.
pub(crate) fn front_end_run(
    rec: &dpsa_sim::simulation::recording::Recording,
    intra_period: u32,
    fabric_codec: bool,
    progress: bool,
) -> Result<FrontEndRun> {
    use dpsa_fpga::{front, model::Model};
    let core = dpsa_sim::reconstruct::config(&rec.manifest)?;
    let dir = tempfile::Builder::new().prefix("dpsa-fabric").tempdir()?;
    let create = |name: &str| -> Result<Box<dyn std::io::Write>> {
        let path = dir.path().join(name);
        let file = std::fs::File::create(&path)
            .with_context(|| format!("creating the front end's log {}", path.display()))?;
        Ok(Box::new(std::io::BufWriter::new(file)))
    };
    let mut fabric =
        front::Fabric::new(&Model::repo()?, core.cfg, &core.ref_phase, core.columns())?;
    fabric.log_to(create("fabric.dpsf")?, rec.run_id())?;
    let mut coder = match fabric_codec {
        false => None,
        true => {
            let w = core.cfg.width as usize;
            let mut c = front::Coder::new(&Model::codec_repo()?, w, intra_period)?;
            c.log_to(create("payloads.dpsp")?, rec.run_id())?;
            Some(c)
        }
    };
    let res = dpsa_sim::reconstruct::run_front_end(
        rec,
        Vec::new(),
        intra_period,
        &mut fabric,
        coder
            .as_mut()
            .map(|c| c as &mut dyn dpsa_core::offload::RowCoder),
        progress,
    );
    let stream = match res {
        Ok((_, s)) => s,
        Err(e) => match (fabric.error(), coder.as_ref().and_then(|c| c.error())) {
            (Some(why), _) => anyhow::bail!("the front end's pixel model failed: {why} ({e})"),
            (_, Some(why)) => anyhow::bail!("the front end's codec model failed: {why} ({e})"),
            _ => return Err(e.into()),
        },
    };
    let (rows, pixels) = (fabric.rows, fabric.pixels);
    fabric.finish()?;
    let coded = match coder {
        None => None,
        Some(c) => {
            let figures = (c.rows, c.bytes, c.clocks);
            c.finish()?;
            Some(figures)
        }
    };
    let (_, core_stream) = dpsa_sim::reconstruct::run_with(rec, Vec::new(), intra_period, false)?;
    if stream != core_stream {
        let at = stream
            .iter()
            .zip(&core_stream)
            .position(|(a, b)| a != b)
            .unwrap_or(stream.len().min(core_stream.len()));
        anyhow::bail!(
            "the front end's stream differs from the core's at byte {at} ({} against {} bytes): \
             the RTL's rows or payloads are not the core's",
            stream.len(),
            core_stream.len()
        );
    }
    Ok(FrontEndRun {
        log: dir.path().join("fabric.dpsf"),
        payloads: fabric_codec.then(|| dir.path().join("payloads.dpsp")),
        coded,
        _dir: dir,
        rows,
        pixels,
        core_stream,
    })
}

/// Runs the firmware on the recording, writes the stream to `--out` and prints a summary (or
/// one JSON object with `--json`). The decoded firmware log goes to stderr.
pub fn run(a: Args, progress: bool) -> Result<()> {
    dpsa_sim::kind::expect(&a.recording, "DIR", dpsa_sim::kind::Kind::Recording, &[])?;
    if let Some(c) = &a.cal {
        dpsa_sim::kind::expect(c, "--cal", dpsa_sim::kind::Kind::Calibration, &[])?;
    }
    // Before any work: the ELF a regular file of bounded size, the output not a FIFO.
    if let Some(elf) = &a.elf {
        target::read_elf(elf)?;
    }
    if let Some(out) = &a.out {
        files::refuse_fifo_output("--out", out)?;
        let mut inputs = vec![files::Input::Dir(&a.recording)];
        if let Some(elf) = &a.elf {
            inputs.push(files::Input::File(elf));
        }
        if let Some(cal) = &a.cal {
            inputs.push(files::Input::File(cal));
        }
        files::refuse_overwrite("--out", out, &inputs)?;
    }
    let mut rec = open(&a.recording)?;
    if let Some(path) = &a.cal {
        super::apply_cal(&mut rec, path, a.camera)?;
    }
    let elf = match a.elf {
        Some(e) => e,
        None => target::firmware_elf(true)?,
    };
    let elf_bytes = target::read_elf(&elf)?;
    let sizes =
        target::elf_sizes(&elf_bytes).with_context(|| format!("firmware ELF {}", elf.display()))?;
    let opts = target::RunOptions {
        intra_period: a.intra_period,
        bench: a.bench,
        echo: target::Echo {
            log: true,
            progress,
        },
        link: a.link,
    };
    let fe = if a.front_end {
        Some(front_end_run(&rec, a.intra_period, !a.mcu_codec, progress)?)
    } else {
        None
    };
    let logs = fe.as_ref().map(|f| f.logs());
    let run = target::run_with_fabric(&rec, &elf, opts, logs)?;
    if let Some(fe) = &fe {
        if run.stream != fe.core_stream {
            anyhow::bail!(
                "the firmware's stream with the front end differs from the core's ({} against {} bytes)",
                run.stream.len(),
                fe.core_stream.len()
            );
        }
    }
    if let Some(link) = a.link {
        out!(
            "target: the stream went to {link} over the board's UART; {:.1} s in QEMU",
            run.outcome.elapsed.as_secs_f64()
        );
        return Ok(());
    }
    if let Some(out) = &a.out {
        files::write_bytes(out, &run.stream)?;
    }
    let (map, rep) = stream::decode_stream(&run.stream, rec.manifest.calibration.height_lsb_um);
    let report = run
        .bench
        .as_ref()
        .map(|raw| target::bench_report(raw, &sizes))
        .transpose()?;
    let seconds = run.outcome.elapsed.as_secs_f64();
    if a.json {
        let mut v = match &report {
            Some(r) => serde_json::to_value(r)?,
            None => serde_json::json!({
                "flash_bytes": sizes.flash,
                "ram_bytes": { "static": sizes.static_ram },
                "elf_sections": sizes.sections,
            }),
        };
        v["stream"] = serde_json::json!({
            "bytes": run.stream.len(),
            "packets": rep.ok,
            "corrupt": rep.corrupt,
            "rows": map.rows.len(),
            "triggers": rep.stream.triggers,
            "file": a.out.as_ref().map(|p| p.display().to_string()),
        });
        if let Some(fe) = &fe {
            v["front_end"] = serde_json::json!({
                "rows": fe.rows,
                "pixels": fe.pixels,
                "model": "fpga/rtl (Verilator)",
                "codec": if fe.coded.is_some() { "fabric" } else { "mcu" },
                "coded_rows": fe.coded.map(|c| c.0),
                "payload_bytes": fe.coded.map(|c| c.1),
                "codec_clocks": fe.coded.map(|c| c.2),
                "stream_equals_core": true,
            });
        }
        v["elf"] = serde_json::json!(elf.display().to_string());
        v["qemu_seconds"] = serde_json::json!(seconds);
        out!("{}", serde_json::to_string_pretty(&v)?);
        return Ok(());
    }
    let dest = a
        .out
        .as_ref()
        .map(|p| format!(" -> {}", p.display()))
        .unwrap_or_default();
    if let Some(fe) = &fe {
        out!(
            "front end: {} rows ({} pixels) from the RTL's model, coded by the {}; the host's and \
             the firmware's streams with it equal the core's byte for byte",
            fe.rows,
            fe.pixels,
            if fe.coded.is_some() {
                "fabric's row codec"
            } else {
                "MCU"
            }
        );
    }
    let mut text = format!(
        "target: {} packets ({} corrupt), {} bytes{dest}; {seconds:.1} s in QEMU\n",
        rep.ok,
        rep.corrupt,
        run.stream.len()
    );
    match &report {
        Some(r) => text.push_str(&r.summary()),
        None => text.push_str(&format!(
            "firmware: flash {} bytes, static RAM {} bytes",
            sizes.flash, sizes.static_ram
        )),
    }
    out!("{text}");
    Ok(())
}
