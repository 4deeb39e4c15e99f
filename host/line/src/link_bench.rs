//! `dpsa line link-bench`: TCP against UDP on loopback, the measurement behind the link's
//! choice of TCP (docs/line.md, "The link").
//!
//! One camera's stream is carried from a paced sender to a receiver that reads like a link
//! thread and, halfway through, stops reading for `stall_ms` (the host busy: the gate holding a
//! third board, a long inspection, a disk flush). UDP carries it in datagrams of
//! [`DATAGRAM`] bytes (an Ethernet frame's payload), each numbered, so the receiver counts
//! what never arrived; TCP carries it as a byte stream, whose flow control holds the sender
//! back instead, so the figure is how late the sender fell behind its schedule. Each
//! transport is run with no stall and with the stall.

use crate::LineError;
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream, UdpSocket};
use std::time::{Duration, Instant};

/// A datagram's bytes: 1,500-byte Ethernet MTU less the IPv4 and UDP headers.
pub const DATAGRAM: usize = 1472;

/// What the bench does.
#[derive(Clone, Debug)]
pub struct Options {
    /// Bytes carried per run.
    pub bytes: u64,
    /// The sender's rate, bytes/s.
    pub rate: f64,
    /// The receiver's stall halfway, ms.
    pub stall_ms: u64,
}

/// One run of one transport.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Run {
    /// `tcp` or `udp`.
    pub transport: &'static str,
    /// The receiver's stall, ms (0: none).
    pub stall_ms: u64,
    /// Bytes the sender sent.
    pub bytes_sent: u64,
    /// Bytes the receiver got.
    pub bytes_received: u64,
    /// Datagrams sent (UDP).
    pub datagrams_sent: Option<u64>,
    /// Datagrams that never arrived (UDP).
    pub datagrams_lost: Option<u64>,
    /// Share of the stream lost, 0..=1.
    pub lost_share: f64,
    /// How far the sender fell behind its schedule at worst, ms (TCP's back-pressure).
    pub sender_late_max_ms: f64,
    /// From the first byte sent to the last byte received, s.
    pub seconds: f64,
}

/// The bench's JSON.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Report {
    /// Bytes per run.
    pub bytes: u64,
    /// The sender's rate, MB/s (10^6 bytes).
    pub rate_mb_s: f64,
    /// The receiver's socket buffer the kernel gives by default (`net.core.rmem_default`),
    /// bytes; what UDP can hold while the receiver stalls.
    pub rmem_default: Option<u64>,
    /// The runs.
    pub runs: Vec<Run>,
}

fn io(what: &str) -> impl Fn(std::io::Error) -> LineError + '_ {
    move |e| LineError::Io(format!("link bench: {what}: {e}"))
}

/// Sends `bytes` at `rate` in pieces of `piece` bytes through `put`; returns the worst
/// lateness behind the schedule, s.
fn paced(
    bytes: u64,
    rate: f64,
    piece: usize,
    mut put: impl FnMut(u64, usize) -> std::io::Result<()>,
) -> std::io::Result<f64> {
    let t0 = Instant::now();
    let (mut sent, mut late) = (0u64, 0.0f64);
    while sent < bytes {
        let due = sent as f64 / rate;
        let now = t0.elapsed().as_secs_f64();
        if due > now + 0.001 {
            std::thread::sleep(Duration::from_secs_f64(due - now));
        } else {
            late = late.max(now - due);
        }
        let n = piece.min((bytes - sent) as usize);
        put(sent, n)?;
        sent += n as u64;
    }
    Ok(late)
}

fn tcp(o: &Options, stall_ms: u64) -> Result<Run, LineError> {
    let listener = TcpListener::bind("127.0.0.1:0").map_err(io("bind"))?;
    let addr = listener.local_addr().map_err(io("address"))?;
    let total = o.bytes;
    let receiver = std::thread::spawn(move || -> std::io::Result<(u64, Instant)> {
        let (mut s, _) = listener.accept()?;
        let mut buf = vec![0u8; 64 * 1024];
        let (mut got, mut stalled) = (0u64, stall_ms == 0);
        loop {
            let n = s.read(&mut buf)?;
            if n == 0 {
                return Ok((got, Instant::now()));
            }
            got += n as u64;
            if !stalled && got >= total / 2 {
                stalled = true;
                std::thread::sleep(Duration::from_millis(stall_ms));
            }
        }
    });
    let t0 = Instant::now();
    let mut s = TcpStream::connect(addr).map_err(io("connect"))?;
    s.set_nodelay(true).map_err(io("nodelay"))?;
    let chunk = vec![0x5au8; 16 * 1024];
    let late = paced(o.bytes, o.rate, chunk.len(), |_, n| {
        s.write_all(&chunk[..n])
    })
    .map_err(io("send"))?;
    drop(s);
    let (got, end) = receiver
        .join()
        .map_err(|_| LineError::Io("link bench: the TCP receiver panicked".into()))?
        .map_err(io("receive"))?;
    Ok(Run {
        transport: "tcp",
        stall_ms,
        bytes_sent: o.bytes,
        bytes_received: got,
        datagrams_sent: None,
        datagrams_lost: None,
        lost_share: 1.0 - got as f64 / o.bytes as f64,
        sender_late_max_ms: late * 1e3,
        seconds: end.duration_since(t0).as_secs_f64(),
    })
}

