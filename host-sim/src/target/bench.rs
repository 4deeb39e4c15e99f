//! The firmware's measurements of itself, as JSON figures.

use super::elf::{ElfSizes, Sections};
use crate::{At, Result, SimError};
use serde::Serialize;
use std::collections::BTreeMap;

/// Every key the firmware's bench file must hold (integers; ticks are SysTick ticks).
pub const BENCH_KEYS: [&str; 19] = [
    "calib_loop_instructions",
    "calib_ticks",
    "rows_out",
    "pixels_out",
    "ticks_total",
    "ticks_encode",
    "ticks_io",
    "stage_pixels",
    "ticks_accumulate",
    "ticks_phase_height",
    "solves",
    "ticks_solve",
    "stack_high_water",
    "state_bytes",
    "state_total_bytes",
    "width",
    "n",
    "dsp_checks",
    "dsp_mismatches",
];

/// Parses a bench file: one `key value` pair (an integer) per line; blank lines are ignored.
pub fn parse_bench(text: &str) -> Result<BTreeMap<String, i64>> {
    let mut out = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let mut it = line.split_whitespace();
        let (Some(k), Some(v), None) = (it.next(), it.next(), it.next()) else {
            return Err(SimError::Refused(format!(
                "bench file line {}: expected `key value`, got {line:?}",
                i + 1
            )));
        };
        let v: i64 = v
            .parse()
            .map_err(|e: std::num::ParseIntError| SimError::refused(e.to_string()))
            .at(|| format!("bench file line {}: {k}: {v:?} is not an integer", i + 1))?;
        if out.insert(k.to_string(), v).is_some() {
            return Err(SimError::Refused(format!(
                "bench file line {}: {k} given twice",
                i + 1
            )));
        }
    }
    Ok(out)
}

/// Instructions per output pixel, by stage.
#[derive(Clone, Debug, Serialize)]
pub struct PerPixel {
    /// The whole pipeline (accumulate, solve, phase, height, mask, encode), I/O excluded; with
    /// the FPGA front end, the MCU's part only (the fabric log's reads are I/O).
    pub total: f64,
    /// `v = P i` per pixel (`null` with the front end: the fabric's).
    pub accumulate: Option<f64>,
    /// Phase, height and the validity mask (`null` with the front end: the fabric's).
    pub phase_height: Option<f64>,
    /// Packet framing and row compression.
    pub encode: f64,
}

/// RAM figures, bytes.
#[derive(Clone, Debug, Serialize)]
pub struct Ram {
    /// `.data + .bss + .uninit` of the ELF.
    #[serde(rename = "static")]
    pub static_: u64,
    /// Core pipeline state for this recording's configuration (`Layout::bytes`).
    pub state: u64,
    /// Every configuration-sized buffer of the firmware (core state, codec reference row,
    /// line and packet buffers).
    pub state_total: u64,
    /// Deepest stack use measured by the firmware.
    pub stack_high_water: u64,
    /// What the RAM budget counts: every configuration-sized buffer
    /// (`state_total`), the static RAM (`static`) and the stack high-water mark.
    pub total: u64,
}

/// Real-time model: what the measured instruction count means on a production frame grabber.
///
/// The clock and the instructions per cycle are *assumptions*, not measurements: QEMU counts
/// retired instructions, and a Cortex-M7 at 600 MHz (i.MX RT1060 class) is assumed to retire
/// one per cycle on integer code in TCM (firmware/README.md lists what real cycles add or
/// save: dual issue, divider and load-use stalls, mispredicted branches, bus waits). The
/// board is the paper's
/// 220 x 168 mm at 28 um per pixel, its width shared by [`CAMERAS`] cameras of `W` pixels.
#[derive(Clone, Debug, Serialize)]
pub struct Realtime {
    /// Core clock assumed, Hz.
    pub clock_hz: f64,
    /// Instructions per cycle assumed (not measured).
    pub ipc_assumed: f64,
    /// Output pixels per second one camera's frame grabber keeps up with:
    /// `clock_hz * ipc_assumed / instructions_per_pixel.total`.
    pub pixels_per_second_per_camera: f64,
    /// Board rows per second (`pixels_per_second_per_camera / W`).
    pub board_rows_per_second: f64,
    /// Board length along the conveyor, mm.
    pub board_length_mm: f64,
    /// Board width across the conveyor, mm.
    pub board_width_mm: f64,
    /// Pixel pitch on the board, um.
    pub pixel_um: f64,
    /// Frame grabbers (cameras) side by side across the board width.
    pub cameras: u32,
    /// Board rows along the conveyor (`board_length_mm / pixel`).
    pub board_rows: f64,
    /// Output pixels each camera delivers per board (`board_rows * W`).
    pub pixels_per_camera: f64,
    /// Seconds of processing per board (the cameras work in parallel).
    pub board_seconds: f64,
    /// Whether the `W`-pixel cameras cover the board width.
    pub width_covered: bool,
}

