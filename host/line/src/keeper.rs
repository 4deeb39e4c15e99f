//! The keeper: the one thread that owns the store. A board's begin is stored at once (state
//! `open`, so that a board the service dies in is found on restart and recorded incomplete);
//! a finished board's map is inspected against its product's program, and the board, its
//! cameras' losses and every pad are stored in one transaction, then its CFX message is
//! spooled; an incomplete board is stored with its reason and gets no message.
//!
//! Every finished board also goes through its product's loop back to the printer
//! ([`crate::printer`]): the print's placement measured on it (none on an incomplete board,
//! which was printed all the same and so counts in the loop's delay), the correction the loop
//! proposes after it, stored with the board in the same transaction (`prints`) and, for an
//! inspected board, spooled as `RUNID.printer.json` beside its CFX message. The loop of a
//! product is resumed from the store's last rows when the service starts, so a restart
//! neither forgets a correction in flight nor issues one twice.

use crate::config::Product;
use crate::printer::{Loop, LoopConfig, Proposal};
use crate::store::{BoardStart, CameraLoss, Outcome, PadImage, PadRow, PrintRow, Store};
use dpsa_formats::grid::{BoardGrid, Grid};
use dpsa_formats::kept_map::DesignToBoard;
use dpsa_inspect::map::BoardMap;
use dpsa_inspect::print::PrintOffset;
use dpsa_inspect::verdict::Level;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::mpsc::Receiver;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// What the boards hand the keeper.
pub enum Job {
    /// A board began.
    Begin {
        /// Its run id.
        run_id: u64,
        /// Its product (index into the configuration's products).
        product: usize,
        /// When, s since 1970.
        started_unix_s: f64,
    },
    /// A board's map is done.
    Finished {
        /// Its run id.
        run_id: u64,
        /// The map's grid.
        grid: BoardGrid,
        /// The map, um (NaN invalid).
        heights: Grid,
        /// What each camera lost.
        losses: Vec<CameraLoss>,
        /// When the last camera's last row came.
        last_row_at: Instant,
    },
    /// A board ended incomplete.
    Incomplete {
        /// Its run id.
        run_id: u64,
        /// Why.
        reason: String,
        /// What each camera lost.
        losses: Vec<CameraLoss>,
    },
}

/// A finished board's map, handed to the maps' writer once the board is stored: its grid,
/// its heights and where the design lies on it (`None`: it could not be registered).
type MapKept = (BoardGrid, Grid, Option<DesignToBoard>);

/// One board as the keeper stored it.
#[derive(Clone, Debug)]
pub struct Kept {
    /// The run id.
    pub run_id: u64,
    /// `pass`, `warn`, `fail` or `incomplete`.
    pub verdict: String,
    /// From the last camera's last row to the board stored, s (inspected boards).
    pub latency_s: Option<f64>,
    /// The service's resident memory when the board was stored, MB (Linux).
    pub rss_mb: Option<f64>,
}

/// What the keeper stored so far, for the service's summary: counts of every board, the
/// newest [`LATENCIES_KEPT`] latencies, the memory at the first and the last board.
#[derive(Clone, Debug, Default)]
pub struct Tally {
    /// Boards stored, by verdict (`pass`, `warn`, `fail`, `incomplete`).
    pub by_verdict: std::collections::BTreeMap<String, usize>,
    /// Boards stored.
    pub boards: usize,
    /// Latencies of the newest inspected boards, s.
    pub latencies: std::collections::VecDeque<f64>,
    /// Resident memory when the first board was stored, MB.
    pub rss_first_mb: Option<f64>,
    /// Resident memory when the last board was stored, MB.
    pub rss_last_mb: Option<f64>,
    /// Resident memory when board 1, 10, 100, ... was stored, MB: flat memory shows as the
    /// same figure from a hundred boards on.
    pub rss_by_boards: std::collections::BTreeMap<usize, f64>,
    /// Finished boards whose measured map was kept (`[maps]`).
    pub maps_kept: usize,
    /// Finished boards whose map was not kept (the writer busy, or a write that failed).
    pub maps_not_kept: usize,
    /// Pad rows the retention deleted (`[retention]`).
    pub pad_rows_pruned: u64,
}

