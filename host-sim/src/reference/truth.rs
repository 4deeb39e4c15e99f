//! Ground-truth lookups: heights and illumination at a board row, and the flat-pixel mask.

use crate::simulation::recording::Truth;

/// Index of board row `b` in the truth arrays.
pub(crate) fn truth_row_index(truth: &Truth, b: i64) -> Option<usize> {
    let i = b.checked_sub(truth.first_row)?;
    (i >= 0 && (i as u64) < truth.rows as u64).then_some(i as usize)
}

/// `(height um, background DN, contrast DN)` of truth row index `ti`, column `c`.
pub(crate) fn truth_at(truth: &Truth, ti: usize, c: usize) -> Option<(f64, f64, f64)> {
    if c >= truth.width {
        return None;
    }
    let idx = ti.checked_mul(truth.width)?.checked_add(c)?;
    Some((
        f64::from(*truth.height_um.get(idx)?),
        f64::from(*truth.background.get(idx)?),
        f64::from(*truth.contrast.get(idx)?),
    ))
}

/// True height of board row `b`, column `c`, um, when inside the truth.
pub fn truth_height(truth: &Truth, b: i64, c: usize) -> Option<f64> {
    let ti = truth_row_index(truth, b)?;
    if c >= truth.width {
        return None;
    }
    truth
        .height_um
        .get(ti * truth.width + c)
        .map(|&h| f64::from(h))
}

/// Flat-pixel mask of the truth, row-major `truth.rows x truth.width`.
///
/// A pixel is flat when it and its 8 neighbours (board rows `b-1..=b+1`, columns
/// `c-1..=c+1`) have exactly the same truth height; border pixels are never flat. Errors
/// against truth are measured only on flat pixels: registration rounds each frame's offset to
/// a whole pixel, so a sample can come from up to half a pixel away along the motion, and on
/// deposit walls the error would measure that lateral sampling rather than the phase
/// algorithm.
pub fn flat_mask(truth: &Truth) -> Vec<bool> {
    let (rows, w) = (truth.rows, truth.width);
    let mut mask = vec![false; rows.saturating_mul(w)];
    if rows < 3 || w < 3 || truth.height_um.len() < rows * w {
        return mask;
    }
    let h = &truth.height_um;
    for r in 1..rows - 1 {
        for c in 1..w - 1 {
            let v = h[r * w + c];
            mask[r * w + c] =
                (r - 1..=r + 1).all(|rr| (c - 1..=c + 1).all(|cc| h[rr * w + cc] == v));
        }
    }
    mask
}
