//! `dpsa line run`: the service. One listener per camera (TCP, the configured address), a
//! thread per connection ([`crate::link`]), the boards on this thread ([`crate::boards`]), the
//! store on the keeper's ([`crate::keeper`]).
//!
//! Stopping: `SIGTERM` (or a first `SIGINT`) takes no new board (a stream of a board not yet
//! begun is dropped), lets the boards in progress end (finished, or incomplete by their
//! timeouts), stores them and exits. The ports stay open until then: a camera of a board in
//! progress may connect after the signal (cameras do not connect at the same instant) and its
//! stream is taken. A second
//! `SIGINT` exits at once: what is stored stays (every board is one transaction; WAL), a board
//! in progress is found `open` on the next start and recorded incomplete.

use crate::boards::{Boards, Setup};
use crate::config::LineConfig;
use crate::keeper::{Keeper, Tally};
use crate::link::{Event, LinkSetup};
use crate::store::Store;
use crate::LineError;
use std::net::TcpListener;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

/// Connections one camera's port serves at once; more are closed at once (logged).
pub const MAX_CONNECTIONS_PER_CAMERA: usize = 4;
/// Jobs (a board begun, a board map done) waiting for the keeper at most.
pub const JOBS_QUEUED: usize = 2;
/// The store's file in the data directory (when LINE.toml's `store` names none).
pub const STORE_FILE: &str = "line.sqlite";
/// A store of at most this many bytes is checked whole at every start ([`Store::check`]:
/// 5.7 - 13.5 s for SQLite's 1.4 GB of 2,000 paper boards in `dpsa line store-bench`); a
/// larger one on its newest [`CHECK_NEWEST_BOARDS`] boards ([`Store::check_newest`]), so that
/// a line with weeks of pad rows (terabytes at the scale: hours to read) restarts in
/// seconds. `dpsa line check` checks the whole of it, in a maintenance window.
pub const WHOLE_CHECK_BYTES: u64 = 2 << 30;
/// Boards whose rows a start checks when the store is larger than [`WHOLE_CHECK_BYTES`]:
/// the last quarter of an hour at a board a second, the boards a crash could have touched
/// many times over.
pub const CHECK_NEWEST_BOARDS: usize = 1000;

/// What a start checks of a store of `bytes` bytes: `None` the whole store, or its newest
/// boards.
pub fn start_check(bytes: u64) -> Option<usize> {
    (bytes > WHOLE_CHECK_BYTES).then_some(CHECK_NEWEST_BOARDS)
}

/// How the service ran.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Summary {
    /// The line's name.
    pub line: String,
    /// The store (a PostgreSQL URL with its password hidden).
    pub store: String,
    /// Boards ended (stored) while it ran.
    pub boards: usize,
    /// Of them inspected and passed / warned / failed, and incomplete.
    pub pass: usize,
    /// See `pass`.
    pub warn: usize,
    /// See `pass`.
    pub fail: usize,
    /// See `pass`.
    pub incomplete: usize,
    /// Boards found open at the start (the service had died in them), recorded incomplete.
    pub recovered: usize,
    /// What the start checked of the store: `whole`, or `newest N boards` (a store larger
    /// than [`WHOLE_CHECK_BYTES`]).
    pub store_checked: String,
    /// The store's size at the start, bytes (SQLite: the file and its WAL; PostgreSQL: the
    /// tables with their indexes).
    pub store_bytes_at_start: u64,
    /// How long the start's check took, s.
    pub store_check_s: f64,
    /// Median and largest time from a board's last row to its verdict stored, s (over the
    /// newest 10,000 boards).
    pub latency_median_s: Option<f64>,
    /// See `latency_median_s`.
    pub latency_max_s: Option<f64>,
    /// Resident memory when the first board was stored, MB (Linux; `None` elsewhere).
    pub rss_first_board_mb: Option<f64>,
    /// Resident memory when the last board was stored, MB.
    pub rss_last_board_mb: Option<f64>,
    /// Resident memory when board 1, 10, 100, ... was stored, MB (flat memory: the same
    /// figure from a hundred boards on).
    pub rss_by_boards_mb: std::collections::BTreeMap<usize, f64>,
    /// Finished boards (inspected, or left incomplete by a failed registration) whose measured
    /// map was kept for the pages (`[maps]`).
    pub maps_kept: usize,
    /// Such boards whose map was not kept (the writer busy, or a write that failed).
    pub maps_not_kept: usize,
    /// Pad rows deleted by the retention (`[retention] pad_days`) while it ran.
    pub pad_rows_pruned: u64,
    /// Peak resident memory of the whole run (`VmHWM`), MB.
    pub peak_rss_mb: Option<f64>,
    /// Processor time of the run, all threads, s (Linux; `None` elsewhere), over `seconds`:
    /// the start-up (the configuration already read), the waits and every board.
    pub cpu_s: Option<f64>,
    /// `cpu_s` over the boards ended (`None` without one): what a board costs the host, its
    /// share of the start-up included. A line that sends a board every `T` s keeps up only
    /// with more than `cpu_s_per_board / T` cores.
    pub cpu_s_per_board: Option<f64>,
    /// Wall time, s.
    pub seconds: f64,
}

