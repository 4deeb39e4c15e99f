//! Provenance: which frames fed each board row, replayed on the frames' triggers.
//!
//! The registration of `docs/model.md` (steps 1-4), the same decisions the fixed-point core
//! makes row for row, replayed in f64 from a camera's triggers (frame counter and encoder
//! latch, frame order) and its [`Registration`] (`H`, `n`, `max_step_rows`, counts per pixel):
//! the triggers of a recording's manifest, or the trigger log a camera's packet stream carries
//! (`docs/stream.md`), so that the board map of streams needs no frames. [`plan_triggers`] is
//! the decision per row; [`Provenance`] keeps every row's window, which two things need:
//!
//! - **Dead pixels** ([`mask_dead_pixels`]): a dead or weak image pixel `(r, c)` of the
//!   calibration feeds board row `b` at column `c` exactly when one of `b`'s window frames `k`
//!   saw `b` at image row `b - o_k = r`. With a steady step of `s` rows per frame that is one
//!   board row in about `s`, a streak the least squares would otherwise turn into a wrong
//!   height (tens of um) that looks valid.
//! - **Row places** ([`row_places`]): where each row's board points lie, off the nominal place
//!   by the window frames' sub-row travel and image rows.
//!
//! Each emitted row carries its window's first latch (the row packet's latch field), which
//! confirms the replay row by row ([`Provenance::confirms`]): a row the replay cannot confirm
//! (a lost trigger record) has no known mask or place.

use crate::places::{RowPlaces, SamplePlace};
use crate::Grid;
use dpsa_core::Trigger;
use dpsa_formats::heightmap::flags;
use std::collections::HashMap;

/// Largest number of board rows [`plan_triggers`] will enumerate. Offsets spanning more rows
/// than this (absurd latches or calibration) are treated as unusable data and give an empty
/// plan rather than an enormous allocation.
pub const MAX_PLAN_ROWS: i64 = 1 << 24;

/// Largest absolute offset accepted, px; keeps `o_k + H` far from `i64` overflow.
const MAX_ABS_OFFSET: f64 = (1u64 << 60) as f64;

/// Registration step 1: `o = floor(e / cpp + 1/2)` (round half up), px.
///
/// Computed in f64. `cpp` is a multiple of 2^-16, so the exact quotient `e / cpp` is at least
/// `1 / (2 * 65536 * cpp)` away from a half-integer unless it is one; the f64 quotient is
/// correctly rounded, so the result is exact while `|e| < 2^36` counts (and `e` itself is exact
/// in f64 up to 2^53). Returns `None` for a non-finite result or `|o| >= 2^60`
/// (non-positive or non-finite `cpp`).
pub fn offset(latch: i64, counts_per_pixel: f64) -> Option<i64> {
    if !(counts_per_pixel > 0.0 && counts_per_pixel.is_finite()) {
        return None;
    }
    let o = (latch as f64 / counts_per_pixel + 0.5).floor();
    (o.is_finite() && o.abs() < MAX_ABS_OFFSET).then_some(o as i64)
}

/// Offsets `o_k` of frames triggered at `triggers`, px; `None` when any is unusable (see
/// [`offset`]).
pub fn trigger_offsets(triggers: &[Trigger], counts_per_pixel: f64) -> Option<Vec<i64>> {
    triggers
        .iter()
        .map(|t| offset(t.latch, counts_per_pixel))
        .collect()
}

/// What the registration of a camera's frames needs besides their triggers: the frame
/// geometry and processing of its configuration (the stream header's `H`, `n` and
/// `max_step_rows`, the calibration's counts per pixel).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Registration {
    /// ROI rows per frame `H`.
    pub rows: u32,
    /// Observations per row `n`.
    pub n: u8,
    /// Rows a frame admits at most.
    pub max_step_rows: u32,
    /// Encoder counts per board row (a multiple of 2^-16).
    pub counts_per_pixel: f64,
}

/// The registration decision for one board row.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RowPlan {
    /// Board row `b`.
    pub row: i64,
    /// Index into the triggers of the frame `w` at which the row entered; `None` for rows that
    /// never entered (`SKIPPED`).
    pub first_frame: Option<usize>,
    /// Row-level flags decidable from the triggers alone: `SKIPPED`, `INCOMPLETE`,
    /// `FRAME_GAP` (sequence gaps), `ENCODER_REVERSAL`. Zero when the window is usable.
    pub flags: u16,
}

