//! When to clean the stencil: paste drying in the fine apertures (their volume falling board
//! after board) and paste on the stencil's underside (smears and bridges on the boards).
//!
//! - **Fine apertures** are those whose area ratio (opening area over its wall area,
//!   `area / (perimeter x stencil thickness)`) is below [`StencilConfig::fine_area_ratio`]: near
//!   the 0.66 under which IPC-7525 expects poor release, the first to clog.
//! - **The last clean** is the last one recorded (a printer's or an operator's report, `dpsa
//!   line clean`: the first board begun after it). Without a record it is found in the data:
//!   the last board whose fine apertures' mean volume rose from the board before by more than
//!   [`StencilConfig::clean_step_pct`] and more than 4 board-to-board sigmas (a clean restores
//!   the release at once; nothing else raises every fine aperture together). Without either,
//!   the study's first board.
//! - **Clogging**: the fine apertures' mean volume now (the last 3 boards) against just after the
//!   clean (its first 3 boards), and the trend between (least squares, % a board).
//! - **Smear**: pads judged `bridge` or `shape` a board, over the last 5 boards.
//!
//! A cleaning is recommended when the fine volume has fallen by [`StencilConfig::drop_pct`] or
//! more, or the smears reach [`StencilConfig::smears_per_board`], with the reasons said.

/// When to recommend a clean.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct StencilConfig {
    /// Apertures below this area ratio are the fine ones watched for clogging.
    pub fine_area_ratio: f64,
    /// A rise of the fine apertures' mean volume by more than this (points of %) from one
    /// board to the next is taken for a clean.
    pub clean_step_pct: f64,
    /// Recommend a clean when the fine volume has fallen by this much (points of %) since the
    /// last.
    pub drop_pct: f64,
    /// ... or when this many pads a board are bridges or smears (over the last 5 boards).
    pub smears_per_board: f64,
}

impl Default for StencilConfig {
    fn default() -> Self {
        StencilConfig {
            fine_area_ratio: 0.8,
            clean_step_pct: 5.0,
            drop_pct: 8.0,
            smears_per_board: 1.0,
        }
    }
}

/// What a board says about the stencil.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoardStencil {
    /// Mean volume of its fine apertures, % (`None`: none measured).
    pub fine_volume_pct: Option<f64>,
    /// Its pads judged `bridge` or `shape`.
    pub smears: usize,
}