/// Cameras (frame grabbers) across the board in the real-time model.
pub const CAMERAS: u32 = 3;

impl Realtime {
    /// The model for `ipp` instructions per output pixel and `width` pixels per camera row.
    pub fn model(ipp: f64, width: f64) -> Realtime {
        let (clock_hz, ipc_assumed) = (600e6, 1.0);
        let (board_length_mm, board_width_mm, pixel_um) = (220.0f64, 168.0f64, 28.0f64);
        let pps = clock_hz * ipc_assumed / ipp;
        let board_rows = (board_length_mm * 1000.0 / pixel_um).ceil();
        let pixels_per_camera = board_rows * width;
        Realtime {
            clock_hz,
            ipc_assumed,
            pixels_per_second_per_camera: pps,
            board_rows_per_second: pps / width,
            board_length_mm,
            board_width_mm,
            pixel_um,
            cameras: CAMERAS,
            board_rows,
            pixels_per_camera,
            board_seconds: pixels_per_camera / pps,
            width_covered: CAMERAS as f64 * width * pixel_um / 1000.0 >= board_width_mm,
        }
    }
}

/// The firmware's measured figures (`dpsa target-run --bench --json`).
#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    /// Instructions per output pixel, by stage.
    pub instructions_per_pixel: PerPixel,
    /// One-off cost of `P` for one window (the integer solve).
    pub instructions_per_window_solve: f64,
    /// RAM use, bytes.
    pub ram_bytes: Ram,
    /// The real-time model (assumed clock and IPC; see [`Realtime`]).
    pub realtime: Realtime,
    /// The run had the FPGA front end (`dpsa target-run --front-end`): the figures are the
    /// MCU's share (the JSON's `front_end` object, added by `target-run`, says so).
    #[serde(skip)]
    pub front_end: bool,
    /// Bytes the firmware occupies in flash.
    pub flash_bytes: u64,
    /// Retired instructions per SysTick tick, calibrated by the firmware (40 on mps2 at
    /// `-icount shift=0`).
    pub instructions_per_tick: f64,
    /// Pixels per row `W` of the recording.
    pub width: i64,
    /// Observations per board row (frames in a phase window).
    pub n: i64,
    /// Height rows the firmware wrote to the stream.
    pub rows_out: i64,
    /// Height pixels it wrote (`rows_out x width`).
    pub pixels_out: i64,
    /// Pixels the per-stage loops (accumulate, phase + height) were timed over.
    pub stage_pixels: i64,
    /// Window solves timed (`instructions_per_window_solve` is their mean).
    pub solves: i64,
    /// Inputs on which the firmware checked its `asm!` SMLAD and UQSUB16 against their
    /// portable twins (`core/src/dsp.rs`); a report is only made when none differed.
    pub dsp_checks: i64,
    /// Instructions spent in semihosting file I/O (context: QEMU's host I/O, not the board's).
    pub io_instructions: f64,
    /// Section sizes of the firmware ELF, bytes.
    pub elf_sections: Sections,
    /// The bench file as the firmware wrote it.
    pub raw: BTreeMap<String, i64>,
}

