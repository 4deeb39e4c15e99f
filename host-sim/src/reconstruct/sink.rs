//! The host's end of the packet path: owned core state and codec rows, and a packet sink that
//! writes to any `std::io::Write`.

use anyhow::{anyhow, Result};
use dpsa_core::{
    packets::{self, codec},
    pipeline::{Layout, Memory, Slot},
    Config, Row, Sink,
};
use std::io::Write;

/// Owned state for a [`Pipeline`], sized by [`Layout`].
pub struct State {
    lines: Vec<u16>,
    free: Vec<u16>,
    slots: Vec<Slot>,
    heights: Vec<i16>,
    valid: Vec<u8>,
}

impl State {
    pub fn new(cfg: &Config) -> State {
        let l = Layout::of(cfg);
        State {
            lines: vec![0; l.pool_lines * l.width],
            free: vec![0; l.pool_lines],
            slots: vec![Slot::default(); l.slots],
            heights: vec![0; l.width],
            valid: vec![0; l.width.div_ceil(8)],
        }
    }

    pub fn memory(&mut self) -> Memory<'_> {
        Memory {
            lines: &mut self.lines,
            free: &mut self.free,
            slots: &mut self.slots,
            heights: &mut self.heights,
            valid: &mut self.valid,
        }
    }
}

/// Codec reference rows (the previous row) for one end of a stream.
pub struct CodecState {
    heights: Vec<i16>,
    valid: Vec<u8>,
}

impl CodecState {
    pub fn new(width: usize) -> CodecState {
        CodecState { heights: vec![0; width], valid: vec![0; width.div_ceil(8)] }
    }

    /// An encoder with intra period `k` (the stream default is [`packets::STREAM_INTRA_PERIOD`]).
    pub fn encoder(&mut self, k: u32) -> Result<codec::Encoder<'_>> {
        let w = self.heights.len();
        let mut e = codec::Encoder::new(&mut self.heights, &mut self.valid, w)
            .ok_or_else(|| anyhow!("width {w} is not supported by the codec"))?;
        e.set_intra_period(k);
        Ok(e)
    }

    pub fn decoder(&mut self) -> Option<codec::Decoder<'_>> {
        let w = self.heights.len();
        codec::Decoder::new(&mut self.heights, &mut self.valid, w)
    }
}

/// A sink that frames rows into compressed packets and writes them to `out`.
pub struct PacketSink<'e, W: Write> {
    pub(crate) out: W,
    enc: codec::Encoder<'e>,
    buf: Vec<u8>,
    /// Packets and bytes written.
    pub packets: u64,
    pub bytes: u64,
}

impl<'e, W: Write> PacketSink<'e, W> {
    pub fn new(out: W, enc: codec::Encoder<'e>) -> Self {
        let w = enc.width();
        PacketSink { out, enc, buf: vec![0; packets::max_packet_len(w)], packets: 0, bytes: 0 }
    }

    pub fn into_inner(self) -> W {
        self.out
    }
}

impl<W: Write> Sink for PacketSink<'_, W> {
    type Error = std::io::Error;
    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error> {
        let n = packets::encode(row, &mut self.enc, &mut self.buf)
            .map_err(|e| std::io::Error::other(format!("packet encode: {e:?}")))?;
        self.out.write_all(&self.buf[..n])?;
        self.packets += 1;
        self.bytes += n as u64;
        Ok(())
    }
}
