//! dpsa-firmware: the `dpsa-core` pipeline on a Cortex-M7 frame grabber.
//!
//! Data flow, the same as on the host (`dpsa reconstruct`):
//! frames (board [`LineSource`]) -> solve/accumulate/phase/height (`dpsa_core::Pipeline`,
//! line by line, `P` solved on the target once per window) -> packets -> sink (the core's
//! `PacketSink` over the board's link, which implements `dpsa_core::sink::Link`; timed for the
//! benchmark by [`TimedSink`]).
//!
//! The board layer is in [`board`]; this file only wires it to the core. Under QEMU the
//! command line is `dpsa-firmware FEED OUT [BENCH]` (semihosting) and the exit status
//! says whether the run succeeded; the reason of a failure is in the defmt log.
#![no_std]
#![no_main]

mod bench;
mod board;
mod sink;
mod state;

use board::qemu::{self, Feed, Output, SysTickClock};
use board::{Clock, LineSource, Triggered};
use defmt_semihosting as _;
use dpsa_core::height::ColumnScale;
use dpsa_core::offload::Line;
use dpsa_core::packets::codec;
use dpsa_core::pipeline::{Memory, Pipeline};
use sink::TimedSink;

#[cortex_m_rt::entry]
#[allow(unsafe_code)] // the ITCM copy, once, first
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
    let mut args = qemu::Args::empty();
    args.read().map_err(|e| fail("command line", e))?;
    let st = state::take().ok_or_else(|| fail("state", "taken twice"))?;

    // Calibration and geometry come with the feed (on a real board: from its flash).
    st.open_ref_phase();
    let feed = Feed::open(
        &args.feed,
        &mut st.ref_phase,
        &mut st.column_scale,
        qemu::as_bytes_mut(&mut st.lines),
    )
    .map_err(|e| fail("opening the feed", e))?;
    let header = feed.header();
    let cfg = header.cfg;
    let table = header.column_scale.is_some();
    let (layout, pool_at) = st
        .size_for(&header)
        .map_err(|e| fail("state too small for this geometry", e))?;
    let state::State {
        lines,
        free,
        slots,
        heights,
        valid,
        ref_phase,
        column_scale,
        line,
        scratch,
        codec_heights,
        codec_valid,
        packet,
    } = st;
    let w = layout.width;
    let lines: &mut [u16] = match pool_at {
        state::PoolAt::State => &mut lines[..],
        state::PoolAt::External => {
            state::ext_pool().ok_or_else(|| fail("external pool", "taken twice"))?
        }
    };
    defmt::info!(
        "line pool: {} ({=usize} lines of {=usize} B, Mono12p {=bool})",
        pool_at,
        layout.pool_lines,
        layout.pool_line_units * 2,
        layout.packed
    );
    defmt::info!(
        "W {=usize} H {=u16} n {=u8} max step {=u16} rows: {=u32} frames, state {=usize} B (pipeline {=usize} B), per-column height scale {=bool}",
        w,
        cfg.rows,
        cfg.n,
        cfg.max_step_rows,
        header.frames,
        state::State::bytes_for(&header),
        layout.bytes(),
        table
    );

    let (strobe, capture, port) = feed.parts();
    let mut source = Triggered {
        trigger: strobe,
        encoder: capture,
        port,
    };
    // A host file, or `uart:` for the board's UART (carried live to the line by QEMU).
    let link = Output::open(&args.out).map_err(|e| fail("creating the output", e))?;
    let enc = codec::Encoder::new(
        &mut codec_heights[..w],
        &mut codec_valid[..],
        w,
        header.intra_period,
    )
    .ok_or_else(|| fail("codec", "width not supported"))?;
    let bench_on = args.bench.is_some();
    // The fabric's row codec (`payloads=LOG`, with `fabric=LOG`): the MCU frames its payloads.
    let mut payloads = match (&args.fabric, &args.payloads) {
        (_, None) => None,
        (None, Some(_)) => return Err(fail("command line", "payloads=LOG needs fabric=LOG")),
        (Some(_), Some(p)) => Some(
            qemu::FabricPayloads::open(p, w, header.run_id, &clock)
                .map_err(|e| fail("payload log", e))?,
        ),
    };
    let mut sink = TimedSink::new(link, enc, &mut packet[..], bench_on.then_some(&clock));
    sink.set_run_id(header.run_id);
    if let Some(p) = payloads.as_mut() {
        sink.set_coder(p);
    }
    let mem = Memory {
        lines: &mut lines[..layout.pool_units()],
        scratch: &mut scratch[..],
        free: &mut free[..layout.pool_lines],
        slots: &mut slots[..layout.slots],
        heights: &mut heights[..w],
        valid: &mut valid[..w.div_ceil(8)],
    };
    // The calibration's per-column height scale, when the feed has one (sized by `size_for`).
    let columns = header
        .column_scale
        .map(|shift| ColumnScale::new(shift, &column_scale[..]));
    let mut pipe = Pipeline::with_column_scale(cfg, &ref_phase[..w], columns, mem)
        .map_err(|e| fail("pipeline", e))?;
    let mut meter = bench::Meter::new();
    let line_len = header.line_len();
    // With the FPGA front end (`fabric=LOG`): the per-pixel stages are the fabric's, the rest
    // (registration, windows, flags, encoding, the link) stays here.
    let mut fabric = match &args.fabric {
        Some(p) => Some(
            qemu::FabricLog::open(p, w, header.run_id, &clock)
                .map_err(|e| fail("fabric log", e))?,
        ),
        None => None,
    };
    if fabric.is_some() {
        defmt::info!("front end: the FPGA's rows (fabric log)");
    }

    let mut frames = 0u32;
    loop {
        let t = clock.ticks();
        let next = source.next_frame().map_err(|e| fail("camera", e))?;
        meter.io += clock.ticks() - t;
        let Some(trigger) = next else { break };
        let t = clock.ticks();
        pipe.begin_frame(trigger, &mut sink)
            .map_err(|e| fail("begin_frame", e))?;
        meter.pipe += clock.ticks() - t;
        if bench_on {
            meter.solve(&cfg, trigger.latch, &clock);
        }
        for r in 0..cfg.rows {
            let t = clock.ticks();
            source
                .read_line(&mut qemu::as_bytes_mut(line)[..line_len])
                .map_err(|e| fail("camera", e))?;
            let t1 = clock.ticks();
            match (fabric.as_mut(), header.mono12p) {
                (None, true) => {
                    pipe.push_packed_line(r, &qemu::as_bytes_mut(line)[..line_len], &mut sink)
                }
                (None, false) => pipe.push_line(r, &line[..w], &mut sink),
                (Some(fe), true) => {
                    let l = Line::Packed(&qemu::as_bytes_mut(line)[..line_len]);
                    pipe.push_to_front_end(r, l, fe, &mut sink)
                }
                (Some(fe), false) => {
                    pipe.push_to_front_end(r, Line::Wide(&line[..w]), fe, &mut sink)
                }
            }
            .map_err(|e| {
                if let Some(e) = fabric.as_ref().and_then(|f| f.error) {
                    fail("fabric log", e)
                } else {
                    fail("push_line", e)
                }
            })?;
            let t2 = clock.ticks();
            meter.io += t1 - t;
            meter.pipe += t2 - t1;
        }
        let t = clock.ticks();
        pipe.end_frame(&mut sink)
            .map_err(|e| fail("end_frame", e))?;
        meter.pipe += clock.ticks() - t;
        frames += 1;
    }
    let t = clock.ticks();
    pipe.finish(&mut sink).map_err(|e| fail("finish", e))?;
    meter.pipe += clock.ticks() - t;
    sink.sink.flush().map_err(|e| fail("link", e))?;
    let mut ticks = sink.ticks();
    drop(sink);
    // The logs' reads happened inside the pipeline calls (the payloads' inside the sink's):
    // host I/O, not the MCU's work.
    if let Some(f) = &fabric {
        meter.pipe -= f.io_ticks;
        meter.io += f.io_ticks;
        defmt::info!("front end: {=u64} rows from the fabric", f.rows);
    }
    if let Some(p) = &payloads {
        meter.pipe -= p.io_ticks;
        meter.io += p.io_ticks;
        ticks.encode -= p.io_ticks;
        defmt::info!(
            "front end: {=u64} payloads from the fabric's row codec",
            p.rows
        );
    }
    let rows = ticks.rows;
    defmt::info!("{=u32} frames in, {=u64} rows out", frames, rows);
    if frames != header.frames {
        return Err(fail("feed", "fewer frames than its header says"));
    }

    if let Some(path) = &args.bench {
        // With the front end the pool holds no lines (they stay in the fabric): the per-pixel
        // stages are not the MCU's and are not timed.
        let stages = match fabric {
            Some(_) => bench::Stages::none(),
            None => bench::stages(
                &cfg, &layout, &meter, ref_phase, columns, lines, heights, valid, &clock,
            ),
        };
        write_bench(path, &header, &meter, &ticks, &stages, &clock)?;
    }
    Ok(())
}

/// Writes the bench report; never inlined, so its text buffer is not in `run`'s frame.
#[inline(never)]
fn write_bench(
    path: &qemu::Path,
    header: &dpsa_core::frames::feed::Header,
    meter: &bench::Meter,
    ticks: &sink::SinkTicks,
    stages: &bench::Stages,
    clock: &SysTickClock,
) -> Result<(), Failed> {
    let report = bench::report(header, meter, ticks, stages, clock);
    qemu::write_text(path, report.as_bytes()).map_err(|e| fail("bench file", e))
}

/// Copies the ITCM image (dpsa-core's code, see `memory.x`) from flash to ITCM.
///
/// # Safety
/// Must run before any function placed in `.itcm` is called, and only once.
#[allow(unsafe_code)]
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
#[allow(unsafe_code)] // the signature cortex-m-rt requires
unsafe fn HardFault(ef: &cortex_m_rt::ExceptionFrame) -> ! {
    defmt::error!("hard fault at pc {=u32:#x}", ef.pc());
    qemu::exit(102)
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    defmt::error!("panic: {}", defmt::Display2Format(info));
    qemu::exit(101)
}
