//! The open boards: the connections' [`Event`]s sorted by run id, each camera's rows stitched
//! into its board's map band by band as they arrive, and every board ended exactly once:
//! finished (every camera's end packet came) and handed to the [`crate::keeper`] with its map,
//! or incomplete with the reason (a camera cut off, silent for `timeouts.silent_s`, never
//! begun, the board open longer than `timeouts.board_s`, a third board begun before it ended).
//!
//! A board is one run id across all cameras; rows of one board never reach another's map. At
//! most [`MAX_OPEN_BOARDS`] are open at once (the next board's first camera may begin before
//! the last camera of this one ends), so memory is bounded by two maps. Run ids that ended are
//! remembered ([`REMEMBERED`]): a late stream of one is logged and dropped, never a new board.

use crate::keeper::Job;
use crate::link::Event;
use crate::store::CameraLoss;
use dpsa_board::assemble::{Stitcher, BAND_ROWS};
use dpsa_board::run::Chunk;
use dpsa_board::unwrap::CHUNK_ROWS;
use dpsa_formats::calibration::CalFile;
use dpsa_formats::grid::BoardGrid;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

/// Boards open at once.
pub const MAX_OPEN_BOARDS: usize = 2;
/// Ended run ids remembered.
pub const REMEMBERED: usize = 256;

/// Which boards may be open: a connection whose next stream is of a board not admitted yet
/// waits here before it reads on, so the frame grabber feels the back-pressure (TCP) instead
/// of the line holding a third board's rows in memory. The boards release a board's place
/// when it ends (or when they drop its stream).
pub struct Gate {
    admitted: Mutex<Vec<u64>>,
    freed: Condvar,
}

impl Default for Gate {
    fn default() -> Self {
        Gate::new()
    }
}

impl Gate {
    /// No board admitted.
    pub fn new() -> Gate {
        Gate {
            admitted: Mutex::new(Vec::new()),
            freed: Condvar::new(),
        }
    }

    /// Waits until board `run_id` has a place (at most [`MAX_OPEN_BOARDS`]); `false` when
    /// `stop` is set first.
    pub fn admit(&self, run_id: u64, stop: &AtomicBool) -> bool {
        let Ok(mut a) = self.admitted.lock() else {
            return false;
        };
        loop {
            if a.contains(&run_id) {
                return true;
            }
            if a.len() < MAX_OPEN_BOARDS {
                a.push(run_id);
                return true;
            }
            if stop.load(Ordering::Relaxed) {
                return false;
            }
            a = match self.freed.wait_timeout(a, Duration::from_millis(100)) {
                Ok((a, _)) => a,
                Err(_) => return false,
            };
        }
    }

    /// Board `run_id` ended (or was dropped): its place is free.
    pub fn release(&self, run_id: u64) {
        if let Ok(mut a) = self.admitted.lock() {
            a.retain(|&r| r != run_id);
            self.freed.notify_all();
        }
    }
}

/// Seconds since 1970.
pub fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// Longest product id the product file may hold, bytes.
const MAX_PRODUCT_FILE: u64 = 1024;

/// The product `file` names among `products` (its text, surrounding white space trimmed), or
/// `default` when there is no file. `Err` says why not when the file cannot be read, is too
/// long, or names none of them.
pub fn product_named(
    file: &std::path::Path,
    products: &[(String, BoardGrid)],
    default: usize,
) -> Result<usize, String> {
    let shown = file.display();
    let bytes = match dpsa_formats::files::read_capped_io(file, MAX_PRODUCT_FILE) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(default),
        Err(e) => {
            return Err(format!(
                "the line's product file {shown} could not be read: {e}"
            ))
        }
    };
    let text = String::from_utf8_lossy(&bytes);
    let id = text.trim();
    products.iter().position(|(p, _)| p == id).ok_or_else(|| {
        let known: Vec<&str> = products.iter().map(|(p, _)| p.as_str()).collect();
        format!("{shown} names product {id:?}, which is not one of LINE.toml's ({known:?})")
    })
}

/// A camera's part of an open board.
struct Part {
    /// The connection whose stream it is.
    conn: Option<u64>,
    /// Its last event.
    last: Instant,
    /// Rows waiting for the stitcher.
    waiting: Vec<Chunk>,
    /// The board row after its last row handed on.
    next_row: Option<i64>,
    /// Its end packet came, with what it lost.
    ended: Option<CameraLoss>,
}

