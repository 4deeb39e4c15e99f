//! Where a camera's rows were seen: the row places that the provenance of a board recording
//! (its latches replayed) gives, and that the resampling uses instead of the nominal placement.

/// Where a camera's rows were seen ([`crate::provenance::row_places`] makes them).
#[derive(Clone, Debug, PartialEq)]
pub struct RowPlaces {
    /// Position of row `i` along the motion, in rows (increasing: neighbours differ by
    /// `1 +- (less than 1)`).
    pub along: Vec<f64>,
    /// How far the board point of column `c` of row `i` lies from the nominal column, px:
    /// the point the placement puts at column `c` is at column `c - across[i]`.
    pub across: Vec<f64>,
}
