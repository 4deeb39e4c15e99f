//! dpsa-firmware: the `dpsa-core` pipeline on a Cortex-M7 frame grabber.
//!
//! Data flow, the same as on the host (`dpsa reconstruct`):
//! frames (board [`LineSource`]) -> solve/accumulate/phase/height (`dpsa_core::Pipeline`,
//! line by line, `P` solved on the target once per window) -> packets -> sink ([`LinkSink`]
//! over the board's [`PacketLink`]).
//!
//! The board layer is in [`board`]; this file only wires it to the core. Under QEMU the
//! command line is `dpsa-firmware RECORDING OUT [BENCH]` (semihosting) and the exit status
//! says whether the run succeeded; the reason of a failure is in the defmt log.
#![no_std]
#![no_main]

mod bench;
mod board;
mod sink;
mod state;

use board::qemu::{self, HostFile, Recording, SysTickClock};
use board::{Clock, LineSource, PacketLink, Triggered};
use dpsa_core::packets::codec;
use dpsa_core::pipeline::{Memory, Pipeline};
use defmt_semihosting as _;
use sink::LinkSink;

#[cortex_m_rt::entry]
fn main() -> ! {
    // SAFETY: runs first, before any code placed in ITCM is called.
    unsafe { itcm_load() };
    bench::paint_stack();
    let code = match run() {
        Ok(()) => 0,
        Err(Failed) => 1,
    };
    qemu::exit(code)
}

/// A failure, already logged.
struct Failed;

fn fail<E: defmt::Format>(what: &str, e: E) -> Failed {
    defmt::error!("{=str}: {}", what, e);
    Failed
}

fn run() -> Result<(), Failed> {
    let cp = cortex_m::Peripherals::take().ok_or_else(|| fail("peripherals", "taken twice"))?;
    let clock = SysTickClock::start(cp.SYST);
    let args = qemu::Args::get().map_err(|e| fail("command line", e))?;
    let st = state::take().ok_or_else(|| fail("state", "taken twice"))?;
    let state::State { lines, free, slots, heights, valid, ref_phase, line, codec_heights, codec_valid, packet, bench_acc } = st;

    // Calibration and geometry come with the recording (on a real board: from its flash).
    let rec = Recording::open(&args.recording, ref_phase, qemu::as_bytes_mut(lines))
        .map_err(|e| fail("opening the recording", e))?;
    let header = rec.header();
    let cfg = header.cfg;
    let layout = state::State::check(&cfg).map_err(|e| fail("state too small for this geometry", e))?;
    let w = layout.width;
    defmt::info!(
        "W {=usize} H {=u16} n {=u8} max step {=u16}: {=u32} frames, state {=usize} B (pipeline {=usize} B)",
        w,
        cfg.rows,
        cfg.n,
        cfg.max_step,
        header.frames,
        state::State::bytes_for(&cfg),
        layout.bytes()
    );

    let (strobe, capture, port) = rec.parts();
    let mut source = Triggered { trigger: strobe, encoder: capture, port };
    let link = HostFile::create(&args.out).map_err(|e| fail("creating the output", e))?;
    let mut enc = codec::Encoder::new(&mut codec_heights[..w], &mut codec_valid[..], w)
        .ok_or_else(|| fail("codec", "width not supported"))?;
    enc.set_intra_period(header.intra_period);
    let bench_on = args.bench.is_some();
    let mut sink = LinkSink::new(link, enc, &mut packet[..], bench_on.then_some(&clock));
    let mem = Memory {
        lines: &mut lines[..layout.pool_lines * w],
        free: &mut free[..layout.pool_lines],
        slots: &mut slots[..layout.slots],
        heights: &mut heights[..w],
        valid: &mut valid[..w.div_ceil(8)],
    };
    let mut pipe = Pipeline::new(cfg, &ref_phase[..w], mem).map_err(|e| fail("pipeline", defmt::Debug2Format(&e)))?;
    let mut meter = bench::Meter::new();
    let line = &mut line[..w];

    let mut frames = 0u32;
    loop {
        let t = clock.ticks();
        let next = source.next_frame().map_err(|e| fail("camera", e))?;
        meter.io += clock.ticks() - t;
        let Some(f) = next else { break };
        let t = clock.ticks();
        pipe.begin_frame(f.seq, f.latch, &mut sink).map_err(|e| fail("begin_frame", defmt::Debug2Format(&e)))?;
        meter.pipe += clock.ticks() - t;
        if bench_on {
            meter.solve(&cfg, f.latch, &clock);
        }
        for r in 0..cfg.rows {
            let t = clock.ticks();
            source.read_line(line).map_err(|e| fail("camera", e))?;
            let t1 = clock.ticks();
            pipe.push_line(r, line, &mut sink).map_err(|e| fail("push_line", defmt::Debug2Format(&e)))?;
            let t2 = clock.ticks();
            meter.io += t1 - t;
            meter.pipe += t2 - t1;
        }
        let t = clock.ticks();
        pipe.end_frame(&mut sink).map_err(|e| fail("end_frame", defmt::Debug2Format(&e)))?;
        meter.pipe += clock.ticks() - t;
        frames += 1;
    }
    let t = clock.ticks();
    pipe.finish(&mut sink).map_err(|e| fail("finish", defmt::Debug2Format(&e)))?;
    meter.pipe += clock.ticks() - t;
    sink.link.flush().map_err(|e| fail("link", e))?;
    let rows = sink.ticks.rows;
    defmt::info!("{=u32} frames in, {=u64} rows out", frames, rows);
    if frames != header.frames {
        return Err(fail("recording", "fewer frames than its header says"));
    }

    if let Some(path) = &args.bench {
        drop(pipe);
        let stages = bench::stages(&cfg, &meter, ref_phase, lines, heights, valid, bench_acc, &clock);
        let report = bench::report(&cfg, &meter, &sink.ticks, &stages, &clock);
        qemu::write_text(path, report.as_bytes()).map_err(|e| fail("bench file", e))?;
    }
    Ok(())
}

/// Copies the ITCM image (dpsa-core's code, see `memory.x`) from flash to ITCM.
///
/// # Safety
/// Must run before any function placed in `.itcm` is called, and only once.
unsafe fn itcm_load() {
    extern "C" {
        static mut __sitcm: u32;
        static mut __eitcm: u32;
        static __siitcm: u32;
    }
    let dst = core::ptr::addr_of_mut!(__sitcm);
    let end = core::ptr::addr_of_mut!(__eitcm);
    let src = core::ptr::addr_of!(__siitcm);
    let words = (end as usize - dst as usize) / 4;
    // Volatile word copy: the compiler must not turn this into a call of code that might
    // itself live in ITCM.
    for i in 0..words {
        core::ptr::write_volatile(dst.add(i), core::ptr::read_volatile(src.add(i)));
    }
    cortex_m::asm::dsb();
    cortex_m::asm::isb();
}

#[cortex_m_rt::exception]
unsafe fn HardFault(ef: &cortex_m_rt::ExceptionFrame) -> ! {
    defmt::error!("hard fault at pc {=u32:#x}", ef.pc());
    qemu::exit(102)
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    defmt::error!("panic: {}", defmt::Display2Format(info));
    qemu::exit(101)
}
