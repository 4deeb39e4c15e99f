//! `dpsa fpga-bench`: the FPGA front end synthesised for a Lattice ECP5 LFE5U-85F, its
//! co-simulation against the core, and the rates they give (dpsa-fpga's `bench`).

use super::out;
use anyhow::Result;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Pixel units in parallel (output pixels per clock).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=8))]
    lanes: u32,
    /// nextpnr's timing target, MHz.
    #[arg(long, default_value_t = 150, value_parser = clap::value_parser!(u32).range(10..=500))]
    freq: u32,
    /// Pixels per camera row for the board figures (2048: the narrowest power of two whose
    /// three cameras cover the paper board's 168 mm at 28 um).
    #[arg(long, default_value_t = 2048, value_parser = clap::value_parser!(u32).range(1..=65535))]
    width: u32,
    /// Pixels through the co-simulation.
    #[arg(long, default_value_t = 1_000_000)]
    cosim_pixels: u64,
    /// Synthesis logs, netlist, placed design and bitstream.
    #[arg(long, default_value = "target/fpga-synth")]
    out: PathBuf,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
    /// Skip the firmware run with the front end (QEMU): the MCU's share and the board time
    /// are then `null`.
    #[arg(long)]
    no_firmware: bool,
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    let mut r = dpsa_fpga::bench::run(a.lanes, a.freq, a.width, a.cosim_pixels, &a.out)?;
    let codec = dpsa_fpga::bench::synth(0, a.freq, &a.out.join("codec"))?;
    if !a.no_firmware {
        let (m, clocks_per_pixel) = mcu_share(progress)?;
        r.set_codec(codec, clocks_per_pixel);
        if m.width as u32 != a.width {
            anyhow::bail!(
                "the firmware ran at width {} but the board figures are for --width {}",
                m.width,
                a.width
            );
        }
        let p = &m.instructions_per_pixel;
        r.set_mcu(p.total, p.encode, m.realtime.board_seconds);
    } else {
        r.not_measured.push(format!(
            "codec: the row codec synthesises at {:.1} MHz; its clocks per pixel come from the \
             firmware run (--no-firmware)",
            codec.fmax_mhz
        ));
    }
    if a.json {
        out!("{}", serde_json::to_string_pretty(&r)?);
        return Ok(());
    }
    let s = &r.synth;
    out!("part                {}", s.part);
    out!(
        "fmax                {:.1} MHz ({} pixel units)",
        s.fmax_mhz,
        s.lanes
    );
    out!("LUT4                {} of {}", s.luts, s.luts_total);
    out!("flip-flops          {}", s.ffs);
    out!("DSP (18x18)         {} of {}", s.dsp, s.dsp_total);
    out!("block RAM (18 kbit) {} of {}", s.bram, s.bram_total);
    if let Some(c) = &r.codec {
        let cs = &c.synth;
        out!(
            "row codec           {:.1} MHz, {} LUT4, {} flip-flops, {} DSP, {} block RAM; {:.3} clocks a pixel: {:.1} Mpx/s",
            cs.fmax_mhz, cs.luts, cs.ffs, cs.dsp, cs.bram, c.clocks_per_pixel, c.mpx_s
        );
    }
    out!(
        "per camera          {:.1} Mpx/s (goal {:.0})",
        r.mpx_s_per_camera,
        r.goal_mpx_s_per_camera
    );
    out!(
        "paper board         {:.3} s in the fabric ({} rows of {} pixels a camera)",
        r.fabric_board_s,
        r.board_rows,
        r.width
    );
    out!(
        "co-simulation       {} pixels, {} differ from dpsa-core",
        r.cosim_pixels,
        r.cosim_mismatches
    );
    if let (Some(i), Some(e), Some(mb), Some(b)) = (
        r.mcu_instructions_per_pixel,
        r.mcu_encode_instructions_per_pixel,
        r.mcu_board_s,
        r.board_s,
    ) {
        out!(
            "MCU with the fabric {i:.1} instructions per pixel (of which encode {e:.1}; goal {:.0}), {mb:.3} s a board at 600 MHz",
            r.goal_mcu_instructions_per_pixel
        );
        out!("paper board         {b:.3} s (the slower of fabric and MCU)");
    }
    for m in &r.not_measured {
        out!("not measured        {m}");
    }
    Ok(())
}

/// The MCU's share with the front end: the default scene (W = 2048, n = 4, 12-bit), its rows
/// computed by the RTL's model, the firmware under QEMU taking them from the fabric log and
/// measuring itself (`dpsa target-run R --front-end --bench`).
fn mcu_share(progress: bool) -> Result<(dpsa_sim::target::BenchReport, f64)> {
    use dpsa_sim::target;
    let dir = tempfile::Builder::new()
        .prefix("dpsa-fpga-bench")
        .tempdir()?;
    let scene = dpsa_sim::simulation::scene::Scene::default();
    dpsa_sim::simulation::simulate::simulate(&scene, 1, dir.path(), false)?;
    let rec = dpsa_sim::simulation::recording::Recording::open(dir.path())?;
    let fe = super::target_run::front_end_run(&rec, 1, true, progress)?;
    let elf = target::firmware_elf(true)?;
    let sizes = target::elf_sizes(&target::read_elf(&elf)?)?;
    let opts = target::RunOptions {
        bench: true,
        echo: target::Echo {
            log: false,
            progress,
        },
        ..target::RunOptions::default()
    };
    let run = target::run_with_fabric(&rec, &elf, opts, Some(fe.logs()))?;
    if run.stream != fe.core_stream {
        anyhow::bail!("the firmware's stream with the front end differs from the core's");
    }
    let raw = run
        .bench
        .ok_or_else(|| anyhow::anyhow!("the firmware wrote no bench figures"))?;
    let (rows, _, clocks) = fe
        .coded
        .ok_or_else(|| anyhow::anyhow!("the fabric's row codec did not run"))?;
    let w = rec.manifest.camera.width as f64;
    Ok((
        target::bench_report(&raw, &sizes)?,
        clocks as f64 / (rows as f64 * w),
    ))
}
