//! Sink: where completed height rows go. [`PacketSink`] frames each row into a compressed
//! packet ([`crate::packets`]) and sends it over a [`Link`]: a file or pipe on the host, the
//! frame grabber's output link on the target.

use crate::frames::Trigger;
use crate::offload::{FrontEndError, RowCoder};
use crate::packets::{self, codec, PacketError};
use crate::row::{Gap, Row, RowHeader, StreamInfo};

/// Receives the pipeline's output in increasing board-row order: every board row exactly
/// once, either as a row or inside a gap record; [`Sink::start`] before anything else and
/// [`Sink::end`] last (from `Pipeline::finish`).
pub trait Sink {
    /// What a failed call reports (the pipeline returns it as [`crate::pipeline::Error::Sink`]).
    type Error;
    /// A completed board row.
    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error>;
    /// The stream starts (once, before the first row or gap). Default: nothing.
    fn start(&mut self, _info: &StreamInfo) -> Result<(), Self::Error> {
        Ok(())
    }
    /// A frame's trigger, once per frame the pipeline takes, before the rows and the gap that
    /// frame completes (the stream's trigger log). Default: nothing.
    fn trigger(&mut self, _trigger: &Trigger) -> Result<(), Self::Error> {
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
    /// What a failed send or flush reports.
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
    /// A front end's row codec gave no payload ([`CodedSink`]).
    FrontEnd(FrontEndError),
}

/// A [`Sink`] that frames the pipeline's output into a version 2 packet stream over `L`: the
/// stream header at [`Sink::start`] (with the run id of [`PacketSink::set_run_id`] and the
/// encoder's intra period), one trigger record per frame, one compressed row packet (codec 1)
/// per row, one gap packet per gap record, the end-of-stream packet with the totals at [`Sink::end`]; sequence numbers
/// count every packet from 0.
///
/// `buf` must hold [`packets::max_packet_len`]`(W)` bytes; the encoder's reference row and
/// intra period decide how rows are coded ([`codec::Encoder`]).
pub struct PacketSink<'a, L> {
    link: L,
    enc: codec::Encoder<'a>,
    buf: &'a mut [u8],
    run_id: u64,
    info: StreamInfo,
    totals: packets::Totals,
    bytes: u64,
}

impl<'a, L: Link> PacketSink<'a, L> {
    /// A sink that encodes rows with `enc` into packets built in `buf` (see [`PacketSink`]
    /// for its size) and sends them on `link`.
    pub fn new(link: L, enc: codec::Encoder<'a>, buf: &'a mut [u8]) -> Self {
        PacketSink {
            link,
            enc,
            buf,
            run_id: 0,
            info: StreamInfo::default(),
            totals: packets::Totals {
                last_row: -1,
                ..packets::Totals::default()
            },
            bytes: 0,
        }
    }

    /// The run identity written into the stream header (default 0).
    pub fn set_run_id(&mut self, run_id: u64) {
        self.run_id = run_id;
    }

    /// Packets sent (every kind).
    pub fn packets(&self) -> u64 {
        self.totals.packets
    }

    /// Row packets sent.
    pub fn rows(&self) -> u64 {
        self.totals.rows
    }

    /// Bytes sent.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// The link.
    pub fn link(&self) -> &L {
        &self.link
    }

    /// The link, mutably.
    pub fn link_mut(&mut self) -> &mut L {
        &mut self.link
    }

    /// Where a row's payload goes in the packet buffer: [`codec::max_len`]`(W)` bytes after the
    /// packet header, the place a front end's row codec delivers a payload to before
    /// [`PacketSink::row_coded`].
    pub fn payload_mut(&mut self) -> &mut [u8] {
        let w = self.enc.width();
        let end = (packets::HEADER_LEN + codec::max_len(w)).min(self.buf.len());
        &mut self.buf[packets::HEADER_LEN.min(end)..end]
    }

