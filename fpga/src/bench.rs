//! `dpsa fpga-bench`: synthesis figures for a real part, the co-simulation's counts, and what
//! they mean for the paper board.
//!
//! Synthesis is `fpga/synth/run.sh` (yosys `synth_ecp5`, nextpnr-ecp5, ecppack; it installs
//! what is missing), which prints one JSON line; this module runs it, runs the
//! co-simulation, and derives the rates:
//! - `pixels_per_clock`: the pixel units in parallel (`lanes`), each taking one pixel's `n`
//!   samples and giving its `V`, phase, height and flags every clock;
//! - `mpx_s_per_camera = fmax_mhz * pixels_per_clock` (output heights, one front end per
//!   camera);
//! - `fabric_board_s`: the paper board (220 mm at 28 um: 7,858 rows of `width` pixels per
//!   camera, the cameras in parallel) at that rate.
//!
//! The MCU's share per pixel with the front end, and so the whole board's time, come from a
//! firmware run under QEMU with the fabric modelled (`dpsa target-run --front-end --bench`,
//! which the CLI's `fpga-bench` runs on the default scene: [`Report::set_mcu`]); without it
//! they are `null` and `not_measured` says why. The board's time is the slower of the fabric
//! and the MCU (they work in a pipeline, row by row).

use serde::{Deserialize, Serialize};
use std::path::Path;
use std::process::Command;

use crate::cosim;
use crate::model::{Model, ModelError};

/// Why the bench failed.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The synthesis script failed.
    #[error("synthesis failed ({0}); its logs are in the --out folder")]
    Synth(String),
    /// The co-simulation model failed.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// Running the script.
    #[error("running fpga/synth/run.sh: {0}")]
    Io(#[from] std::io::Error),
}

/// What `fpga/synth/run.sh` prints.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Synth {
    /// The device and package.
    pub part: String,
    /// Pixel units in parallel (0 for the codec).
    #[serde(default)]
    pub lanes: u32,
    /// nextpnr's achieved maximum frequency of the pixel clock, MHz.
    pub fmax_mhz: f64,
    /// LUT4s (TRELLIS_COMB) used.
    pub luts: u64,
    /// Flip-flops (TRELLIS_FF) used.
    pub ffs: u64,
    /// 18 x 18 multipliers (MULT18X18D) used.
    pub dsp: u64,
    /// 18 kbit block RAMs (DP16KD) used.
    pub bram: u64,
    /// LUT4s on the part.
    pub luts_total: u64,
    /// Multipliers on the part.
    pub dsp_total: u64,
    /// Block RAMs on the part.
    pub bram_total: u64,
    /// Synthesis, place and route and packing, wall seconds.
    pub seconds: f64,
}

/// The bench's JSON.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    /// Synthesis figures.
    #[serde(flatten)]
    pub synth: Synth,
    /// Output pixels per clock (`lanes`).
    pub pixels_per_clock: u32,
    /// Output heights per second per camera, millions: the pixel units' rate, or the row
    /// codec's when it is slower and measured ([`Report::set_codec`]).
    pub mpx_s_per_camera: f64,
    /// The row codec in the fabric (`null` until [`Report::set_codec`]).
    pub codec: Option<CodecFigures>,
    /// The goal, Mpx/s per camera (twice the paper's rate).
    pub goal_mpx_s_per_camera: f64,
    /// Pixels per camera row assumed for the board.
    pub width: u32,
    /// Board rows of the paper board.
    pub board_rows: u32,
    /// The fabric's time for the paper board, s.
    pub fabric_board_s: f64,
    /// Pixels compared in the co-simulation.
    pub cosim_pixels: u64,
    /// Pixels that differed from dpsa-core.
    pub cosim_mismatches: u64,
    /// Instructions the MCU spends per output pixel with the front end (QEMU count).
    pub mcu_instructions_per_pixel: Option<f64>,
    /// Of which the packet encode (row codec, framing, CRC).
    pub mcu_encode_instructions_per_pixel: Option<f64>,
    /// The goal for the MCU's share, instructions per output pixel.
    pub goal_mcu_instructions_per_pixel: f64,
    /// The MCU's time for the paper board at 600 MHz, IPC 1 (assumed), s.
    pub mcu_board_s: Option<f64>,
    /// The paper board's time with three front ends and their MCUs: the slower of the two, s.
    pub board_s: Option<f64>,
    /// What is `null` above, and why.
    pub not_measured: Vec<String>,
}

/// The paper board: 220 mm along the conveyor at 28 um per pixel.
pub const BOARD_ROWS: u32 = 7858;