/// The assessment.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Cleaning {
    /// Whether a clean is recommended now.
    pub recommend: bool,
    /// Why (or why not), for a person.
    pub reasons: Vec<String>,
    /// The board after the last clean found (index into the study's boards), or the first.
    pub since_board: usize,
    /// Whether `since_board` is a clean, recorded or found in the data (else the study's start).
    pub clean_found: bool,
    /// Whether that clean was recorded (`dpsa line clean`), not found in the data.
    pub clean_recorded: bool,
    /// Fine apertures watched.
    pub fine_pads: usize,
    /// Their mean volume just after the clean (its first 3 boards), %.
    pub fine_volume_after_clean_pct: Option<f64>,
    /// And now (the last 3 boards), %.
    pub fine_volume_now_pct: Option<f64>,
    /// The trend since the clean, points of % a board.
    pub fine_volume_trend_pct_per_board: Option<f64>,
    /// Bridges and smears a board over the last 5 boards.
    pub smears_per_board: f64,
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Assesses the stencil from the study's `boards` (oldest first) with `fine_pads` fine
/// apertures; `recorded`: the first board after the last recorded clean (`boards.len()` when
/// the stencil was cleaned after the newest board), which then stands for the one found in the
/// data.
pub fn assess(
    boards: &[BoardStencil],
    fine_pads: usize,
    cfg: &StencilConfig,
    recorded: Option<usize>,
) -> Cleaning {
    let fine: Vec<(usize, f64)> = boards
        .iter()
        .enumerate()
        .filter_map(|(i, b)| Some((i, b.fine_volume_pct?)))
        .collect();
    // Board-to-board sigma of the fine volume: the median moving range / 0.954 (robust to the
    // steps a clean makes).
    let mut mr: Vec<f64> = fine.windows(2).map(|w| (w[1].1 - w[0].1).abs()).collect();
    mr.sort_by(f64::total_cmp);
    let sigma = mr.get(mr.len() / 2).map_or(0.0, |m| m / 0.954);
    let clean = fine
        .windows(2)
        .rev()
        .find(|w| {
            let up = w[1].1 - w[0].1;
            up > cfg.clean_step_pct && up > 4.0 * sigma
        })
        .map(|w| w[1].0);
    let clean = recorded.or(clean);
    let since = clean.unwrap_or(0);
    let after: Vec<(usize, f64)> = fine.iter().copied().filter(|(i, _)| *i >= since).collect();
    let head: Vec<f64> = after.iter().take(3).map(|p| p.1).collect();
    let tail: Vec<f64> = after.iter().rev().take(3).map(|p| p.1).collect();
    let (v0, v1) = (mean(&head), mean(&tail));
    let trend = (after.len() >= 3).then(|| {
        let n = after.len() as f64;
        let mx = after.iter().map(|p| p.0 as f64).sum::<f64>() / n;
        let my = after.iter().map(|p| p.1).sum::<f64>() / n;
        let sxy: f64 = after.iter().map(|p| (p.0 as f64 - mx) * (p.1 - my)).sum();
        let sxx: f64 = after.iter().map(|p| (p.0 as f64 - mx).powi(2)).sum();
        sxy / sxx
    });
    let recent: Vec<f64> = boards
        .iter()
        .rev()
        .take(5)
        .map(|b| b.smears as f64)
        .collect();
    let smears = mean(&recent).unwrap_or(0.0);
    let mut reasons = Vec::new();
    let mut recommend = false;
    match (v0, v1) {
        (Some(a), Some(b)) if after.len() >= 6 && a - b >= cfg.drop_pct => {
            recommend = true;
            reasons.push(format!(
                "fine apertures (area ratio < {}): volume {a:.1} % after the {} to {b:.1} % now, \
                 down {:.1} points over {} boards ({:+.2} a board): clogging",
                cfg.fine_area_ratio,
                if recorded.is_some() {
                    "last clean (recorded)"
                } else if clean.is_some() {
                    "last clean"
                } else {
                    "study's start"
                },
                a - b,
                after.len(),
                trend.unwrap_or(0.0)
            ));
        }
        _ if recorded.is_some_and(|r| r >= boards.len()) => reasons.push(
            "the stencil was cleaned after the newest board: nothing printed since".to_owned(),
        ),
        (Some(a), Some(b)) => reasons.push(format!(
            "fine apertures: volume {a:.1} % then, {b:.1} % now (a clean is due at a fall of {} \
             points)",
            cfg.drop_pct
        )),
        _ => reasons.push("no fine aperture measured".to_owned()),
    }
    if smears >= cfg.smears_per_board {
        recommend = true;
        reasons.push(format!(
            "{smears:.1} bridges or smears a board over the last {} boards: paste under the \
             stencil",
            recent.len()
        ));
    }
    Cleaning {
        recommend,
        reasons,
        since_board: since,
        clean_found: clean.is_some(),
        clean_recorded: recorded.is_some(),
        fine_pads,
        fine_volume_after_clean_pct: v0,
        fine_volume_now_pct: v1,
        fine_volume_trend_pct_per_board: trend,
        smears_per_board: smears,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn boards(
        v: impl Fn(usize) -> f64,
        smears: impl Fn(usize) -> usize,
        n: usize,
    ) -> Vec<BoardStencil> {
        // A fixed wobble of +-0.8 points (no seed to depend on).
        (0..n)
            .map(|i| BoardStencil {
                fine_volume_pct: Some(v(i) + ((i * 7) % 5) as f64 * 0.4 - 0.8),
                smears: smears(i),
            })
            .collect()
    }

    /// Clogging at 1 point a board, a clean at board 15, clogging again: the clean is found,
    /// and a clean is recommended once the fall since passes 8 points, not before.
    #[test]
    fn clogging_since_the_last_clean_is_found_and_called() {
        let v = |i: usize| {
            if i < 15 {
                100.0 - i as f64
            } else {
                100.0 - (i - 15) as f64
            }
        };
        let c = assess(&boards(v, |_| 0, 22), 40, &StencilConfig::default(), None);
        assert!(c.clean_found && c.since_board == 15, "{c:?}");
        assert!(!c.recommend, "{c:?}");
        let c = assess(&boards(v, |_| 0, 30), 40, &StencilConfig::default(), None);
        assert!(c.recommend && c.since_board == 15, "{c:?}");
        eprintln!("{}", c.reasons[0]);
        assert!(c.reasons[0].contains("clogging"), "{c:?}");
        let t = c.fine_volume_trend_pct_per_board.unwrap();
        assert!((t + 1.0).abs() < 0.1, "{t}");
    }

    /// A recorded clean stands for the one the data would give: counted from there, said so;
    /// one after the newest board leaves nothing to judge.
    #[test]
    fn a_recorded_clean_is_counted_from() {
        let v = |i: usize| 100.0 - (i % 15) as f64;
        let c = assess(
            &boards(v, |_| 0, 30),
            40,
            &StencilConfig::default(),
            Some(20),
        );
        assert!(
            c.clean_found && c.clean_recorded && c.since_board == 20,
            "{c:?}"
        );
        assert!(!c.recommend, "5 points since board 20: {c:?}");
        let c = assess(
            &boards(v, |_| 0, 30),
            40,
            &StencilConfig::default(),
            Some(30),
        );
        assert!(
            !c.recommend && c.reasons[0].contains("nothing printed since"),
            "{c:?}"
        );
        let c = assess(&boards(v, |_| 0, 30), 40, &StencilConfig::default(), None);
        assert!(
            c.clean_found && !c.clean_recorded && c.since_board == 15,
            "{c:?}"
        );
    }

    /// A steady print with noise: no clean found, none recommended.
    #[test]
    fn a_steady_print_needs_no_clean() {
        let c = assess(
            &boards(|_| 97.0, |_| 0, 60),
            40,
            &StencilConfig::default(),
            None,
        );
        assert!(!c.recommend && !c.clean_found, "{c:?}");
        assert_eq!(c.since_board, 0);
    }

    #[test]
    fn smears_call_for_a_clean() {
        let c = assess(
            &boards(|_| 97.0, |i| usize::from(i >= 55) * 2, 60),
            40,
            &StencilConfig::default(),
            None,
        );
        assert!(
            c.recommend && c.reasons.iter().any(|r| r.contains("under the stencil")),
            "{c:?}"
        );
        let none = assess(&[], 0, &StencilConfig::default(), None);
        assert!(!none.recommend && none.reasons[0].contains("no fine aperture"));
    }
}
