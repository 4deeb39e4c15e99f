//! `dpsa line send`: simulated frame grabbers. Each camera's recorded packet stream is
//! replayed to its address over TCP, as `boards` consecutive boards, each with a fresh run id
//! (the stream header rewritten, its CRCs with it), the cameras of a board side by side. At
//! the paper's conveyor rate a row packet goes out no earlier than its board row's time under
//! the cameras (all cameras on one clock, from the board's first row); at `max` as fast as the
//! link takes it.
//!
//! Faults on request: each packet but the stream header and the end packet dropped with
//! probability `loss` (seeded); one camera falling silent at a board row of the first board
//! (its connection stays open and silent for `silent_for_s`; the camera reconnects for the
//! next board).

use crate::LineError;
use dpsa_core::packets::{self, Item, Kind};
use rand::{RngExt, SeedableRng};
use std::io::Write;
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

/// The paper's conveyor speed, mm/s (`--rate paper`): a 220 mm board in 1 s.
pub const CONVEYOR_MM_S: f64 = 220.0;

/// How fast the boards come.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Rate {
    /// A board row every `row_s` seconds (the conveyor).
    Paced {
        /// Seconds per board row.
        row_s: f64,
    },
    /// As fast as the link takes it.
    Max,
}

/// What `send` does.
#[derive(Clone, Debug)]
pub struct SendOptions {
    /// Camera `i`'s address.
    pub to: Vec<SocketAddr>,
    /// The rate.
    pub rate: Rate,
    /// Consecutive boards.
    pub boards: usize,
    /// Probability a packet is dropped (0: none).
    pub loss: f64,
    /// Camera that falls silent at a board row of the first board.
    pub silent: Option<(usize, i64)>,
    /// How long the silent camera's connection stays open after it fell silent, s.
    pub silent_for_s: f64,
    /// Seeds the run ids and the losses.
    pub seed: u64,
}

/// What was sent.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SendReport {
    /// The boards' run ids (16 hex digits), in order.
    pub run_ids: Vec<String>,
    /// Bytes sent, all cameras.
    pub bytes: u64,
    /// Packets sent, all cameras.
    pub packets: u64,
    /// Packets dropped on purpose (`--loss`).
    pub dropped: u64,
    /// Wall time, s.
    pub seconds: f64,
    /// Boards per second.
    pub boards_per_s: f64,
}

/// One camera's stream cut into packets.
struct Packets {
    /// The stream header's contents.
    info: dpsa_core::row::StreamInfo,
    /// Every packet after the header: its bytes, its board row (rows), whether it is the end.
    rest: Vec<(Vec<u8>, Option<i64>, bool)>,
}

fn cut(camera: usize, bytes: &[u8]) -> Result<Packets, LineError> {
    let mut info = None;
    let mut rest = Vec::new();
    let mut it = packets::Stream::new(bytes);
    let mut start = 0usize;
    while let Some(item) = it.next() {
        let end = it.position();
        match item {
            Item::Packet { offset, packet } => {
                start = offset;
                match packet.kind {
                    Kind::StreamHeader if info.is_none() => info = packet.stream_info(),
                    Kind::StreamHeader => {
                        return Err(LineError::Refused(format!(
                            "camera {camera}'s stream holds a second stream header: give one board's stream"
                        )))
                    }
                    k => rest.push((
                        bytes[start..end].to_vec(),
                        (k == Kind::Row).then_some(packet.header.row),
                        k == Kind::End,
                    )),
                }
            }
            Item::Damage { offset, .. } => {
                return Err(LineError::Refused(format!(
                    "camera {camera}'s stream is damaged at byte {offset}: replay a clean stream"
                )))
            }
        }
    }
    let _ = start;
    let info = info.ok_or_else(|| {
        LineError::Refused(format!("camera {camera}'s stream has no stream header"))
    })?;
    if !rest.last().is_some_and(|p| p.2) {
        return Err(LineError::Refused(format!(
            "camera {camera}'s stream has no end packet: replay a whole stream"
        )));
    }
    Ok(Packets { info, rest })
}

