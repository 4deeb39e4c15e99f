//! Packets: one height row framed with a sync word, a header, a payload and a CRC-32.
//!
//! Layout (all integers little-endian), format version [`VERSION`]:
//!
//! | offset | size | field |
//! | --- | --- | --- |
//! | 0 | 4 | sync word `"DPSA"` (`44 50 53 41`) |
//! | 4 | 1 | format version |
//! | 5 | 1 | payload codec (`0` = raw) |
//! | 6 | 1 | camera id |
//! | 7 | 1 | `n` |
//! | 8 | 8 | board row (i64) |
//! | 16 | 8 | encoder latch of the window's first frame (i64) |
//! | 24 | 2 | row flags (u16) |
//! | 26 | 2 | width `W` (u16) |
//! | 28 | 4 | payload length `L` (u32) |
//! | 32 | L | payload |
//! | 32+L | 4 | CRC-32 (ISO-HDLC, as zlib) of bytes `4 .. 32+L` |
//!
//! Raw payload (codec 0): the validity bitmask, `ceil(W/8)` bytes (bit `c % 8` of byte `c / 8`,
//! 1 = valid), then `W` heights as i16 (LSB units, 0 where invalid).
//!
//! Compressed payload (codec 1, what the pipeline emits): the lossless row code of [`codec`],
//! at most [`codec::max_len`]`(W)` = raw + 2 bytes. Streams use intra period
//! [`STREAM_INTRA_PERIOD`] = 1: every packet decodes on its own, so a damaged packet loses that
//! packet only. The full stream format is in `docs/stream.md`.

pub mod codec;

use crate::row::{Row, RowHeader};
use crc::{Crc, CRC_32_ISO_HDLC};

/// Sync word at the start of every packet.
pub const SYNC: [u8; 4] = *b"DPSA";
/// Stream format version.
pub const VERSION: u8 = 1;
/// Bytes before the payload.
pub const HEADER_LEN: usize = 32;
/// Bytes after the payload.
pub const TRAILER_LEN: usize = 4;
/// Payload codec: raw bitmask + i16 heights.
pub const CODEC_RAW: u8 = 0;
/// Payload codec: the compressed row code of [`codec`].
pub const CODEC_COMPRESSED: u8 = 1;
/// Intra period of a packet stream: 1, every row decodable on its own.
pub const STREAM_INTRA_PERIOD: u32 = 1;
/// Intra period of predicted streams in the codec benchmark (`dpsa codec-bench`): rows are
/// predicted from the previous one, with an intra row every 32 rows.
pub const PREDICTED_INTRA_PERIOD: u32 = 32;

const CRC: Crc<u32> = Crc::<u32>::new(&CRC_32_ISO_HDLC);

/// Raw payload bytes for a row of `width` pixels.
pub const fn raw_payload_len(width: usize) -> usize {
    width.div_ceil(8) + 2 * width
}

/// Largest packet for a row of `width` pixels, any codec.
pub const fn max_packet_len(width: usize) -> usize {
    HEADER_LEN + codec::max_len(width) + TRAILER_LEN
}

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
    /// Payload length does not fit the codec and width.
    BadLength,
    /// CRC mismatch.
    BadCrc,
    /// The compressed payload does not decode (or needs a reference the decoder lacks).
    Codec(codec::CodecError),
}

/// Frames a row into `buf` with a compressed payload (codec 1); returns the packet length.
/// `buf` must hold [`max_packet_len`]`(W)` bytes.
#[inline(never)]
pub fn encode(
    row: &Row<'_>,
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
    Ok(frame(&row.header, CODEC_COMPRESSED, plen, buf))
}

/// Frames a row into `buf` with a raw payload (codec 0); returns the packet length.
pub fn encode_raw(row: &Row<'_>, buf: &mut [u8]) -> Result<usize, PacketError> {
    let w = row.header.width as usize;
    let plen = raw_payload_len(w);
    if buf.len() < HEADER_LEN + plen + TRAILER_LEN
        || row.heights.len() < w
        || row.valid.len() < w.div_ceil(8)
    {
        return Err(PacketError::BufferTooSmall);
    }
    let payload = &mut buf[HEADER_LEN..HEADER_LEN + plen];
    let nb = w.div_ceil(8);
    payload[..nb].copy_from_slice(&row.valid[..nb]);
    for (dst, &h) in payload[nb..].chunks_exact_mut(2).zip(row.heights) {
        dst.copy_from_slice(&h.to_le_bytes());
    }
    Ok(frame(&row.header, CODEC_RAW, plen, buf))
}

/// Writes the header before and the CRC after a payload of `plen` bytes already in place.
fn frame(h: &RowHeader, codec: u8, plen: usize, buf: &mut [u8]) -> usize {
    write_header(h, codec, plen as u32, &mut buf[..HEADER_LEN]);
    let crc = CRC.checksum(&buf[4..HEADER_LEN + plen]);
    buf[HEADER_LEN + plen..HEADER_LEN + plen + TRAILER_LEN].copy_from_slice(&crc.to_le_bytes());
    HEADER_LEN + plen + TRAILER_LEN
}

