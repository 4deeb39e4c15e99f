//! Packets: height rows (and the stream's own records) framed with a sync word, a header, a
//! payload and CRC-32s. The full stream format, enough to write a decoder in another language,
//! is `docs/stream.md`; this is its summary.
//!
//! ## Version 2 (what the pipeline emits, [`VERSION`])
//!
//! Every packet (all integers little-endian):
//!
//! | offset | size | field |
//! | --- | --- | --- |
//! | 0 | 4 | sync word `"DPSA"` (`44 50 53 41`) |
//! | 4 | 1 | format version `2` |
//! | 5 | 1 | kind: `0` row (raw payload), `1` row (compressed payload), `2` stream header, `3` gap, `4` end of stream, `5` frame trigger |
//! | 6 | 1 | camera id |
//! | 7 | 1 | `n` |
//! | 8 | 4 | sequence number (u32): 0 for the stream header, then +1 per packet of any kind |
//! | 12 | 8 | `A` (i64): row: board row; header: run id (u64); gap: first board row; end: first board row; trigger: the frame's encoder latch |
//! | 20 | 8 | `B` (i64): row: latch of the window's first frame; header: config hash (u64); gap: row count (u64); end: last board row; trigger: the frame's counter (u32, zero-extended) |
//! | 28 | 2 | flags (u16): row flags; gap: the rows' flags; header, end, trigger: 0 |
//! | 30 | 2 | width `W` (u16, `1 ..= 8192`) |
//! | 32 | 4 | payload length `L` (u32): row `<= codec::max_len(W)`; header 8; gap 0; end 24; trigger 0 |
//! | 36 | 4 | header CRC-32 of bytes `4 .. 36` |
//! | 40 | L | payload: row: the row payload (codec = kind); header: intra period u32, `H` u16, `max_step_rows` u16; end: packets u64, rows u64, gap rows u64 |
//! | 40+L | 4 | CRC-32 (ISO-HDLC, as zlib) of bytes `4 .. 40+L` |
//!
//! The header CRC lets a decoder reject a false sync word after 36 bytes, so a walk through
//! any input costs O(1) per sync candidate; a packet whose header checks out but whose payload
//! CRC does not is skipped whole (its extent is known), so no byte is CRC'd twice.
//!
//! A stream: one stream header (seq 0), then rows and gap records in increasing board-row
//! order, each frame's trigger record before the rows and gap its frame completes, then one
//! end-of-stream packet with totals. The trigger records are the stream's trigger log: with
//! the stream header's `H`, `n` and `max_step_rows` and the calibration's counts per pixel a
//! receiver replays the registration (which frames fed each row, at which image rows) without
//! the frames; each row packet's latch (its window's first frame) checks the replay. [`Tracker`] follows a stream and reports
//! missing, duplicated, reordered packets, a truncated stream and packets of another width.
//!
//! ## Version 1 (still decoded)
//!
//! | offset | size | field |
//! | --- | --- | --- |
//! | 0 | 4 | sync word |
//! | 4 | 1 | version `1` |
//! | 5 | 1 | payload codec (`0` = raw, `1` = compressed) |
//! | 6 | 1 | camera id |
//! | 7 | 1 | `n` |
//! | 8 | 8 | board row (i64) |
//! | 16 | 8 | encoder latch of the window's first frame (i64) |
//! | 24 | 2 | row flags (u16) |
//! | 26 | 2 | width `W` (u16, at most 8192) |
//! | 28 | 4 | payload length `L` (u32) |
//! | 32 | L | payload |
//! | 32+L | 4 | CRC-32 of bytes `4 .. 32+L` |
//!
//! Raw payload (codec 0): the validity bitmask, `ceil(W/8)` bytes (bit `c % 8` of byte `c / 8`,
//! 1 = valid), then `W` heights as i16 (LSB units, 0 where invalid).
//!
//! Compressed payload (codec 1): the lossless row code of [`codec`], at most
//! [`codec::max_len`]`(W)` = raw + 2 bytes. Streams use intra period [`STREAM_INTRA_PERIOD`] = 1:
//! every packet decodes on its own, so a damaged packet loses that packet only.

pub mod codec;
mod track;

pub use track::{Summary, Tracker, Verdict};

use crate::crc32;
use crate::frames::Trigger;
use crate::row::{Gap, Row, RowHeader, StreamInfo};

/// Sync word at the start of every packet.
pub const SYNC: [u8; 4] = *b"DPSA";
/// Stream format version the encoder writes.
pub const VERSION: u8 = 2;
/// The previous format version (row packets only), still decoded.
pub const VERSION_1: u8 = 1;
/// Bytes before the payload (version 2, including the header CRC).
pub const HEADER_LEN: usize = 40;
/// Bytes before the payload in version 1.
pub const HEADER_LEN_V1: usize = 32;
/// Bytes after the payload.
pub const TRAILER_LEN: usize = 4;
/// Payload codec: raw bitmask + i16 heights (also the kind of a raw row packet).
pub const CODEC_RAW: u8 = 0;
/// Payload codec: the compressed row code of [`codec`] (also the kind of such a row packet).
pub const CODEC_COMPRESSED: u8 = 1;
/// Kind byte of a stream header packet.
pub const KIND_STREAM_HEADER: u8 = 2;
/// Kind byte of a gap record.
pub const KIND_GAP: u8 = 3;
/// Kind byte of an end-of-stream packet.
pub const KIND_END: u8 = 4;
/// Kind byte of a frame trigger record (the stream's trigger log).
pub const KIND_TRIGGER: u8 = 5;
/// Payload bytes of a stream header packet.
pub const STREAM_HEADER_PAYLOAD_LEN: usize = 8;
/// Payload bytes of an end-of-stream packet.
pub const END_PAYLOAD_LEN: usize = 24;
/// Intra period of a packet stream: 1, every row decodable on its own.
pub const STREAM_INTRA_PERIOD: u32 = 1;
/// Intra period of predicted streams in the codec benchmark (`dpsa codec-bench`): rows are
/// predicted from the previous one, with an intra row every 32 rows.
pub const PREDICTED_INTRA_PERIOD: u32 = 32;

/// Raw payload bytes for a row of `width` pixels.
pub const fn raw_payload_len(width: usize) -> usize {
    width.div_ceil(8) + 2 * width
}

/// Largest (version 2) packet of a stream of `width` pixels: a row of any codec, or the end
/// packet (the buffer a `PacketSink` needs).
pub const fn max_packet_len(width: usize) -> usize {
    let row = codec::max_len(width);
    let p = if row > END_PAYLOAD_LEN {
        row
    } else {
        END_PAYLOAD_LEN
    };
    HEADER_LEN + p + TRAILER_LEN
}