/// An open board.
struct Open {
    run_id: u64,
    began: Instant,
    parts: Vec<Part>,
    stitcher: Option<Stitcher>,
    /// The last camera's last row came at (for the latency).
    last_row_at: Option<Instant>,
    /// Its product (index into the setup's).
    product: usize,
    /// Why it will not be inspected, known at its start (the line was told a product it does
    /// not have): its rows are dropped and it ends incomplete with this reason.
    refused: Option<String>,
}

/// What the boards need to stitch.
pub struct Setup {
    /// The calibration.
    pub cal: CalFile,
    /// Each product's id and board map grid, in the configuration's order.
    pub products: Vec<(String, BoardGrid)>,
    /// Each product's paste reflectance (its program's), which the map takes out of the
    /// walls; in the order of `products` (missing: none taken out).
    pub pastes: Vec<dpsa_board::places::PasteReflectance>,
    /// The product of a board when the line is told none (LINE.toml's `default_product`).
    pub default_product: usize,
    /// The file that tells the line the product of the boards that begin
    /// ([`crate::config::PRODUCT_FILE`] in the data directory; `dpsa line product` writes it).
    pub product_file: std::path::PathBuf,
    /// `timeouts.silent_s`.
    pub silent_s: f64,
    /// `timeouts.board_s`.
    pub board_s: f64,
}

/// The open boards (see the module docs).
pub struct Boards {
    setup: Setup,
    open: Vec<Open>,
    ended: VecDeque<u64>,
    keeper: SyncSender<Job>,
    /// The line is stopping: no new board begins.
    closing: bool,
    gate: Arc<Gate>,
}

impl Boards {
    /// No board open; finished and incomplete boards go to `keeper`; places are admitted by
    /// `gate`.
    pub fn new(setup: Setup, keeper: SyncSender<Job>, gate: Arc<Gate>) -> Boards {
        Boards {
            setup,
            open: Vec::new(),
            ended: VecDeque::new(),
            keeper,
            closing: false,
            gate,
        }
    }

    /// The line is stopping: streams of boards not begun yet are dropped (logged).
    pub fn close_doors(&mut self) {
        self.closing = true;
    }

    /// Boards open now.
    pub fn open(&self) -> usize {
        self.open.len()
    }

    fn index(&self, run_id: u64) -> Option<usize> {
        self.open.iter().position(|b| b.run_id == run_id)
    }

    /// One connection's event.
    pub fn event(&mut self, e: Event) {
        match e {
            Event::Begin {
                conn,
                camera,
                run_id,
            } => self.begin(conn, camera, run_id),
            Event::Rows {
                conn,
                camera,
                run_id,
                chunk,
            } => {
                let Some(k) = self.part_of(conn, camera, run_id) else {
                    return;
                };
                let p = &mut self.open[k].parts[camera];
                if p.ended.is_some() {
                    // A second stream of this board on the same connection, after the first
                    // one's end: its rows are not this camera's board any more.
                    let run = format!("{run_id:016x}");
                    tracing::warn!(camera, conn, %run, "rows after this camera's end of the board: dropped");
                    return;
                }
                p.last = Instant::now();
                p.next_row = Some(chunk.first_row + chunk.rows as i64);
                p.waiting.push(*chunk);
                self.stitch(k);
            }
            Event::End {
                conn,
                camera,
                run_id,
                loss,
                cut,
            } => {
                let Some(k) = self.part_of(conn, camera, run_id) else {
                    return;
                };
                if let Some(why) = cut {
                    let mut losses = self.losses(k);
                    losses[camera] = loss;
                    self.close(k, format!("camera {camera}: {why}"), losses);
                    return;
                }
                let p = &mut self.open[k].parts[camera];
                p.last = Instant::now();
                p.ended = Some(loss);
                self.open[k].last_row_at = Some(Instant::now());
                self.stitch(k);
                if self.open[k].parts.iter().all(|p| p.ended.is_some()) {
                    self.finish(k);
                }
            }
        }
    }

    /// The open board `run_id` whose camera `camera` is connection `conn`'s (a stream of a
    /// board that ended, or a second stream of one camera, is dropped).
    fn part_of(&self, conn: u64, camera: usize, run_id: u64) -> Option<usize> {
        let k = self.index(run_id)?;
        (self.open[k].parts.get(camera)?.conn == Some(conn)).then_some(k)
    }