fn write_header(h: &RowHeader, codec: u8, plen: u32, out: &mut [u8]) {
    out[0..4].copy_from_slice(&SYNC);
    out[4] = VERSION;
    out[5] = codec;
    out[6] = h.camera;
    out[7] = h.n;
    out[8..16].copy_from_slice(&h.row.to_le_bytes());
    out[16..24].copy_from_slice(&h.latch.to_le_bytes());
    out[24..26].copy_from_slice(&h.flags.to_le_bytes());
    out[26..28].copy_from_slice(&h.width.to_le_bytes());
    out[28..32].copy_from_slice(&plen.to_le_bytes());
}

/// A checked packet borrowed from a byte stream.
#[derive(Clone, Copy, Debug)]
pub struct Packet<'a> {
    pub header: RowHeader,
    pub codec: u8,
    pub payload: &'a [u8],
}

impl Packet<'_> {
    /// Unpacks the payload into `heights` (`W`) and `valid` (`ceil(W/8)`); `dec` decodes
    /// compressed payloads (its width must be the packet's).
    pub fn unpack(
        &self,
        dec: &mut codec::Decoder<'_>,
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> Result<(), PacketError> {
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

/// Parses the packet at the start of `buf`; returns it and its length in bytes.
pub fn decode(buf: &[u8]) -> Result<(Packet<'_>, usize), PacketError> {
    if buf.len() < 4 {
        return Err(PacketError::Truncated);
    }
    if buf[0..4] != SYNC {
        return Err(PacketError::BadSync);
    }
    if buf.len() < HEADER_LEN {
        return Err(PacketError::Truncated);
    }
    let u16_at = |i: usize| u16::from_le_bytes([buf[i], buf[i + 1]]);
    let i64_at = |i: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&buf[i..i + 8]);
        i64::from_le_bytes(b)
    };
    if buf[4] != VERSION {
        return Err(PacketError::BadVersion(buf[4]));
    }
    let codec = buf[5];
    let width = u16_at(26);
    let plen = u32::from_le_bytes([buf[28], buf[29], buf[30], buf[31]]) as usize;
    // No payload exceeds the compressed codec's bound (raw + 2 bytes).
    if plen > codec::max_len(width as usize) {
        return Err(PacketError::BadLength);
    }
    let total = HEADER_LEN + plen + TRAILER_LEN;
    if buf.len() < total {
        return Err(PacketError::Truncated);
    }
    let crc = u32::from_le_bytes([
        buf[total - 4],
        buf[total - 3],
        buf[total - 2],
        buf[total - 1],
    ]);
    if CRC.checksum(&buf[4..HEADER_LEN + plen]) != crc {
        return Err(PacketError::BadCrc);
    }
    let header = RowHeader {
        camera: buf[6],
        n: buf[7],
        row: i64_at(8),
        latch: i64_at(16),
        flags: u16_at(24),
        width,
    };
    Ok((
        Packet {
            header,
            codec,
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

/// One step through a packet stream: a packet whose framing and CRC check out, or damage.
#[derive(Clone, Copy, Debug)]
pub enum Item<'a> {
    /// A packet starting at byte `offset`.
    Packet { offset: usize, packet: Packet<'a> },
    /// Bytes at `offset` that are not a packet (bad sync, truncation, bad length, bad CRC, ...).
    /// The stream resynchronises on the next sync word after `offset`.
    Damage { offset: usize, error: PacketError },
}

/// The packets of a byte stream, in order, with damage reported and skipped.
///
/// From the start of the stream: a packet that parses ([`decode`]) is yielded and the walk
/// continues right after it; bytes that do not parse are yielded as [`Item::Damage`] at their
/// offset and the walk resynchronises on the next sync word after that offset ([`find_sync`]),
/// or ends if there is none. Offsets strictly increase and lie inside the stream; every
/// [`Item::Damage`] is one resynchronisation.
#[derive(Clone, Debug)]
pub struct Stream<'a> {
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Stream<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        Stream { bytes, pos: 0 }
    }
}

impl<'a> Iterator for Stream<'a> {
    type Item = Item<'a>;

    fn next(&mut self) -> Option<Item<'a>> {
        let bytes = self.bytes;
        let offset = self.pos;
        if offset >= bytes.len() {
            return None;
        }
        match decode(&bytes[offset..]) {
            Ok((packet, len)) => {
                self.pos = offset + len;
                Some(Item::Packet { offset, packet })
            }
            Err(error) => {
                self.pos = find_sync(bytes, offset + 1).unwrap_or(bytes.len());
                Some(Item::Damage { offset, error })
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
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
            for compressed in [false, true] {
                let n = if compressed {
                    encode(&row, &mut enc, &mut buf)
                } else {
                    encode_raw(&row, &mut buf)
                }
                .unwrap();
                let (p, used) = decode(&buf[..n]).unwrap();
                assert_eq!(used, n);
                assert_eq!(p.header, header);
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
        let mut buf = vec![0u8; max_packet_len(40)];
        let n = encode_raw(&row, &mut buf).unwrap();
        for bit in 0..n * 8 {
            let mut b = buf.clone();
            b[bit / 8] ^= 1 << (bit % 8);
            assert!(decode(&b).is_err(), "bit {bit} undetected");
        }
        for cut in 0..n {
            assert_eq!(decode(&buf[..cut]).err().map(|_| ()), Some(()), "cut {cut}");
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
        let n = encode_raw(&row, &mut one).unwrap();
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
}