/// Largest packet of any version and width a decoder accepts: a chunked reader that keeps
/// this many bytes ahead of its position can always decide the next item.
pub const MAX_PACKET_LEN: usize = max_packet_len(codec::MAX_WIDTH);

/// Why bytes are not a packet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PacketError {
    /// The output buffer is too small.
    BufferTooSmall,
    /// Fewer bytes than the header or the declared payload need.
    Truncated,
    /// No sync word at the start.
    BadSync,
    /// Unknown format version.
    BadVersion(u8),
    /// Unknown payload codec.
    BadCodec(u8),
    /// Payload length does not fit the kind, codec and width.
    BadLength,
    /// CRC mismatch (version 2: the header checked out, the payload CRC did not).
    BadCrc,
    /// The compressed payload does not decode (or needs a reference the decoder lacks).
    Codec(codec::CodecError),
    /// Unknown packet kind (version 2).
    BadKind(u8),
    /// Width 0 or above 8192 (version 2).
    BadWidth(u16),
    /// Header CRC mismatch (version 2).
    BadHeaderCrc,
    /// A version 1 packet left unchecked: the walk's budget for payload CRCs over false sync
    /// words is spent (see [`Walk`]).
    Unchecked,
}

/// What a packet holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A height row (codec in [`Packet::codec`]).
    Row,
    /// The stream header.
    StreamHeader,
    /// A gap record.
    Gap,
    /// The end of the stream.
    End,
    /// A frame's trigger (frame counter and encoder latch), one per frame the pipeline took.
    Trigger,
}

/// Totals of a stream, carried by its end-of-stream packet.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Totals {
    /// Packets of the stream, the stream header and this end packet included.
    pub packets: u64,
    /// Row packets.
    pub rows: u64,
    /// Board rows inside gap records.
    pub gap_rows: u64,
    /// First board row covered by a row or gap (0 when none).
    pub first_row: i64,
    /// Last board row covered by a row or gap (-1 when none).
    pub last_row: i64,
}

/// Frames a row into `buf` with a compressed payload (codec 1, version 2, sequence number
/// `seq`); returns the packet length. `buf` must hold [`max_packet_len`]`(W)` bytes.
#[inline(never)]
pub fn encode(
    row: &Row<'_>,
    seq: u32,
    enc: &mut codec::Encoder<'_>,
    buf: &mut [u8],
) -> Result<usize, PacketError> {
    let w = row.header.width as usize;
    if buf.len() < max_packet_len(w) || enc.width() != w {
        return Err(PacketError::BufferTooSmall);
    }
    let plen = enc
        .encode(
            row.heights,
            row.valid,
            &mut buf[HEADER_LEN..HEADER_LEN + codec::max_len(w)],
        )
        .map_err(PacketError::Codec)?;
    Ok(frame_row(&row.header, CODEC_COMPRESSED, seq, plen, buf))
}

/// Frames a compressed row payload of `plen` bytes that is already in place at
/// `buf[HEADER_LEN..]` (coded elsewhere: a front end's row codec, `docs/fpga.md`) as a version
/// 2 row packet (codec 1, sequence number `seq`); returns the packet length. Refused when
/// `plen` is above [`codec::max_len`]`(W)` or `buf` is shorter than
/// [`max_packet_len`]`(W)`.
pub fn frame_coded(
    header: &RowHeader,
    seq: u32,
    plen: usize,
    buf: &mut [u8],
) -> Result<usize, PacketError> {
    let w = header.width as usize;
    if buf.len() < max_packet_len(w) || plen > codec::max_len(w) {
        return Err(PacketError::BufferTooSmall);
    }
    Ok(frame_row(header, CODEC_COMPRESSED, seq, plen, buf))
}

/// Frames a row into `buf` with a raw payload (codec 0, version 2); returns the packet length.
pub fn encode_raw(row: &Row<'_>, seq: u32, buf: &mut [u8]) -> Result<usize, PacketError> {
    let plen = raw_payload(row, HEADER_LEN, buf)?;
    Ok(frame_row(&row.header, CODEC_RAW, seq, plen, buf))
}

/// Frames a row as a version 1 packet with a compressed payload (legacy streams, the corpus).
pub fn encode_v1(
    row: &Row<'_>,
    enc: &mut codec::Encoder<'_>,
    buf: &mut [u8],
) -> Result<usize, PacketError> {
    let w = row.header.width as usize;
    if buf.len() < HEADER_LEN_V1 + codec::max_len(w) + TRAILER_LEN || enc.width() != w {
        return Err(PacketError::BufferTooSmall);
    }
    let plen = enc
        .encode(
            row.heights,
            row.valid,
            &mut buf[HEADER_LEN_V1..HEADER_LEN_V1 + codec::max_len(w)],
        )
        .map_err(PacketError::Codec)?;
    Ok(frame_v1(&row.header, CODEC_COMPRESSED, plen, buf))
}

/// Frames a row as a version 1 packet with a raw payload (legacy streams).
pub fn encode_raw_v1(row: &Row<'_>, buf: &mut [u8]) -> Result<usize, PacketError> {
    let plen = raw_payload(row, HEADER_LEN_V1, buf)?;
    Ok(frame_v1(&row.header, CODEC_RAW, plen, buf))
}

/// Writes the raw payload (codec 0) of `row` into `buf` after a header of `header_len` bytes,
/// checking that the row and the whole packet fit; returns the payload length.
fn raw_payload(row: &Row<'_>, header_len: usize, buf: &mut [u8]) -> Result<usize, PacketError> {
    let w = row.header.width as usize;
    let (nb, plen) = (w.div_ceil(8), raw_payload_len(w));
    if buf.len() < header_len + plen + TRAILER_LEN || row.heights.len() < w || row.valid.len() < nb
    {
        return Err(PacketError::BufferTooSmall);
    }
    let payload = &mut buf[header_len..header_len + plen];
    payload[..nb].copy_from_slice(&row.valid[..nb]);
    for (dst, &h) in payload[nb..].chunks_exact_mut(2).zip(row.heights) {
        dst.copy_from_slice(&h.to_le_bytes());
    }
    Ok(plen)
}

/// Frames the stream header packet (sequence number 0); returns its length
/// (`HEADER_LEN + 8 + TRAILER_LEN` = 52 bytes).
pub fn encode_stream_header(info: &StreamInfo, buf: &mut [u8]) -> Result<usize, PacketError> {
    let f = Fields {
        kind: KIND_STREAM_HEADER,
        camera: info.camera,
        n: info.n,
        seq: 0,
        a: info.run_id as i64,
        b: info.config_hash as i64,
        flags: 0,
        width: info.width,
    };
    let mut p = [0u8; STREAM_HEADER_PAYLOAD_LEN];
    p[0..4].copy_from_slice(&info.intra_period.to_le_bytes());
    p[4..6].copy_from_slice(&info.rows.to_le_bytes());
    p[6..8].copy_from_slice(&info.max_step_rows.to_le_bytes());
    frame_with(&f, &p, buf)
}