/// The row codec in the fabric (`dpsa_codec`): its synthesis and its measured clocks.
#[derive(Clone, Debug, Serialize)]
pub struct CodecFigures {
    /// Synthesis of `dpsa_codec` alone (`run.sh --design codec`).
    #[serde(flatten)]
    pub synth: Synth,
    /// Clocks per pixel the codec's model took on the default scene (first pixel in to last
    /// word out, every row; it takes one pixel a clock and then writes the payload out).
    pub clocks_per_pixel: f64,
    /// Pixels per second it codes at its Fmax, millions.
    pub mpx_s: f64,
}

/// Runs the synthesis script for the pixel units (`lanes` of them) or, with `lanes == 0`, the
/// row codec; timing target `freq_mhz`, logs in `out`.
pub fn synth(lanes: u32, freq_mhz: u32, out: &Path) -> Result<Synth, BenchError> {
    let script = crate::fpga_dir().join("synth").join("run.sh");
    let mut cmd = Command::new("bash");
    cmd.arg(&script);
    if lanes == 0 {
        cmd.args(["--design", "codec"]);
    } else {
        cmd.args(["--lanes", &lanes.to_string()]);
    }
    let res = cmd
        .args(["--freq", &freq_mhz.to_string()])
        .arg("--out")
        .arg(out)
        .stderr(std::process::Stdio::inherit())
        .output()?;
    if !res.status.success() {
        return Err(BenchError::Synth(format!("exit {}", res.status)));
    }
    let text = String::from_utf8_lossy(&res.stdout);
    let line = text.lines().rev().find(|l| l.trim_start().starts_with('{'));
    let line = line.ok_or_else(|| BenchError::Synth("no JSON line printed".into()))?;
    serde_json::from_str(line).map_err(|e| BenchError::Synth(format!("its JSON: {e}")))
}

/// The whole bench: synthesis, `cosim_pixels` pixels of co-simulation, the rates.
pub fn run(
    lanes: u32,
    freq_mhz: u32,
    width: u32,
    cosim_pixels: u64,
    out: &Path,
) -> Result<Report, BenchError> {
    let model = Model::repo()?;
    let cs = cosim::run(&model, 0xb0a7d, cosim_pixels, 4096)?;
    let synth = synth(lanes, freq_mhz, out)?;
    let mpx = synth.fmax_mhz * lanes as f64;
    let fabric_board_s = BOARD_ROWS as f64 * width as f64 / (mpx * 1e6);
    Ok(Report {
        pixels_per_clock: lanes,
        mpx_s_per_camera: mpx,
        codec: None,
        goal_mpx_s_per_camera: 32.0,
        width,
        board_rows: BOARD_ROWS,
        fabric_board_s,
        cosim_pixels: cs.pixels,
        cosim_mismatches: cs.mismatches,
        mcu_instructions_per_pixel: None,
        mcu_encode_instructions_per_pixel: None,
        goal_mcu_instructions_per_pixel: 32.0,
        mcu_board_s: None,
        board_s: None,
        not_measured: vec![
            "mcu_instructions_per_pixel, mcu_board_s and board_s: no firmware run with the \
             front end"
                .into(),
        ],
        synth,
    })
}

impl Report {
    /// The row codec's synthesis and its measured clocks per pixel: the camera's rate becomes
    /// the slower of pixel units and codec, and the fabric's board time follows.
    pub fn set_codec(&mut self, synth: Synth, clocks_per_pixel: f64) {
        let mpx_s = synth.fmax_mhz / clocks_per_pixel;
        self.mpx_s_per_camera = self.mpx_s_per_camera.min(mpx_s);
        self.fabric_board_s = BOARD_ROWS as f64 * self.width as f64 / (self.mpx_s_per_camera * 1e6);
        if let Some(b) = self.board_s.as_mut() {
            *b = b.max(self.fabric_board_s);
        }
        self.codec = Some(CodecFigures {
            synth,
            clocks_per_pixel,
            mpx_s,
        });
    }

    /// The MCU's measured share with the front end: `instructions_per_pixel` in all, of which
    /// `encode`; `mcu_board_s` its time for the paper board. Sets `board_s`.
    pub fn set_mcu(&mut self, instructions_per_pixel: f64, encode: f64, mcu_board_s: f64) {
        self.mcu_instructions_per_pixel = Some(instructions_per_pixel);
        self.mcu_encode_instructions_per_pixel = Some(encode);
        self.mcu_board_s = Some(mcu_board_s);
        self.board_s = Some(mcu_board_s.max(self.fabric_board_s));
        self.not_measured.clear();
    }
}