    /// Sends a row whose payload (`len` bytes) was coded elsewhere and put in place through
    /// [`PacketSink::payload_mut`]: framed and counted as [`Sink::row`] does with its own
    /// encoder. The front end's codec must code every row of the stream, in order, with this
    /// sink's intra period (the stream header announces it).
    pub fn row_coded(&mut self, header: &RowHeader, len: usize) -> Result<(), SinkError<L::Error>> {
        let n =
            packets::frame_coded(header, self.seq(), len, self.buf).map_err(SinkError::Encode)?;
        self.send(n)?;
        self.totals.rows += 1;
        self.cover(header.row, header.row);
        Ok(())
    }

    /// Flushes the link.
    pub fn flush(&mut self) -> Result<(), L::Error> {
        self.link.flush()
    }

    /// The link back (every packet has been handed to it already).
    pub fn into_link(self) -> L {
        self.link
    }

    fn send(&mut self, n: usize) -> Result<(), SinkError<L::Error>> {
        self.link.send(&self.buf[..n]).map_err(SinkError::Link)?;
        self.totals.packets += 1;
        self.bytes += n as u64;
        Ok(())
    }

    fn cover(&mut self, first: i64, last: i64) {
        if self.totals.first_row > self.totals.last_row {
            self.totals.first_row = first;
        }
        self.totals.last_row = last;
    }

    fn seq(&self) -> u32 {
        self.totals.packets as u32
    }
}

impl<L: Link> Sink for PacketSink<'_, L> {
    type Error = SinkError<L::Error>;

    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error> {
        let n =
            packets::encode(row, self.seq(), &mut self.enc, self.buf).map_err(SinkError::Encode)?;
        self.send(n)?;
        self.totals.rows += 1;
        self.cover(row.header.row, row.header.row);
        Ok(())
    }

    fn start(&mut self, info: &StreamInfo) -> Result<(), Self::Error> {
        self.info = StreamInfo {
            run_id: self.run_id,
            intra_period: self.enc.intra_period(),
            ..*info
        };
        let n = packets::encode_stream_header(&self.info, self.buf).map_err(SinkError::Encode)?;
        self.send(n)
    }

    fn trigger(&mut self, trigger: &Trigger) -> Result<(), Self::Error> {
        let (camera, n, width, seq) = (self.info.camera, self.info.n, self.info.width, self.seq());
        let len = packets::encode_trigger(trigger, camera, n, width, seq, self.buf)
            .map_err(SinkError::Encode)?;
        self.send(len)
    }

    fn gap(&mut self, gap: &Gap) -> Result<(), Self::Error> {
        let n = packets::encode_gap(gap, self.info.n, self.info.width, self.seq(), self.buf)
            .map_err(SinkError::Encode)?;
        self.send(n)?;
        self.totals.gap_rows = self.totals.gap_rows.saturating_add(gap.count);
        let last = gap
            .first
            .saturating_add(gap.count.saturating_sub(1).min(i64::MAX as u64) as i64);
        self.cover(gap.first, last);
        Ok(())
    }

    fn end(&mut self) -> Result<(), Self::Error> {
        let mut t = self.totals;
        t.packets += 1;
        if t.first_row > t.last_row {
            (t.first_row, t.last_row) = (0, -1);
        }
        let (camera, n, width, seq) = (self.info.camera, self.info.n, self.info.width, self.seq());
        let len =
            packets::encode_end(&t, camera, n, width, seq, self.buf).map_err(SinkError::Encode)?;
        self.send(len)
    }
}

/// A [`PacketSink`] whose rows a front end's row codec codes ([`RowCoder`], `docs/fpga.md`):
/// each row's payload comes from the coder into [`PacketSink::payload_mut`] and is framed by
/// [`PacketSink::row_coded`]; the stream's other records are the sink's own. The stream equals
/// the sink's own when the coder's payloads equal its encoder's.
pub struct CodedSink<'s, 'a, L> {
    /// The sink that frames and sends.
    pub sink: &'s mut PacketSink<'a, L>,
    /// The row codec.
    pub coder: &'s mut dyn RowCoder,
}