/// Frames a gap record (`n`, `width` as in the stream header); returns its length (44 bytes).
pub fn encode_gap(
    gap: &Gap,
    n: u8,
    width: u16,
    seq: u32,
    buf: &mut [u8],
) -> Result<usize, PacketError> {
    let f = Fields {
        kind: KIND_GAP,
        camera: gap.camera,
        n,
        seq,
        a: gap.first,
        b: gap.count as i64,
        flags: gap.flags,
        width,
    };
    frame_with(&f, &[], buf)
}

/// Frames a frame's trigger record (`camera`, `n`, `width` as in the stream header); returns
/// its length (44 bytes).
pub fn encode_trigger(
    trigger: &Trigger,
    camera: u8,
    n: u8,
    width: u16,
    seq: u32,
    buf: &mut [u8],
) -> Result<usize, PacketError> {
    let f = Fields {
        kind: KIND_TRIGGER,
        camera,
        n,
        seq,
        a: trigger.latch,
        b: i64::from(trigger.seq),
        flags: 0,
        width,
    };
    frame_with(&f, &[], buf)
}

/// Frames the end-of-stream packet; returns its length (68 bytes).
pub fn encode_end(
    totals: &Totals,
    camera: u8,
    n: u8,
    width: u16,
    seq: u32,
    buf: &mut [u8],
) -> Result<usize, PacketError> {
    let f = Fields {
        kind: KIND_END,
        camera,
        n,
        seq,
        a: totals.first_row,
        b: totals.last_row,
        flags: 0,
        width,
    };
    let mut p = [0u8; END_PAYLOAD_LEN];
    p[0..8].copy_from_slice(&totals.packets.to_le_bytes());
    p[8..16].copy_from_slice(&totals.rows.to_le_bytes());
    p[16..24].copy_from_slice(&totals.gap_rows.to_le_bytes());
    frame_with(&f, &p, buf)
}

/// The common header fields of a version 2 packet.
struct Fields {
    kind: u8,
    camera: u8,
    n: u8,
    seq: u32,
    a: i64,
    b: i64,
    flags: u16,
    width: u16,
}

fn frame_with(f: &Fields, payload: &[u8], buf: &mut [u8]) -> Result<usize, PacketError> {
    let plen = payload.len();
    if buf.len() < HEADER_LEN + plen + TRAILER_LEN {
        return Err(PacketError::BufferTooSmall);
    }
    buf[HEADER_LEN..HEADER_LEN + plen].copy_from_slice(payload);
    Ok(frame(f, plen, buf))
}

fn frame_row(h: &RowHeader, codec: u8, seq: u32, plen: usize, buf: &mut [u8]) -> usize {
    let f = Fields {
        kind: codec,
        camera: h.camera,
        n: h.n,
        seq,
        a: h.row,
        b: h.latch,
        flags: h.flags,
        width: h.width,
    };
    frame(&f, plen, buf)
}

/// Writes the version 2 header (with its CRC) before and the CRC after a payload of `plen`
/// bytes already in place.
fn frame(f: &Fields, plen: usize, buf: &mut [u8]) -> usize {
    let out = &mut buf[..HEADER_LEN];
    out[0..4].copy_from_slice(&SYNC);
    out[4] = VERSION;
    out[5] = f.kind;
    out[6] = f.camera;
    out[7] = f.n;
    out[8..12].copy_from_slice(&f.seq.to_le_bytes());
    out[12..20].copy_from_slice(&f.a.to_le_bytes());
    out[20..28].copy_from_slice(&f.b.to_le_bytes());
    out[28..30].copy_from_slice(&f.flags.to_le_bytes());
    out[30..32].copy_from_slice(&f.width.to_le_bytes());
    out[32..36].copy_from_slice(&(plen as u32).to_le_bytes());
    let hcrc = crc32::checksum(&out[4..36]);
    out[36..40].copy_from_slice(&hcrc.to_le_bytes());
    let crc = crc32::checksum(&buf[4..HEADER_LEN + plen]);
    buf[HEADER_LEN + plen..HEADER_LEN + plen + TRAILER_LEN].copy_from_slice(&crc.to_le_bytes());
    HEADER_LEN + plen + TRAILER_LEN
}

/// Writes a version 1 header before and the CRC after a payload of `plen` bytes in place.
fn frame_v1(h: &RowHeader, codec: u8, plen: usize, buf: &mut [u8]) -> usize {
    let out = &mut buf[..HEADER_LEN_V1];
    out[0..4].copy_from_slice(&SYNC);
    out[4] = VERSION_1;
    out[5] = codec;
    out[6] = h.camera;
    out[7] = h.n;
    out[8..16].copy_from_slice(&h.row.to_le_bytes());
    out[16..24].copy_from_slice(&h.latch.to_le_bytes());
    out[24..26].copy_from_slice(&h.flags.to_le_bytes());
    out[26..28].copy_from_slice(&h.width.to_le_bytes());
    out[28..32].copy_from_slice(&(plen as u32).to_le_bytes());
    let crc = crc32::checksum(&buf[4..HEADER_LEN_V1 + plen]);
    buf[HEADER_LEN_V1 + plen..HEADER_LEN_V1 + plen + TRAILER_LEN]
        .copy_from_slice(&crc.to_le_bytes());
    HEADER_LEN_V1 + plen + TRAILER_LEN
}

/// A checked packet borrowed from a byte stream.
#[derive(Clone, Copy, Debug)]
pub struct Packet<'a> {
    /// Format version (1 or 2).
    pub version: u8,
    /// What the packet holds (always [`Kind::Row`] in version 1).
    pub kind: Kind,
    /// Sequence number (version 2; 0 in version 1).
    pub seq: u32,
    /// Row packets: the row header. Other kinds: camera, `n`, width and flags as framed,
    /// `row` = field `A`, `latch` = field `B` (see the module table).
    pub header: RowHeader,
    /// Row packets: the payload codec; other kinds: the kind byte.
    pub codec: u8,
    /// The payload bytes (CRC-checked, still encoded).
    pub payload: &'a [u8],
}

