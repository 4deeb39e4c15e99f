//! Measurements the firmware makes of itself: instruction counts by stage, the cost of a
//! window solve, the stack high-water mark.
//!
//! Under QEMU `-icount shift=0` every retired instruction advances virtual time by 1 ns and
//! SysTick runs at the 25 MHz core clock, so one tick is 40 instructions; [`calibrate`] checks
//! that on a loop of known length. Figures are written as `key value` lines for
//! `dpsa target-run --bench`, which turns them into JSON.

use crate::board::Clock;
use crate::sink::SinkTicks;
// The core's internal stages, timed apart, come through its one bench-facing module.
use dpsa_core::bench::{self, Window, MAX_N, V};
use dpsa_core::height::{ColumnScale, Scale};
use dpsa_core::Config;

/// Ticks of the main run and of the window solves.
pub struct Meter {
    /// In the pipeline calls (begin_frame, push_line, end_frame, finish), sink included.
    pub pipe: u64,
    /// Reading lines and triggers.
    pub io: u64,
    /// Window solves timed, their ticks, the last good window.
    pub solves: u64,
    pub solve_ticks: u64,
    pub window: Option<Window>,
    offsets: [i64; MAX_N],
    frames: usize,
}

impl Meter {
    pub fn new() -> Meter {
        Meter {
            pipe: 0,
            io: 0,
            solves: 0,
            solve_ticks: 0,
            window: None,
            offsets: [0; MAX_N],
            frames: 0,
        }
    }

    /// Times a solve of the window ending at this frame, from the same shifts the pipeline
    /// derives from the latches ([`Config::shifts`]: `theta_j = -(o_j - o_0) 2 pi f_x`).
    pub fn solve<C: Clock>(&mut self, cfg: &Config, latch: i64, clock: &C) {
        let n = cfg.n as usize;
        self.offsets.copy_within(1..MAX_N, 0);
        self.offsets[MAX_N - 1] = cfg.offset(latch);
        self.frames += 1;
        if self.frames < n {
            return;
        }
        let mut shifts = [0u32; MAX_N];
        cfg.shifts(&self.offsets[MAX_N - n..], &mut shifts);
        let t = clock.ticks();
        let w = Window::solve(core::hint::black_box(&shifts[..n]), cfg.max_noise_gain);
        self.solve_ticks += clock.ticks() - t;
        self.solves += 1;
        if let Ok(w) = w {
            self.window = Some(w);
        }
    }
}

/// The per-stage loops, timed apart.
pub struct Stages {
    pub pixels: u64,
    pub accumulate: u64,
    pub phase_height: u64,
    /// The front end ran the per-pixel stages (nothing timed here).
    pub front_end: bool,
}

impl Stages {
    /// No stage timed (the front end runs them).
    pub fn none() -> Stages {
        Stages {
            pixels: 0,
            accumulate: 0,
            phase_height: 0,
            front_end: true,
        }
    }
}

/// Runs the two stages of the core's per-pixel loop (`accumulate::block` and `Scale::row`,
/// the very functions `Pipeline::compute` calls block by block) timed apart, over
/// real samples (lines left in the pool by the run) with the last solved window, block by
/// block as the pipeline runs them: [`dpsa_core::pipeline::BLOCK`] reduced pixels on the stack
/// between the stages (no row-sized buffer). Each stage's time includes one clock read per
/// block (about 0.2 instructions per pixel).
#[allow(clippy::too_many_arguments)]
pub fn stages<C: Clock>(
    cfg: &Config,
    layout: &dpsa_core::Layout,
    meter: &Meter,
    ref_phase: &[u32],
    columns: Option<ColumnScale<'_>>,
    pool: &[u16],
    heights: &mut [i16],
    valid: &mut [u8],
    clock: &C,
) -> Stages {
    use dpsa_core::pipeline::BLOCK;
    let mut s = Stages {
        pixels: 0,
        accumulate: 0,
        phase_height: 0,
        front_end: false,
    };
    let Some(win) = meter.window else { return s };
    let Some(coef) = bench::Coef::of(&win, cfg.saturation) else {
        return s;
    };
    let mut v = [[0i32; 2]; BLOCK];
    // The block buffer as a run-time pointer: otherwise the compiler may fold its address into
    // `accumulate::block` (its only caller is this function), and the cost of that constant
    // would be measured instead of the pipeline's code, which always has a pointer.
    let v: &mut [V; BLOCK] = core::hint::black_box(&mut v);
    // The same for the reference-phase table (the pipeline reads it through a pointer too).
    let ref_phase = core::hint::black_box(ref_phase);
    let (w, n) = (cfg.width as usize, cfg.n as usize);
    let scale = Scale::new(cfg);
    let gate = scale.gate(coef.frac);
    // Groups of `n` pool lines, in the pool's own format (Mono12p when packed).
    let u = layout.pool_line_units;
    let groups = (pool.len() / (u * n)).min(16);
    for g in 0..groups {
        let base = &pool[g * u * n..(g + 1) * u * n];
        let mut lines: [&[u16]; MAX_N] = [&[]; MAX_N];
        let mut packed: [&[u8]; MAX_N] = [&[]; MAX_N];
        for j in 0..n {
            lines[j] = &base[j * u..j * u + w.min(u)];
            let b: &[u8] = bytemuck::cast_slice(&base[j * u..(j + 1) * u]);
            packed[j] = &b[..dpsa_core::frames::mono12p::stored_len(w).min(b.len())];
        }
        let rho = cfg.row_phase(g as i64);
        let mut c0 = 0;
        while c0 < w {
            let len = BLOCK.min(w - c0);
            let t0 = clock.ticks();
            if layout.packed {
                bench::block_packed(&coef, &packed[..n], c0, cfg.saturation, &mut v[..len]);
            } else {
                bench::block(&coef, &lines[..n], c0, cfg.saturation, &mut v[..len]);
            }
            let t1 = clock.ticks();
            let (r, h) = (&ref_phase[c0..c0 + len], &mut heights[c0..c0 + len]);
            let m = &mut valid[c0 / 8..w.div_ceil(8)];
            let f = match &columns {
                None => scale.row(&gate, &v[..len], rho, r, h, m),
                Some(t) => {
                    let k = &t.mantissa()[c0..c0 + len];
                    scale.row_columns(&gate, &v[..len], rho, r, t, k, h, m)
                }
            };
            let t2 = clock.ticks();
            core::hint::black_box((&heights, &valid, f));
            s.accumulate += t1 - t0;
            s.phase_height += t2 - t1;
            c0 += len;
        }
        s.pixels += w as u64;
    }
    s
}

