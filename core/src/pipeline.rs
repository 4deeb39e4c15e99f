//! The streaming pipeline: frames arrive line by line, completed board rows go to a [`Sink`].
//!
//! ```text
//! begin_frame(trigger) -> push_line(0, ..) ... push_line(H-1, ..) -> end_frame()  (repeat)
//! finish()
//! ```
//!
//! At `begin_frame` the encoder latch gives the frame's row offset `o`; rows that left the ROI
//! are closed, new rows at the bottom are admitted ([`crate::frames::registration`]), and the window of the rows that complete in
//! this frame is solved (once, see `crate::solve`). Each `push_line` either stores the line for
//! the rows it opens or continues, or combines it with the stored lines of the rows it completes
//! and emits them. Rows reach the sink in increasing board-row order, each exactly once, with
//! flags that say why a row or pixel is invalid (see [`crate::flags`]).
//!
//! All state lives in caller-supplied [`Memory`] sized by [`Layout`]: nothing is allocated, and
//! bad input (lines out of order, wrong width, truncated frames, sequence gaps, encoder stalls or
//! reversals, exhausted state) yields an error or flagged rows, never a panic.

use crate::accumulate::Coef;
use crate::accumulate::{self, Pool};
use crate::frames::registration::{self, Kind, Registry, Step};
use crate::frames::{mono12p, Config, ConfigError, Trigger};
use crate::height::{ColumnScale, ColumnScaleError, Gate, Scale};
use crate::lanes::Kernel;
use crate::offload::{FrontEnd, FrontEndError, Line, RowJob};
use crate::row::{flags, Gap, Row, RowHeader, StreamInfo};
use crate::sink::Sink;
use crate::solve::{SolveError, Window, MAX_N};

pub use crate::frames::registration::Slot;

/// Sizes of the caller-supplied state for a configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Layout {
    /// Columns `W`.
    pub width: usize,
    /// Line slots of the raw-sample pool: `max_step_rows * n (n - 1) / 2`.
    pub pool_lines: usize,
    /// Open-row slots: `max_step_rows * n`.
    pub slots: usize,
    /// Entries of the per-column height-scale table ([`ColumnScale`], 2 bytes each): `W` when
    /// the pipeline is given one ([`Layout::with_column_scale`]), else 0.
    pub scale_columns: usize,
    /// The pool keeps lines as Mono12p ([`mono12p`]): when `saturation <= 4095`, so that
    /// every sample that decides a pixel fits 12 bits (a larger one is stored as 4095, still
    /// saturated).
    pub packed: bool,
    /// u16 units per pool line: `W`, or [`mono12p::stored_len`]`(W) / 2` when packed (3 bytes
    /// per pair of pixels, rounded up to whole words: every line starts word-aligned for the
    /// kernel's aligned loads, [`accumulate::block_packed`]).
    pub pool_line_units: usize,
}

impl Layout {
    /// The state sizes of a configuration (without a per-column height-scale table; see
    /// [`Layout::with_column_scale`]).
    pub const fn of(cfg: &Config) -> Layout {
        let n = cfg.n as usize;
        let m = cfg.max_step_rows as usize;
        let w = cfg.width as usize;
        let packed = cfg.saturation <= mono12p::MAX;
        Layout {
            width: w,
            pool_lines: m * n * (n - 1) / 2,
            slots: m * n,
            scale_columns: 0,
            packed,
            pool_line_units: if packed {
                mono12p::stored_len(w) / 2
            } else {
                w
            },
        }
    }

    /// u16 units of the line pool ([`Memory::lines`]).
    pub const fn pool_units(&self) -> usize {
        self.pool_lines * self.pool_line_units
    }

    /// Bytes of [`Memory::scratch`] that [`Pipeline::push_line`] needs on a packed pool (the
    /// last observation of a row, packed): [`mono12p::stored_len`]`(W)`; 0 for a 16-bit pool.
    /// Not in [`Layout::bytes`]: a caller that delivers every line packed
    /// ([`Pipeline::push_packed_line`], as a 12-bit camera's frame grabber does) passes an
    /// empty scratch.
    pub const fn scratch_bytes(&self) -> usize {
        if self.packed {
            mono12p::stored_len(self.width)
        } else {
            0
        }
    }

    /// The layout with (`true`) or without a per-column height-scale table.
    pub const fn with_column_scale(mut self, table: bool) -> Layout {
        self.scale_columns = if table { self.width } else { 0 };
        self
    }

    /// Bytes of pipeline state: the line pool, its free list, the row slots, the output row
    /// (heights and validity bits), the reference-phase table (`W` binary angles) and, if
    /// present, the per-column height-scale table (`W` u16 mantissas).
    pub const fn bytes(&self) -> usize {
        self.pool_units() * 2
            + self.pool_lines * 2
            + self.slots * size_of::<Slot>()
            + self.width * 2
            + self.width.div_ceil(8)
            + self.width * 4
            + self.scale_columns * 2
    }
}

/// Caller-supplied state (see [`Layout`] for the sizes).
pub struct Memory<'a> {
    /// [`Layout::pool_units`] u16 units: the line pool.
    pub lines: &'a mut [u16],
    /// [`Layout::scratch_bytes`] bytes, or empty when every line arrives packed.
    pub scratch: &'a mut [u8],
    /// `pool_lines` entries.
    pub free: &'a mut [u16],
    /// `slots` entries.
    pub slots: &'a mut [Slot],
    /// `W` heights of the row being emitted.
    pub heights: &'a mut [i16],
    /// `ceil(W/8)` validity bytes of the row being emitted.
    pub valid: &'a mut [u8],
}

/// Owned pipeline state sized by [`Layout`] (`alloc` feature): the same buffers as [`Memory`],
/// on the heap. [`State::memory`] lends them to [`Pipeline::new`].
#[cfg(feature = "alloc")]
pub struct State {
    lines: alloc::boxed::Box<[u16]>,
    scratch: alloc::boxed::Box<[u8]>,
    free: alloc::boxed::Box<[u16]>,
    slots: alloc::boxed::Box<[Slot]>,
    heights: alloc::boxed::Box<[i16]>,
    valid: alloc::boxed::Box<[u8]>,
}

#[cfg(feature = "alloc")]
impl State {
    /// Zeroed state for `cfg` (`Layout::of(cfg)`).
    pub fn new(cfg: &Config) -> State {
        use alloc::vec;
        let l = Layout::of(cfg);
        State {
            lines: vec![0; l.pool_units()].into_boxed_slice(),
            scratch: vec![0; l.scratch_bytes()].into_boxed_slice(),
            free: vec![0; l.pool_lines].into_boxed_slice(),
            slots: vec![Slot::default(); l.slots].into_boxed_slice(),
            heights: vec![0; l.width].into_boxed_slice(),
            valid: vec![0; l.width.div_ceil(8)].into_boxed_slice(),
        }
    }

    /// The borrowed view a [`Pipeline`] runs on.
    pub fn memory(&mut self) -> Memory<'_> {
        Memory {
            lines: &mut self.lines,
            scratch: &mut self.scratch,
            free: &mut self.free,
            slots: &mut self.slots,
            heights: &mut self.heights,
            valid: &mut self.valid,
        }
    }
}

/// Why a pipeline could not be built.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NewError {
    /// The configuration is out of range.
    Config(ConfigError),
    /// A memory slice or the reference-phase table is smaller than [`Layout`] says.
    Memory,
    /// The per-column height-scale table does not fit the configuration.
    ColumnScale(ColumnScaleError),
}

/// A streaming error. The pipeline stays usable: the rows affected are flagged.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Error<E> {
    /// The sink failed.
    Sink(E),
    /// `begin_frame` while a frame is open.
    FrameOpen,
    /// `push_line`/`end_frame` without an open frame.
    NoFrame,
    /// Lines must arrive in order `0..H`.
    LineOrder {
        /// The next line due.
        expected: u16,
        /// The line pushed.
        got: u16,
    },
    /// A line of the wrong width.
    LineWidth {
        /// Columns `W`.
        expected: u16,
        /// Pixels in the line pushed (a packed line: `2 / 3` of its bytes).
        got: usize,
    },
    /// `begin_frame` after `finish`.
    Finished,
    /// [`Pipeline::push_packed_line`] on a 16-bit pool, or [`Pipeline::push_line`] on a
    /// packed pool whose [`Memory::scratch`] is shorter than [`Layout::scratch_bytes`].
    LineFormat,
    /// The front end gave no row ([`Pipeline::push_to_front_end`]).
    FrontEnd(FrontEndError),
}