/// Turns the firmware's bench file and the ELF sizes into figures. Every ratio needs a
/// positive denominator.
pub fn bench_report(raw: &BTreeMap<String, i64>, elf: &ElfSizes) -> Result<BenchReport> {
    let missing: Vec<&str> = BENCH_KEYS
        .iter()
        .copied()
        .filter(|k| !raw.contains_key(*k))
        .collect();
    if !missing.is_empty() {
        return Err(SimError::Refused(format!(
            "the firmware's bench file lacks {}",
            missing.join(", ")
        )));
    }
    let get = |k: &str| raw[k];
    let positive = |k: &str| -> Result<f64> {
        let v = get(k);
        if v <= 0 {
            return Err(SimError::Refused(format!("bench {k} = {v}, expected > 0")));
        }
        Ok(v as f64)
    };
    let unsigned = |k: &str| -> Result<u64> {
        u64::try_from(get(k))
            .map_err(|_| SimError::Refused(format!("bench {k} = {} is negative", get(k))))
    };
    if get("dsp_mismatches") != 0 {
        return Err(SimError::Tool(format!(
            "the firmware's SMLAD/UQSUB16 differ from their portable twins on {} of {} inputs \
             (core/src/dsp.rs): its results cannot be trusted to match the host",
            get("dsp_mismatches"),
            get("dsp_checks")
        )));
    }
    let ipt = positive("calib_loop_instructions")? / positive("calib_ticks")?;
    let ticks = |k: &str| -> Result<f64> { Ok(unsigned(k)? as f64 * ipt) };
    let pixels = positive("pixels_out")?;
    // With the front end the per-pixel stages ran in the fabric: none timed on the MCU.
    let front_end = raw.get("front_end").copied().unwrap_or(0) != 0;
    let stage = |k: &str| -> Result<Option<f64>> {
        if front_end {
            return Ok(None);
        }
        Ok(Some(ticks(k)? / positive("stage_pixels")?))
    };
    let solves = positive("solves")?;
    let total = ticks("ticks_total")? / pixels;
    let (state_total, stack) = (
        unsigned("state_total_bytes")?,
        unsigned("stack_high_water")?,
    );
    Ok(BenchReport {
        instructions_per_pixel: PerPixel {
            total,
            accumulate: stage("ticks_accumulate")?,
            phase_height: stage("ticks_phase_height")?,
            encode: ticks("ticks_encode")? / pixels,
        },
        instructions_per_window_solve: ticks("ticks_solve")? / solves,
        ram_bytes: Ram {
            static_: elf.static_ram,
            state: unsigned("state_bytes")?,
            state_total,
            stack_high_water: stack,
            total: state_total + stack + elf.static_ram,
        },
        realtime: Realtime::model(total, positive("width")?),
        front_end,
        flash_bytes: elf.flash,
        instructions_per_tick: ipt,
        width: get("width"),
        n: get("n"),
        rows_out: get("rows_out"),
        pixels_out: get("pixels_out"),
        stage_pixels: get("stage_pixels"),
        solves: get("solves"),
        dsp_checks: get("dsp_checks"),
        io_instructions: ticks("ticks_io")?,
        elf_sections: elf.sections.clone(),
        raw: raw.clone(),
    })
}