/// Registration steps 1-4 of `docs/model.md` on the frames triggered at `triggers` (frame
/// order) with `reg`.
///
/// Returns every board row from the first frame's top row (`o_0`) to `E_last - 1` exactly
/// once, in increasing order (rows below `o_0`, visible only after a reversal, never enter):
/// - rows that entered at frame `w` (`[max(E_{w-1}, o_w + H - max_step_rows), o_w + H)`) carry
///   `first_frame = Some(w)` and the window flags: `INCOMPLETE` when the row is not visible
///   in one of the frames `w..w+n-1` or the window runs past the last frame, `FRAME_GAP` when
///   consecutive window frames do not have consecutive `seq` (wrapping `u32` counter),
///   `ENCODER_REVERSAL` when the latch decreases between consecutive window frames (a
///   decrease never re-admits rows because `E_k` is a running maximum). The flags of a window
///   truncated by the last frame are evaluated over the frames that exist;
/// - all other rows (below the `max_step_rows` bound of the frame that first showed them) are
///   `SKIPPED` with no frame.
///
/// Frame-content checks (a frame that did not deliver the row's line) are the reference's
/// (`dpsa_sim::reference::reconstruct`). No triggers, `H = 0`, an unusable
/// `counts_per_pixel` or a row span above [`MAX_PLAN_ROWS`] gives an empty plan.
pub fn plan_triggers(triggers: &[Trigger], reg: &Registration) -> Vec<RowPlan> {
    let h = i64::from(reg.rows);
    let n = usize::from(reg.n);
    let max_step_rows = i64::from(reg.max_step_rows);
    let Some(o) = trigger_offsets(triggers, reg.counts_per_pixel) else {
        return Vec::new();
    };
    let (Some(&lo), Some(&hi)) = (o.first(), o.iter().max()) else {
        return Vec::new();
    };
    let end = hi + h; // E_last
    if h == 0 || end - lo > MAX_PLAN_ROWS {
        return Vec::new();
    }

    let mut rows: Vec<RowPlan> = (lo..end)
        .map(|row| RowPlan {
            row,
            first_frame: None,
            flags: flags::SKIPPED,
        })
        .collect();

    let mut e_prev = i64::MIN; // E_{k-1}, -inf before the first frame
    for (k, &ok) in o.iter().enumerate() {
        let top = ok + h;
        let from = e_prev.max(top - max_step_rows).max(lo);
        for b in from..top {
            let f = window_flags(b, k, n, h, &o, triggers);
            rows[(b - lo) as usize] = RowPlan {
                row: b,
                first_frame: Some(k),
                flags: f,
            };
        }
        e_prev = e_prev.max(top);
    }
    rows
}

/// Window flags of board row `b` entering at frame `w` (step 4).
fn window_flags(b: i64, w: usize, n: usize, h: i64, o: &[i64], frames: &[Trigger]) -> u16 {
    let mut f = 0;
    for j in 0..n {
        let k = w + j;
        if k >= o.len() {
            f |= flags::INCOMPLETE;
            break;
        }
        if !(o[k] <= b && b < o[k] + h) {
            f |= flags::INCOMPLETE;
        }
        if j > 0 {
            if frames[k].seq != frames[k - 1].seq.wrapping_add(1) {
                f |= flags::FRAME_GAP;
            }
            if frames[k].latch < frames[k - 1].latch {
                f |= flags::ENCODER_REVERSAL;
            }
        }
    }
    f
}

/// One board row's window in the registration replay.
#[derive(Clone, Debug, PartialEq)]
struct RowWindow {
    /// Latch of the window's first frame (what the row's packet carries).
    first_latch: i64,
    /// Row offsets `o_w .. o_{w+n-1}` of the window's frames.
    offsets: Vec<i64>,
    /// Each window frame's sub-row travel `latch_k / cpp - o_k`, in `[-1/2, 1/2)` rows.
    frac: Vec<f64>,
}