impl<L: Link> Sink for CodedSink<'_, '_, L> {
    type Error = SinkError<L::Error>;

    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error> {
        let len = self
            .coder
            .code(row, self.sink.payload_mut())
            .map_err(SinkError::FrontEnd)?;
        self.sink.row_coded(&row.header, len)
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

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::row::RowHeader;
    use std::vec;
    use std::vec::Vec;

    struct Bytes(Vec<u8>);
    impl Link for Bytes {
        type Error = ();
        fn send(&mut self, p: &[u8]) -> Result<(), ()> {
            self.0.extend_from_slice(p);
            Ok(())
        }
        fn flush(&mut self) -> Result<(), ()> {
            Ok(())
        }
    }

    /// A row codec in software: the core's encoder.
    struct Soft<'e, 'b>(&'e mut codec::Encoder<'b>);
    impl RowCoder for Soft<'_, '_> {
        fn code(&mut self, row: &Row<'_>, payload: &mut [u8]) -> Result<usize, FrontEndError> {
            self.0
                .encode(row.heights, row.valid, payload)
                .map_err(|_| FrontEndError::Failed)
        }
    }

    /// Rows whose payloads a separate encoder coded (as a front end's codec does), framed by
    /// `row_coded` (by hand, and through [`CodedSink`]), make the stream `row` makes with the sink's own encoder, byte for byte,
    /// predicted rows included; a payload longer than `codec::max_len` is refused.
    #[test]
    fn rows_coded_elsewhere_make_the_same_stream() {
        let w: usize = 37;
        let rows: Vec<(Vec<i16>, Vec<u8>)> = (0..12)
            .map(|r| {
                let h = (0..w)
                    .map(|c| ((r * 7 + c * c) % 300) as i16 - 100)
                    .collect();
                let v = (0..w.div_ceil(8))
                    .map(|i| if r % 5 == 0 { 0 } else { 0xF7 ^ i as u8 })
                    .collect();
                (h, v)
            })
            .collect();
        let info = StreamInfo {
            width: w as u16,
            n: 4,
            ..StreamInfo::default()
        };
        let header = |r: usize| RowHeader {
            row: r as i64 + 100,
            width: w as u16,
            n: 4,
            flags: if r % 5 == 0 { 2 } else { 0 },
            ..RowHeader::default()
        };
        for period in [1, 4] {
            let run = |coded: bool| -> Vec<u8> {
                let (mut rh, mut rv) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
                let enc = codec::Encoder::new(&mut rh, &mut rv, w, period).unwrap();
                let mut buf = vec![0u8; packets::max_packet_len(w)];
                let mut sink = PacketSink::new(Bytes(Vec::new()), enc, &mut buf);
                let (mut fh, mut fv) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
                let mut front = codec::Encoder::new(&mut fh, &mut fv, w, period).unwrap();
                let mut payload = vec![0u8; codec::max_len(w)];
                sink.start(&info).unwrap();
                for (r, (h, v)) in rows.iter().enumerate() {
                    if coded && r % 2 == 0 {
                        let len = front.encode(h, v, &mut payload).unwrap();
                        sink.payload_mut()[..len].copy_from_slice(&payload[..len]);
                        sink.row_coded(&header(r), len).unwrap();
                    } else if coded {
                        let row = Row {
                            header: header(r),
                            heights: h,
                            valid: v,
                        };
                        let mut coder = Soft(&mut front);
                        let mut cs = CodedSink {
                            sink: &mut sink,
                            coder: &mut coder,
                        };
                        cs.row(&row).unwrap();
                    } else {
                        let row = Row {
                            header: header(r),
                            heights: h,
                            valid: v,
                        };
                        sink.row(&row).unwrap();
                    }
                }
                sink.end().unwrap();
                assert_eq!(sink.rows(), rows.len() as u64);
                sink.into_link().0
            };
            assert_eq!(run(true), run(false), "intra period {period}");
        }
        let (mut rh, mut rv) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
        let enc = codec::Encoder::new(&mut rh, &mut rv, w, 1).unwrap();
        let mut buf = vec![0u8; packets::max_packet_len(w)];
        let mut sink = PacketSink::new(Bytes(Vec::new()), enc, &mut buf);
        assert_eq!(
            sink.row_coded(&header(0), codec::max_len(w) + 1),
            Err(SinkError::Encode(PacketError::BufferTooSmall))
        );
        assert_eq!(sink.packets(), 0);
    }
}