/// The streaming D-PSA pipeline.
pub struct Pipeline<'a> {
    cfg: Config,
    scale: Scale,
    ref_phase: &'a [u32],
    /// Per-column height scale (`None`: the uniform [`Config::lsb_per_turn`]).
    columns: Option<ColumnScale<'a>>,
    pool: Pool<'a>,
    /// A packed copy of a 16-bit last observation ([`Layout::scratch_bytes`]).
    scratch: &'a mut [u8],
    reg: Registry<'a>,
    heights: &'a mut [i16],
    valid: &'a mut [u8],
    /// Next board row to emit.
    next_row: i64,
    open: bool,
    next_line: u16,
    prev_seq: u32,
    prev_latch: i64,
    /// Window of the rows completing in the open frame, in the kernel's form, with its
    /// modulation gate.
    win: Result<(Coef, Gate), SolveError>,
    /// `Config::hash` of the configuration and reference phase.
    hash: u64,
    /// The sink was told the stream started / ended.
    started: bool,
    ended: bool,
    /// The build of the phase + height stage ([`Kernel::best`] unless set).
    kernel: Kernel,
}

impl<'a> Pipeline<'a> {
    /// Builds a pipeline. `ref_phase[c]` is `phi_0(c)` as a binary angle (a wrapping `u32`,
    /// see [`crate::phase`]). Every column has the height scale [`Config::lsb_per_turn`].
    pub fn new(cfg: Config, ref_phase: &'a [u32], mem: Memory<'a>) -> Result<Self, NewError> {
        Self::with_column_scale(cfg, ref_phase, None, mem)
    }

    /// [`Pipeline::new`] with an optional per-column height scale: with `Some(table)`
    /// column `c`'s heights are in LSB at `table`'s `k_c` LSB per turn (checked by
    /// [`ColumnScale::check`]), so every column's heights are in the same calibrated unit;
    /// with `None` exactly [`Pipeline::new`]. The table joins the stream's `config_hash`
    /// ([`Config::hash_with`]).
    pub fn with_column_scale(
        cfg: Config,
        ref_phase: &'a [u32],
        columns: Option<ColumnScale<'a>>,
        mem: Memory<'a>,
    ) -> Result<Self, NewError> {
        cfg.validate().map_err(NewError::Config)?;
        if let Some(t) = &columns {
            t.check(&cfg).map_err(NewError::ColumnScale)?;
        }
        let lay = Layout::of(&cfg);
        let w = lay.width;
        if ref_phase.len() < w
            || mem.free.len() < lay.pool_lines
            || mem.slots.len() < lay.slots
            || mem.heights.len() < w
            || mem.valid.len() < w.div_ceil(8)
        {
            return Err(NewError::Memory);
        }
        let pool = Pool::new(
            w,
            lay.pool_line_units,
            lay.packed,
            mem.lines,
            &mut mem.free[..lay.pool_lines],
        )
        .ok_or(NewError::Memory)?;
        let heights = &mut mem.heights[..w];
        let valid = &mut mem.valid[..w.div_ceil(8)];
        heights.fill(0);
        valid.fill(0);
        Ok(Pipeline {
            cfg,
            scale: Scale::new(&cfg),
            ref_phase: &ref_phase[..w],
            columns,
            pool,
            scratch: mem.scratch,
            reg: Registry::new(&mut mem.slots[..lay.slots]),
            heights,
            valid,
            next_row: 0,
            open: false,
            next_line: 0,
            prev_seq: 0,
            prev_latch: 0,
            win: Err(SolveError::BadCount),
            hash: cfg.hash_with(&ref_phase[..w], columns.as_ref()),
            started: false,
            ended: false,
            kernel: Kernel::best(),
        })
    }

    /// Runs the phase + height stage with `kernel` (the results are the same with every
    /// kernel: tested in [`crate::lanes`] and below).
    pub fn set_kernel(&mut self, kernel: Kernel) {
        self.kernel = kernel;
    }

    /// The kernel of the phase + height stage.
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// What the stream holds ([`Sink::start`]); `run_id` and `intra_period` are 0 (the sink
    /// sets them).
    pub fn stream_info(&self) -> StreamInfo {
        StreamInfo {
            camera: self.cfg.camera,
            n: self.cfg.n,
            width: self.cfg.width,
            rows: self.cfg.rows,
            max_step_rows: self.cfg.max_step_rows,
            config_hash: self.hash,
            run_id: 0,
            intra_period: 0,
        }
    }

    fn start<S: Sink>(&mut self, sink: &mut S) -> Result<(), Error<S::Error>> {
        if !self.started {
            self.started = true;
            sink.start(&self.stream_info()).map_err(Error::Sink)?;
        }
        Ok(())
    }

    /// The configuration the pipeline runs.
    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// Line slots in use (for high-water measurements).
    pub fn pool_used(&self) -> usize {
        self.pool.used()
    }

    /// Starts the frame of `trigger` (frame counter `seq`, latched encoder count `latch`).
    pub fn begin_frame<S: Sink>(
        &mut self,
        trigger: Trigger,
        sink: &mut S,
    ) -> Result<(), Error<S::Error>> {
        if self.open {
            return Err(Error::FrameOpen);
        }
        if self.ended {
            return Err(Error::Finished);
        }
        self.start(sink)?;
        // The stream's trigger log: every frame taken, before anything it completes.
        sink.trigger(&trigger).map_err(Error::Sink)?;
        let Trigger { seq, latch } = trigger;
        let f = self.reg.begun();
        let o = self.cfg.offset(latch);
        let step = registration::classify(f == 0, self.prev_latch, latch, self.reg.entered_end, o);
        if step == Step::First {
            self.next_row = o;
            self.reg.entered_end = o;
        } else if seq != self.prev_seq.wrapping_add(1) {
            self.kill_open(flags::FRAME_GAP);
        }
        match step {
            Step::Reversal => self.kill_open(flags::ENCODER_REVERSAL),
            Step::Jump { .. } => self.kill_open(flags::ENCODER_FAULT),
            Step::First | Step::Forward => {}
        }
        // Rows above the ROI can no longer be observed.
        self.drain_until(o, flags::INCOMPLETE, sink)?;
        if let Step::Jump {
            gap_first,
            gap_rows,
        } = step
        {
            // One record for the rows no frame showed; registration restarts at `o`.
            self.reg.restart(o);
            self.next_row = o;
            sink.gap(&Gap {
                camera: self.cfg.camera,
                first: gap_first,
                count: gap_rows,
                flags: flags::SKIPPED | flags::ENCODER_FAULT,
            })
            .map_err(Error::Sink)?;
        }
        // Admission of the rows that entered at the bottom.
        self.reg
            .admit(o, latch, self.cfg.rows, self.cfg.max_step_rows);
        // Window of the rows that entered n-1 frames ago and complete now.
        let n = self.cfg.n as usize;
        self.win = Err(SolveError::BadCount);
        if f as usize + 1 >= n {
            let w0 = f + 1 - n as u32;
            let mut offsets = [0i64; MAX_N];
            for (j, o) in offsets.iter_mut().enumerate().take(n) {
                *o = self.reg.admission(w0 + j as u32).offset;
            }
            let mut shifts = [0u32; MAX_N];
            self.cfg.shifts(&offsets[..n], &mut shifts);
            self.win = Window::solve(&shifts[..n], self.cfg.max_noise_gain).and_then(|w| {
                let c = Coef::of(&w, self.cfg.saturation).ok_or(SolveError::IllConditioned)?;
                Ok((c, self.scale.gate(c.frac)))
            });
        }
        self.open = true;
        self.next_line = 0;
        self.prev_seq = seq;
        self.prev_latch = latch;
        Ok(())
    }

