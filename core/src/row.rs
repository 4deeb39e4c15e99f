//! The output row: what the pipeline emits for every board row (header, heights, validity) and
//! the row flags that say why a row or pixel is invalid.

/// Row flags carried in every row packet (bit values are part of the stream format).
pub mod flags {
    /// Window noise gain above `max_noise_gain` (includes a stalled conveyor).
    pub const ILL_CONDITIONED: u16 = 1 << 0;
    /// Row not seen in `n` consecutive frames (left the ROI, recording ended).
    pub const INCOMPLETE: u16 = 1 << 1;
    /// Row never admitted (first frame, encoder step above `max_step_rows`).
    pub const SKIPPED: u16 = 1 << 2;
    /// Encoder count decreased while the row was open.
    pub const ENCODER_REVERSAL: u16 = 1 << 3;
    /// Frame sequence gap, or a frame that ended before delivering the row's line.
    pub const FRAME_GAP: u16 = 1 << 4;
    /// At least one pixel had a saturated sample (per-pixel summary).
    pub const SATURATED: u16 = 1 << 5;
    /// At least one pixel had modulation below the threshold (per-pixel summary).
    pub const LOW_MODULATION: u16 = 1 << 6;
    /// The caller-supplied state had no free line slot for this row.
    pub const OVERFLOW: u16 = 1 << 7;
    /// An encoder jump (`crate::frames::registration::Step::Jump`): the row was open when the
    /// latch leapt past every row seen so far, or lies in the gap the jump left (gap records).
    pub const ENCODER_FAULT: u16 = 1 << 8;
    /// Flags that invalidate the whole row.
    pub const ROW_INVALID: u16 = ILL_CONDITIONED
        | INCOMPLETE
        | SKIPPED
        | ENCODER_REVERSAL
        | FRAME_GAP
        | OVERFLOW
        | ENCODER_FAULT;
}

/// Header of one height row; the same fields are framed into every row packet.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RowHeader {
    /// Camera id.
    pub camera: u8,
    /// Observations per row `n`.
    pub n: u8,
    /// Board row index `b` (pixels of travel from the encoder zero).
    pub row: i64,
    /// Encoder latch of the first frame of the row's window (0 for rows without a window).
    pub latch: i64,
    /// Row flags, see [`flags`].
    pub flags: u16,
    /// Columns `W`.
    pub width: u16,
}

/// One completed board row. `heights[c]` is in LSB; bit `c % 8` of `valid[c / 8]` is 1 when
/// pixel `c` is valid. Invalid pixels carry height 0.
#[derive(Clone, Copy, Debug)]
pub struct Row<'a> {
    /// Board row, latch and flags.
    pub header: RowHeader,
    /// `W` heights, LSB.
    pub heights: &'a [i16],
    /// `ceil(W / 8)` bytes of validity bits.
    pub valid: &'a [u8],
}

impl Row<'_> {
    /// Whether pixel `c` is valid.
    pub fn is_valid(&self, c: usize) -> bool {
        self.valid
            .get(c / 8)
            .is_some_and(|b| b & (1 << (c % 8)) != 0)
    }
}

/// A bounded record of board rows that were never imaged: `count` rows from board row
/// `first`, all invalid with `flags` (`SKIPPED | ENCODER_FAULT`). The pipeline emits one per
/// encoder jump instead of one row per skipped board row.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Gap {
    /// Camera id.
    pub camera: u8,
    /// First board row of the gap.
    pub first: i64,
    /// Board rows in the gap (at least 1).
    pub count: u64,
    /// Row flags of every row in the gap.
    pub flags: u16,
}

/// What a stream holds, announced once before its first row (the stream header packet).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StreamInfo {
    /// Camera id.
    pub camera: u8,
    /// Observations per row `n`.
    pub n: u8,
    /// Columns `W` of every row of the stream.
    pub width: u16,
    /// ROI rows per frame `H`.
    pub rows: u16,
    /// `Config::max_step_rows`.
    pub max_step_rows: u16,
    /// FNV-1a 64 of the integer configuration and the reference-phase table
    /// ([`crate::frames::Config::hash`]).
    pub config_hash: u64,
    /// Run identity chosen by the caller (0 if none); set by the sink, not the pipeline.
    pub run_id: u64,
    /// Codec intra period of the stream; set by the sink (0 when the pipeline announces it).
    pub intra_period: u32,
}