impl Packet<'_> {
    /// The stream header's contents (`None` for other kinds).
    pub fn stream_info(&self) -> Option<StreamInfo> {
        if self.kind != Kind::StreamHeader {
            return None;
        }
        let p = self.payload;
        Some(StreamInfo {
            camera: self.header.camera,
            n: self.header.n,
            width: self.header.width,
            rows: u16::from_le_bytes([p[4], p[5]]),
            max_step_rows: u16::from_le_bytes([p[6], p[7]]),
            config_hash: self.header.latch as u64,
            run_id: self.header.row as u64,
            intra_period: u32::from_le_bytes([p[0], p[1], p[2], p[3]]),
        })
    }

    /// The gap record's contents (`None` for other kinds).
    pub fn gap(&self) -> Option<Gap> {
        (self.kind == Kind::Gap).then_some(Gap {
            camera: self.header.camera,
            first: self.header.row,
            count: self.header.latch as u64,
            flags: self.header.flags,
        })
    }

    /// The trigger record's frame trigger (`None` for other kinds; a counter field above
    /// `u32::MAX` is not a trigger either).
    pub fn trigger(&self) -> Option<Trigger> {
        if self.kind != Kind::Trigger {
            return None;
        }
        Some(Trigger {
            seq: u32::try_from(self.header.latch).ok()?,
            latch: self.header.row,
        })
    }

    /// The end packet's totals (`None` for other kinds).
    pub fn totals(&self) -> Option<Totals> {
        if self.kind != Kind::End {
            return None;
        }
        let p = self.payload;
        let u64_at = |i: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&p[i..i + 8]);
            u64::from_le_bytes(b)
        };
        Some(Totals {
            packets: u64_at(0),
            rows: u64_at(8),
            gap_rows: u64_at(16),
            first_row: self.header.row,
            last_row: self.header.latch,
        })
    }

    /// Unpacks a row payload into `heights` (`W`) and `valid` (`ceil(W/8)`); `dec` decodes
    /// compressed payloads (its width must be the packet's). Other kinds: `BadKind`.
    pub fn unpack(
        &self,
        dec: &mut codec::Decoder<'_>,
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> Result<(), PacketError> {
        if self.kind != Kind::Row {
            return Err(PacketError::BadKind(self.codec));
        }
        let w = self.header.width as usize;
        let nb = w.div_ceil(8);
        if heights.len() < w || valid.len() < nb {
            return Err(PacketError::BufferTooSmall);
        }
        match self.codec {
            CODEC_RAW => {
                if self.payload.len() != raw_payload_len(w) {
                    return Err(PacketError::BadLength);
                }
                valid[..nb].copy_from_slice(&self.payload[..nb]);
                for (h, src) in heights.iter_mut().zip(self.payload[nb..].chunks_exact(2)) {
                    *h = i16::from_le_bytes([src[0], src[1]]);
                }
                Ok(())
            }
            CODEC_COMPRESSED => {
                if dec.width() != w {
                    return Err(PacketError::BadLength);
                }
                dec.decode(self.payload, &mut heights[..w], &mut valid[..nb])
                    .map_err(PacketError::Codec)
            }
            c => Err(PacketError::BadCodec(c)),
        }
    }
}

fn u16_at(buf: &[u8], i: usize) -> u16 {
    u16::from_le_bytes([buf[i], buf[i + 1]])
}

fn u32_at(buf: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([buf[i], buf[i + 1], buf[i + 2], buf[i + 3]])
}

fn i64_at(buf: &[u8], i: usize) -> i64 {
    let mut b = [0u8; 8];
    b.copy_from_slice(&buf[i..i + 8]);
    i64::from_le_bytes(b)
}

/// Parses the packet at the start of `buf`; returns it and its length in bytes.
///
/// Every check that needs no more than the header comes before the payload CRC (version,
/// kind, width, length bound, and in version 2 the header CRC), so a false sync word costs
/// O(header) bytes.
pub fn decode(buf: &[u8]) -> Result<(Packet<'_>, usize), PacketError> {
    decode_inner(buf, true).map_err(|(e, _)| e)
}

/// [`decode`], and on error the length of the packet when its version 2 header checked out
/// (so a walk may skip it whole).
///
/// `v1_crc == false` rejects a version 1 packet that would need its payload CRC with
/// [`PacketError::Unchecked`].
fn decode_inner(
    buf: &[u8],
    v1_crc: bool,
) -> Result<(Packet<'_>, usize), (PacketError, Option<usize>)> {
    if buf.len() < 4 {
        return Err((PacketError::Truncated, None));
    }
    if buf[0..4] != SYNC {
        return Err((PacketError::BadSync, None));
    }
    if buf.len() < HEADER_LEN_V1 {
        return Err((PacketError::Truncated, None));
    }
    match buf[4] {
        VERSION_1 => decode_v1(buf, v1_crc).map_err(|e| (e, None)),
        VERSION => decode_v2(buf),
        v => Err((PacketError::BadVersion(v), None)),
    }
}

fn decode_v1(buf: &[u8], crc: bool) -> Result<(Packet<'_>, usize), PacketError> {
    let codec = buf[5];
    let width = u16_at(buf, 26);
    let plen = u32_at(buf, 28) as usize;
    // Version 1 wrote codecs 0 and 1 only, a raw payload of exactly its width's size, no
    // payload above the compressed codec's bound (raw + 2 bytes) and no width above the
    // codec's (a decoder could not unpack it): all checked before the CRC.
    if codec != CODEC_RAW && codec != CODEC_COMPRESSED {
        return Err(PacketError::BadCodec(codec));
    }
    if width == 0
        || width as usize > codec::MAX_WIDTH
        || plen > codec::max_len(width as usize)
        || (codec == CODEC_RAW && plen != raw_payload_len(width as usize))
    {
        return Err(PacketError::BadLength);
    }
    let total = HEADER_LEN_V1 + plen + TRAILER_LEN;
    if buf.len() < total {
        return Err(PacketError::Truncated);
    }
    if !crc {
        return Err(PacketError::Unchecked);
    }
    if crc32::checksum(&buf[4..HEADER_LEN_V1 + plen]) != u32_at(buf, total - 4) {
        return Err(PacketError::BadCrc);
    }
    let header = RowHeader {
        camera: buf[6],
        n: buf[7],
        row: i64_at(buf, 8),
        latch: i64_at(buf, 16),
        flags: u16_at(buf, 24),
        width,
    };
    Ok((
        Packet {
            version: VERSION_1,
            kind: Kind::Row,
            seq: 0,
            header,
            codec,
            payload: &buf[HEADER_LEN_V1..HEADER_LEN_V1 + plen],
        },
        total,
    ))
}

