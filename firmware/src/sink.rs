//! Packets -> link, timed for the benchmark: the core's [`PacketSink`] (the same code as
//! `dpsa reconstruct` runs on the host) over the board's link, wrapped so that a benchmark run
//! can split the sink's time into encoding and sending. With the FPGA front end's row codec
//! ([`TimedSink::set_coder`]) the rows' payloads come from the fabric and the encode time is
//! the framing alone (the payload log's reads are I/O; `main` moves them out).

use crate::board::Clock;
use dpsa_core::offload::RowCoder;
use dpsa_core::row::{Gap, StreamInfo};
use dpsa_core::sink::{CodedSink, Link, PacketSink, SinkError};
use dpsa_core::{Row, Sink, Trigger};

/// Ticks spent in the sink, split into encoding and sending (benchmark only).
#[derive(Clone, Copy, Debug, Default)]
pub struct SinkTicks {
    pub encode: u64,
    pub send: u64,
    pub rows: u64,
}

/// A link whose sends are timed when a clock is given.
pub struct Timed<'c, L, C> {
    pub link: L,
    clock: Option<&'c C>,
    /// Ticks in `send`.
    send: u64,
    /// Tick at the start of the last send.
    started: u64,
}

impl<L, C: Clock> Timed<'_, L, C> {
    fn now(&self) -> u64 {
        self.clock.map_or(0, |c| c.ticks())
    }
}

impl<L: Link, C: Clock> Link for Timed<'_, L, C> {
    type Error = L::Error;

    fn send(&mut self, packet: &[u8]) -> Result<(), L::Error> {
        let t0 = self.now();
        self.started = t0;
        self.link.send(packet)?;
        self.send += self.now() - t0;
        Ok(())
    }

    fn flush(&mut self) -> Result<(), L::Error> {
        self.link.flush()
    }
}

/// The core's packet sink over a [`Timed`] link, timed as a whole: the encode time of a row is
/// the sink's time up to the start of its send.
pub struct TimedSink<'a, L, C> {
    pub sink: PacketSink<'a, Timed<'a, L, C>>,
    clock: Option<&'a C>,
    encode: u64,
    /// The FPGA front end's row codec, when the fabric codes the rows (`CodedSink`).
    coder: Option<&'a mut dyn RowCoder>,
}

impl<'a, L: Link, C: Clock> TimedSink<'a, L, C> {
    /// `clock`: time the encoder and the link (benchmark runs).
    pub fn new(
        link: L,
        enc: dpsa_core::packets::codec::Encoder<'a>,
        buf: &'a mut [u8],
        clock: Option<&'a C>,
    ) -> Self {
        let link = Timed {
            link,
            clock,
            send: 0,
            started: 0,
        };
        TimedSink {
            sink: PacketSink::new(link, enc, buf),
            clock,
            encode: 0,
            coder: None,
        }
    }

    /// The rows' payloads come from the front end's row codec: this sink frames them.
    pub fn set_coder(&mut self, coder: &'a mut dyn RowCoder) {
        self.coder = Some(coder);
    }

    /// The run identity of the stream header (the feed's).
    pub fn set_run_id(&mut self, run_id: u64) {
        self.sink.set_run_id(run_id);
    }

    pub fn ticks(&self) -> SinkTicks {
        SinkTicks {
            encode: self.encode,
            send: self.sink.link().send,
            rows: self.sink.rows(),
        }
    }
}

impl<L: Link, C: Clock> Sink for TimedSink<'_, L, C> {
    type Error = SinkError<L::Error>;

    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error> {
        let t0 = self.clock.map_or(0, |c| c.ticks());
        match self.coder.as_deref_mut() {
            None => self.sink.row(row)?,
            Some(coder) => CodedSink {
                sink: &mut self.sink,
                coder,
            }
            .row(row)?,
        }
        self.encode += self.sink.link().started - t0;
        Ok(())
    }

    fn start(&mut self, info: &StreamInfo) -> Result<(), Self::Error> {
        self.sink.start(info)
    }

    fn trigger(&mut self, trigger: &Trigger) -> Result<(), Self::Error> {
        self.sink.trigger(trigger)
    }

    fn gap(&mut self, gap: &Gap) -> Result<(), Self::Error> {
        self.sink.gap(gap)
    }

    fn end(&mut self) -> Result<(), Self::Error> {
        self.sink.end()
    }
}