/// The registration of a camera's frames replayed on their triggers: for every board row with
/// a complete, unflagged window, the window (the core registers whole rows, `o_k =
/// round(latch_k / cpp)`). The same triggers give the same windows, whether they come from a
/// recording's manifest or a stream's trigger log.
#[derive(Clone, Debug, Default)]
pub struct Provenance {
    windows: HashMap<i64, RowWindow>,
}

impl Provenance {
    /// Replays the registration on `triggers` (frame order) with `reg`.
    pub fn replay(triggers: &[Trigger], reg: &Registration) -> Provenance {
        let n = usize::from(reg.n);
        let cpp = reg.counts_per_pixel;
        let Some(o) = trigger_offsets(triggers, cpp) else {
            return Provenance::default();
        };
        let windows = plan_triggers(triggers, reg)
            .into_iter()
            .filter_map(|p| {
                let w = p.first_frame?;
                (p.flags == 0 && w + n <= o.len()).then(|| {
                    let frac = (w..w + n)
                        .map(|k| triggers[k].latch as f64 / cpp - o[k] as f64)
                        .collect();
                    let win = RowWindow {
                        first_latch: triggers[w].latch,
                        offsets: o[w..w + n].to_vec(),
                        frac,
                    };
                    (p.row, win)
                })
            })
            .collect();
        Provenance { windows }
    }

    /// Whether board row `row`, emitted with its window's first latch `latch`, has that window
    /// in the replay: only then are its dead-pixel mask and its place known.
    pub fn confirms(&self, row: i64, latch: i64) -> bool {
        self.windows
            .get(&row)
            .is_some_and(|w| w.first_latch == latch)
    }

    /// The row offsets `o_w .. o_{w+n-1}` of board row `row`'s window frames (`None`: the row
    /// has no complete, unflagged window).
    pub fn window_offsets(&self, row: i64) -> Option<&[i64]> {
        self.windows.get(&row).map(|w| &w.offsets[..])
    }
}

