//! Registration: which board rows each frame admits or skips, and where the open rows live.
//!
//! Frame `k` with row offset `o_k` shows board rows `o_k .. o_k + H`. The rows that enter at the
//! bottom of the ROI (those past every row entered so far) are *admitted*, at most
//! `max_step_rows` of them per frame: each gets a [`Slot`] in a ring of `max_step_rows * n`
//! slots. Rows that entered beyond that bound are *skipped* (they never get samples). The
//! `Admission` of each of the last `n + 1` frames records both ranges, so a board row can be
//! classified (`Registry::kind`) and its window's latch found (`Registry::window_latch`)
//! without per-row bookkeeping beyond the slot. The full rule is in `docs/model.md`.

//!
//! ## Encoder faults
//!
//! Every trigger is classified against the previous one ([`classify`], [`Step`]):
//! - a latch below the previous latch is a **reversal**: the open rows are flagged
//!   `ENCODER_REVERSAL`; rows already emitted are never seen again, and registration goes on
//!   when the motion passes the highest row entered so far (the output stays increasing);
//! - a frame whose top row `o_k` lies beyond every row entered so far (`o_k > E_{k-1}`, i.e. a
//!   forward step of more than the ROI height `H` over the previous bottom) is a **jump**: the
//!   board rows `[E_{k-1}, o_k)` were never in any frame. They are emitted as ONE gap record
//!   (`SKIPPED | ENCODER_FAULT`), the open rows are flagged `ENCODER_FAULT`, and registration
//!   restarts at `o_k` exactly as at the first frame (`Registry::restart`).
//!
//! So a frame enters at most `H` board rows (plus at most one gap record), whatever the latch:
//! with every row emitted once, the pipeline's output per input frame is bounded by
//! [`MAX_OUTPUT_PER_FRAME`]`(n, H)` items (rows and gap records), see `docs/model.md`.

use crate::solve::MAX_N;

/// Largest number of sink items (rows and gap records) the pipeline emits between the start of
/// one `begin_frame` and the start of the next: `K = n * H + 1`. The rows still pending after
/// a frame entered in its last `n - 1` frames (at most `H` each), the frame enters at most `H`
/// more, and a jump adds one gap record. The frame's trigger record comes on top (one per
/// frame), and the stream header and end-of-stream records once per stream.
pub const fn max_output_per_frame(n: u8, rows: u16) -> u64 {
    n as u64 * rows as u64 + 1
}

/// [`max_output_per_frame`] for the largest `n` and `H`.
pub const MAX_OUTPUT_PER_FRAME: u64 = max_output_per_frame(MAX_N as u8, u16::MAX);

/// How a frame's trigger relates to the previous frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Step {
    /// The first frame of the stream.
    First,
    /// Forward or standing still within the plausibility bound.
    Forward,
    /// The latch decreased.
    Reversal,
    /// The frame's top row lies past every row entered so far: board rows
    /// `[gap_first, gap_first + gap_rows)` were never imaged.
    Jump {
        /// First board row of the gap.
        gap_first: i64,
        /// Board rows in the gap.
        gap_rows: u64,
    },
}

/// Classifies a trigger: `first` for the stream's first frame, `prev_latch` / `latch` the
/// latches of the previous and this frame, `entered_end` one past the highest board row
/// entered so far (`E_{k-1}`), `offset` this frame's row offset `o_k`.
pub fn classify(first: bool, prev_latch: i64, latch: i64, entered_end: i64, offset: i64) -> Step {
    if first {
        Step::First
    } else if latch < prev_latch {
        Step::Reversal
    } else if offset > entered_end {
        Step::Jump {
            gap_first: entered_end,
            gap_rows: offset.abs_diff(entered_end),
        }
    } else {
        Step::Forward
    }
}

/// Admissions kept: the `n <= MAX_N` frames of the current window plus one.
pub(crate) const HIST: usize = MAX_N + 1;

/// Per open board row: its stored lines and how far it got.
#[derive(Clone, Copy, Debug, Default)]
pub struct Slot {
    pub(crate) lines: [u16; MAX_N - 1],
    pub(crate) count: u8,
    pub(crate) flags: u16,
    pub(crate) enter: u32,
}