/// A run id from `seed` and the board's number: never 0.
fn run_id(seed: u64, k: usize) -> u64 {
    let mut z = seed ^ (k as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    (z ^ (z >> 31)).max(1)
}

/// Connects to `addr`, retrying for up to 10 s (the line may still be starting).
fn connect(addr: SocketAddr) -> Result<TcpStream, LineError> {
    let t0 = Instant::now();
    loop {
        match TcpStream::connect_timeout(&addr, Duration::from_secs(2)) {
            Ok(s) => {
                let _ = s.set_nodelay(true);
                return Ok(s);
            }
            Err(e) if t0.elapsed() > Duration::from_secs(10) => {
                return Err(LineError::Io(format!("cannot connect to {addr}: {e}")))
            }
            Err(_) => std::thread::sleep(Duration::from_millis(100)),
        }
    }
}

/// Replays `streams` (one per camera, camera order) as `opts` says.
pub fn send(streams: &[Vec<u8>], opts: &SendOptions) -> Result<SendReport, LineError> {
    if streams.len() != opts.to.len() {
        return Err(LineError::Refused(format!(
            "{} streams for {} addresses: one address per camera",
            streams.len(),
            opts.to.len()
        )));
    }
    if !(0.0..1.0).contains(&opts.loss) {
        return Err(LineError::Refused(format!(
            "--loss {} is not a probability below 1",
            opts.loss
        )));
    }
    let cams: Vec<Packets> = streams
        .iter()
        .enumerate()
        .map(|(i, s)| cut(i, s))
        .collect::<Result<_, _>>()?;
    let first_row = cams
        .iter()
        .filter_map(|c| c.rest.iter().find_map(|p| p.1))
        .min()
        .unwrap_or(0);
    let t0 = Instant::now();
    let mut socks: Vec<Option<TcpStream>> = (0..cams.len()).map(|_| None).collect();
    let (mut bytes, mut sent, mut dropped) = (0u64, 0u64, 0u64);
    let mut run_ids = Vec::new();
    let mut held: Vec<(TcpStream, Instant)> = Vec::new();
    for k in 0..opts.boards {
        let id = run_id(opts.seed, k);
        run_ids.push(format!("{id:016x}"));
        let start = Instant::now();
        let results: Vec<Result<(TcpStream, Sent), LineError>> = std::thread::scope(|s| {
            let handles: Vec<_> = cams
                .iter()
                .enumerate()
                .zip(socks.iter_mut())
                .map(|((i, c), sock)| {
                    let sock = sock.take();
                    let silent = opts
                        .silent
                        .filter(|&(cam, _)| cam == i && k == 0)
                        .map(|s| s.1);
                    let seed = opts.seed ^ ((k as u64) << 32) ^ i as u64;
                    s.spawn(move || {
                        let mut sock = match sock {
                            Some(s) => s,
                            None => connect(opts.to[i])?,
                        };
                        let sent = board(&mut sock, c, id, opts, silent, first_row, start, seed)?;
                        Ok((sock, sent))
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join()
                        .unwrap_or_else(|_| Err(LineError::Io("a sender thread panicked".into())))
                })
                .collect()
        });
        for (i, r) in results.into_iter().enumerate() {
            let (sock, got) = r?;
            bytes += got.bytes;
            sent += got.packets;
            dropped += got.dropped;
            let cut_short = got.cut_short;
            if cut_short {
                // Silent, not gone: the connection stays open (nothing more on it) for
                // `silent_for_s`; the camera reconnects for the next board.
                held.push((
                    sock,
                    Instant::now() + Duration::from_secs_f64(opts.silent_for_s),
                ));
            } else {
                socks[i] = Some(sock);
            }
        }
    }
    for s in socks.iter_mut().flatten() {
        let _ = s.flush();
        let _ = s.shutdown(std::net::Shutdown::Write);
    }
    let seconds = t0.elapsed().as_secs_f64();
    for (sock, until) in held {
        let now = Instant::now();
        if until > now {
            std::thread::sleep(until - now);
        }
        drop(sock);
    }
    Ok(SendReport {
        run_ids,
        bytes,
        packets: sent,
        dropped,
        seconds,
        boards_per_s: opts.boards as f64 / seconds.max(1e-9),
    })
}

/// What one camera sent of one board.
struct Sent {
    bytes: u64,
    packets: u64,
    dropped: u64,
    /// It fell silent before its end.
    cut_short: bool,
}

/// One camera's stream of one board.
#[allow(clippy::too_many_arguments)]
fn board(
    sock: &mut TcpStream,
    c: &Packets,
    id: u64,
    opts: &SendOptions,
    silent: Option<i64>,
    first_row: i64,
    start: Instant,
    seed: u64,
) -> Result<Sent, LineError> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let io =
        |e: std::io::Error| LineError::Io(format!("camera {}: sending failed: {e}", c.info.camera));
    let mut info = c.info;
    info.run_id = id;
    let mut buf = [0u8; 64];
    let n = packets::encode_stream_header(&info, &mut buf)
        .map_err(|e| LineError::Io(format!("stream header: {e:?}")))?;
    // Packets are gathered and written a few KiB at a time (one write per packet costs a
    // system call each at the max rate).
    let mut out: Vec<u8> = Vec::with_capacity(1 << 16);
    out.extend_from_slice(&buf[..n]);
    let (mut bytes, mut sent, mut dropped) = (n as u64, 1u64, 0u64);
    for (p, row, end) in &c.rest {
        if let (Some(r), Some(at)) = (row, silent) {
            if *r >= at {
                sock.write_all(&out).map_err(io)?;
                return Ok(Sent {
                    bytes,
                    packets: sent,
                    dropped,
                    cut_short: true,
                });
            }
        }
        if let (Rate::Paced { row_s }, Some(r)) = (opts.rate, row) {
            let due = start + Duration::from_secs_f64(row_s * (r - first_row).max(0) as f64);
            let now = Instant::now();
            if due > now {
                sock.write_all(&out).map_err(io)?;
                out.clear();
                std::thread::sleep(due - now);
            }
        }
        if !end && opts.loss > 0.0 && rng.random::<f64>() < opts.loss {
            dropped += 1;
            continue;
        }
        out.extend_from_slice(p);
        bytes += p.len() as u64;
        sent += 1;
        if out.len() >= 1 << 15 {
            sock.write_all(&out).map_err(io)?;
            out.clear();
        }
    }
    sock.write_all(&out).map_err(io)?;
    sock.flush().map_err(io)?;
    Ok(Sent {
        bytes,
        packets: sent,
        dropped,
        cut_short: false,
    })
}