    fn begin(&mut self, conn: u64, camera: usize, run_id: u64) {
        let run = format!("{run_id:016x}");
        if self.ended.contains(&run_id) {
            tracing::warn!(camera, conn, %run, "a stream of a board that already ended: dropped");
            self.gate.release(run_id);
            return;
        }
        let k = match self.index(run_id) {
            Some(k) => k,
            None if self.closing => {
                tracing::warn!(camera, conn, %run, "the line is stopping: a new board's stream is dropped");
                self.gate.release(run_id);
                return;
            }
            None => {
                if self.open.len() >= MAX_OPEN_BOARDS {
                    let losses = self.losses(0);
                    self.close(
                        0,
                        format!("board {run} began before this board ended (a camera never finished it)"),
                        losses,
                    );
                }
                let n = self.setup.cal.camera.len();
                let now = Instant::now();
                let (product, refused) = match self.product_now() {
                    Ok(p) => (p, None),
                    Err(why) => (self.setup.default_product, Some(why)),
                };
                self.open.push(Open {
                    run_id,
                    began: now,
                    parts: (0..n)
                        .map(|_| Part {
                            conn: None,
                            last: now,
                            waiting: Vec::new(),
                            next_row: None,
                            ended: None,
                        })
                        .collect(),
                    stitcher: None,
                    last_row_at: None,
                    product,
                    refused: refused.clone(),
                });
                match &refused {
                    None => {
                        tracing::info!(%run, product = %self.setup.products[product].0, "board began")
                    }
                    Some(why) => {
                        tracing::warn!(%run, "board began; it will not be inspected: {why}")
                    }
                }
                let _ = self.keeper.send(Job::Begin {
                    run_id,
                    product,
                    started_unix_s: unix_now(),
                });
                self.open.len() - 1
            }
        };
        let Some(p) = self.open[k].parts.get_mut(camera) else {
            return;
        };
        if let Some(other) = p.conn {
            tracing::warn!(camera, conn, %run, "camera {camera} of this board is connection {other}'s already: a second stream of it is dropped");
            return;
        }
        p.conn = Some(conn);
        p.last = Instant::now();
    }

    /// The product of a board that begins now: the one [`Setup::product_file`] names, or the
    /// default when there is no such file. `Err` with the reason when the file cannot be read
    /// or names no product of the configuration: the board is then never inspected against
    /// another product's program.
    fn product_now(&self) -> Result<usize, String> {
        product_named(
            &self.setup.product_file,
            &self.setup.products,
            self.setup.default_product,
        )
    }

    /// Hands what arrived to board `k`'s stitcher (made once every camera's first rows are
    /// known) and builds every band that is in.
    fn stitch(&mut self, k: usize) {
        let b = &mut self.open[k];
        if b.refused.is_some() {
            for p in &mut b.parts {
                p.waiting.clear();
            }
            return;
        }
        if b.stitcher.is_none()
            && b.parts
                .iter()
                .all(|p| !p.waiting.is_empty() || p.ended.is_some())
        {
            if b.parts.iter().any(|p| p.waiting.is_empty()) {
                // A camera ended without a row: nothing to stitch; the end says so.
                return;
            }
            let max_step = self.setup.cal.processing.max_step_rows;
            let feeds = b
                .parts
                .iter()
                .zip(&self.setup.cal.camera)
                .map(|(p, c)| {
                    dpsa_board::run::feed(c, p.waiting.first().map_or(0, |c| c.first_row), max_step)
                })
                .collect();
            let grid = self.setup.products[b.product].1;
            let mut st = Stitcher::new(grid, feeds, BAND_ROWS, CHUNK_ROWS);
            st.set_paste(
                self.setup
                    .pastes
                    .get(b.product)
                    .copied()
                    .unwrap_or_default(),
            );
            b.stitcher = Some(st);
        }
        if let Some(st) = b.stitcher.as_mut() {
            for (i, p) in b.parts.iter_mut().enumerate() {
                for c in p.waiting.drain(..) {
                    st.push(i, &c.heights, None);
                    st.push_places(i, &c.places, c.first_row);
                    // Copied into the stitcher: the memory serves a later chunk.
                    dpsa_board::pool::give_rows(c.heights);
                }
                if p.ended.is_some() {
                    st.end(i);
                }
            }
            st.advance();
        }
    }

    /// Every camera ended: the last bands, then the map to the keeper.
    fn finish(&mut self, k: usize) {
        let b = self.open.remove(k);
        self.remember(b.run_id);
        let run = format!("{:016x}", b.run_id);
        let losses: Vec<CameraLoss> = b.parts.iter().filter_map(|p| p.ended.clone()).collect();
        let st = match (b.refused, b.stitcher) {
            (None, Some(st)) => st,
            (refused, _) => {
                // Refused at its start, or a camera ended without a row: nothing to inspect.
                let reason = refused.unwrap_or_else(|| {
                    let empty: Vec<usize> = (0..b.parts.len())
                        .filter(|&i| b.parts[i].next_row.is_none())
                        .collect();
                    format!("camera(s) {empty:?} sent no row of this board")
                });
                tracing::warn!(%run, "board incomplete: {reason}");
                let _ = self.keeper.send(Job::Incomplete {
                    run_id: b.run_id,
                    reason,
                    losses,
                });
                return;
            }
        };
        let a = st.finish();
        tracing::info!(%run, "board map done");
        dpsa_board::pool::give_camera(a.blended.camera);
        if let Some(v) = a.blended.variance {
            dpsa_board::pool::give_map(v);
        }
        let _ = self.keeper.send(Job::Finished {
            run_id: b.run_id,
            grid: self.setup.products[b.product].1,
            heights: a.blended.heights,
            losses,
            last_row_at: b.last_row_at.unwrap_or_else(Instant::now),
        });
    }