/// What one frame admitted: its offset and latch, and the board rows it skipped and admitted.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Admission {
    pub(crate) index: u32,
    pub(crate) offset: i64,
    pub(crate) latch: i64,
    /// Rows `[skip_start, admit_start)` were never admitted.
    pub(crate) skip_start: i64,
    /// Rows `[admit_start, admit_end)` entered at this frame.
    pub(crate) admit_start: i64,
    pub(crate) admit_end: i64,
    /// Slot-ring position of `admit_start`.
    pub(crate) slot_base: u32,
}

/// What a board row is.
pub(crate) enum Kind {
    /// Entered, but beyond the frame's `max_step_rows`: no samples.
    Skipped,
    /// Open in this slot.
    Admitted(usize),
    /// Entered more than `n` frames ago (or never): its admission is forgotten.
    Gone,
}

/// The admissions of the last frames and the ring of row slots.
pub(crate) struct Registry<'a> {
    pub(crate) slots: &'a mut [Slot],
    hist: [Admission; HIST],
    /// Frames registered so far (index of the next frame).
    begun: u32,
    /// One past the highest row admitted or skipped.
    pub(crate) entered_end: i64,
    /// Admitted rows so far (slot-ring cursor).
    admitted: u32,
}

impl<'a> Registry<'a> {
    pub(crate) fn new(slots: &'a mut [Slot]) -> Self {
        Registry {
            slots,
            hist: [Admission::default(); HIST],
            begun: 0,
            entered_end: 0,
            admitted: 0,
        }
    }

    /// Restarts registration at row offset `offset` (after a jump, see [`Step::Jump`]): the
    /// next frame enters rows from `offset` on, as the first frame does.
    pub(crate) fn restart(&mut self, offset: i64) {
        self.entered_end = offset;
    }

    /// Frames registered so far: the index the next frame gets.
    pub(crate) fn begun(&self) -> u32 {
        self.begun
    }

    /// The admission of frame `index` (one of the last [`HIST`] frames).
    pub(crate) fn admission(&self, index: u32) -> &Admission {
        &self.hist[index as usize % HIST]
    }

    /// Registers the next frame (offset `offset`, latch `latch`, `rows` ROI rows): admits the
    /// rows that entered at the bottom, at most `max_step_rows`, each in a fresh slot.
    pub(crate) fn admit(&mut self, offset: i64, latch: i64, rows: u16, max_step_rows: u16) {
        let f = self.begun;
        let end = offset + rows as i64;
        let mut adm = Admission {
            index: f,
            offset,
            latch,
            skip_start: self.entered_end,
            admit_start: self.entered_end,
            admit_end: self.entered_end,
            slot_base: self.admitted,
        };
        if end > self.entered_end {
            adm.admit_start = self.entered_end.max(end - max_step_rows as i64);
            adm.admit_end = end;
            let count = (end - adm.admit_start) as u32;
            for k in 0..count {
                let s = adm.slot_base.wrapping_add(k) as usize % self.slots.len();
                self.slots[s] = Slot {
                    enter: f,
                    ..Slot::default()
                };
            }
            self.admitted = self.admitted.wrapping_add(count);
            self.entered_end = end;
        }
        self.hist[f as usize % HIST] = adm;
        self.begun = f.wrapping_add(1);
    }

    /// Classifies board row `b` (not yet emitted) against the admissions of the last frames.
    pub(crate) fn kind(&self, b: i64) -> Kind {
        let f = self.begun.wrapping_sub(1);
        for back in 0..HIST as u32 {
            if back > f {
                break;
            }
            let r = self.admission(f - back);
            if b >= r.skip_start && b < r.admit_end {
                if b < r.admit_start {
                    return Kind::Skipped;
                }
                let k = r.slot_base.wrapping_add((b - r.admit_start) as u32);
                return Kind::Admitted(k as usize % self.slots.len());
            }
        }
        Kind::Gone
    }

    /// Latch of frame `enter` (the first frame of a row's window), 0 if it is forgotten.
    pub(crate) fn window_latch(&self, enter: u32) -> i64 {
        let r = self.admission(enter);
        if r.index == enter {
            r.latch
        } else {
            0
        }
    }
}