/// Where each row of a camera's grid (row `i` is board row `first_row + i`) was seen, as
/// [`RowPlaces`]: along the motion `i + mean_k(latch_k / cpp - o_k)` over its window frames,
/// across it the mean image row `mean_k(b - o_k)` against the placement's `r_w`.
///
/// The core registers whole rows, so the board points behind one board row lie up to half a row
/// off its nominal place in each window frame, by that frame's sub-row travel; and the row is
/// seen at a different image row in each window frame, which with a rotation `a` of the image
/// rows moves it across by `p sin a` per image row. The row's height is the least-squares blend
/// of those points, centred on their mean; each pixel's own place about it
/// ([`RowPlaces::samples`], [`crate::places`]) follows from the window's shifts (the core's
/// fringe period `period_px`). Rows without a window keep the nominal place.
pub fn row_places(
    prov: &Provenance,
    first_row: i64,
    rows: usize,
    r_w: f64,
    rotation_rad: f64,
    period_px: f64,
) -> RowPlaces {
    let mean = |v: &mut dyn Iterator<Item = f64>| {
        let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
        s / n.max(1) as f64
    };
    let mut along = Vec::with_capacity(rows);
    let mut across = Vec::with_capacity(rows);
    let mut samples = Vec::with_capacity(rows);
    for i in 0..rows {
        let b = first_row + i as i64;
        match prov.windows.get(&b) {
            Some(w) => {
                along.push(i as f64 + mean(&mut w.frac.iter().copied()));
                let r_mean = mean(&mut w.offsets.iter().map(|&ok| (b - ok) as f64));
                across.push((r_mean - r_w) * rotation_rad.tan());
                samples.push(
                    SamplePlace::of_window(b, &w.offsets, &w.frac, period_px).unwrap_or_default(),
                );
            }
            None => {
                along.push(i as f64);
                across.push(0.0);
                samples.push(SamplePlace::default());
            }
        }
    }
    RowPlaces {
        along,
        across,
        samples,
    }
}
/// Masks (sets to NaN) every pixel of `g` (row `i` is board row `first_row + i`) that a dead
/// image pixel `[r, c]` of `dead` fed; returns how many valid pixels it masked.
pub fn mask_dead_pixels(prov: &Provenance, dead: &[[u32; 2]], first_row: i64, g: &mut Grid) -> u64 {
    if dead.is_empty() {
        return 0;
    }
    let mut by_row: HashMap<i64, Vec<usize>> = HashMap::new();
    for &[r, c] in dead {
        by_row.entry(i64::from(r)).or_default().push(c as usize);
    }
    let mut masked = 0;
    for (&b, w) in &prov.windows {
        let offs = &w.offsets;
        let Some(i) = b
            .checked_sub(first_row)
            .filter(|&i| i >= 0 && (i as usize) < g.rows)
        else {
            continue;
        };
        for &ok in offs {
            if let Some(cols) = by_row.get(&(b - ok)) {
                for &c in cols {
                    if c < g.width {
                        let v = g.at_mut(i as usize, c);
                        masked += u64::from(v.is_finite());
                        *v = f32::NAN;
                    }
                }
            }
        }
    }
    masked
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `frames` frames at `step` rows each (cpp 10 counts per row), `H` 40, `n` 4, admitting
    /// up to 12 rows.
    fn steady(frames: u32, step: i64) -> (Vec<Trigger>, Registration) {
        let t = (0..frames)
            .map(|k| Trigger {
                seq: 100 + k,
                latch: i64::from(k) * step * 10 + 3,
            })
            .collect();
        let reg = Registration {
            rows: 40,
            n: 4,
            max_step_rows: 12,
            counts_per_pixel: 10.0,
        };
        (t, reg)
    }

    #[test]
    fn a_steady_run_gives_every_admitted_row_its_window() {
        let (t, reg) = steady(30, 8);
        let p = Provenance::replay(&t, &reg);
        // Frame k admits rows [8k + 32, 8k + 40) (the first frame its last 12 rows); a row's
        // window is its entering frame and the 3 after it.
        for k in 1..26usize {
            for b in 8 * k as i64 + 32..8 * k as i64 + 40 {
                assert!(p.confirms(b, t[k].latch), "row {b}");
                assert!(!p.confirms(b, t[k - 1].latch), "row {b}");
                let o: Vec<i64> = (k..k + 4).map(|j| 8 * j as i64).collect();
                assert_eq!(p.window_offsets(b), Some(&o[..]));
            }
        }
        // The last 3 frames' rows never complete their window.
        assert_eq!(p.window_offsets(8 * 29 + 32), None);
    }

    #[test]
    fn a_lost_trigger_unconfirms_exactly_the_rows_it_fed() {
        let (t, reg) = steady(30, 8);
        let full = Provenance::replay(&t, &reg);
        let mut lost = t.clone();
        lost.remove(15);
        let p = Provenance::replay(&lost, &reg);
        for b in 40..8 * 26 + 32 {
            let k = ((b - 32) / 8) as usize; // the frame the row entered at
            let fed_by_15 = (12..=15).contains(&k);
            assert_eq!(
                p.confirms(b, t[k].latch),
                !fed_by_15,
                "row {b} (entered at frame {k})"
            );
            assert!(full.confirms(b, t[k].latch));
        }
    }

    #[test]
    fn a_dead_image_pixel_masks_one_row_per_window_frame() {
        let (t, reg) = steady(30, 8);
        let p = Provenance::replay(&t, &reg);
        let first = 40;
        let mut g = Grid {
            width: 4,
            rows: 160,
            data: vec![1.0; 4 * 160],
        };
        // Image row 37, column 2: board row b sees it in window frame j when b - 8 j = 37.
        let masked = mask_dead_pixels(&p, &[[37, 2]], first, &mut g);
        let hit: Vec<i64> = (0..160)
            .filter(|&i| g.at(i, 2).is_nan())
            .map(|i| i as i64 + first)
            .collect();
        assert_eq!(masked, hit.len() as u64);
        assert!(hit.len() > 10);
        for b in &hit {
            let w = p.window_offsets(*b).unwrap();
            assert!(w.iter().any(|&o| b - o == 37), "row {b} {w:?}");
        }
        for i in 0..160 {
            for c in [0, 1, 3] {
                assert_eq!(g.at(i, c), 1.0);
            }
        }
    }
}