fn decode_v2(buf: &[u8]) -> Result<(Packet<'_>, usize), (PacketError, Option<usize>)> {
    if buf.len() < HEADER_LEN {
        return Err((PacketError::Truncated, None));
    }
    let k = buf[5];
    let width = u16_at(buf, 30);
    let plen = u32_at(buf, 32) as usize;
    let (kind, len_ok) = match k {
        CODEC_RAW => (Kind::Row, plen == raw_payload_len(width as usize)),
        CODEC_COMPRESSED => (Kind::Row, plen <= codec::max_len(width as usize)),
        KIND_STREAM_HEADER => (Kind::StreamHeader, plen == STREAM_HEADER_PAYLOAD_LEN),
        KIND_GAP => (Kind::Gap, plen == 0),
        KIND_END => (Kind::End, plen == END_PAYLOAD_LEN),
        KIND_TRIGGER => (Kind::Trigger, plen == 0),
        _ => return Err((PacketError::BadKind(k), None)),
    };
    if width == 0 || width as usize > codec::MAX_WIDTH {
        return Err((PacketError::BadWidth(width), None));
    }
    if !len_ok {
        return Err((PacketError::BadLength, None));
    }
    if crc32::checksum(&buf[4..36]) != u32_at(buf, 36) {
        return Err((PacketError::BadHeaderCrc, None));
    }
    let total = HEADER_LEN + plen + TRAILER_LEN;
    if buf.len() < total {
        return Err((PacketError::Truncated, None));
    }
    if crc32::checksum(&buf[4..HEADER_LEN + plen]) != u32_at(buf, total - 4) {
        return Err((PacketError::BadCrc, Some(total)));
    }
    let header = RowHeader {
        camera: buf[6],
        n: buf[7],
        row: i64_at(buf, 12),
        latch: i64_at(buf, 20),
        flags: u16_at(buf, 28),
        width,
    };
    Ok((
        Packet {
            version: VERSION,
            kind,
            seq: u32_at(buf, 8),
            header,
            codec: k,
            payload: &buf[HEADER_LEN..HEADER_LEN + plen],
        },
        total,
    ))
}

/// Offset of the next sync word at or after `from`, for resynchronising after damage.
pub fn find_sync(buf: &[u8], from: usize) -> Option<usize> {
    buf.get(from..)?
        .windows(4)
        .position(|w| w == SYNC)
        .map(|p| p + from)
}

/// One step through a packet stream: a packet whose framing and CRCs check out, or damage.
#[derive(Clone, Copy, Debug)]
pub enum Item<'a> {
    /// A packet starting at byte `offset`.
    Packet {
        /// Byte offset of the packet's sync word in the stream.
        offset: usize,
        /// The packet.
        packet: Packet<'a>,
    },
    /// Bytes at `offset` that are not a packet (bad sync, truncation, bad length, bad CRC, ...).
    /// The stream resynchronises on the next sync word after `offset` (or, for a version 2
    /// packet whose header checked out but whose payload CRC did not, right after it).
    Damage {
        /// Byte offset where the damage starts.
        offset: usize,
        /// What is wrong there.
        error: PacketError,
    },
}

/// The resynchronising walk through a stream that arrives in pieces: the state a chunked
/// reader keeps between buffers (the host's `dpsa decode` reads files this way, in constant
/// memory). [`Stream`] is the same walk over one whole slice.
///
/// Each call of [`Walk::next`] looks at `bytes` (the buffer, whose byte 0 is the stream byte
/// the caller last [`Walk::shift`]ed to); with `eof == false` it returns `None` when the next
/// item needs bytes past the end of the buffer; bytes before [`Walk::position`] are done with.
/// Every byte is looked at O(1) times: a false sync word costs at most a header (40 bytes)
/// before it is rejected, the payload CRC is computed only for a header that checked out, and
/// such a packet is then skipped whole.
///
/// Version 1 has no header CRC: a false sync word whose header fields look plausible costs a
/// payload CRC (up to [`MAX_PACKET_LEN`] bytes) before the walk moves on by one byte. The
/// payload bytes of failed version 1 CRCs are therefore budgeted: at most
/// [`V1_CRC_BUDGET_PER_BYTE`] per stream byte walked past plus [`V1_CRC_BUDGET_BASE`]. Past the
/// budget a version 1 candidate that would need its CRC is reported as damage
/// ([`PacketError::Unchecked`]) without one, so hostile input stays linear in time; genuine
/// version 1 streams never fail a CRC unless damaged and never come near the budget.
#[derive(Clone, Copy, Debug, Default)]
pub struct Walk {
    pos: usize,
    seeking: bool,
    /// Stream bytes dropped by [`Walk::shift`] so far.
    base: u64,
    /// Payload bytes of failed version 1 CRCs so far.
    v1_failed: u64,
}

/// Failed version 1 CRC bytes allowed per stream byte ([`Walk`]).
pub const V1_CRC_BUDGET_PER_BYTE: u64 = 8;
/// Failed version 1 CRC bytes always allowed ([`Walk`]): a few damaged packets of the widest
/// rows.
pub const V1_CRC_BUDGET_BASE: u64 = 1 << 20;

impl Walk {
    /// A walk from the start of a stream.
    pub fn new() -> Self {
        Walk::default()
    }

    /// Buffer offset of the first byte still needed.
    pub fn position(&self) -> usize {
        self.pos
    }

    /// The caller dropped the first `n <= position()` bytes of its buffer.
    pub fn shift(&mut self, n: usize) {
        let n = n.min(self.pos);
        self.pos -= n;
        self.base += n as u64;
    }

    /// True while failed version 1 CRCs stay within the budget at stream offset `at`.
    fn v1_budget(&self, at: usize) -> bool {
        let walked = self.base.saturating_add(at as u64);
        self.v1_failed
            <= walked
                .saturating_mul(V1_CRC_BUDGET_PER_BYTE)
                .saturating_add(V1_CRC_BUDGET_BASE)
    }

    /// The next item in `bytes`, or `None` (end of the stream with `eof`, or more bytes
    /// needed without it).
    pub fn next<'a>(&mut self, bytes: &'a [u8], eof: bool) -> Option<Item<'a>> {
        if self.seeking {
            match find_sync(bytes, self.pos) {
                Some(p) => {
                    self.pos = p;
                    self.seeking = false;
                }
                None => {
                    // Keep the last 3 bytes: a sync word may straddle the buffer end.
                    self.pos = if eof {
                        bytes.len()
                    } else {
                        self.pos.max(bytes.len().saturating_sub(3))
                    };
                    return None;
                }
            }
        }
        let offset = self.pos;
        if offset >= bytes.len() {
            return None;
        }
        match decode_inner(&bytes[offset..], self.v1_budget(offset)) {
            Ok((packet, len)) => {
                self.pos = offset + len;
                Some(Item::Packet { offset, packet })
            }
            Err((PacketError::Truncated, _)) if !eof => None,
            Err((error, skip)) => {
                if error == PacketError::BadCrc && bytes.get(offset + 4) == Some(&VERSION_1) {
                    let plen = bytes
                        .get(offset + 28..offset + 32)
                        .map_or(0, |b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as u64);
                    self.v1_failed = self.v1_failed.saturating_add(plen);
                }
                match skip {
                    Some(len) => self.pos = offset + len,
                    None => {
                        self.pos = offset + 1;
                        self.seeking = true;
                    }
                }
                Some(Item::Damage { offset, error })
            }
        }
    }
}