    /// Delivers image row `r` (in order `0..H`) of the open frame: `W` samples. On a packed
    /// pool ([`Layout::packed`]) the line is packed on the way in, which needs
    /// [`Memory::scratch`] ([`Error::LineFormat`] without it).
    pub fn push_line<S: Sink>(
        &mut self,
        r: u16,
        line: &[u16],
        sink: &mut S,
    ) -> Result<(), Error<S::Error>> {
        self.push(r, Line::Wide(line), None, sink)
    }

    /// Delivers image row `r` of the open frame as a 12-bit camera sends it: Mono12p,
    /// [`mono12p::packed_len`]`(W)` bytes (extra bytes are ignored). Only for a packed pool
    /// ([`Layout::packed`]; else [`Error::LineFormat`]); the pool keeps the bytes as they
    /// are, and the final observation of a row is read in place.
    pub fn push_packed_line<S: Sink>(
        &mut self,
        r: u16,
        line: &[u8],
        sink: &mut S,
    ) -> Result<(), Error<S::Error>> {
        self.push(r, Line::Packed(line), None, sink)
    }

    /// Delivers image row `r` of the open frame ([`Line::Wide`] as [`Pipeline::push_line`],
    /// [`Line::Packed`] as [`Pipeline::push_packed_line`]) to a pipeline whose per-pixel
    /// stages run in the front end `fe` ([`crate::offload`]): every decision is the one the
    /// pipeline makes on its own (admission, pool slots, flags, rows emitted), but a kept line
    /// goes to [`FrontEnd::keep`] instead of this pool's memory and a completed row is
    /// [`FrontEnd::row`]'s. The rows equal the pipeline's own when the front end's rows do.
    /// A front end that gives no row ([`Error::FrontEnd`]) ends what this stream can be
    /// trusted with: the row is not emitted.
    pub fn push_to_front_end<S: Sink>(
        &mut self,
        r: u16,
        line: Line<'_>,
        fe: &mut dyn FrontEnd,
        sink: &mut S,
    ) -> Result<(), Error<S::Error>> {
        self.push(r, line, Some(fe), sink)
    }

    fn push<S: Sink>(
        &mut self,
        r: u16,
        line: Line<'_>,
        fe: Option<&mut dyn FrontEnd>,
        sink: &mut S,
    ) -> Result<(), Error<S::Error>> {
        if !self.open {
            return Err(Error::NoFrame);
        }
        if r != self.next_line || r >= self.cfg.rows {
            return Err(Error::LineOrder {
                expected: self.next_line,
                got: r,
            });
        }
        let w = self.cfg.width as usize;
        let line = match line {
            Line::Wide(_) if self.pool.packed() && self.scratch.len() < mono12p::stored_len(w) => {
                return Err(Error::LineFormat);
            }
            Line::Packed(_) if !self.pool.packed() => return Err(Error::LineFormat),
            Line::Wide(l) if l.len() != w => {
                return Err(Error::LineWidth {
                    expected: self.cfg.width,
                    got: l.len(),
                });
            }
            Line::Packed(b) if b.len() < mono12p::packed_len(w) => {
                return Err(Error::LineWidth {
                    expected: self.cfg.width,
                    got: 2 * b.len() / 3,
                });
            }
            Line::Packed(b) => Line::Packed(&b[..mono12p::packed_len(w)]),
            wide => wide,
        };
        self.next_line += 1;
        let f = self.reg.begun().wrapping_sub(1);
        let b = self.reg.admission(f).offset + r as i64;
        if b < self.next_row {
            return Ok(()); // emitted already (more than n observations, or after a reversal)
        }
        let Kind::Admitted(s) = self.reg.kind(b) else {
            return Ok(()); // skipped rows carry no samples
        };
        let n = self.cfg.n as usize;
        let slot = &mut self.reg.slots[s];
        if slot.flags & flags::ROW_INVALID != 0 {
            return Ok(());
        }
        let j = f.wrapping_sub(slot.enter) as usize;
        if j != slot.count as usize {
            self.kill(s, flags::FRAME_GAP);
            return Ok(());
        }
        if j + 1 < n {
            let stored = match (fe, line) {
                (Some(fe), line) => self.pool.take_slot().inspect(|&l| fe.keep(l, line)),
                (None, Line::Wide(l)) => self.pool.store(l),
                (None, Line::Packed(b)) => self.pool.store_packed(b),
            };
            match stored {
                Some(l) => {
                    let slot = &mut self.reg.slots[s];
                    slot.lines[j] = l;
                    slot.count += 1;
                }
                None => self.kill(s, flags::OVERFLOW),
            }
            return Ok(());
        }
        // Final observation: everything before this row is finished first.
        self.drain_until(b, flags::FRAME_GAP, sink)?;
        let win = match self.win {
            Ok(w) => w,
            Err(_) => {
                self.kill(s, flags::ILL_CONDITIONED);
                return self.emit_dead(b, sink);
            }
        };
        let w0 = f + 1 - n as u32;
        let (o0, latch0) = (self.reg.admission(w0).offset, self.reg.admission(w0).latch);
        let rho = self.cfg.row_phase(b - o0);
        let row_flags = match fe {
            None => self.compute(s, &win.0, &win.1, rho, line),
            Some(fe) => {
                let slot = self.reg.slots[s];
                let job = RowJob {
                    row: b,
                    slots: &slot.lines[..n - 1],
                    coef: &win.0,
                    gate: &win.1,
                    rho,
                };
                match fe.row(&job, line, self.heights, self.valid) {
                    Ok(f) => f,
                    Err(e) => {
                        self.release(s);
                        self.heights.fill(0);
                        self.valid.fill(0);
                        return Err(Error::FrontEnd(e));
                    }
                }
            }
        };
        self.release(s);
        let header = self.header(b, latch0, row_flags);
        let res = sink.row(&Row {
            header,
            heights: self.heights,
            valid: self.valid,
        });
        self.heights.fill(0);
        self.valid.fill(0);
        self.next_row = b + 1;
        res.map_err(Error::Sink)
    }

    /// Ends the open frame. A frame that delivered fewer than `H` lines flags the rows whose
    /// line is missing (`FRAME_GAP`).
    pub fn end_frame<S: Sink>(&mut self, sink: &mut S) -> Result<(), Error<S::Error>> {
        if !self.open {
            return Err(Error::NoFrame);
        }
        let f = self.reg.begun().wrapping_sub(1);
        let o = self.reg.admission(f).offset;
        let missing_from = (o + self.next_line as i64).max(self.next_row);
        for b in missing_from..o + self.cfg.rows as i64 {
            if let Kind::Admitted(s) = self.reg.kind(b) {
                if self.reg.slots[s].flags & flags::ROW_INVALID == 0 {
                    self.kill(s, flags::FRAME_GAP);
                }
            }
        }
        self.open = false;
        // Emit finished rows at the front: skipped rows and dead rows whose window has ended.
        let n = self.cfg.n as u32;
        while self.next_row < self.reg.entered_end {
            match self.reg.kind(self.next_row) {
                Kind::Admitted(s) => {
                    let slot = self.reg.slots[s];
                    let ended = f.wrapping_sub(slot.enter) + 1 >= n;
                    if slot.flags & flags::ROW_INVALID == 0 || !ended {
                        break;
                    }
                }
                Kind::Skipped | Kind::Gone => {}
            }
            self.emit_dead(self.next_row, sink)?;
        }
        Ok(())
    }

    /// Ends the stream: closes an open frame, emits every open row as `INCOMPLETE` and tells
    /// the sink the stream ended ([`Sink::end`], once; a stream without frames is announced
    /// and ended too). Afterwards `begin_frame` is an error; `finish` again does nothing.
    pub fn finish<S: Sink>(&mut self, sink: &mut S) -> Result<(), Error<S::Error>> {
        if self.ended {
            return Ok(());
        }
        self.start(sink)?;
        if self.open {
            self.end_frame(sink)?;
        }
        self.drain_until(self.reg.entered_end, flags::INCOMPLETE, sink)?;
        self.ended = true;
        sink.end().map_err(Error::Sink)
    }

