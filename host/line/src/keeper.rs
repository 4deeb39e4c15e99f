//! The keeper: the one thread that owns the store. A board's begin is stored at once (state
//! `open`, so that a board the service dies in is found on restart and recorded incomplete);
//! a finished board's map is inspected against its product's program, and the board, its
//! cameras' losses and every pad are stored in one transaction, then its CFX message is
//! spooled; an incomplete board is stored with its reason and gets no message.

use crate::config::Product;
use crate::store::{BoardStart, CameraLoss, Outcome, PadRow, Store};
use dpsa_formats::grid::{BoardGrid, Grid};
use dpsa_inspect::map::BoardMap;
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

/// One board as the keeper stored it (for the service's summary and the tests).
#[derive(Clone, Debug, serde::Serialize)]
pub struct Kept {
    /// The run id.
    pub run_id: u64,
    /// `pass`, `warn`, `fail` or `incomplete`.
    pub verdict: String,
    /// From the last camera's last row to the board stored, s (inspected boards).
    pub latency_s: Option<f64>,
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
    /// Every board kept so far (the newest [`KEPT_LISTED`]).
    pub kept: Arc<Mutex<Vec<Kept>>>,
}

/// Boards listed in [`Keeper::kept`] at most.
pub const KEPT_LISTED: usize = 10_000;

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
                    let (outcome, cfx) = self.inspect(product, run_id, grid, heights);
                    let verdict = match &outcome {
                        Outcome::Inspected { verdict, .. } => verdict.clone(),
                        Outcome::Incomplete { .. } => "incomplete".into(),
                    };
                    let run = format!("{run_id:016x}");
                    match self
                        .store
                        .finish_board(id, crate::boards::unix_now(), &losses, &outcome)
                    {
                        Ok(()) => {
                            // The message only for a board stored.
                            if let Some(m) = cfx {
                                if let Err(e) = crate::cfx::spool(&self.spool, run_id, &m) {
                                    tracing::error!(%run, "CFX message not spooled: {e}");
                                }
                            }
                            let latency = last_row_at.elapsed().as_secs_f64();
                            tracing::info!(%run, %verdict, latency_s = format!("{latency:.3}"), "board stored");
                            self.keep(Kept {
                                run_id,
                                verdict,
                                latency_s: Some(latency),
                            });
                        }
                        Err(e) => tracing::error!(%run, "not stored: {e}"),
                    }
                }
                Job::Incomplete {
                    run_id,
                    reason,
                    losses,
                } => {
                    let Some((id, _)) = open.remove(&run_id) else {
                        continue;
                    };
                    let outcome = Outcome::Incomplete { reason };
                    match self
                        .store
                        .finish_board(id, crate::boards::unix_now(), &losses, &outcome)
                    {
                        Ok(()) => self.keep(Kept {
                            run_id,
                            verdict: "incomplete".into(),
                            latency_s: None,
                        }),
                        Err(e) => {
                            tracing::error!(run = %format!("{run_id:016x}"), "not stored: {e}")
                        }
                    }
                }
            }
        }
    }

    fn keep(&self, k: Kept) {
        if let Ok(mut v) = self.kept.lock() {
            if v.len() >= KEPT_LISTED {
                v.remove(0);
            }
            v.push(k);
        }
    }

    /// Registers, measures and judges every pad of `product` on the map: the stored outcome
    /// and the CFX message (none when the design cannot be registered: the board is then
    /// incomplete, never passed).
    fn inspect(
        &self,
        product: usize,
        run_id: u64,
        grid: BoardGrid,
        heights: Grid,
    ) -> (Outcome, Option<serde_json::Value>) {
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
                )
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
                uncertainty_um3: None,
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
        (Outcome::Inspected { verdict, pads }, Some(msg))
    }
}