/// The packets of a byte stream, in order, with damage reported and skipped.
///
/// From the start of the stream: a packet that parses ([`decode`]) is yielded and the walk
/// continues right after it; bytes that do not parse are yielded as [`Item::Damage`] at their
/// offset and the walk resynchronises on the next sync word after that offset ([`find_sync`]),
/// or ends if there is none; a version 2 packet whose header CRC checks out but whose payload
/// CRC does not is damage skipped whole. Offsets strictly increase and lie inside the stream.
#[derive(Clone, Debug)]
pub struct Stream<'a> {
    bytes: &'a [u8],
    walk: Walk,
}

impl<'a> Stream<'a> {
    /// The walk through `bytes`, from its first byte.
    pub fn new(bytes: &'a [u8]) -> Self {
        Stream {
            bytes,
            walk: Walk::new(),
        }
    }

    /// Offset where the walk goes on (after damage: where it searches for a sync word from).
    pub fn position(&self) -> usize {
        self.walk.position()
    }
}

impl<'a> Iterator for Stream<'a> {
    type Item = Item<'a>;

    fn next(&mut self) -> Option<Item<'a>> {
        self.walk.next(self.bytes, true)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::row::{Gap, StreamInfo};
    use std::vec;
    use std::vec::Vec;

    fn sample(width: u16) -> (RowHeader, Vec<i16>, Vec<u8>) {
        let w = width as usize;
        let heights: Vec<i16> = (0..w).map(|c| (c as i16).wrapping_mul(331)).collect();
        let valid: Vec<u8> = (0..w.div_ceil(8))
            .map(|i| (i as u8).wrapping_mul(37))
            .collect();
        let header = RowHeader {
            camera: 2,
            n: 4,
            row: -77,
            latch: 1 << 40,
            flags: 0x21,
            width,
        };
        (header, heights, valid)
    }

    /// Encoder and decoder state for `w` columns, intra period 1.
    struct Ends {
        eh: Vec<i16>,
        ev: Vec<u8>,
        dh: Vec<i16>,
        dv: Vec<u8>,
    }
    impl Ends {
        fn new(w: usize) -> Ends {
            Ends {
                eh: vec![0; w],
                ev: vec![0; w.div_ceil(8)],
                dh: vec![0; w],
                dv: vec![0; w.div_ceil(8)],
            }
        }
    }

    #[test]
    fn round_trip() {
        for width in [1u16, 7, 8, 9, 2048] {
            let w = width as usize;
            let (header, heights, mut valid) = sample(width);
            // Bits past W are padding: the codec does not carry them.
            if w % 8 != 0 {
                *valid.last_mut().unwrap() &= (1u8 << (w % 8)) - 1;
            }
            let want: Vec<i16> = (0..w)
                .map(|c| {
                    if valid[c / 8] & (1 << (c % 8)) != 0 {
                        heights[c]
                    } else {
                        0
                    }
                })
                .collect();
            let row = Row {
                header,
                heights: &want,
                valid: &valid,
            };
            let mut ends = Ends::new(w);
            let mut enc =
                codec::Encoder::new(&mut ends.eh, &mut ends.ev, w, STREAM_INTRA_PERIOD).unwrap();
            let mut dec = codec::Decoder::new(&mut ends.dh, &mut ends.dv, w).unwrap();
            let mut buf = vec![0u8; max_packet_len(w)];
            for (compressed, v1) in [(false, false), (true, false), (false, true), (true, true)] {
                let n = match (compressed, v1) {
                    (true, false) => encode(&row, 77, &mut enc, &mut buf),
                    (false, false) => encode_raw(&row, 77, &mut buf),
                    (true, true) => encode_v1(&row, &mut enc, &mut buf),
                    (false, true) => encode_raw_v1(&row, &mut buf),
                }
                .unwrap();
                let (p, used) = decode(&buf[..n]).unwrap();
                assert_eq!(used, n);
                assert_eq!(p.header, header);
                assert_eq!(p.kind, Kind::Row);
                assert_eq!(
                    (p.version, p.seq),
                    if v1 { (VERSION_1, 0) } else { (VERSION, 77) }
                );
                assert_eq!(
                    p.codec,
                    if compressed {
                        CODEC_COMPRESSED
                    } else {
                        CODEC_RAW
                    }
                );
                let mut h2 = vec![0i16; w];
                let mut v2 = vec![0u8; valid.len()];
                p.unpack(&mut dec, &mut h2, &mut v2).unwrap();
                assert_eq!(h2, want);
                assert_eq!(v2, valid);
            }
        }
    }

    #[test]
    fn every_single_bit_flip_is_detected() {
        let (header, heights, valid) = sample(40);
        let row = Row {
            header,
            heights: &heights,
            valid: &valid,
        };
        for v1 in [false, true] {
            let mut buf = vec![0u8; max_packet_len(40)];
            let n = if v1 {
                encode_raw_v1(&row, &mut buf)
            } else {
                encode_raw(&row, 3, &mut buf)
            }
            .unwrap();
            for bit in 0..n * 8 {
                let mut b = buf.clone();
                b[bit / 8] ^= 1 << (bit % 8);
                assert!(decode(&b).is_err(), "bit {bit} undetected");
            }
            for cut in 0..n {
                assert_eq!(decode(&buf[..cut]).err().map(|_| ()), Some(()), "cut {cut}");
            }
        }
    }

    #[test]
    fn resync_finds_next_packet() {
        let (header, heights, valid) = sample(16);
        let row = Row {
            header,
            heights: &heights,
            valid: &valid,
        };
        let mut one = vec![0u8; max_packet_len(16)];
        let n = encode_raw_v1(&row, &mut one).unwrap();
        let mut stream = Vec::new();
        stream.extend_from_slice(b"garbage");
        stream.extend_from_slice(&one[..n]);
        assert_eq!(find_sync(&stream, 0), Some(7));
        assert!(decode(&stream[7..]).is_ok());
        assert_eq!(find_sync(&stream, 8), None);
        // The same stream walked: damage at 0, the packet at 7; then a cut packet.
        stream.extend_from_slice(&one[..n - 1]);
        let items: Vec<_> = Stream::new(&stream)
            .map(|i| match i {
                Item::Packet { offset, .. } => (offset, None),
                Item::Damage { offset, error } => (offset, Some(error)),
            })
            .collect();
        assert_eq!(
            items,
            [
                (0, Some(PacketError::BadSync)),
                (7, None),
                (7 + n, Some(PacketError::Truncated))
            ]
        );
        assert_eq!(Stream::new(&[]).count(), 0);
    }