/// Most pad images kept per board (failures first): a board of many calls is a board to
/// look at as a whole, and its store rows stay bounded (a 1 mm pad's image is about 5 kB).
pub const MAX_IMAGES: usize = 200;

fn is_power_of_ten(mut n: usize) -> bool {
    while n >= 10 && n % 10 == 0 {
        n /= 10;
    }
    n == 1
}

/// Boards whose pad rows the keeper deletes at most after each board it stores, when
/// `[retention]` asks for it: twice the boards that come, so that a backlog (a retention
/// shortened on an old store, or a line back after a long stop) is worked off at a board
/// more each board, and no board waits for more than two boards' deletes (`dpsa line
/// store-bench`'s `prune.keeper_call_*` on SQLite: 9 ms median, under 20 ms, for two boards
/// of 6,000 pads).
pub const PRUNE_BOARDS_PER_BOARD: usize = 2;

/// Latencies [`Tally`] keeps (the newest).
pub const LATENCIES_KEPT: usize = 10_000;

impl Tally {
    fn add(&mut self, k: Kept) {
        *self.by_verdict.entry(k.verdict).or_default() += 1;
        self.boards += 1;
        if let Some(l) = k.latency_s {
            if self.latencies.len() >= LATENCIES_KEPT {
                self.latencies.pop_front();
            }
            self.latencies.push_back(l);
        }
        if self.boards == 1 {
            self.rss_first_mb = k.rss_mb;
        }
        if let Some(mb) = k.rss_mb.filter(|_| is_power_of_ten(self.boards)) {
            self.rss_by_boards.insert(self.boards, mb);
        }
        self.rss_last_mb = k.rss_mb;
    }
}

/// What the keeper needs.
pub struct Keeper {
    /// The store.
    pub store: Store,
    /// The products.
    pub products: Vec<Product>,
    /// The CFX spool directory.
    pub spool: PathBuf,
    /// The calibration's hash.
    pub calibration_hash: String,
    /// What was stored so far.
    pub tally: Arc<Mutex<Tally>>,
    /// The loop back to the printer's settings.
    pub printer: LoopConfig,
    /// Each product's loop (by index into `products`), resumed from the store at its first
    /// board.
    pub loops: HashMap<usize, PrinterLoop>,
    /// The writer of the measured maps kept for the pages (none: no map kept).
    pub maps: Option<crate::maps::MapKeeper>,
    /// Days a board's pad rows are kept after it ended (`None`: for ever).
    pub pad_days: Option<f64>,
}

/// One product's loop back to the printer and the run ids of its newest boards.
#[derive(Clone, Debug)]
pub struct PrinterLoop {
    /// The loop.
    pub state: Loop,
    /// Run ids of the newest boards it took, oldest first (as many as its memory).
    pub recent: std::collections::VecDeque<u64>,
}

impl PrinterLoop {
    /// Takes board `run_id`'s placement; the proposal after it.
    fn board(&mut self, run_id: u64, placement: Option<&PrintOffset>) -> Proposal {
        let p = self.state.board(placement);
        self.recent.push_back(run_id);
        while self.recent.len() > self.state.memory() {
            self.recent.pop_front();
        }
        p
    }
}