    /// Board `k` is incomplete: why.
    fn close(&mut self, k: usize, reason: String, losses: Vec<CameraLoss>) {
        let b = self.open.remove(k);
        self.remember(b.run_id);
        tracing::warn!(run = %format!("{:016x}", b.run_id), "board incomplete: {reason}");
        let _ = self.keeper.send(Job::Incomplete {
            run_id: b.run_id,
            reason,
            losses,
        });
    }

    /// What board `k`'s cameras lost so far (a camera that has not ended: the rows it sent).
    fn losses(&self, k: usize) -> Vec<CameraLoss> {
        self.open[k]
            .parts
            .iter()
            .enumerate()
            .map(|(i, p)| {
                p.ended.clone().unwrap_or(CameraLoss {
                    camera: i as u8,
                    rows: 0,
                    missing_rows: 0,
                    missing_packets: 0,
                    damaged_packets: 0,
                })
            })
            .collect()
    }

    fn remember(&mut self, run_id: u64) {
        self.gate.release(run_id);
        if self.ended.len() >= REMEMBERED {
            self.ended.pop_front();
        }
        self.ended.push_back(run_id);
    }

    /// Ends the boards whose cameras fell silent or that are open too long.
    pub fn tick(&mut self) {
        let mut k = 0;
        while k < self.open.len() {
            let b = &self.open[k];
            let silent = b.parts.iter().enumerate().find_map(|(i, p)| {
                let idle = p.last.elapsed().as_secs_f64();
                (p.ended.is_none() && idle > self.setup.silent_s).then(|| {
                    match (p.conn, p.next_row) {
                        (None, _) => format!(
                            "camera {i} never began this board within {:.1} s",
                            self.setup.silent_s
                        ),
                        (Some(_), Some(r)) => format!(
                            "camera {i} silent for {idle:.1} s after board row {}",
                            r - 1
                        ),
                        (Some(_), None) => {
                            format!("camera {i} silent for {idle:.1} s before its first row")
                        }
                    }
                })
            });
            let age = b.began.elapsed().as_secs_f64();
            let why = silent.or_else(|| {
                (age > self.setup.board_s)
                    .then(|| format!("open for {age:.1} s, more than timeouts.board_s"))
            });
            match why {
                Some(why) => {
                    let losses = self.losses(k);
                    self.close(k, why, losses);
                }
                None => k += 1,
            }
        }
    }

    /// Ends every open board as incomplete (the line stops before they ended).
    pub fn abandon(&mut self, why: &str) {
        while !self.open.is_empty() {
            let losses = self.losses(0);
            self.close(0, why.to_string(), losses);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_product_file_names_a_product_or_the_board_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("product");
        let grid = BoardGrid {
            x0_mm: 0.0,
            y0_mm: 0.0,
            pitch_mm: 0.03,
            rows: 10,
            width: 10,
        };
        let products = vec![("a".to_owned(), grid), ("b-2".to_owned(), grid)];
        assert_eq!(
            product_named(&file, &products, 1),
            Ok(1),
            "no file: the default"
        );
        for (text, want) in [("a", 0), ("b-2\n", 1), ("  a \r\n", 0)] {
            std::fs::write(&file, text).unwrap();
            assert_eq!(product_named(&file, &products, 1), Ok(want), "{text:?}");
        }
        for text in ["", "c", "a b", "A"] {
            std::fs::write(&file, text).unwrap();
            let why = product_named(&file, &products, 1).unwrap_err();
            assert!(why.contains("not one of LINE.toml's"), "{text:?}: {why}");
        }
        std::fs::write(&file, "a".repeat(2000)).unwrap();
        let why = product_named(&file, &products, 0).unwrap_err();
        assert!(why.contains("could not be read"), "{why}");
        std::fs::remove_file(&file).unwrap();
        std::fs::create_dir(&file).unwrap();
        assert!(
            product_named(&file, &products, 0).is_err(),
            "a directory is no product"
        );
    }
}
