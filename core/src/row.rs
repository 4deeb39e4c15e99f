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
    /// Flags that invalidate the whole row.
    pub const ROW_INVALID: u16 =
        ILL_CONDITIONED | INCOMPLETE | SKIPPED | ENCODER_REVERSAL | FRAME_GAP | OVERFLOW;
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
    pub header: RowHeader,
    pub heights: &'a [i16],
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