impl Keeper {
    /// Serves jobs until every sender is gone.
    pub fn run(mut self, rx: Receiver<Job>) {
        // Run id -> (store id, product).
        let mut open: HashMap<u64, (i64, usize)> = HashMap::new();
        for job in rx {
            match job {
                Job::Begin {
                    run_id,
                    product,
                    started_unix_s,
                } => {
                    let p = &self.products[product];
                    let start = BoardStart {
                        run_id,
                        product: p.id.clone(),
                        program_hash: p.program_hash.clone(),
                        calibration_hash: self.calibration_hash.clone(),
                        started_unix_s,
                    };
                    match self.store.begin_board(&start) {
                        Ok(id) => {
                            open.insert(run_id, (id, product));
                        }
                        Err(e) => {
                            tracing::error!(run = %format!("{run_id:016x}"), "not stored: {e}")
                        }
                    }
                }
                Job::Finished {
                    run_id,
                    grid,
                    heights,
                    losses,
                    last_row_at,
                } => {
                    let Some((id, product)) = open.remove(&run_id) else {
                        continue;
                    };
                    let (outcome, cfx, placement, images, map) =
                        self.inspect(product, run_id, grid, heights);
                    let verdict = match &outcome {
                        Outcome::Inspected { verdict, .. } => verdict.clone(),
                        Outcome::Incomplete { .. } => "incomplete".into(),
                    };
                    let run = format!("{run_id:016x}");
                    match self.finish(id, run_id, product, &losses, &outcome, placement, &images) {
                        Ok((next, row)) => {
                            // The messages only for a board stored.
                            if let Some(m) = cfx {
                                if let Err(e) = crate::cfx::spool(&self.spool, run_id, &m) {
                                    tracing::error!(%run, "CFX message not spooled: {e}");
                                }
                                let m = self.printer_message(product, &next, &row);
                                let name = format!("{run}.printer.json");
                                if let Err(e) = crate::cfx::spool_named(&self.spool, &name, &m) {
                                    tracing::error!(%run, "printer proposal not spooled: {e}");
                                }
                            }
                            let latency = last_row_at.elapsed().as_secs_f64();
                            tracing::info!(%run, %verdict, latency_s = format!("{latency:.3}"), "board stored");
                            match (&self.maps, map) {
                                (Some(m), Some((grid, heights, design_to_board))) => {
                                    m.offer(crate::maps::MapJob {
                                        board: id,
                                        run_id,
                                        grid,
                                        heights,
                                        design_to_board,
                                    })
                                }
                                // Not kept: its memory serves the next board's map.
                                (None, Some((_, heights, _))) => {
                                    dpsa_board::pool::give_map(heights)
                                }
                                (_, None) => {}
                            }
                            self.keep(Kept {
                                run_id,
                                verdict,
                                latency_s: Some(latency),
                                rss_mb: crate::memory::status_mb("VmRSS"),
                            });
                            self.retain(crate::boards::unix_now());
                        }
                        Err(e) => {
                            tracing::error!(%run, "not stored: {e}");
                            if let Some((_, heights, _)) = map {
                                dpsa_board::pool::give_map(heights);
                            }
                        }
                    }
                }
                Job::Incomplete {
                    run_id,
                    reason,
                    losses,
                } => {
                    let Some((id, product)) = open.remove(&run_id) else {
                        continue;
                    };
                    let outcome = Outcome::Incomplete { reason };
                    // Printed all the same: the loop counts it (no placement, held).
                    match self.finish(id, run_id, product, &losses, &outcome, None, &[]) {
                        Ok(_) => {
                            self.keep(Kept {
                                run_id,
                                verdict: "incomplete".into(),
                                latency_s: None,
                                rss_mb: crate::memory::status_mb("VmRSS"),
                            });
                            self.retain(crate::boards::unix_now());
                        }
                        Err(e) => {
                            tracing::error!(run = %format!("{run_id:016x}"), "not stored: {e}")
                        }
                    }
                }
            }
        }
    }

    /// The retention after a board stored at `now_unix_s`: the pad rows of at most
    /// [`PRUNE_BOARDS_PER_BOARD`] boards that ended more than `pad_days` days before, the
    /// oldest first. A failure is logged and tried again after the next board: the boards
    /// themselves are stored either way.
    fn retain(&mut self, now_unix_s: f64) {
        let Some(days) = self.pad_days else {
            return;
        };
        let t = Instant::now();
        match self
            .store
            .prune_pads_oldest(now_unix_s - days * 86_400.0, PRUNE_BOARDS_PER_BOARD)
        {
            Ok(0) => {}
            Ok(rows) => {
                if let Ok(mut tally) = self.tally.lock() {
                    tally.pad_rows_pruned += rows;
                }
                tracing::debug!(
                    rows,
                    ms = format!("{:.1}", t.elapsed().as_secs_f64() * 1e3),
                    "pad rows past the retention deleted"
                );
            }
            Err(e) => tracing::error!("retention: pad rows not deleted: {e}"),
        }
    }