    /// Marks an admitted row invalid and returns its lines to the pool.
    fn kill(&mut self, s: usize, flag: u16) {
        self.release(s);
        self.reg.slots[s].flags |= flag;
    }

    fn release(&mut self, s: usize) {
        let slot = &mut self.reg.slots[s];
        let used = (slot.count as usize).min(MAX_N - 1);
        for &l in &slot.lines[..used] {
            self.pool.release(l);
        }
        slot.count = 0;
    }

    /// Marks every open admitted row invalid.
    fn kill_open(&mut self, flag: u16) {
        let mut b = self.next_row;
        while b < self.reg.entered_end {
            if let Kind::Admitted(s) = self.reg.kind(b) {
                self.kill(s, flag);
            }
            b += 1;
        }
    }

    /// Emits every row in `[next_row, until)` as invalid; open rows get `reason`.
    fn drain_until<S: Sink>(
        &mut self,
        until: i64,
        reason: u16,
        sink: &mut S,
    ) -> Result<(), Error<S::Error>> {
        let until = until.min(self.reg.entered_end);
        while self.next_row < until {
            if let Kind::Admitted(s) = self.reg.kind(self.next_row) {
                if self.reg.slots[s].flags & flags::ROW_INVALID == 0 {
                    self.kill(s, reason);
                }
            }
            self.emit_dead(self.next_row, sink)?;
        }
        Ok(())
    }

    /// Emits row `b` (== next_row) without heights.
    fn emit_dead<S: Sink>(&mut self, b: i64, sink: &mut S) -> Result<(), Error<S::Error>> {
        let (fl, latch) = match self.reg.kind(b) {
            Kind::Admitted(s) => {
                let slot = self.reg.slots[s];
                self.release(s);
                (slot.flags, self.reg.window_latch(slot.enter))
            }
            Kind::Skipped | Kind::Gone => (flags::SKIPPED, 0),
        };
        let header = self.header(b, latch, fl);
        self.next_row = b + 1;
        sink.row(&Row {
            header,
            heights: self.heights,
            valid: self.valid,
        })
        .map_err(Error::Sink)
    }

    fn header(&self, row: i64, latch: i64, flags: u16) -> RowHeader {
        RowHeader {
            camera: self.cfg.camera,
            n: self.cfg.n,
            row,
            latch,
            flags,
            width: self.cfg.width,
        }
    }

    /// The hot loop: `v = P i`, phase, height and mask for every column of a completed row.
    fn compute(&mut self, s: usize, coef: &Coef, gate: &Gate, rho: u32, last: Line<'_>) -> u16 {
        let n = coef.n;
        let slot = self.reg.slots[s];
        let w = self.cfg.width as usize;
        let lines = if self.pool.packed() {
            let mut lines: [&[u8]; MAX_N] = [&[]; MAX_N];
            for (j, l) in lines.iter_mut().enumerate().take(n - 1) {
                *l = self.pool.packed_line(slot.lines[j]);
            }
            lines[n - 1] = match last {
                Line::Packed(b) => b,
                Line::Wide(l) => {
                    mono12p::pack(l, self.scratch);
                    &self.scratch[..]
                }
            };
            if lines[..n].iter().any(|l| l.len() < mono12p::packed_len(w)) {
                return flags::OVERFLOW;
            }
            Lines::Packed(lines)
        } else {
            let mut lines: [&[u16]; MAX_N] = [&[]; MAX_N];
            for (j, l) in lines.iter_mut().enumerate().take(n - 1) {
                *l = self.pool.line(slot.lines[j]);
            }
            lines[n - 1] = match last {
                Line::Wide(l) => l,
                Line::Packed(_) => &[],
            };
            if lines[..n].iter().any(|l| l.len() < w) {
                return flags::OVERFLOW;
            }
            Lines::Wide(lines)
        };
        let rows = Rows {
            lines,
            w,
            sat: self.cfg.saturation,
            rho,
            ref_phase: self.ref_phase,
            columns: self.columns,
            kernel: self.kernel,
        };
        rows.run(n, coef, gate, &self.scale, self.heights, self.valid)
    }
}

