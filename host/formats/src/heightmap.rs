//! Height maps: the common result type of every reconstruction path.
//!
//! The fixed-point core's packets decode into a [`HeightMap`]; the f64 reference
//! (`dpsa_sim::reference::RefOutput::to_height_map`) can be converted into one as well, so the
//! comparison tools treat both alike. Row flag bit values are those of `docs/model.md`
//! ("Validity").

/// Row flags: the core's definitions (`dpsa_core::flags`) plus naming helpers.
pub mod flags {
    pub use dpsa_core::flags::*;

    /// All flags with their names, in bit order.
    pub const ALL: [(u16, &str); 9] = [
        (ILL_CONDITIONED, "ILL_CONDITIONED"),
        (INCOMPLETE, "INCOMPLETE"),
        (SKIPPED, "SKIPPED"),
        (ENCODER_REVERSAL, "ENCODER_REVERSAL"),
        (FRAME_GAP, "FRAME_GAP"),
        (SATURATED, "SATURATED"),
        (LOW_MODULATION, "LOW_MODULATION"),
        (OVERFLOW, "OVERFLOW"),
        (ENCODER_FAULT, "ENCODER_FAULT"),
    ];

    /// True when `flags` contains a flag that invalidates the whole row.
    pub fn invalidates(flags: u16) -> bool {
        flags & ROW_INVALID != 0
    }

    /// Names of the known flags set in `flags`, in bit order (unknown bits are ignored).
    pub fn names(flags: u16) -> Vec<&'static str> {
        ALL.iter()
            .filter(|(bit, _)| flags & bit != 0)
            .map(|&(_, name)| name)
            .collect()
    }
}

/// One reconstructed board row.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct HeightRow {
    /// Board row `b` (image row `r` of frame `k` shows board row `r + o_k`).
    pub row: i64,
    /// Encoder count associated with the row (as carried by the producer's packet), counts.
    pub latch: i64,
    /// Row flags, see [`flags`].
    pub flags: u16,
    /// Heights in LSB of [`HeightMap::lsb_um`], one per column.
    pub heights: Vec<i16>,
    /// Per-pixel validity, one per column.
    pub valid: Vec<bool>,
}

impl HeightRow {
    /// True when the row carries no invalidating flag (its pixels may still be invalid).
    pub fn is_valid(&self) -> bool {
        !flags::invalidates(self.flags)
    }

    /// True when pixel `col` is valid: its valid bit is set and the row is not invalidated.
    /// Out-of-range columns are invalid.
    pub fn pixel_valid(&self, col: usize) -> bool {
        self.is_valid() && self.valid.get(col).copied().unwrap_or(false)
    }

    /// Number of valid pixels (see [`HeightRow::pixel_valid`]).
    pub fn valid_count(&self) -> usize {
        if self.is_valid() {
            self.valid.iter().filter(|&&v| v).count()
        } else {
            0
        }
    }
}

/// A height map: rows sorted by increasing board row.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct HeightMap {
    /// Columns per row, px.
    pub width: usize,
    /// Height of one LSB, um.
    pub lsb_um: f64,
    /// Rows sorted by `row` (unique).
    pub rows: Vec<HeightRow>,
}

impl HeightMap {
    /// An empty map.
    pub fn new(width: usize, lsb_um: f64) -> Self {
        HeightMap {
            width,
            lsb_um,
            rows: Vec::new(),
        }
    }

    /// Sorts the rows by board row (stable; call after pushing rows out of order).
    pub fn sort(&mut self) {
        self.rows.sort_by_key(|r| r.row);
    }

    /// The row for board row `row`, if present (binary search; rows must be sorted).
    pub fn get(&self, row: i64) -> Option<&HeightRow> {
        self.rows
            .binary_search_by_key(&row, |r| r.row)
            .ok()
            .map(|i| &self.rows[i])
    }

    /// Lowest board row present.
    pub fn first_row(&self) -> Option<i64> {
        self.rows.first().map(|r| r.row)
    }

    /// Highest board row present.
    pub fn last_row(&self) -> Option<i64> {
        self.rows.last().map(|r| r.row)
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// True when there are no rows.
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Height of pixel (`row`, `col`) in um, or `None` when absent or invalid.
    pub fn height_um(&self, row: i64, col: usize) -> Option<f64> {
        let r = self.get(row)?;
        if !r.pixel_valid(col) {
            return None;
        }
        r.heights.get(col).map(|&h| f64::from(h) * self.lsb_um)
    }

    /// Total pixels (`rows x width`).
    pub fn total_pixels(&self) -> usize {
        self.rows.len() * self.width
    }

    /// Number of valid pixels over all rows.
    pub fn valid_pixels(&self) -> usize {
        self.rows.iter().map(HeightRow::valid_count).sum()
    }

    /// Number of rows without an invalidating flag.
    pub fn valid_rows(&self) -> usize {
        self.rows.iter().filter(|r| r.is_valid()).count()
    }

    /// Number of rows with any of the bits of `mask` set.
    pub fn rows_with(&self, mask: u16) -> usize {
        self.rows.iter().filter(|r| r.flags & mask != 0).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(row: i64, flags: u16, heights: Vec<i16>, valid: Vec<bool>) -> HeightRow {
        HeightRow {
            row,
            latch: 0,
            flags,
            heights,
            valid,
        }
    }

    #[test]
    fn flag_bits_match_model() {
        assert_eq!(flags::ROW_INVALID, 0b1_1001_1111);
        assert_eq!(
            flags::names(flags::SKIPPED | flags::OVERFLOW),
            ["SKIPPED", "OVERFLOW"]
        );
        assert!(!flags::invalidates(
            flags::SATURATED | flags::LOW_MODULATION
        ));
        assert!(flags::invalidates(flags::FRAME_GAP));
    }

    #[test]
    fn lookup_and_counts() {
        let mut m = HeightMap::new(2, 0.25);
        m.rows.push(row(7, 0, vec![4, -8], vec![true, false]));
        m.rows
            .push(row(3, flags::INCOMPLETE, vec![1, 1], vec![true, true]));
        m.sort();
        assert_eq!(m.first_row(), Some(3));
        assert_eq!(m.last_row(), Some(7));
        assert_eq!(m.get(7).map(|r| r.heights[0]), Some(4));
        assert!(m.get(5).is_none());
        assert_eq!(m.height_um(7, 0), Some(1.0));
        assert_eq!(m.height_um(7, 1), None);
        assert_eq!(m.height_um(7, 9), None);
        // The valid bits of an invalidated row are ignored.
        assert_eq!(m.height_um(3, 0), None);
        assert_eq!(m.valid_pixels(), 1);
        assert_eq!(m.total_pixels(), 4);
        assert_eq!(m.valid_rows(), 1);
        assert_eq!(m.rows_with(flags::INCOMPLETE), 1);
        assert!(HeightMap::default().first_row().is_none());
    }
}