    /// Ends board `id` in the store with its print row (the placement and what `product`'s
    /// loop proposes after it) and the images of its calls. The loop moves on only once the
    /// board is stored; the loop after the board and the row stored.
    #[allow(clippy::too_many_arguments)]
    fn finish(
        &mut self,
        id: i64,
        run_id: u64,
        product: usize,
        losses: &[CameraLoss],
        outcome: &Outcome,
        placement: Option<PrintOffset>,
        images: &[PadImage],
    ) -> Result<(PrinterLoop, PrintRow), crate::store::StoreError> {
        let mut next = self.printer_loop(product);
        let row = PrintRow {
            placement,
            proposal: next.board(run_id, placement.as_ref()),
        };
        self.store.finish_board_with_images(
            id,
            crate::boards::unix_now(),
            losses,
            outcome,
            Some(&row),
            images,
        )?;
        self.loops.insert(product, next.clone());
        Ok((next, row))
    }

    /// A copy of `product`'s loop, resumed from the store's newest rows of the product on
    /// this line the first time (a loop the store cannot give starts afresh, and says so).
    fn printer_loop(&mut self, product: usize) -> PrinterLoop {
        if let Some(l) = self.loops.get(&product) {
            return l.clone();
        }
        let fresh = Loop::new(self.printer.clone());
        let want = (self.printer.delay + 1).max(fresh.memory());
        let id = &self.products[product].id;
        let l = match self.store.prints(id, want) {
            Ok(mut rows) => {
                rows.reverse();
                let history: Vec<Proposal> =
                    rows.iter().map(|r| r.print.proposal.clone()).collect();
                let state = Loop::resume(self.printer.clone(), &history);
                let keep = rows.len().saturating_sub(state.memory());
                if let Some(last) = history.last() {
                    tracing::info!(
                        product = %id,
                        correction = ?last.correction,
                        "the loop back to the printer resumed from the store"
                    );
                }
                PrinterLoop {
                    recent: rows[keep..].iter().map(|r| r.run_id).collect(),
                    state,
                }
            }
            Err(e) => {
                tracing::error!(product = %id, "the printer loop starts afresh: {e}");
                PrinterLoop {
                    state: fresh,
                    recent: Default::default(),
                }
            }
        };
        self.loops.insert(product, l.clone());
        l
    }

    /// The proposal after a board as the message the spool gets ([`crate::printer::message`]):
    /// based on the boards that weigh 1 % or more in the loop's estimate.
    fn printer_message(
        &self,
        product: usize,
        l: &PrinterLoop,
        row: &PrintRow,
    ) -> serde_json::Value {
        let line = self.store.line();
        let hex = |r: &u64| format!("{r:016x}");
        crate::printer::message(
            &row.proposal,
            l.state.config(),
            &format!("dpsa/{line}"),
            line,
            &self.products[product].id,
            &l.recent.front().map(hex).unwrap_or_default(),
            &l.recent.back().map(hex).unwrap_or_default(),
            l.recent.len(),
            row.placement.map(|p| p.stretch_ppm),
            &dpsa_inspect::report::iso_now(),
        )
    }

    fn keep(&self, k: Kept) {
        if let Ok(mut t) = self.tally.lock() {
            t.add(k);
        }
    }