    /// Raw version 1 packets of width 16 for `rows`.
    fn v1_stream(rows: &[i64]) -> Vec<Vec<u8>> {
        let (mut header, heights, valid) = sample(16);
        let mut buf = vec![0u8; max_packet_len(16)];
        rows.iter()
            .map(|&r| {
                header.row = r;
                let row = Row {
                    header,
                    heights: &heights,
                    valid: &valid,
                };
                let n = encode_raw_v1(&row, &mut buf).unwrap();
                buf[..n].to_vec()
            })
            .collect()
    }

    /// A v2 stream through a `PacketSink`-like sequence: header, rows, a gap, end.
    fn v2_stream(rows: &[i64], gap_after: Option<usize>) -> Vec<Vec<u8>> {
        let (mut header, heights, valid) = sample(16);
        header.flags = 0;
        let mut out = Vec::new();
        let mut buf = vec![0u8; max_packet_len(16)];
        let info = StreamInfo {
            camera: 2,
            n: 4,
            width: 16,
            rows: 40,
            max_step_rows: 10,
            config_hash: 0x1234,
            run_id: 99,
            intra_period: 1,
        };
        let n = encode_stream_header(&info, &mut buf).unwrap();
        out.push(buf[..n].to_vec());
        let mut t = Totals {
            first_row: rows[0],
            last_row: *rows.last().unwrap(),
            ..Totals::default()
        };
        for (i, &r) in rows.iter().enumerate() {
            header.row = r;
            let row = Row {
                header,
                heights: &heights,
                valid: &valid,
            };
            let n = encode_raw(&row, out.len() as u32, &mut buf).unwrap();
            out.push(buf[..n].to_vec());
            t.rows += 1;
            if gap_after == Some(i) {
                let g = Gap {
                    camera: 2,
                    first: r + 1,
                    count: 1000,
                    flags: crate::flags::SKIPPED | crate::flags::ENCODER_FAULT,
                };
                let n = encode_gap(&g, 4, 16, out.len() as u32, &mut buf).unwrap();
                out.push(buf[..n].to_vec());
                t.gap_rows += 1000;
            }
        }
        t.packets = out.len() as u64 + 1;
        let n = encode_end(&t, 2, 4, 16, out.len() as u32, &mut buf).unwrap();
        out.push(buf[..n].to_vec());
        out
    }

    fn track(bytes: &[u8]) -> Summary {
        let mut t = Tracker::new();
        for item in Stream::new(bytes) {
            match item {
                Item::Packet { packet, .. } => {
                    t.packet(&packet);
                }
                Item::Damage { .. } => t.damage(),
            }
        }
        t.summary()
    }

    #[test]
    fn v2_records_round_trip_and_a_clean_stream_is_clean() {
        let pk = v2_stream(&[10, 11, 12, 1013], Some(2));
        let (p, _) = decode(&pk[0]).unwrap();
        let info = p.stream_info().unwrap();
        assert_eq!(
            (info.run_id, info.config_hash, info.width),
            (99, 0x1234, 16)
        );
        assert_eq!(
            (info.rows, info.max_step_rows, info.intra_period),
            (40, 10, 1)
        );
        let (g, _) = decode(&pk[4]).unwrap();
        assert_eq!(g.gap().unwrap().count, 1000);
        assert_eq!(g.seq, 4);
        let (e, _) = decode(pk.last().unwrap()).unwrap();
        let t = e.totals().unwrap();
        assert_eq!((t.packets, t.rows, t.gap_rows), (7, 4, 1000));
        assert_eq!((t.first_row, t.last_row), (10, 1013));
        let s = track(&pk.concat());
        assert!(s.clean(), "{s:?}");
        assert!(s.totals_agree);
        assert_eq!((s.packets, s.rows, s.gaps, s.gap_rows), (7, 4, 1, 1000));
    }

    #[test]
    fn trigger_records_round_trip_and_count_in_the_totals() {
        let mut pk = v2_stream(&[10, 11], None);
        let end = pk.pop().unwrap();
        let mut buf = vec![0u8; max_packet_len(16)];
        // The widest values the fields carry: a negative latch, the counter's top value.
        let triggers = [
            Trigger {
                seq: u32::MAX,
                latch: -7,
            },
            Trigger {
                seq: 0,
                latch: i64::MAX,
            },
        ];
        for t in &triggers {
            let n = encode_trigger(t, 2, 4, 16, pk.len() as u32, &mut buf).unwrap();
            assert_eq!(n, HEADER_LEN + TRAILER_LEN);
            pk.push(buf[..n].to_vec());
        }
        let (p, _) = decode(&pk[3]).unwrap();
        assert_eq!(p.kind, Kind::Trigger);
        assert_eq!(p.trigger(), Some(triggers[0]));
        assert_eq!(decode(&pk[4]).unwrap().0.trigger(), Some(triggers[1]));
        // Other kinds are not triggers, and a trigger is no row.
        assert_eq!(decode(&pk[0]).unwrap().0.trigger(), None);
        let mut h = [0i16; 16];
        let mut v = [0u8; 2];
        let mut r = codec::ReferenceRow::new(16);
        let mut d = r.decoder().unwrap();
        assert_eq!(
            p.unpack(&mut d, &mut h, &mut v),
            Err(PacketError::BadKind(KIND_TRIGGER))
        );
        // A trigger record with a payload is refused before its CRC.
        let mut long = pk[3].clone();
        long[32] = 1;
        assert_eq!(decode(&long).unwrap_err(), PacketError::BadLength);
        // The end packet's total counts them: re-frame it after them.
        let (e, _) = decode(&end).unwrap();
        let mut t = e.totals().unwrap();
        t.packets += 2;
        let n = encode_end(&t, 2, 4, 16, pk.len() as u32, &mut buf).unwrap();
        pk.push(buf[..n].to_vec());
        let s = track(&pk.concat());
        assert!(s.clean(), "{s:?}");
        assert_eq!((s.packets, s.rows, s.triggers), (6, 2, 2));
    }

