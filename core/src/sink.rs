//! Sink: where completed height rows go. [`PacketSink`] frames each row into a compressed
//! packet ([`crate::packets`]) and sends it over a [`Link`]: a file or pipe on the host, the
//! frame grabber's output link on the target.

use crate::packets::{self, codec, PacketError};
use crate::row::{Gap, Row, StreamInfo};

/// Receives the pipeline's output in increasing board-row order: every board row exactly
/// once, either as a row or inside a gap record; [`Sink::start`] before anything else and
/// [`Sink::end`] last (from `Pipeline::finish`).
pub trait Sink {
    type Error;
    /// A completed board row.
    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error>;
    /// The stream starts (once, before the first row or gap). Default: nothing.
    fn start(&mut self, _info: &StreamInfo) -> Result<(), Self::Error> {
        Ok(())
    }
    /// Board rows that no frame showed (encoder jump), as one record instead of one row each.
    /// Default: nothing, so a sink that keeps a map sees a hole there.
    fn gap(&mut self, _gap: &Gap) -> Result<(), Self::Error> {
        Ok(())
    }
    /// The stream ended (once, after the last row). Default: nothing.
    fn end(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// The link a packet stream leaves by (Ethernet, USB, a FIFO to the host PC, a file).
pub trait Link {
    type Error;
    /// Sends one whole packet (the link may queue it).
    fn send(&mut self, packet: &[u8]) -> Result<(), Self::Error>;
    /// Waits until every packet has left.
    fn flush(&mut self) -> Result<(), Self::Error>;
}

/// Why a row could not leave a [`PacketSink`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SinkError<E> {
    /// The row could not be framed (a buffer too small for the row's width).
    Encode(PacketError),
    /// The link failed.
    Link(E),
}

/// A [`Sink`] that frames every row into a compressed packet (codec 1) and sends it over `L`.
///
/// `buf` must hold [`packets::max_packet_len`]`(W)` bytes; the encoder's reference row and
/// intra period decide how rows are coded ([`codec::Encoder`]).
pub struct PacketSink<'a, L> {
    link: L,
    enc: codec::Encoder<'a>,
    buf: &'a mut [u8],
    packets: u64,
    bytes: u64,
}

impl<'a, L: Link> PacketSink<'a, L> {
    pub fn new(link: L, enc: codec::Encoder<'a>, buf: &'a mut [u8]) -> Self {
        PacketSink {
            link,
            enc,
            buf,
            packets: 0,
            bytes: 0,
        }
    }

    /// Packets sent.
    pub fn packets(&self) -> u64 {
        self.packets
    }

    /// Bytes sent.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    pub fn link(&self) -> &L {
        &self.link
    }

    pub fn link_mut(&mut self) -> &mut L {
        &mut self.link
    }

    /// Flushes the link.
    pub fn flush(&mut self) -> Result<(), L::Error> {
        self.link.flush()
    }

    pub fn into_link(self) -> L {
        self.link
    }
}

impl<L: Link> Sink for PacketSink<'_, L> {
    type Error = SinkError<L::Error>;

    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error> {
        let n = packets::encode(row, &mut self.enc, self.buf).map_err(SinkError::Encode)?;
        self.link.send(&self.buf[..n]).map_err(SinkError::Link)?;
        self.packets += 1;
        self.bytes += n as u64;
        Ok(())
    }
}
