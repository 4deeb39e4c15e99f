//! The board map directory (`dpsa board` writes it, `dpsa inspect` reads it): its format name
//! and the colour scale its false-colour images share.

use crate::grid::Grid;

/// The `format` of a board map's `board.json`.
pub const FORMAT: &str = "dpsa-board-map";

/// The false-colour scale of a height grid, um: its 1st and 99th percentiles of the valid
/// pixels (an upper end above the lower one), None without a valid pixel.
///
/// Exact order statistics in bounded memory (a copy of a paper board's 47 Mpx of heights was
/// 190 MB): a histogram of the top 16 bits of each value's order key (the bits of
/// [`f32::total_cmp`]'s order), then a selection among the values of the one bin each
/// percentile falls in.
pub fn colour_range(h: &Grid) -> Option<(f32, f32)> {
    // Unsigned and increasing in `total_cmp`'s order.
    let key = |x: f32| {
        let b = x.to_bits();
        if b >> 31 == 1 {
            !b
        } else {
            b | 1 << 31
        }
    };
    let mut hist = vec![0usize; 1 << 16];
    let mut n = 0usize;
    for &x in h.data.iter().filter(|x| x.is_finite()) {
        hist[(key(x) >> 16) as usize] += 1;
        n += 1;
    }
    if n == 0 {
        return None;
    }
    let nth = |i: usize| -> Option<f32> {
        let mut below = 0usize;
        let bin = hist.iter().position(|&c| {
            let here = below + c > i;
            if !here {
                below += c;
            }
            here
        })?;
        let mut v: Vec<f32> = h
            .data
            .iter()
            .copied()
            .filter(|x| x.is_finite() && (key(*x) >> 16) as usize == bin)
            .collect();
        Some(*v.select_nth_unstable_by(i - below, f32::total_cmp).1)
    };
    let (lo, hi) = (nth(n / 100)?, nth((n * 99 / 100).min(n - 1))?);
    Some((lo, if hi > lo { hi } else { lo + 1.0 }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The percentiles of a sorted copy, the definition the selections must meet.
    fn by_sorting(h: &Grid) -> Option<(f32, f32)> {
        let mut v: Vec<f32> = h.data.iter().copied().filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return None;
        }
        v.sort_by(f32::total_cmp);
        let lo = v[v.len() / 100];
        let hi = v[(v.len() * 99 / 100).min(v.len() - 1)];
        Some((lo, if hi > lo { hi } else { lo + 1.0 }))
    }

    #[test]
    fn the_colour_range_is_the_sorted_percentiles() {
        // A small LCG: sizes 0..600, with NaN, repeats, infinities and flat grids.
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (x >> 33) as u32
        };
        for case in 0..400 {
            let n = (next() % 600) as usize;
            let data: Vec<f32> = (0..n)
                .map(|_| match next() % 10 {
                    0 => f32::NAN,
                    1 if case % 7 == 0 => f32::INFINITY,
                    2 => (next() % 4) as f32,
                    _ if case % 5 == 0 => 3.0,
                    _ => (next() % 100_000) as f32 / 7.0 - 5000.0,
                })
                .collect();
            let g = Grid {
                width: n.max(1),
                rows: usize::from(n > 0),
                data,
            };
            assert_eq!(colour_range(&g), by_sorting(&g), "case {case}");
        }
    }
}