    #[test]
    fn tracker_reports_missing_duplicated_reordered_truncated_and_wrong_width() {
        let pk = v2_stream(&[0, 1, 2, 3, 4, 5], None);
        // Lost packet 2 (row 1).
        let mut lost = pk.clone();
        lost.remove(2);
        let s = track(&lost.concat());
        assert_eq!((s.missing, s.truncated), (1, true));
        // Duplicate of packet 3 and packets 4, 5 swapped.
        let mut dr = pk.clone();
        dr.insert(4, pk[3].clone());
        dr.swap(5, 6);
        let s = track(&dr.concat());
        assert_eq!((s.duplicated, s.reordered, s.missing), (1, 1, 0), "{s:?}");
        assert!(s.row_order >= 1);
        assert!(!s.clean());
        // Cut before the end packet.
        let s = track(&pk[..pk.len() - 1].concat());
        assert!(s.truncated && s.totals.is_none());
        // A stray packet of another width before a good stream only costs itself.
        let (h, heights, valid) = sample(24);
        let mut buf = vec![0u8; max_packet_len(24)];
        let row = Row {
            header: h,
            heights: &heights,
            valid: &valid,
        };
        let n = encode_raw(&row, 0, &mut buf).unwrap();
        let mut stray = buf[..n].to_vec();
        stray.extend(pk.concat());
        let s = track(&stray);
        // The stream header restarts the sequence bookkeeping: the stray packet is reported as
        // before the header, every good packet counts.
        assert_eq!(
            (s.rows, s.before_header, s.missing, s.duplicated),
            (7, 1, 0, 0)
        );
        assert!(!s.clean());
        // After the header, another width is refused per packet.
        let mut late = pk.clone();
        let n = encode_raw(&row, 3, &mut buf).unwrap();
        late[3] = buf[..n].to_vec();
        let s = track(&late.concat());
        assert_eq!((s.wrong_width, s.rows), (1, 5));
    }

    /// `DPSA\x01\x8a\x00\x00` repeated and repeated `DPSA`: every candidate is rejected from its
    /// header; the walk is linear (no 35 KB CRC per candidate).
    #[test]
    fn hostile_sync_floods_are_rejected_from_the_header() {
        let flood: Vec<u8> = b"DPSA\x01\x8a\x00\x00".repeat(1 << 14);
        let items: Vec<_> = Stream::new(&flood).collect();
        assert_eq!(items.len(), 1 << 14);
        // All but the last 4 (fewer than 32 bytes left: truncated): codec 0x8a never existed.
        assert!(items[..items.len() - 4].iter().all(|i| matches!(
            i,
            Item::Damage {
                error: PacketError::BadCodec(0x8a),
                ..
            }
        )));
        let flood = b"DPSA".repeat(1 << 14);
        assert_eq!(Stream::new(&flood).count(), 1 << 14);
        // Version 2 headers with a plausible length but a wrong header CRC.
        let mut v2 = Vec::new();
        for _ in 0..1000 {
            v2.extend_from_slice(b"DPSA\x02\x01\x00\x04");
            v2.extend_from_slice(&[0; 22]);
            v2.extend_from_slice(&16u16.to_le_bytes());
            v2.extend_from_slice(&20u32.to_le_bytes());
            v2.extend_from_slice(&[0; 4]);
        }
        assert!(Stream::new(&v2).all(|i| matches!(
            i,
            Item::Damage {
                error: PacketError::BadHeaderCrc,
                ..
            }
        )));
    }

    /// Version 1 headers with plausible fields every 32 bytes, each claiming the largest
    /// payload: without a budget every one costs a ~16 KB CRC (quadratic in the flood). The
    /// failed CRC bytes stay within the walk's linear budget, the rest is flagged unchecked,
    /// and a genuine version 1 packet right after the flood still decodes while the budget
    /// allows (here: the flood is short enough that it does).
    #[test]
    fn hostile_version_1_floods_stay_linear() {
        let w = codec::MAX_WIDTH as u16;
        let plen = codec::max_len(w as usize) as u32;
        let mut head = Vec::new();
        head.extend_from_slice(b"DPSA\x01\x01\x00\x04");
        head.extend_from_slice(&[0; 18]);
        head.extend_from_slice(&w.to_le_bytes());
        head.extend_from_slice(&plen.to_le_bytes());
        assert_eq!(head.len(), HEADER_LEN_V1);
        let flood = head.repeat(1 << 15); // 1 MiB
        let mut walk = Walk::new();
        let (mut unchecked, mut bad_crc) = (0u64, 0u64);
        while let Some(item) = walk.next(&flood, true) {
            match item {
                Item::Damage {
                    error: PacketError::Unchecked,
                    ..
                } => unchecked += 1,
                Item::Damage {
                    error: PacketError::BadCrc,
                    ..
                } => bad_crc += 1,
                _ => {}
            }
        }
        let n = flood.len() as u64;
        assert!(walk.v1_failed <= n * V1_CRC_BUDGET_PER_BYTE + V1_CRC_BUDGET_BASE + plen as u64);
        assert!(bad_crc > 0 && unchecked > 0, "{bad_crc} {unchecked}");

        // A real version 1 stream behind a short flood still decodes whole.
        let mut bytes = head.repeat(8);
        let good = v1_stream(&[5, 6, 7]);
        for p in &good {
            bytes.extend_from_slice(p);
        }
        let rows: Vec<i64> = Stream::new(&bytes)
            .filter_map(|i| match i {
                Item::Packet { packet, .. } => Some(packet.header.row),
                _ => None,
            })
            .collect();
        assert_eq!(rows, [5, 6, 7]);
    }

    /// The chunked walk finds exactly the items of the whole-slice walk, whatever the chunking.
    #[test]
    fn chunked_walk_matches_whole_walk() {
        let mut bytes = b"xxDPSAgarbage".to_vec();
        let pk = v2_stream(&[5, 6, 7, 8], Some(1));
        for (i, p) in pk.iter().enumerate() {
            let mut p = p.clone();
            if i == 3 {
                let l = p.len();
                p[l - 6] ^= 1; // payload CRC damage: skipped whole
            }
            bytes.extend(p);
        }
        bytes.extend_from_slice(b"DPS");
        let whole: Vec<(usize, bool)> = Stream::new(&bytes)
            .map(|i| match i {
                Item::Packet { offset, .. } => (offset, true),
                Item::Damage { offset, .. } => (offset, false),
            })
            .collect();
        assert!(whole.contains(&(2, false)));
        for chunk in [1usize, 3, 7, 64, 1000] {
            let mut got = Vec::new();
            let mut walk = Walk::new();
            let mut buf: Vec<u8> = Vec::new();
            let mut base = 0usize;
            let mut fed = 0usize;
            loop {
                let eof = fed == bytes.len();
                while let Some(i) = walk.next(&buf, eof) {
                    got.push(match i {
                        Item::Packet { offset, .. } => (base + offset, true),
                        Item::Damage { offset, .. } => (base + offset, false),
                    });
                }
                if eof {
                    break;
                }
                let drop = walk.position().min(buf.len());
                buf.drain(..drop);
                walk.shift(drop);
                base += drop;
                let end = (fed + chunk).min(bytes.len());
                buf.extend_from_slice(&bytes[fed..end]);
                fed = end;
            }
            assert_eq!(got, whole, "chunk {chunk}");
        }
    }
}
