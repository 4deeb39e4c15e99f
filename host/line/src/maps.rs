//! The measured maps the line keeps for its pages (`[maps]` of `LINE.toml`): each finished
//! board's map (inspected, or incomplete because the design could not be registered on it)
//! written by a thread of its own ([`MapKeeper`]) after the board is stored, so
//! the verdict never waits for it, in `dpsa_formats::kept_map`'s files; the oldest removed
//! beyond `keep_boards`.
//!
//! Bounded: one map written and one waiting at most. A board whose map comes while both
//! places are taken has its map not kept (logged and counted in the summary); its verdict,
//! pads and images are stored all the same.

use crate::config::Maps;
use crate::keeper::Tally;
use dpsa_formats::grid::{BoardGrid, Grid};
use dpsa_formats::kept_map::DesignToBoard;
use std::sync::mpsc::{sync_channel, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

/// A map to keep.
pub struct MapJob {
    /// The board's store id.
    pub board: i64,
    /// Its run id.
    pub run_id: u64,
    /// The map's grid.
    pub grid: BoardGrid,
    /// The map, um (NaN invalid).
    pub heights: Grid,
    /// Where the design lies on it (`None`: it could not be registered).
    pub design_to_board: Option<DesignToBoard>,
}

/// The thread that writes the kept maps.
pub struct MapKeeper {
    tx: Option<SyncSender<MapJob>>,
    thread: Option<JoinHandle<()>>,
    tally: Arc<Mutex<Tally>>,
}

impl MapKeeper {
    /// Starts the writer for `maps`; `None` when no map is kept (`keep_boards = 0`).
    pub fn start(
        maps: &Maps,
        line: &str,
        tally: Arc<Mutex<Tally>>,
    ) -> std::io::Result<Option<MapKeeper>> {
        if maps.keep_boards == 0 {
            return Ok(None);
        }
        match dpsa_formats::kept_map::remove_unfinished(&maps.dir, line) {
            Ok(gone) if !gone.is_empty() => {
                tracing::warn!(files = ?gone, "unfinished map writes of a killed run removed")
            }
            Ok(_) => {}
            Err(e) => tracing::error!("unfinished map writes not removed: {e}"),
        }
        let (tx, rx) = sync_channel::<MapJob>(1);
        let (dir, keep, line) = (maps.dir.clone(), maps.keep_boards, line.to_owned());
        let t = Arc::clone(&tally);
        let thread = std::thread::Builder::new()
            .name("maps".into())
            .spawn(move || {
                for job in rx {
                    let t0 = Instant::now();
                    let r = dpsa_formats::kept_map::write(
                        &dir,
                        &line,
                        job.board,
                        job.run_id,
                        &job.grid,
                        &job.heights,
                        job.design_to_board,
                    );
                    dpsa_board::pool::give_map(job.heights);
                    match r {
                        Ok(k) => {
                            tracing::debug!(
                                board = job.board,
                                mb = format!("{:.1}", k.png_bytes as f64 / 1e6),
                                seconds = format!("{:.2}", t0.elapsed().as_secs_f64()),
                                "map kept"
                            );
                            if k.clipped > 0 {
                                tracing::warn!(
                                    board = job.board,
                                    pixels = k.clipped,
                                    "map kept with heights beyond 16 bits marked invalid"
                                );
                            }
                            if let Ok(mut t) = t.lock() {
                                t.maps_kept += 1;
                            }
                        }
                        Err(e) => {
                            tracing::error!(board = job.board, "map not kept: {e}");
                            if let Ok(mut t) = t.lock() {
                                t.maps_not_kept += 1;
                            }
                        }
                    }
                    match dpsa_formats::kept_map::prune(&dir, &line, keep) {
                        Ok(gone) if !gone.is_empty() => {
                            tracing::debug!(boards = ?gone, "older maps removed")
                        }
                        Ok(_) => {}
                        Err(e) => tracing::error!("older maps not removed: {e}"),
                    }
                }
            })?;
        Ok(Some(MapKeeper {
            tx: Some(tx),
            thread: Some(thread),
            tally,
        }))
    }

    /// Hands `job` to the writer; a map that finds the writer busy with one waiting is not
    /// kept (said and counted).
    pub fn offer(&self, job: MapJob) {
        let Some(tx) = &self.tx else {
            dpsa_board::pool::give_map(job.heights);
            return;
        };
        let board = job.board;
        match tx.try_send(job) {
            Ok(()) => {}
            Err(TrySendError::Full(job)) => {
                dpsa_board::pool::give_map(job.heights);
                tracing::warn!(
                    board,
                    "map not kept: the writer is still busy with two maps"
                );
                if let Ok(mut t) = self.tally.lock() {
                    t.maps_not_kept += 1;
                }
            }
            Err(TrySendError::Disconnected(job)) => {
                dpsa_board::pool::give_map(job.heights);
                tracing::error!(board, "map not kept: the writer has stopped");
                if let Ok(mut t) = self.tally.lock() {
                    t.maps_not_kept += 1;
                }
            }
        }
    }
}

impl Drop for MapKeeper {
    /// The maps handed over are written before the service ends.
    fn drop(&mut self) {
        drop(self.tx.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