fn udp(o: &Options, stall_ms: u64) -> Result<Run, LineError> {
    let rx = UdpSocket::bind("127.0.0.1:0").map_err(io("bind"))?;
    let addr = rx.local_addr().map_err(io("address"))?;
    // The receiver ends when no datagram came for this long after the sender's last one.
    rx.set_read_timeout(Some(Duration::from_millis(500)))
        .map_err(io("timeout"))?;
    let datagrams = o.bytes.div_ceil(DATAGRAM as u64);
    let receiver = std::thread::spawn(move || -> std::io::Result<(u64, u64, Instant)> {
        let mut buf = [0u8; DATAGRAM];
        let (mut got, mut bytes, mut stalled) = (0u64, 0u64, stall_ms == 0);
        let mut seen = vec![false; datagrams as usize];
        let mut last = Instant::now();
        loop {
            match rx.recv(&mut buf) {
                Ok(n) if n >= 8 => {
                    let seq = u64::from_le_bytes(buf[..8].try_into().unwrap_or([0; 8]));
                    if let Some(s) = seen.get_mut(seq as usize) {
                        if !*s {
                            *s = true;
                            got += 1;
                            bytes += n as u64;
                            last = Instant::now();
                        }
                    }
                    if !stalled && got >= datagrams / 2 {
                        stalled = true;
                        std::thread::sleep(Duration::from_millis(stall_ms));
                    }
                    if got == datagrams {
                        return Ok((got, bytes, last));
                    }
                }
                Ok(_) => {}
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    return Ok((got, bytes, last))
                }
                Err(e) => return Err(e),
            }
        }
    });
    let tx = UdpSocket::bind("127.0.0.1:0").map_err(io("bind"))?;
    tx.connect(addr).map_err(io("connect"))?;
    let t0 = Instant::now();
    let mut d = [0x5au8; DATAGRAM];
    let late = paced(o.bytes, o.rate, DATAGRAM, |at, n| {
        d[..8].copy_from_slice(&(at / DATAGRAM as u64).to_le_bytes());
        // A full socket buffer on the sending side is a loss too, not an error.
        match tx.send(&d[..n.max(8)]) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => Ok(()),
            r => r.map(|_| ()),
        }
    })
    .map_err(io("send"))?;
    let (got, bytes, end) = receiver
        .join()
        .map_err(|_| LineError::Io("link bench: the UDP receiver panicked".into()))?
        .map_err(io("receive"))?;
    Ok(Run {
        transport: "udp",
        stall_ms,
        bytes_sent: o.bytes,
        bytes_received: bytes,
        datagrams_sent: Some(datagrams),
        datagrams_lost: Some(datagrams - got),
        lost_share: (datagrams - got) as f64 / datagrams as f64,
        sender_late_max_ms: late * 1e3,
        seconds: end.duration_since(t0).as_secs_f64(),
    })
}

/// Runs TCP and UDP, each without and with the stall.
pub fn run(o: &Options) -> Result<Report, LineError> {
    if o.bytes == 0 || !(o.rate.is_finite() && o.rate > 0.0) {
        return Err(LineError::Io(
            "link bench: the bytes and the rate must be positive".into(),
        ));
    }
    let mut runs = Vec::new();
    for stall in [0, o.stall_ms] {
        runs.push(tcp(o, stall)?);
        runs.push(udp(o, stall)?);
    }
    let rmem_default = std::fs::read_to_string("/proc/sys/net/core/rmem_default")
        .ok()
        .and_then(|s| s.trim().parse().ok());
    Ok(Report {
        bytes: o.bytes,
        rate_mb_s: o.rate / 1e6,
        rmem_default,
        runs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// TCP carries every byte, stall or not; UDP's count of what arrived never exceeds what
    /// was sent, and a stall far longer than the socket buffer can cover loses datagrams.
    #[test]
    fn tcp_loses_nothing_and_a_stalled_udp_receiver_loses_datagrams() {
        // The receiver stops for as long as the second half takes to send, which is ten
        // times what the kernel's default socket buffer holds or more: most of that half is
        // lost.
        let rmem = std::fs::read_to_string("/proc/sys/net/core/rmem_default")
            .ok()
            .and_then(|s| s.trim().parse::<u64>().ok())
            .unwrap_or(212_992);
        let (bytes, rate) = ((20 * rmem).max(4_000_000), 20e6);
        let o = Options {
            bytes,
            rate,
            stall_ms: (bytes as f64 / 2.0 / rate * 1e3).ceil() as u64,
        };
        let r = run(&o).unwrap();
        assert_eq!(r.runs.len(), 4);
        for run in &r.runs {
            assert!(run.bytes_received <= run.bytes_sent, "{run:?}");
            if run.transport == "tcp" {
                assert_eq!(run.bytes_received, o.bytes, "{run:?}");
            }
        }
        let stalled_udp = &r.runs[3];
        assert_eq!(
            (stalled_udp.transport, stalled_udp.stall_ms),
            ("udp", o.stall_ms)
        );
        assert!(stalled_udp.datagrams_lost.unwrap() > 0, "{stalled_udp:?}");
    }
}
