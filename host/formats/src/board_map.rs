//! The board map directory (`dpsa board` writes it, `dpsa inspect` reads it): its format name
//! and the colour scale its false-colour images share.

use crate::grid::Grid;

/// The `format` of a board map's `board.json`.
pub const FORMAT: &str = "dpsa-board-map";

/// The false-colour scale of a height grid, um: its 1st and 99th percentiles of the valid
/// pixels (an upper end above the lower one), None without a valid pixel.
pub fn colour_range(h: &Grid) -> Option<(f32, f32)> {
    let mut v: Vec<f32> = h.data.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f32::total_cmp);
    let lo = v[v.len() / 100];
    let hi = v[(v.len() * 99 / 100).min(v.len() - 1)];
    Some((lo, if hi > lo { hi } else { lo + 1.0 }))
}