impl BenchReport {
    /// A few lines for people.
    pub fn summary(&self) -> String {
        let p = &self.instructions_per_pixel;
        let stage = |x: Option<f64>| x.map_or("in the fabric".to_string(), |x| format!("{x:.1}"));
        let r = &self.ram_bytes;
        let s = &self.elf_sections;
        format!(
            "Cortex-M7 (QEMU, {:.2} instructions per SysTick tick), W = {}, n = {}, {} pixels out\n\
             instructions per pixel{}: {:.1} total (accumulate {}, phase + height {}, encode {:.1})\n\
             instructions per window solve: {:.0} ({} solves)\n\
             flash {} bytes (text {}, rodata {}, data {}, itcm {}); static RAM {} bytes (data {}, bss {}, uninit {})\n\
             core state {} bytes, all config-sized buffers {} bytes, stack high water {} bytes; RAM total {} bytes\n\
             real time (assumed {:.0} MHz, IPC {:.1}): {:.1} Mpx/s per camera, {:.2} s per {:.0} x {:.0} mm board with {} cameras",
            self.instructions_per_tick, self.width, self.n, self.pixels_out,
            if self.front_end { " on the MCU, with the FPGA front end" } else { "" },
            p.total, stage(p.accumulate), stage(p.phase_height), p.encode,
            self.instructions_per_window_solve, self.solves,
            self.flash_bytes, s.text, s.rodata, s.data, s.itcm, r.static_, s.data, s.bss, s.uninit,
            r.state, r.state_total, r.stack_high_water, r.total,
            self.realtime.clock_hz / 1e6, self.realtime.ipc_assumed,
            self.realtime.pixels_per_second_per_camera / 1e6, self.realtime.board_seconds,
            self.realtime.board_length_mm, self.realtime.board_width_mm, self.realtime.cameras
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw() -> BTreeMap<String, i64> {
        let mut m: BTreeMap<String, i64> = BENCH_KEYS.iter().map(|k| (k.to_string(), 1)).collect();
        for (k, v) in [
            ("calib_loop_instructions", 4000),
            ("calib_ticks", 100),
            ("pixels_out", 1000),
            ("ticks_total", 500),
            ("ticks_encode", 50),
            ("stage_pixels", 200),
            ("ticks_accumulate", 20),
            ("ticks_phase_height", 40),
            ("solves", 4),
            ("ticks_solve", 30),
            ("width", 2048),
            ("state_total_bytes", 1000),
            ("stack_high_water", 24),
            ("dsp_checks", 100),
            ("dsp_mismatches", 0),
        ] {
            m.insert(k.into(), v);
        }
        m
    }

    #[test]
    fn bench_figures_are_ticks_times_instructions_per_tick_over_pixels() {
        let r = bench_report(
            &raw(),
            &ElfSizes {
                flash: 9,
                static_ram: 7,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(r.instructions_per_tick, 40.0);
        assert_eq!(r.instructions_per_pixel.total, 20.0);
        assert_eq!(r.instructions_per_pixel.encode, 2.0);
        assert_eq!(r.instructions_per_pixel.accumulate, Some(4.0));
        assert_eq!(r.instructions_per_pixel.phase_height, Some(8.0));
        assert_eq!(r.instructions_per_window_solve, 300.0);
        assert_eq!((r.flash_bytes, r.ram_bytes.static_), (9, 7));
        assert_eq!(r.ram_bytes.total, 1000 + 24 + 7);
        // 20 instructions per pixel at 600 MHz, IPC 1: 30 Mpx/s; 7858 rows x 2048 px per
        // camera: 0.536 s per board.
        assert_eq!(r.realtime.pixels_per_second_per_camera, 30e6);
        assert_eq!(r.realtime.board_rows, 7858.0);
        assert!((r.realtime.board_seconds - 7858.0 * 2048.0 / 30e6).abs() < 1e-12);
        assert!(r.realtime.width_covered);
        let v = serde_json::to_value(&r).unwrap();
        assert_eq!(v["ram_bytes"]["static"], 7);
        assert_eq!(v["instructions_per_pixel"]["total"], 20.0);
        assert_eq!(v["dsp_checks"], 100);
    }

    #[test]
    fn bench_file_errors() {
        let mut m = raw();
        m.remove("ticks_solve");
        let e = bench_report(&m, &ElfSizes::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("ticks_solve"), "{e}");
        let mut m = raw();
        m.insert("calib_ticks".into(), 0);
        let e = bench_report(&m, &ElfSizes::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("calib_ticks"), "{e}");
        // The target's asm! DSP instructions disagreed with their portable twins.
        let mut m = raw();
        m.insert("dsp_mismatches".into(), 3);
        let e = bench_report(&m, &ElfSizes::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("3 of 100") && e.contains("portable twins"),
            "{e}"
        );
        assert_eq!(
            parse_bench("a 1\n\nb -2\n").unwrap(),
            BTreeMap::from([("a".into(), 1), ("b".into(), -2)])
        );
        assert!(parse_bench("a 1 2").is_err());
        assert!(parse_bench("a x")
            .unwrap_err()
            .to_string()
            .contains("line 1"));
        assert!(parse_bench("a 1\na 2")
            .unwrap_err()
            .to_string()
            .contains("twice"));
    }
}
