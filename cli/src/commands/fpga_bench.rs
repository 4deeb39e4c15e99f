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
}

pub fn run(a: Args) -> Result<()> {
    let r = dpsa_fpga::bench::run(a.lanes, a.freq, a.width, a.cosim_pixels, &a.out)?;
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
    for m in &r.not_measured {
        out!("not measured        {m}");
    }
    Ok(())
}