/// What `run` is told besides the configuration.
#[derive(Clone, Copy, Debug, Default)]
pub struct RunOptions {
    /// Stop (as on `SIGTERM`) once this many boards ended.
    pub boards: Option<usize>,
}

/// Runs the line until a signal (or `opts.boards` boards); returns its summary.
pub fn run(cfg: LineConfig, opts: RunOptions) -> Result<Summary, LineError> {
    let started = Instant::now();
    let cpu_started = crate::memory::process_cpu_s();
    if !crate::memory::cap_arenas() {
        tracing::debug!("malloc's arenas not capped (not glibc): memory may grow with threads");
    }
    // Board after board: the maps' and the bands' buffers are reused, not faulted in afresh.
    dpsa_board::pool::keep_between_boards();
    let term = Arc::new(AtomicBool::new(false));
    let int = Arc::new(AtomicBool::new(false));
    // A second SIGINT exits at once (status 130); the first one is a stop like SIGTERM.
    for (sig, flag) in [
        (signal_hook::consts::SIGTERM, &term),
        (signal_hook::consts::SIGINT, &int),
    ] {
        if sig == signal_hook::consts::SIGINT {
            signal_hook::flag::register_conditional_shutdown(sig, 130, Arc::clone(flag))
                .map_err(|e| LineError::Io(format!("cannot handle SIGINT: {e}")))?;
        }
        signal_hook::flag::register(sig, Arc::clone(flag))
            .map_err(|e| LineError::Io(format!("cannot handle signal {sig}: {e}")))?;
    }

    let mut store = Store::open(&cfg.store, &cfg.line)?;
    store.claim_line()?;
    let (store_bytes, _) = store.bytes()?;
    let t = Instant::now();
    let store_checked = match start_check(store_bytes) {
        None => {
            store.check()?;
            "whole".to_owned()
        }
        Some(n) => {
            store.check_newest(n)?;
            format!("newest {n} boards")
        }
    };
    let store_check_s = t.elapsed().as_secs_f64();
    tracing::info!(
        store = %cfg.store,
        line = %cfg.line,
        bytes = store_bytes,
        checked = %store_checked,
        seconds = format!("{store_check_s:.1}"),
        "store open and checked"
    );
    if store_checked != "whole" {
        tracing::info!(
            "the store is larger than {WHOLE_CHECK_BYTES} bytes: only its newest boards were \
             checked; `dpsa line check --config {}` checks the whole of it",
            cfg.path.display()
        );
    }
    let recovered = store.recover(
        "the line stopped during this board (killed, crashed or powered off)",
        crate::boards::unix_now(),
    )?;
    for r in &recovered {
        tracing::warn!(run = %format!("{r:016x}"), "board found open from the last run: recorded incomplete");
    }

    // Every listener bound before anything is served.
    let mut listeners = Vec::new();
    for (i, addr) in cfg.listen.iter().enumerate() {
        let l = TcpListener::bind(addr).map_err(|e| LineError::Config {
            path: cfg.path.clone(),
            why: format!("camera {i}: cannot listen on {addr}: {e}"),
        })?;
        l.set_nonblocking(true)
            .map_err(|e| LineError::Io(format!("camera {i}: {e}")))?;
        tracing::info!(camera = i, addr = %l.local_addr().map_or(addr.to_string(), |a| a.to_string()), "listening");
        listeners.push(l);
    }

    // A stream may be as long as four of the longest product's boards.
    let longest = cfg.products.iter().map(|p| p.grid.rows).max().unwrap_or(0);
    let max_rows = (longest as u64).saturating_mul(4) + 4096;
    let gate = Arc::new(crate::boards::Gate::new());
    let links: Vec<LinkSetup> = cfg
        .cal
        .camera
        .iter()
        .enumerate()
        .map(|(i, c)| LinkSetup {
            camera: i,
            cal: c.clone(),
            lsb_um: cfg.cal.height_lsb_um,
            config_hash: cfg.config_hashes[i],
            header_s: cfg.timeouts.header_s,
            silent_s: cfg.timeouts.silent_s,
            max_rows,
            gate: Arc::clone(&gate),
        })
        .collect();
    let setup = Setup {
        cal: cfg.cal.clone(),
        products: cfg.product_grids(),
        pastes: cfg
            .products
            .iter()
            .map(|p| {
                let r = p.program.reflectance.background_step;
                dpsa_board::places::PasteReflectance::new(r, p.program.stencil_um)
            })
            .collect(),
        default_product: cfg.default_product,
        product_file: cfg.product_file(),
        silent_s: cfg.timeouts.silent_s,
        board_s: cfg.timeouts.board_s,
    };
    let tally = Arc::new(Mutex::new(Tally::default()));
    let keeper = Keeper {
        store,
        products: cfg.products,
        spool: cfg.spool.clone(),
        calibration_hash: cfg.calibration_hash.clone(),
        printer: cfg.printer.clone(),
        loops: Default::default(),
        tally: Arc::clone(&tally),
        maps: crate::maps::MapKeeper::start(&cfg.maps, &cfg.line, Arc::clone(&tally))
            .map_err(|e| LineError::Io(format!("cannot start the maps' writer: {e}")))?,
        pad_days: cfg.pad_days,
    };
    // Two jobs queued at most: a board map waiting for the keeper holds the boards' thread
    // (and through the gate the frame grabbers), so memory stays at two open maps, two
    // queued and the one being inspected.
    let (job_tx, job_rx) = mpsc::sync_channel(JOBS_QUEUED);
    let keeper = std::thread::Builder::new()
        .name("keeper".into())
        .spawn(move || keeper.run(job_rx))
        .map_err(|e| LineError::Io(format!("cannot start the keeper: {e}")))?;

    let stop_links = Arc::new(AtomicBool::new(false));
    let (tx, rx) = mpsc::channel::<Event>();
    let conn_ids = Arc::new(AtomicUsize::new(1));
    let mut acceptors = Vec::new();
    for (l, setup) in listeners.into_iter().zip(links) {
        let (tx, stop_links, conn_ids) =
            (tx.clone(), Arc::clone(&stop_links), Arc::clone(&conn_ids));
        acceptors.push(std::thread::spawn(move || {
            accept(l, setup, tx, &stop_links, &conn_ids)
        }));
    }
    drop(tx);

    // The keeper and the links' threads are started: this thread and the stitching threads
    // it starts run below them (`crate::priority`).
    match crate::priority::lower_this_thread(crate::priority::STITCH_NICE) {
        Some(nice) => tracing::debug!(nice, "the boards' thread runs below the keeper"),
        None => tracing::warn!(
            "the boards' thread could not lower its priority: the next board's stitching \
             competes with this board's inspection on equal terms"
        ),
    }
    let mut boards = Boards::new(setup, job_tx, gate);
    let ended = |t: &Mutex<Tally>| t.lock().map_or(0, |t| t.boards);
    let mut stopping = false;
    loop {
        match rx.recv_timeout(Duration::from_millis(100)) {
            Ok(e) => boards.event(e),
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        }
        boards.tick();
        let asked = term.load(Ordering::Relaxed)
            || int.load(Ordering::Relaxed)
            || opts.boards.is_some_and(|n| ended(&tally) >= n);
        if asked && !stopping {
            stopping = true;
            boards.close_doors();
            tracing::info!(
                open = boards.open(),
                "stopping: no new board; the boards in progress end first"
            );
        }
        if stopping && boards.open() == 0 {
            break;
        }
    }
    stop_links.store(true, Ordering::Relaxed);
    // Events still queued belong to boards that had not begun: dropped.
    drop(rx);
    boards.abandon("the line stopped before this board ended");
    drop(boards);
    for a in acceptors {
        let _ = a.join();
    }
    keeper
        .join()
        .map_err(|_| LineError::Io("the keeper thread panicked".into()))?;
    let t = tally.lock().map(|t| t.clone()).unwrap_or_default();
    let cpu_s = crate::memory::process_cpu_s()
        .zip(cpu_started)
        .map(|(b, a)| b - a);
    let count = |v: &str| t.by_verdict.get(v).copied().unwrap_or(0);
    let mut lat: Vec<f64> = t.latencies.iter().copied().collect();
    lat.sort_by(f64::total_cmp);
    Ok(Summary {
        line: cfg.line.clone(),
        store: cfg.store.to_string(),
        boards: t.boards,
        pass: count("pass"),
        warn: count("warn"),
        fail: count("fail"),
        incomplete: count("incomplete"),
        recovered: recovered.len(),
        store_checked,
        store_bytes_at_start: store_bytes,
        store_check_s,
        latency_median_s: lat.get(lat.len() / 2).copied(),
        latency_max_s: lat.last().copied(),
        rss_first_board_mb: t.rss_first_mb,
        rss_last_board_mb: t.rss_last_mb,
        peak_rss_mb: crate::memory::status_mb("VmHWM"),
        cpu_s,
        cpu_s_per_board: cpu_s.filter(|_| t.boards > 0).map(|c| c / t.boards as f64),
        rss_by_boards_mb: t.rss_by_boards.clone(),
        maps_kept: t.maps_kept,
        maps_not_kept: t.maps_not_kept,
        pad_rows_pruned: t.pad_rows_pruned,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// Camera `setup.camera`'s listener: a thread per connection, at most
/// [`MAX_CONNECTIONS_PER_CAMERA`] at once.
fn accept(
    l: TcpListener,
    setup: LinkSetup,
    tx: mpsc::Sender<Event>,
    stop: &Arc<AtomicBool>,
    conn_ids: &AtomicUsize,
) {
    let live = Arc::new(AtomicUsize::new(0));
    let setup = Arc::new(setup);
    let mut handlers = Vec::new();
    // Until the line stops: while it is stopping, a connection may still bring a camera of a
    // board in progress (a new board's stream is dropped by `Boards`).
    while !stop.load(Ordering::Relaxed) {
        match l.accept() {
            Ok((sock, peer)) => {
                let conn = conn_ids.fetch_add(1, Ordering::Relaxed) as u64;
                if live.load(Ordering::Relaxed) >= MAX_CONNECTIONS_PER_CAMERA {
                    tracing::warn!(camera = setup.camera, conn, %peer, "refused: {MAX_CONNECTIONS_PER_CAMERA} connections on this camera's port already");
                    drop(sock);
                    continue;
                }
                if sock.set_nonblocking(false).is_err() {
                    continue;
                }
                live.fetch_add(1, Ordering::Relaxed);
                let (tx, stop, live, setup) = (
                    tx.clone(),
                    Arc::clone(stop),
                    Arc::clone(&live),
                    Arc::clone(&setup),
                );
                handlers.push(std::thread::spawn(move || {
                    crate::link::serve(sock, conn, &setup, &tx, &stop);
                    live.fetch_sub(1, Ordering::Relaxed);
                }));
                handlers.retain(|h| !h.is_finished());
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(20));
            }
            Err(e) => {
                tracing::warn!(camera = setup.camera, "accept failed: {e}");
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
    drop(l);
    // The connections serving boards in progress go on until the line stops them.
    for h in handlers {
        let _ = h.join();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_start_checks_a_small_store_whole_and_a_large_one_on_its_newest_boards() {
        assert_eq!(start_check(0), None);
        assert_eq!(start_check(WHOLE_CHECK_BYTES), None);
        assert_eq!(
            start_check(WHOLE_CHECK_BYTES + 1),
            Some(CHECK_NEWEST_BOARDS)
        );
        assert_eq!(start_check(u64::MAX), Some(CHECK_NEWEST_BOARDS));
    }
}