/// Instructions in the calibration loop and the ticks they took.
#[allow(unsafe_code)] // the `asm!` loop of known length
pub fn calibrate<C: Clock>(clock: &C) -> (u64, u64) {
    const ITER: u32 = 1 << 20;
    let t0 = clock.ticks();
    // Two instructions per iteration (subs, bne), plus the mov.
    unsafe {
        core::arch::asm!(
            "mov {n}, {iter}",
            "2:",
            "subs {n}, {n}, #1",
            "bne 2b",
            n = out(reg) _,
            iter = in(reg) ITER,
            options(nomem, nostack)
        );
    }
    let t1 = clock.ticks();
    (2 * ITER as u64 + 1, t1 - t0)
}

const PAINT: u32 = 0x5AC3_A55A;

extern "C" {
    static mut __sheap: u32;
    static _stack_start: u32;
}

/// Fills the free stack with a pattern (from the end of static RAM up to just below the
/// current stack pointer), so that [`stack_high_water`] can see how deep it went.
#[allow(unsafe_code)] // writes the unused stack
pub fn paint_stack() {
    let sp = cortex_m::register::msp::read() as usize;
    // SAFETY: the words between the end of statics and 256 bytes below the live stack pointer
    // are unused stack; nothing else refers to them.
    unsafe {
        let mut p = core::ptr::addr_of_mut!(__sheap);
        while (p as usize) < sp - 256 {
            core::ptr::write_volatile(p, PAINT);
            p = p.add(1);
        }
    }
}

/// Deepest stack use since [`paint_stack`], in bytes.
#[allow(unsafe_code)] // reads the painted stack
pub fn stack_high_water() -> usize {
    // SAFETY: reads the painted region only (see `paint_stack`).
    unsafe {
        let top = core::ptr::addr_of!(_stack_start) as usize;
        let mut p = core::ptr::addr_of!(__sheap);
        while (p as usize) < top && core::ptr::read_volatile(p) == PAINT {
            p = p.add(1);
        }
        top - p as usize
    }
}

/// The text of a benchmark report.
pub type Text = heapless::String<1024>;

/// The `key value` lines of a benchmark run.
pub fn report<C: Clock>(
    header: &dpsa_core::frames::feed::Header,
    m: &Meter,
    sink: &SinkTicks,
    st: &Stages,
    clock: &C,
) -> Text {
    let (cfg, table) = (&header.cfg, header.column_scale.is_some());
    let (calib_instr, calib_ticks) = calibrate(clock);
    let w = cfg.width as u64;
    let mut t = Text::new();
    // The DSP instructions the accumulate kernel runs as `asm!`, against their portable twins
    // (every lane class pair, then random words): must be 0 (the host refuses the report).
    let dsp_random = 20_000;
    let dsp_mismatches = bench::check_against_twins(dsp_random, 0x9E37_79B9);
    let lines: [(&str, u64); 23] = [
        ("calib_loop_instructions", calib_instr),
        ("calib_ticks", calib_ticks),
        ("rows_out", sink.rows),
        ("pixels_out", sink.rows * w),
        ("ticks_total", m.pipe - sink.send),
        ("ticks_encode", sink.encode),
        ("ticks_io", m.io + sink.send),
        ("stage_pixels", st.pixels),
        ("ticks_accumulate", st.accumulate),
        ("ticks_phase_height", st.phase_height),
        ("solves", m.solves),
        ("ticks_solve", m.solve_ticks),
        ("stack_high_water", stack_high_water() as u64),
        (
            "state_bytes",
            dpsa_core::Layout::of(cfg).with_column_scale(table).bytes() as u64,
        ),
        (
            "state_total_bytes",
            crate::state::State::bytes_for(header) as u64,
        ),
        ("column_scale", table as u64),
        ("width", w),
        ("n", cfg.n as u64),
        ("rows", cfg.rows as u64),
        ("dsp_checks", bench::checks(dsp_random) as u64),
        ("dsp_mismatches", dsp_mismatches as u64),
        ("mono12p", header.mono12p as u64),
        ("front_end", u64::from(st.front_end)),
    ];
    for (k, v) in lines {
        // At most 758 bytes (the 23 keys, 252 bytes, with 20-digit values): within the 1 KiB.
        let _ = t.push_str(k);
        let _ = t.push(' ');
        let _ = t.push_str(decimal(v, &mut [0; 20]));
        let _ = t.push('\n');
    }
    t
}

/// `v` in decimal, written into the end of `buf`. By hand rather than `core::fmt`, whose
/// integer formatting and padding machinery cost the firmware 496 B of flash for these 23
/// lines.
fn decimal(mut v: u64, buf: &mut [u8; 20]) -> &str {
    let mut i = buf.len();
    loop {
        i -= 1;
        buf[i] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 {
            break;
        }
    }
    core::str::from_utf8(&buf[i..]).unwrap_or("")
}
