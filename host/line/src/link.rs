//! One frame grabber's connection: its packet streams (format v2, one per board, one after
//! another on the same connection) decoded as the bytes arrive, each checked against the
//! calibration as soon as its header is in, its rows placed and handed on as [`Event`]s.
//!
//! A stream's header must come within `timeouts.header_s` of the connection (or of the last
//! stream's end) or the connection is closed; a stream must keep coming (`timeouts.silent_s`)
//! until its end packet. Refused, logged and closed: a header of another camera than the port's,
//! of another width or configuration (another calibration), run id 0, more than
//! [`MAX_BYTES_BEFORE_HEADER`] bytes that are not a stream header, a stream of more rows than
//! a board has.

use crate::store::CameraLoss;
use dpsa_board::provenance::{Provenance, Registration};
use dpsa_board::run::{Chunk, Collector};
use dpsa_core::Trigger;
use dpsa_formats::calibration::{round_counts_per_pixel, CameraCal};
use dpsa_stream::{DecodeReport, Live};
use std::io::Read;
use std::net::TcpStream;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Sender;
use std::time::{Duration, Instant};

/// Rows a connection hands on at a time.
pub const FEED_ROWS: usize = 128;
/// Bytes a connection may send that hold no stream header before it is closed as garbage.
pub const MAX_BYTES_BEFORE_HEADER: u64 = 1 << 20;
/// Bytes read at a time.
const READ: usize = 1 << 16;
/// How often a waiting read looks at the stop flag.
const POLL: Duration = Duration::from_millis(100);

/// What a connection tells the boards.
#[derive(Debug)]
pub enum Event {
    /// A stream began: camera `camera`'s part of board `run_id`.
    Begin {
        /// The connection (a number per accepted connection).
        conn: u64,
        /// The camera.
        camera: usize,
        /// The board.
        run_id: u64,
    },
    /// The stream's next rows.
    Rows {
        /// See [`Event::Begin`].
        conn: u64,
        /// See [`Event::Begin`].
        camera: usize,
        /// See [`Event::Begin`].
        run_id: u64,
        /// The rows, placed.
        chunk: Box<Chunk>,
    },
    /// The stream ended: with its end packet (`cut: None`) or cut off (`Some(why)`).
    End {
        /// See [`Event::Begin`].
        conn: u64,
        /// See [`Event::Begin`].
        camera: usize,
        /// See [`Event::Begin`].
        run_id: u64,
        /// What the stream lost.
        loss: CameraLoss,
        /// Why it ended without its end packet.
        cut: Option<String>,
    },
}

/// What a connection on camera `camera`'s port checks and needs.
#[derive(Clone)]
pub struct LinkSetup {
    /// The port's camera.
    pub camera: usize,
    /// Its calibration.
    pub cal: CameraCal,
    /// Height LSB, um.
    pub lsb_um: f64,
    /// The configuration hash its streams carry.
    pub config_hash: u64,
    /// Seconds to the stream header.
    pub header_s: f64,
    /// Seconds of silence inside a stream.
    pub silent_s: f64,
    /// Most board rows one stream may carry (more is an encoder fault or not a board).
    pub max_rows: u64,
    /// Where a board gets its place before its rows are read.
    pub gate: std::sync::Arc<crate::boards::Gate>,
}

/// A stream whose header was accepted.
struct Running {
    run_id: u64,
    rows: Collector,
    triggers: Vec<Trigger>,
    reg: Registration,
    since_chunk: usize,
    received: u64,
}