/// The `n` lines of a completed row, as the pool keeps them.
enum Lines<'l> {
    Wide([&'l [u16]; MAX_N]),
    Packed([&'l [u8]; MAX_N]),
}

/// Columns processed per block: the accumulate stage fills `BLOCK` reduced pixels on the stack
/// (512 B), the phase stage consumes them. A multiple of 8 so validity bytes stay whole.
pub const BLOCK: usize = 64;

/// The inputs of one completed row.
struct Rows<'l> {
    lines: Lines<'l>,
    w: usize,
    sat: u16,
    rho: u32,
    ref_phase: &'l [u32],
    columns: Option<ColumnScale<'l>>,
    kernel: Kernel,
}

impl Rows<'_> {
    /// Both stages, block by block: [`accumulate::block`] and [`Scale::row`] (or
    /// [`Scale::row_columns`]), the never-inlined functions the firmware's stage benchmark
    /// times.
    fn run(
        &self,
        n: usize,
        coef: &Coef,
        gate: &Gate,
        scale: &Scale,
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> u16 {
        let mut v = [[0i32; 2]; BLOCK];
        let mut row_flags = 0;
        let mut c0 = 0;
        while c0 < self.w {
            let len = BLOCK.min(self.w - c0);
            match &self.lines {
                Lines::Wide(l) => {
                    accumulate::block_with(self.kernel, coef, &l[..n], c0, self.sat, &mut v[..len])
                }
                Lines::Packed(l) => accumulate::block_packed_with(
                    self.kernel,
                    coef,
                    &l[..n],
                    c0,
                    self.sat,
                    &mut v[..len],
                ),
            }
            let (v, r) = (&v[..len], &self.ref_phase[c0..c0 + len]);
            let (h, m) = (&mut heights[c0..c0 + len], &mut valid[c0 / 8..]);
            row_flags |= match &self.columns {
                None => self.kernel.row(scale, gate, v, self.rho, r, h, m),
                Some(t) => {
                    let k = &t.mantissa()[c0..c0 + len];
                    self.kernel
                        .row_columns(scale, gate, v, self.rho, r, t, k, h, m)
                }
            };
            c0 += len;
        }
        row_flags
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::phase::from_rad;
    use fixed::types::{U16F16, U20F12, U8F8};
    use proptest::prelude::*;
    use std::f64::consts::PI;
    use std::vec;
    use std::vec::Vec;

    const W: usize = 16;
    const H: u16 = 40;

    fn cfg() -> Config {
        Config {
            width: W as u16,
            rows: H,
            n: 4,
            camera: 3,
            counts_per_pixel: U16F16::from_num(10),
            fx: 1 << 27, // period 32 px
            lsb_per_turn: U16F16::from_num(2000),
            saturation: 4095,
            min_modulation: U20F12::from_num(40),
            max_noise_gain: U8F8::from_num(2),
            max_step_rows: 8,
        }
    }

    /// A row as collected: header, heights, validity bytes.
    type Collected = (RowHeader, Vec<i16>, Vec<u8>);

    #[derive(Default)]
    struct Collect(Vec<Collected>);
    impl Sink for Collect {
        type Error = ();
        fn row(&mut self, r: &Row<'_>) -> Result<(), ()> {
            self.0
                .push((r.header, r.heights.to_vec(), r.valid.to_vec()));
            Ok(())
        }
    }

    /// Height (um) of board row b, column c: a 100 um step on rows 60..80.
    fn truth(b: i64, _c: usize) -> f64 {
        if (60..80).contains(&b) {
            100.0
        } else {
            0.0
        }
    }

    fn phi0(c: usize) -> f64 {
        0.3 + 0.05 * c as f64
    }

    /// Noiseless frame at offset `pos` (px).
    fn frame(pos: i64) -> Vec<Vec<u16>> {
        frame_tz(pos, |_| 500.0)
    }

    /// Noiseless frame at offset `pos` (px) with height per turn `tz(c)` um in column `c`.
    fn frame_tz(pos: i64, tz: impl Fn(usize) -> f64) -> Vec<Vec<u16>> {
        (0..H as i64)
            .map(|r| {
                (0..W)
                    .map(|c| {
                        let ph = 2.0 * PI * r as f64 / 32.0
                            + phi0(c)
                            + 2.0 * PI * truth(r + pos, c) / tz(c);
                        (1800.0 + 700.0 * ph.cos()).round() as u16
                    })
                    .collect()
            })
            .collect()
    }

    fn run(latches: &[i64], seqs: &[u32], lines_per_frame: &[u16]) -> (Collect, usize) {
        let c = cfg();
        let refp: Vec<u32> = (0..W).map(|c| from_rad(phi0(c))).collect();
        let mut m = State::new(&c);
        let mut p = Pipeline::new(c, &refp, m.memory()).unwrap();
        let mut sink = Collect::default();
        for (k, &e) in latches.iter().enumerate() {
            p.begin_frame(
                Trigger {
                    seq: seqs[k],
                    latch: e,
                },
                &mut sink,
            )
            .unwrap();
            let fr = frame(c.offset(e));
            for r in 0..lines_per_frame[k] {
                p.push_line(r, &fr[r as usize], &mut sink).unwrap();
            }
            p.end_frame(&mut sink).unwrap();
        }
        p.finish(&mut sink).unwrap();
        let used = p.pool_used();
        (sink, used)
    }

    fn check_order(rows: &[(RowHeader, Vec<i16>, Vec<u8>)]) {
        for w in rows.windows(2) {
            assert_eq!(
                w[1].0.row,
                w[0].0.row + 1,
                "rows must be contiguous and increasing"
            );
        }
    }

    /// A 12-bit configuration keeps Mono12p lines: lines delivered packed (as a 12-bit camera
    /// sends them) and the same lines as u16 (packed on the way in) give identical rows,
    /// also with samples at and above the saturation level (5000 is stored as 4095 and stays
    /// saturated); a 16-bit pool refuses packed lines and a packed pool refuses u16 lines
    /// without the scratch line.
    #[test]
    fn packed_lines_give_the_rows_of_u16_lines() {
        let c = cfg();
        assert!(Layout::of(&c).packed && Layout::of(&c).scratch_bytes() > 0);
        let refp: Vec<u32> = (0..W).map(|c| from_rad(phi0(c))).collect();
        let latches: Vec<i64> = (0..12).map(|k| k * 70).collect();
        let frames: Vec<Vec<Vec<u16>>> = latches
            .iter()
            .map(|&e| {
                let mut f = frame(c.offset(e));
                f[35][5] = 5000;
                f[36][9] = 4095;
                f[38][11] = 4094;
                f
            })
            .collect();
        let go = |packed: bool| {
            let mut m = State::new(&c);
            let mut p = Pipeline::new(c, &refp, m.memory()).unwrap();
            let mut sink = Collect::default();
            let mut b = vec![0u8; mono12p::packed_len(W)];
            for (k, &e) in latches.iter().enumerate() {
                let t = Trigger {
                    seq: k as u32,
                    latch: e,
                };
                p.begin_frame(t, &mut sink).unwrap();
                for (r, line) in frames[k].iter().enumerate() {
                    if packed {
                        mono12p::pack(line, &mut b);
                        p.push_packed_line(r as u16, &b, &mut sink).unwrap();
                    } else {
                        p.push_line(r as u16, line, &mut sink).unwrap();
                    }
                }
                p.end_frame(&mut sink).unwrap();
            }
            p.finish(&mut sink).unwrap();
            sink.0
        };
        let (wide, packed) = (go(false), go(true));
        assert!(wide.len() > 20);
        assert_eq!(wide, packed);
        assert!(wide.iter().any(|r| r.0.flags & flags::SATURATED != 0));
        // Formats the pool cannot take.
        let mut s = Collect::default();
        let mut m = State::new(&c);
        let Memory {
            lines,
            free,
            slots,
            heights,
            valid,
            ..
        } = m.memory();
        let mem = Memory {
            lines,
            scratch: &mut [],
            free,
            slots,
            heights,
            valid,
        };
        let mut p = Pipeline::new(c, &refp, mem).unwrap();
        p.begin_frame(Trigger { seq: 0, latch: 0 }, &mut s).unwrap();
        assert_eq!(p.push_line(0, &[0; W], &mut s), Err(Error::LineFormat));
        let mut c16 = c;
        c16.saturation = 65535;
        assert!(!Layout::of(&c16).packed);
        let mut m = State::new(&c16);
        let mut p = Pipeline::new(c16, &refp, m.memory()).unwrap();
        p.begin_frame(Trigger { seq: 0, latch: 0 }, &mut s).unwrap();
        let b = vec![0u8; mono12p::packed_len(W)];
        assert_eq!(p.push_packed_line(0, &b, &mut s), Err(Error::LineFormat));
    }

    #[test]
    fn uniform_motion_recovers_heights() {
        let latches: Vec<i64> = (0..40).map(|k| k * 80 - 200).collect(); // 8 px per frame
        let seqs: Vec<u32> = (0..40).collect();
        let (out, used) = run(&latches, &seqs, &[H; 40]);
        assert_eq!(used, 0, "pool leaked");
        check_order(&out.0);
        let mut valid_rows = 0;
        for (h, heights, valid) in &out.0 {
            if h.flags & flags::ROW_INVALID != 0 {
                assert!(valid.iter().all(|&v| v == 0));
                continue;
            }
            valid_rows += 1;
            let b = h.row;
            // Flat rows only (the 100 um step edges are lateral sampling).
            if (56..84).contains(&b) && !(62..78).contains(&b) {
                continue;
            }
            for c in 0..W {
                assert!(valid[c / 8] & (1 << (c % 8)) != 0);
                let want = truth(b, c) / 0.25;
                assert!(
                    (heights[c] as f64 - want).abs() <= 1.0,
                    "row {b} col {c}: {} vs {want}",
                    heights[c]
                );
            }
        }
        let fl: Vec<(i64, u16)> = out.0.iter().map(|r| (r.0.row, r.0.flags)).collect();
        assert!(valid_rows > 200, "{valid_rows} {fl:?}");
        // First frame: rows above the admission band are SKIPPED; the end is INCOMPLETE.
        assert_eq!(out.0[0].0.flags, flags::SKIPPED);
        assert_eq!(
            out.0.last().unwrap().0.flags & flags::INCOMPLETE,
            flags::INCOMPLETE
        );
    }

    /// Runs uniform motion over frames with per-column `T_z`; returns the rows and the
    /// stream's config hash.
    fn run_columns(
        tz: impl Fn(usize) -> f64 + Copy,
        columns: Option<ColumnScale<'_>>,
    ) -> (Vec<Collected>, u64) {
        let c = cfg();
        let refp: Vec<u32> = (0..W).map(|c| from_rad(phi0(c))).collect();
        let mut m = State::new(&c);
        let mut p = Pipeline::with_column_scale(c, &refp, columns, m.memory()).unwrap();
        let mut sink = Collect::default();
        for k in 0..40u32 {
            let e = k as i64 * 80 - 200;
            p.begin_frame(Trigger { seq: k, latch: e }, &mut sink)
                .unwrap();
            for (r, line) in frame_tz(c.offset(e), tz).iter().enumerate() {
                p.push_line(r as u16, line, &mut sink).unwrap();
            }
            p.end_frame(&mut sink).unwrap();
        }
        p.finish(&mut sink).unwrap();
        (sink.0, p.stream_info().config_hash)
    }

    /// Whole rows through every kernel of the phase + height stage ([`Kernel::all`]): the
    /// same rows, byte for byte, as the scalar loop (the firmware's), with noise, saturated
    /// samples, unmodulated columns, an odd width (77: a partial lane group at the end of
    /// every block), n = 3..8, 12- and 16-bit pools, the uniform and the per-column scale.
    #[test]
    fn every_kernel_gives_the_same_rows() {
        const WK: usize = 77;
        let mut seed = 0x1234_5678u64;
        let mut noise = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) % 41) as f64 - 20.0
        };
        let tz = |c: usize| 500.0 * (1.0 + 0.02 * (c as f64 * 0.37).sin());
        let k: Vec<U16F16> = (0..WK)
            .map(|c| U16F16::from_bits((tz(c) / 0.25 * 65536.0).round() as u32))
            .collect();
        let mut mant = vec![0u16; WK];
        let shift = ColumnScale::encode(&k, &mut mant).unwrap();
        let refp: Vec<u32> = (0..WK).map(|c| from_rad(phi0(c))).collect();
        let kernels: Vec<Kernel> = Kernel::all().collect();
        assert!(kernels.len() >= 2);
        for n in 3..=8u8 {
            for saturation in [4095u16, 65535] {
                let mut c = cfg();
                c.width = WK as u16;
                c.n = n;
                c.saturation = saturation;
                c.max_step_rows = 16;
                // Frames: noise, a few saturated samples, columns 40..44 unmodulated; about a
                // turn over the window (32 / n px per frame).
                let step = (32 + i64::from(n) / 2) / i64::from(n) * 10;
                let frames: Vec<Vec<Vec<u16>>> = (0..40i64)
                    .map(|f| {
                        (0..H as i64)
                            .map(|r| {
                                (0..WK)
                                    .map(|col| {
                                        let e = f * step - 200;
                                        let ph = 2.0 * PI * r as f64 / 32.0
                                            + phi0(col)
                                            + 2.0 * PI * truth(r + c.offset(e), col % W) / tz(col);
                                        let amp = if (40..44).contains(&col) { 0.0 } else { 700.0 };
                                        let v = 1800.0 + amp * ph.cos() + noise();
                                        if (r * 7 + col as i64 + f) % 97 == 0 {
                                            saturation
                                        } else {
                                            v.round() as u16
                                        }
                                    })
                                    .collect()
                            })
                            .collect()
                    })
                    .collect();
                for table in [false, true] {
                    let go = |kernel: Kernel| {
                        let mut m = State::new(&c);
                        let cols = table.then(|| ColumnScale::new(shift, &mant));
                        let mut p =
                            Pipeline::with_column_scale(c, &refp, cols, m.memory()).unwrap();
                        p.set_kernel(kernel);
                        let mut sink = Collect::default();
                        for (f, fr) in frames.iter().enumerate() {
                            let t = Trigger {
                                seq: f as u32,
                                latch: f as i64 * step - 200,
                            };
                            p.begin_frame(t, &mut sink).unwrap();
                            for (r, line) in fr.iter().enumerate() {
                                p.push_line(r as u16, line, &mut sink).unwrap();
                            }
                            p.end_frame(&mut sink).unwrap();
                        }
                        p.finish(&mut sink).unwrap();
                        sink.0
                    };
                    let want = go(Kernel::Scalar);
                    assert!(
                        want.iter().any(|r| r.0.flags & flags::SATURATED != 0)
                            && want.iter().any(|r| r.0.flags & flags::LOW_MODULATION != 0)
                            && want.iter().filter(|r| r.0.flags & flags::ROW_INVALID == 0).count() > 50,
                        "n {n}, saturation {saturation}: the input classes must all occur: {} rows, {} valid, saturated {}, low {}",
                        want.len(),
                        want.iter().filter(|r| r.0.flags & flags::ROW_INVALID == 0).count(),
                        want.iter().any(|r| r.0.flags & flags::SATURATED != 0),
                        want.iter().any(|r| r.0.flags & flags::LOW_MODULATION != 0)
                    );
                    for &k in &kernels[1..] {
                        assert!(
                            go(k) == want,
                            "kernel {} differs from the scalar loop: n {n}, saturation {saturation}, table {table}",
                            k.name()
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn column_scale_gives_calibrated_heights_in_every_column() {
        // T_z varies +-2 % over the columns; the configuration's uniform scale is the mean.
        let tz = |c: usize| 500.0 * (1.0 + 0.02 * (c as f64 * 0.9).sin());
        let k: Vec<U16F16> = (0..W)
            .map(|c| U16F16::from_bits((tz(c) / 0.25 * 65536.0).round() as u32))
            .collect();
        let mut m = vec![0u16; W];
        let shift = ColumnScale::encode(&k, &mut m).unwrap();
        let table = ColumnScale::new(shift, &m);
        let (with, hash_with) = run_columns(tz, Some(table));
        let (without, hash_without) = run_columns(tz, None);
        // Without the table the step is 100 um / T_z(c) turns at 2000 LSB per turn: off by up
        // to 2 % of 400 LSB; with it, 400 LSB within rounding in every column.
        let (mut worst_with, mut worst_without, mut pixels) = (0f64, 0f64, 0);
        for ((h, a, va), (_, b, _)) in with.iter().zip(&without) {
            if h.flags & flags::ROW_INVALID != 0 || !(64..76).contains(&h.row) {
                continue;
            }
            for c in 0..W {
                assert!(va[c / 8] & (1 << (c % 8)) != 0);
                worst_with = worst_with.max((a[c] as f64 - 400.0).abs());
                let uniform = 100.0 / tz(c) * 2000.0;
                worst_without = worst_without.max((b[c] as f64 - uniform).abs());
                pixels += 1;
            }
        }
        assert!(pixels > 100, "{pixels}");
        assert!(worst_with <= 1.0, "with the table: {worst_with} LSB");
        assert!(worst_without <= 1.0, "uniform: {worst_without} LSB");
        // The table is part of the configuration: its hash differs, the rest is the same.
        assert_ne!(hash_with, hash_without);
        assert_eq!(with.len(), without.len());
        let c = cfg();
        let refp: Vec<u32> = (0..W).map(|c| from_rad(phi0(c))).collect();
        assert_eq!(hash_without, c.hash(&refp));
        assert_eq!(hash_with, c.hash_with(&refp, Some(&table)));
        // `with_column_scale(.., None, ..)` is `new`: the same rows as the plain run.
        let (plain, _) = run(
            &(0..40).map(|k| k * 80 - 200).collect::<Vec<_>>(),
            &(0..40).collect::<Vec<_>>(),
            &[H; 40],
        );
        let (none, _) = run_columns(|_| 500.0, None);
        assert_eq!(plain.0, none);
    }

    #[test]
    fn bad_column_scale_is_refused() {
        let c = cfg();
        let refp = vec![0u32; W];
        let k = c.lsb_per_turn.to_bits();
        let good = vec![(k >> 11) as u16; W];
        let mut st = State::new(&c);
        let ok =
            Pipeline::with_column_scale(c, &refp, Some(ColumnScale::new(11, &good)), st.memory());
        assert!(ok.is_ok());
        let cases: [(u8, Vec<u16>, ColumnScaleError); 4] = [
            (
                11,
                good[..W - 1].to_vec(),
                ColumnScaleError::Length {
                    expected: W as u16,
                    got: W - 1,
                },
            ),
            (16, good.clone(), ColumnScaleError::Shift(16)),
            (
                11,
                good.iter()
                    .enumerate()
                    .map(|(i, &g)| if i == 2 { 0 } else { g })
                    .collect(),
                ColumnScaleError::Range { column: 2 },
            ),
            (
                15,
                good.clone(), // 16x the configuration's scale
                ColumnScaleError::Range { column: 0 },
            ),
        ];
        for (shift, table, want) in cases {
            let mut st = State::new(&c);
            let r = Pipeline::with_column_scale(
                c,
                &refp,
                Some(ColumnScale::new(shift, &table)),
                st.memory(),
            );
            assert!(
                matches!(r, Err(NewError::ColumnScale(e)) if e == want),
                "{shift}: {want:?}"
            );
        }
    }

    #[test]
    fn layout_counts_the_column_table() {
        let c = cfg();
        let l = Layout::of(&c);
        assert_eq!(l.scale_columns, 0);
        let t = l.with_column_scale(true);
        assert_eq!(t.bytes(), l.bytes() + 2 * W);
        assert_eq!(t.with_column_scale(false), l);
    }

    #[test]
    fn stall_gives_ill_conditioned_rows() {
        let mut latches: Vec<i64> = (0..10).map(|k| k * 80).collect();
        latches.extend([720; 6]);
        latches.extend((0..10).map(|k| 800 + k * 80));
        let seqs: Vec<u32> = (0..latches.len() as u32).collect();
        let (out, used) = run(&latches, &seqs, &[H; 26]);
        assert_eq!(used, 0);
        check_order(&out.0);
        assert!(out
            .0
            .iter()
            .any(|r| r.0.flags & flags::ILL_CONDITIONED != 0));
        assert!(out.0.iter().any(|r| r.0.flags == 0));
    }

    #[test]
    fn reversal_gap_and_truncation_are_flagged() {
        let latches: Vec<i64> = vec![
            0, 80, 160, 240, 320, 400, 300, 380, 460, 540, 620, 700, 780, 860, 940, 1020,
        ];
        let mut seqs: Vec<u32> = (0..16).collect();
        for s in seqs.iter_mut().skip(12) {
            *s += 1; // frame 12 lost
        }
        let mut lines = [H; 16];
        lines[3] = 5; // truncated frame
        let (out, used) = run(&latches, &seqs, &lines);
        assert_eq!(used, 0);
        check_order(&out.0);
        let any = |f: u16| out.0.iter().any(|r| r.0.flags & f != 0);
        assert!(any(flags::ENCODER_REVERSAL));
        assert!(any(flags::FRAME_GAP));
    }

    /// A software front end: its own line pool by slot, the offload seam's reference model per
    /// pixel ([`crate::offload::front_end_pixel`]) and [`crate::offload::finish_row`].
    struct Mirror {
        cfg: Config,
        refp: Vec<u32>,
        pool: Vec<Vec<u16>>,
        rows: usize,
        /// Deliver this row as another (a fault), once.
        misdeliver: Option<i64>,
    }

    impl Mirror {
        fn samples(&self, line: Line<'_>) -> Vec<u16> {
            let mut l = vec![0u16; self.cfg.width as usize];
            line.samples_into(&mut l, Layout::of(&self.cfg).packed);
            l
        }
    }

    impl FrontEnd for Mirror {
        fn keep(&mut self, slot: u16, line: Line<'_>) {
            let l = self.samples(line);
            if self.pool.len() <= slot as usize {
                self.pool.resize(slot as usize + 1, Vec::new());
            }
            self.pool[slot as usize] = l;
        }

        fn row(
            &mut self,
            job: &RowJob<'_>,
            last: Line<'_>,
            heights: &mut [i16],
            valid: &mut [u8],
        ) -> Result<u16, FrontEndError> {
            if self.misdeliver == Some(job.row) {
                self.misdeliver = None;
                return Err(FrontEndError::WrongRow {
                    asked: job.row,
                    got: job.row + 1,
                });
            }
            let last = self.samples(last);
            let lines: Vec<&[u16]> = job
                .slots
                .iter()
                .map(|&s| &self.pool[s as usize][..])
                .chain([&last[..]])
                .collect();
            let v: Vec<accumulate::V> = (0..self.cfg.width as usize)
                .map(|c| {
                    let x: Vec<u16> = lines.iter().map(|l| l[c]).collect();
                    crate::offload::front_end_pixel(job.coef, &x, self.cfg.saturation)
                })
                .collect();
            self.rows += 1;
            let scale = Scale::new(&self.cfg);
            let f = crate::offload::finish_row(
                &scale, job.coef, &v, job.rho, &self.refp, heights, valid,
            );
            Ok(f)
        }
    }

    /// Rows through a front end ([`Pipeline::push_to_front_end`]) equal the pipeline's own,
    /// bit for bit and flag for flag, lines delivered wide and packed, through a reversal, a
    /// lost frame, a truncated frame, an encoder jump, a stall and saturated samples; a front
    /// end that delivers the wrong row stops the stream with [`Error::FrontEnd`].
    #[test]
    fn a_front_end_gives_the_pipelines_rows() {
        let c = cfg();
        let refp: Vec<u32> = (0..W).map(|c| from_rad(phi0(c))).collect();
        let mut latches: Vec<i64> = vec![
            0, 80, 160, 240, 320, 400, 300, 380, 460, 540, 620, 700, 780, 860, 940, 1020,
        ];
        latches.extend((0..8).map(|k| 1_000_000 + k * 90));
        latches.extend([1_000_630; 5]);
        latches.extend((0..8).map(|k| 1_000_720 + k * 90));
        let seqs: Vec<u32> = (0..latches.len() as u32)
            .map(|k| if k >= 12 { k + 1 } else { k })
            .collect();
        let frames: Vec<Vec<Vec<u16>>> = latches
            .iter()
            .map(|&e| {
                let mut f = frame(c.offset(e));
                f[35][5] = 5000;
                f[36][9] = 4095;
                f
            })
            .collect();
        let go = |fe: Option<&mut Mirror>, packed: bool| {
            let mut m = State::new(&c);
            let mut p = Pipeline::new(c, &refp, m.memory()).unwrap();
            let mut sink = Collect::default();
            let mut fe = fe;
            let mut b = vec![0u8; mono12p::packed_len(W)];
            let mut err = None;
            'frames: for (k, &e) in latches.iter().enumerate() {
                let t = Trigger {
                    seq: seqs[k],
                    latch: e,
                };
                p.begin_frame(t, &mut sink).unwrap();
                let lines = if k == 3 { 5 } else { H as usize };
                for (r, l) in frames[k].iter().enumerate().take(lines) {
                    mono12p::pack(l, &mut b);
                    let line = if packed {
                        Line::Packed(&b)
                    } else {
                        Line::Wide(l)
                    };
                    let res = match fe.as_deref_mut() {
                        Some(fe) => p.push_to_front_end(r as u16, line, fe, &mut sink),
                        None if packed => p.push_packed_line(r as u16, &b, &mut sink),
                        None => p.push_line(r as u16, l, &mut sink),
                    };
                    if let Err(e) = res {
                        err = Some(e);
                        break 'frames;
                    }
                }
                p.end_frame(&mut sink).unwrap();
            }
            if err.is_none() {
                p.finish(&mut sink).unwrap();
            }
            (sink.0, err)
        };
        let mirror = || Mirror {
            cfg: c,
            refp: refp.clone(),
            pool: Vec::new(),
            rows: 0,
            misdeliver: None,
        };
        for packed in [false, true] {
            let (core, e) = go(None, packed);
            assert_eq!(e, None);
            let mut fe = mirror();
            let (front, e) = go(Some(&mut fe), packed);
            assert_eq!(e, None);
            assert_eq!(front, core, "packed {packed}");
            let valid_rows = core.iter().filter(|r| r.0.flags & flags::ROW_INVALID == 0);
            assert_eq!(
                fe.rows,
                valid_rows.count(),
                "every computed row came from the front end"
            );
            assert!(fe.rows > 50);
            let any = |f: u16| core.iter().any(|r| r.0.flags & f != 0);
            for f in [
                flags::ENCODER_REVERSAL,
                flags::FRAME_GAP,
                flags::ENCODER_FAULT,
                flags::ILL_CONDITIONED,
                flags::SATURATED,
            ] {
                assert!(any(f), "flag {f:#x} exercised");
            }
        }
        let mut fe = mirror();
        let (core, _) = go(None, false);
        let due = core.iter().find(|r| r.0.flags == 0).unwrap().0.row;
        fe.misdeliver = Some(due);
        let (front, e) = go(Some(&mut fe), false);
        assert_eq!(
            e,
            Some(Error::FrontEnd(FrontEndError::WrongRow {
                asked: due,
                got: due + 1
            }))
        );
        assert!(
            front.iter().all(|r| r.0.row < due),
            "the row was not emitted"
        );
    }

    #[test]
    fn api_misuse_is_an_error() {
        let c = cfg();
        let refp = vec![0u32; W];
        let mut m = State::new(&c);
        let mut p = Pipeline::new(c, &refp, m.memory()).unwrap();
        let mut s = Collect::default();
        assert_eq!(p.push_line(0, &[0; W], &mut s), Err(Error::NoFrame));
        assert_eq!(p.end_frame(&mut s), Err(Error::NoFrame));
        p.begin_frame(Trigger { seq: 0, latch: 0 }, &mut s).unwrap();
        assert_eq!(
            p.begin_frame(Trigger { seq: 1, latch: 0 }, &mut s),
            Err(Error::FrameOpen)
        );
        assert_eq!(
            p.push_line(1, &[0; W], &mut s),
            Err(Error::LineOrder {
                expected: 0,
                got: 1
            })
        );
        assert_eq!(
            p.push_line(0, &[0; 3], &mut s),
            Err(Error::LineWidth {
                expected: W as u16,
                got: 3
            })
        );
        let mut small = State::new(&c);
        let Memory {
            lines,
            scratch,
            free,
            slots,
            heights,
            valid,
        } = small.memory();
        let mem = Memory {
            lines,
            scratch,
            free: &mut free[..1],
            slots,
            heights,
            valid,
        };
        assert!(matches!(
            Pipeline::new(c, &refp, mem),
            Err(NewError::Memory)
        ));
        let mut bad = c;
        bad.n = 9;
        assert!(matches!(
            Pipeline::new(bad, &refp, State::new(&c).memory()),
            Err(NewError::Config(_))
        ));
    }

    /// Rows and gap records in order, start / end calls.
    #[derive(Default)]
    struct Items {
        /// (first board row, rows covered, flags)
        items: Vec<(i64, u64, u16)>,
        /// Each trigger record with the number of items before it.
        triggers: Vec<(usize, Trigger)>,
        starts: usize,
        ends: usize,
    }
    impl Sink for Items {
        type Error = ();
        fn trigger(&mut self, t: &Trigger) -> Result<(), ()> {
            assert_eq!(self.starts, 1, "a trigger record before the stream header");
            self.triggers.push((self.items.len(), *t));
            Ok(())
        }
        fn row(&mut self, r: &Row<'_>) -> Result<(), ()> {
            self.items.push((r.header.row, 1, r.header.flags));
            Ok(())
        }
        fn start(&mut self, _: &StreamInfo) -> Result<(), ()> {
            self.starts += 1;
            Ok(())
        }
        fn gap(&mut self, g: &Gap) -> Result<(), ()> {
            self.items.push((g.first, g.count, g.flags));
            Ok(())
        }
        fn end(&mut self) -> Result<(), ()> {
            self.ends += 1;
            Ok(())
        }
    }

    /// Runs `latches` (consecutive seqs, whole frames) with counts per pixel `cpp_q16`; checks
    /// the per-frame output bound and that the items tile increasing board rows; returns them.
    fn run_faults(latches: &[i64], cpp_q16: u32) -> Items {
        let mut c = cfg();
        c.counts_per_pixel = U16F16::from_bits(cpp_q16);
        let refp: Vec<u32> = (0..W).map(|c| from_rad(phi0(c))).collect();
        let mut m = State::new(&c);
        let mut p = Pipeline::new(c, &refp, m.memory()).unwrap();
        let mut sink = Items::default();
        let k = registration::max_output_per_frame(c.n, c.rows) as usize;
        for (i, &e) in latches.iter().enumerate() {
            let before = sink.items.len();
            p.begin_frame(
                Trigger {
                    seq: i as u32,
                    latch: e,
                },
                &mut sink,
            )
            .unwrap();
            let fr = frame(c.offset(e).clamp(-1 << 40, 1 << 40));
            for (r, line) in fr.iter().enumerate() {
                p.push_line(r as u16, line, &mut sink).unwrap();
            }
            p.end_frame(&mut sink).unwrap();
            let out = sink.items.len() - before;
            assert!(out <= k, "frame {i}: {out} items > K = {k}");
            // The trigger log: this frame's trigger, once, before anything it completed.
            assert_eq!(sink.triggers.len(), i + 1);
            assert_eq!(
                sink.triggers[i],
                (
                    before,
                    Trigger {
                        seq: i as u32,
                        latch: e
                    }
                )
            );
        }
        let before = sink.items.len();
        p.finish(&mut sink).unwrap();
        assert!(sink.items.len() - before <= k);
        p.finish(&mut sink).unwrap();
        assert_eq!((sink.starts, sink.ends), (1, 1));
        assert_eq!(p.pool_used(), 0);
        for w in sink.items.windows(2) {
            assert_eq!(w[1].0 as i128, w[0].0 as i128 + w[0].1 as i128, "{w:?}");
        }
        sink
    }

    #[test]
    fn jump_is_one_gap_record_and_registration_restarts() {
        // 8 px per frame, then +1e12 counts, then 8 px per frame again.
        let mut latches: Vec<i64> = (0..12).map(|k| k * 80).collect();
        let j = 1_000_000_000_000i64;
        latches.extend((0..12).map(|k| j + k * 80));
        let out = run_faults(&latches, 10 << 16);
        let gaps: Vec<_> = out.items.iter().filter(|i| i.1 > 1).collect();
        assert_eq!(gaps.len(), 1, "{gaps:?}");
        let g = gaps[0];
        assert_eq!(g.2, flags::SKIPPED | flags::ENCODER_FAULT);
        assert_eq!(g.0 + g.1 as i64, j / 10, "the gap ends at the new top row");
        // Rows after the jump are measured again (valid rows both before and after).
        assert!(out.items.iter().any(|i| i.0 < g.0 && i.2 == 0));
        assert!(out.items.iter().any(|i| i.0 > g.0 && i.2 == 0));
        // Rows open at the jump carry ENCODER_FAULT.
        assert!(out
            .items
            .iter()
            .any(|i| i.0 < g.0 && i.2 & flags::ENCODER_FAULT != 0));
        // The same with i64::MAX and back down (a reversal): bounded, no overflow.
        let mut latches: Vec<i64> = (0..6).map(|k| k * 80).collect();
        latches.extend([i64::MAX, i64::MAX, i64::MIN, 480, 560, 640, 720, 800]);
        let out = run_faults(&latches, 10 << 16);
        assert!(out
            .items
            .iter()
            .any(|i| i.2 & flags::ENCODER_FAULT != 0 && i.1 > 1));
        // A tiny counts per pixel: every latch step is a jump.
        let latches: Vec<i64> = (0..10).map(|k| k * 3).collect();
        let out = run_faults(&latches, 1);
        assert_eq!(out.items.iter().filter(|i| i.1 > 1).count(), 9);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        /// Any latch sequence (steps small and huge, both ways, i64 extremes), any counts per
        /// pixel: at most K items per frame, rows and gaps tile increasing board rows, start
        /// and end once, no overflow, no leaked line slots.
        #[test]
        fn encoder_faults_are_bounded(
            latches in proptest::collection::vec(prop_oneof![
                4 => -200i64..2000,
                1 => Just(i64::MAX),
                1 => Just(i64::MIN),
                1 => any::<i64>(),
                1 => -(1i64 << 40)..(1i64 << 40),
            ], 1..24),
            cumulative in any::<bool>(),
            cpp in prop_oneof![Just(1u32), Just(10 << 16), 1u32..(40 << 16), Just(u32::MAX)],
        ) {
            let latches: Vec<i64> = if cumulative {
                latches.iter().scan(0i64, |e, &s| { *e = e.saturating_add(s); Some(*e) }).collect()
            } else {
                latches
            };
            run_faults(&latches, cpp);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        /// Any sequence of latches, lost frames and truncated frames: no panic, rows contiguous
        /// and increasing, no leaked line slots.
        #[test]
        fn never_panics_and_keeps_order(steps in proptest::collection::vec(-40i64..120, 1..30),
                                        gaps in proptest::collection::vec(0u32..3, 30),
                                        cuts in proptest::collection::vec(0u16..40, 30)) {
            let mut e = 0i64;
            let mut s = 0u32;
            let mut latches = vec![];
            let mut seqs = vec![];
            let mut lines = vec![];
            for (k, st) in steps.iter().enumerate() {
                e += st;
                s += 1 + if gaps[k] == 2 { 1 } else { 0 };
                latches.push(e);
                seqs.push(s);
                lines.push(cuts[k].min(H));
            }
            let (out, used) = run(&latches, &seqs, &lines);
            prop_assert_eq!(used, 0);
            for w in out.0.windows(2) {
                prop_assert_eq!(w[1].0.row, w[0].0.row + 1);
            }
        }
    }
}