    /// Registers, measures and judges every pad of `product` on the map: the stored outcome,
    /// the CFX message (none when the design cannot be registered: the board is then
    /// incomplete, never passed), the print's placement and the images of the pads that
    /// warned or failed (failures first, at most [`MAX_IMAGES`]).
    fn inspect(
        &self,
        product: usize,
        run_id: u64,
        grid: BoardGrid,
        heights: Grid,
    ) -> (
        Outcome,
        Option<serde_json::Value>,
        Option<PrintOffset>,
        Vec<PadImage>,
        Option<MapKept>,
    ) {
        let p = &self.products[product];
        let map = BoardMap {
            board_id: Some(dpsa_formats::BoardId(run_id)),
            grid,
            heights,
        };
        let i = match dpsa_inspect::run::inspect(&map, &p.pads, &p.program) {
            Ok(i) => i,
            Err(e) => {
                return (
                    Outcome::Incomplete {
                        reason: format!("the design could not be registered on the map: {e}"),
                    },
                    None,
                    None,
                    Vec::new(),
                    // Kept all the same, without a registration: the map shows why.
                    Some((map.grid, map.heights, None)),
                );
            }
        };
        let opt = |v: f64| v.is_finite().then_some(v);
        let pads: Vec<PadRow> = p
            .pads
            .iter()
            .zip(&i.measurements)
            .zip(&i.calls)
            .enumerate()
            .map(|(k, ((pad, m), c))| PadRow {
                pad: k as u32,
                name: dpsa_inspect::report::cfx_pad(pad),
                level: c.level.name().into(),
                class: c.class.map(|k| k.name().to_string()),
                volume_um3: opt(m.volume_um3),
                volume_pct: opt(m.volume_pct),
                area_mm2: opt(m.area_mm2),
                area_pct: opt(m.area_pct),
                height_um: opt(m.height_um),
                height_pct: opt(m.height_pct),
                offset_x_um: opt(m.offset_um[0]),
                offset_y_um: opt(m.offset_um[1]),
                coverage: m.coverage,
                uncertainty_um3: opt(m.volume_u_um3),
            })
            .collect();
        let worst = i.calls.iter().map(|c| c.level).max_by_key(|l| match l {
            Level::Pass => 0,
            Level::Warn => 1,
            Level::Fail => 2,
        });
        let verdict = worst.unwrap_or(Level::Pass).name().to_string();
        let unit = format!("{run_id:016x}");
        let recipe = p.program.name.clone().unwrap_or_else(|| p.id.clone());
        let msg = dpsa_inspect::report::cfx(&p.pads, &i, &p.program, &unit, &recipe);
        let mut calls: Vec<usize> = (0..p.pads.len())
            .filter(|&k| i.calls[k].level != Level::Pass)
            .collect();
        calls.sort_by_key(|&k| (i.calls[k].level != Level::Fail, k));
        let t = i.registration.transform;
        let images = calls
            .into_iter()
            .take(MAX_IMAGES)
            .filter_map(|k| {
                let crop = dpsa_inspect::crop::pad_crop(&map, &p.pads[k], &i.measurements[k], &t)?;
                Some(PadImage {
                    pad: k as u32,
                    family: p.families.get(k).cloned().flatten(),
                    crop,
                })
            })
            .collect();
        let design_to_board = DesignToBoard {
            rotation_rad: t.rotation_rad,
            tx_mm: t.tx,
            ty_mm: t.ty,
        };
        (
            Outcome::Inspected { verdict, pads },
            Some(msg),
            i.print,
            images,
            Some((map.grid, map.heights, Some(design_to_board))),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Counts go on past the latencies kept; the first board's memory stays the first's.
    #[test]
    fn the_tally_counts_every_board() {
        let mut t = Tally::default();
        for k in 0..LATENCIES_KEPT + 5 {
            t.add(Kept {
                run_id: k as u64 + 1,
                verdict: if k % 3 == 0 { "fail" } else { "pass" }.into(),
                latency_s: Some(k as f64),
                rss_mb: Some(k as f64),
            });
        }
        assert_eq!(t.boards, LATENCIES_KEPT + 5);
        assert_eq!(t.by_verdict["fail"] + t.by_verdict["pass"], t.boards);
        assert_eq!(t.latencies.len(), LATENCIES_KEPT);
        assert_eq!(t.latencies.front(), Some(&5.0));
        assert_eq!(
            (t.rss_first_mb, t.rss_last_mb),
            (Some(0.0), Some((LATENCIES_KEPT + 4) as f64))
        );
        // Board n's memory (n = 1, 10, 100, ...) is the n-th board's, k = n - 1.
        let want: Vec<(usize, f64)> = [1, 10, 100, 1000, 10_000]
            .into_iter()
            .map(|n| (n, (n - 1) as f64))
            .collect();
        assert_eq!(t.rss_by_boards.into_iter().collect::<Vec<_>>(), want);
    }
}
