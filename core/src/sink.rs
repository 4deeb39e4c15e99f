//! Sink: where completed height rows go (a file on the host, a link on the frame grabber).

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
    /// Row flags, see [`crate::frames::flags`].
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
        self.valid.get(c / 8).is_some_and(|b| b & (1 << (c % 8)) != 0)
    }
}

/// Receives completed rows in increasing board-row order, each board row exactly once.
pub trait Sink {
    type Error;
    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error>;
}
