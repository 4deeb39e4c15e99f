//! Packets -> link: the core's [`Sink`] that frames each finished row into a compressed packet
//! and sends it, exactly as `dpsa reconstruct` does on the host.

use crate::board::{Clock, PacketLink};
use dpsa_core::packets::{self, codec, PacketError};
use dpsa_core::{Row, Sink};

/// Ticks spent in the sink, split into encoding and sending (benchmark only).
#[derive(Clone, Copy, Debug, Default)]
pub struct SinkTicks {
    pub encode: u64,
    pub send: u64,
    pub rows: u64,
}

/// Why a row could not leave.
#[derive(Clone, Copy, Debug, defmt::Format)]
pub enum SinkError<E> {
    Encode(#[defmt(Debug2Format)] PacketError),
    Link(E),
}

pub struct LinkSink<'a, L, C> {
    pub link: L,
    enc: codec::Encoder<'a>,
    buf: &'a mut [u8],
    clock: Option<&'a C>,
    pub ticks: SinkTicks,
}

impl<'a, L: PacketLink, C: Clock> LinkSink<'a, L, C> {
    /// `clock`: time the encoder and the link (benchmark runs).
    pub fn new(link: L, enc: codec::Encoder<'a>, buf: &'a mut [u8], clock: Option<&'a C>) -> Self {
        LinkSink { link, enc, buf, clock, ticks: SinkTicks::default() }
    }

    fn now(&self) -> u64 {
        self.clock.map_or(0, |c| c.ticks())
    }
}

impl<L: PacketLink, C: Clock> Sink for LinkSink<'_, L, C> {
    type Error = SinkError<L::Error>;

    // Per-row hot path (the codec is inlined here): in ITCM with the core (memory.x).
    #[link_section = ".itcm.sink_row"]
    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error> {
        let t0 = self.now();
        let n = packets::encode(row, &mut self.enc, self.buf).map_err(SinkError::Encode)?;
        let t1 = self.now();
        self.link.send(&self.buf[..n]).map_err(SinkError::Link)?;
        let t2 = self.now();
        self.ticks.encode += t1 - t0;
        self.ticks.send += t2 - t1;
        self.ticks.rows += 1;
        Ok(())
    }
}