/// Serves one connection until it closes, fails, times out or `stop` is set.
pub fn serve(
    mut sock: TcpStream,
    conn: u64,
    setup: &LinkSetup,
    tx: &Sender<Event>,
    stop: &AtomicBool,
) {
    let peer = sock
        .peer_addr()
        .map(|a| a.to_string())
        .unwrap_or_else(|_| "?".into());
    let cam = setup.camera;
    if let Err(e) = sock.set_read_timeout(Some(POLL)) {
        tracing::warn!(camera = cam, conn, %peer, "cannot set a read timeout: {e}; closed");
        return;
    }
    tracing::info!(camera = cam, conn, %peer, "connected");
    let mut live = Live::new(setup.lsb_um);
    let mut running: Option<Running> = None;
    let mut last = Instant::now();
    let mut before_header = 0u64;
    let mut streams = 0u64;
    let mut buf = vec![0u8; READ];
    let why = loop {
        if stop.load(Ordering::Relaxed) {
            break "the line is stopping".to_string();
        }
        let n = match sock.read(&mut buf) {
            Ok(0) => break "the link closed".to_string(),
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock
                        | std::io::ErrorKind::TimedOut
                        | std::io::ErrorKind::Interrupted
                ) =>
            {
                let idle = last.elapsed().as_secs_f64();
                if running.is_some() && idle > setup.silent_s {
                    break format!("silent for {idle:.1} s inside a stream");
                }
                // Between boards a frame grabber may wait as long as it likes; a new
                // connection, or a stream's first bytes, must bring its header in time.
                let awaiting = streams == 0 || live.pending() > 0;
                if running.is_none() && awaiting && idle > setup.header_s {
                    break format!("no stream header within {:.1} s", setup.header_s);
                }
                continue;
            }
            Err(e) => break format!("the link failed: {e}"),
        };
        last = Instant::now();
        let mut bytes = &buf[..n];
        let mut rest: Vec<u8>;
        loop {
            live.push(bytes);
            if running.is_none() {
                match live.info() {
                    None => {
                        // Rows before a header belong to no board.
                        let _ = live.take_rows();
                        let _ = live.take_triggers();
                        before_header += bytes.len() as u64;
                        if before_header > MAX_BYTES_BEFORE_HEADER {
                            let why = format!("{before_header} bytes without a stream header (not a frame grabber?)");
                            tracing::warn!(camera = cam, conn, %peer, "refused: {why}");
                            return;
                        }
                    }
                    Some(info) => {
                        if let Err(why) = check_header(setup, &info) {
                            tracing::warn!(camera = cam, conn, %peer, "refused: {why}; closed");
                            return;
                        }
                        before_header = 0;
                        // A board without a place yet: the connection waits (back-pressure).
                        if !setup.gate.admit(info.run_id, stop) {
                            tracing::info!(camera = cam, conn, "the line is stopping: closed");
                            return;
                        }
                        let reg = Registration {
                            rows: u32::from(info.rows),
                            n: info.n,
                            max_step_rows: u32::from(info.max_step_rows),
                            counts_per_pixel: round_counts_per_pixel(setup.cal.counts_per_pixel),
                        };
                        tracing::info!(camera = cam, conn, run = %format!("{:016x}", info.run_id), "stream began");
                        let _ = tx.send(Event::Begin {
                            conn,
                            camera: cam,
                            run_id: info.run_id,
                        });
                        running = Some(Running {
                            run_id: info.run_id,
                            rows: Collector::new(&setup.cal, setup.lsb_um),
                            triggers: Vec::new(),
                            reg,
                            since_chunk: 0,
                            received: 0,
                        });
                    }
                }
            }
            if let Some(r) = running.as_mut() {
                r.triggers.extend(live.take_triggers());
                for row in live.take_rows() {
                    r.rows.push(&row);
                    r.since_chunk += 1;
                    r.received += 1;
                }
                if r.received > setup.max_rows {
                    let why = format!(
                        "{} rows in one stream, more than a board has ({}): not closed at the board's end",
                        r.received, setup.max_rows
                    );
                    end_cut(&mut running, live, setup, conn, tx, why.clone());
                    tracing::warn!(camera = cam, conn, "{why}; closed");
                    return;
                }
                let ended = live.ended();
                if r.since_chunk >= FEED_ROWS || ended {
                    if let Err(why) = hand_on(r, setup, conn, tx) {
                        end_cut(&mut running, live, setup, conn, tx, why.clone());
                        tracing::warn!(camera = cam, conn, "{why}; closed");
                        return;
                    }
                }
                if ended {
                    let Some(r) = running.take() else { break };
                    let (rep, next) =
                        std::mem::replace(&mut live, Live::new(setup.lsb_um)).finish();
                    let loss = loss_of(cam, &rep, r.received);
                    streams += 1;
                    tracing::info!(camera = cam, conn, run = %format!("{:016x}", r.run_id), rows = r.received, "stream ended");
                    let _ = tx.send(Event::End {
                        conn,
                        camera: cam,
                        run_id: r.run_id,
                        loss,
                        cut: None,
                    });
                    if !next.is_empty() {
                        // The next board's stream began in the same read.
                        rest = next;
                        bytes = &rest;
                        continue;
                    }
                }
            }
            break;
        }
    };
    if running.is_some() {
        end_cut(&mut running, live, setup, conn, tx, why.clone());
        tracing::warn!(camera = cam, conn, "stream cut: {why}");
    } else {
        tracing::info!(camera = cam, conn, "closed: {why}");
    }
}

/// The stream header against the port's camera and calibration.
fn check_header(setup: &LinkSetup, info: &dpsa_core::row::StreamInfo) -> Result<(), String> {
    if usize::from(info.camera) != setup.camera {
        return Err(format!(
            "camera {}'s stream on camera {}'s port",
            info.camera, setup.camera
        ));
    }
    if u32::from(info.width) != setup.cal.width {
        return Err(format!(
            "a stream {} px wide; camera {} is {} px wide",
            info.width, setup.camera, setup.cal.width
        ));
    }
    if info.config_hash != setup.config_hash {
        return Err(format!(
            "configuration hash {:016x}; the line's calibration gives camera {} {:016x} (another calibration, LSB or processing)",
            info.config_hash, setup.camera, setup.config_hash
        ));
    }
    if info.run_id == 0 {
        return Err("run id 0: the stream names no board".into());
    }
    Ok(())
}

/// The rows since the last chunk, placed by the registration replayed on the triggers so far.
fn hand_on(
    r: &mut Running,
    setup: &LinkSetup,
    conn: u64,
    tx: &Sender<Event>,
) -> Result<(), String> {
    r.since_chunk = 0;
    let prov = Provenance::replay(&r.triggers, &r.reg);
    match r.rows.take_chunk(&prov, &setup.cal, r.reg.max_step_rows) {
        Ok(Some(chunk)) => {
            let _ = tx.send(Event::Rows {
                conn,
                camera: setup.camera,
                run_id: r.run_id,
                chunk: Box::new(chunk),
            });
            Ok(())
        }
        Ok(None) => Ok(()),
        Err(e) => Err(e.to_string()),
    }
}

/// The running stream ends without its end packet.
fn end_cut(
    running: &mut Option<Running>,
    live: Live,
    setup: &LinkSetup,
    conn: u64,
    tx: &Sender<Event>,
    why: String,
) {
    if let Some(r) = running.take() {
        let (rep, _) = live.finish();
        let _ = tx.send(Event::End {
            conn,
            camera: setup.camera,
            run_id: r.run_id,
            loss: loss_of(setup.camera, &rep, r.received),
            cut: Some(why),
        });
    }
}

/// What a stream lost, from its report.
fn loss_of(camera: usize, rep: &DecodeReport, rows: u64) -> CameraLoss {
    CameraLoss {
        camera: camera as u8,
        rows,
        missing_rows: rep.stream.rows_missing,
        missing_packets: rep.stream.missing,
        damaged_packets: rep.corrupt as u64,
    }
}
