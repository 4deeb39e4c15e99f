//! The feed: frames and calibration as one little-endian byte stream, as a camera feeds a frame
//! grabber.
//!
//! This is what a frame grabber receives, in the order it receives it: the integer
//! [`Config`] and the reference-phase table (its calibration), then every frame as a
//! trigger record (sequence number, latched encoder count) followed by `H` lines of `W`
//! u16 samples. `dpsa` writes it from a recording directory; the QEMU board of the firmware
//! streams it line by line. Both ends use this module, so they agree by construction.
//!
//! ```text
//! header (64 B)   0 "DPSR"  4 version u16 = 1  6 header length u16 = 64
//!                 8 W u16  10 H u16  12 n u8  13 camera u8  14 saturation u16
//!                16 counts_per_pixel U16F16  20 fx u32  24 lsb_per_turn U16F16
//!                28 min_modulation U20F12  32 max_noise_gain U8F8  34 max_step_rows u16
//!                36 frames u32  40 intra period u32  44 run id u64  52..60 zero
//!                60 CRC-32 (ISO-HDLC) of bytes 0..60
//! ref phase      W x u32 binary angles, then CRC-32 of those 4W bytes
//! frame k        16 B trigger record: 0 seq u32, 4 zero u32, 8 latch i64
//!                then H x W x u16 samples, row-major
//! ```
//!
//! The sample data carries no checksum (a camera link checks its own lines); a short file is
//! caught by the reader as a truncation at a named frame and line.

use super::{Config, Trigger};
use crc::{Crc, CRC_32_ISO_HDLC};
use fixed::types::{U16F16, U20F12, U8F8};

/// Magic of a feed.
pub const MAGIC: [u8; 4] = *b"DPSR";
/// Format version.
pub const VERSION: u16 = 1;
/// Bytes of the feed header.
pub const HEADER_LEN: usize = 64;
/// Bytes of a frame's trigger record.
pub const TRIGGER_LEN: usize = 16;

const CRC: Crc<u32> = Crc::<u32>::new(&CRC_32_ISO_HDLC);

/// What the header says besides the configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Header {
    pub cfg: Config,
    /// Frames that follow.
    pub frames: u32,
    /// Codec intra period of the packet stream to emit (1: every packet decodes alone).
    pub intra_period: u32,
    /// Run identity for the packet stream's header (`dpsa` writes the recording's identity,
    /// so a camera's firmware and the host tag the same board alike). Feeds written before it
    /// existed hold 0 here, their reserved bytes.
    pub run_id: u64,
}

/// A malformed header or table.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FeedError {
    Magic,
    Version(u16),
    HeaderLen(u16),
    HeaderCrc,
    /// Reserved bytes not zero.
    Reserved,
    Config(super::ConfigError),
    /// Intra period 0.
    IntraPeriod,
    TableCrc,
    /// A buffer of the wrong size.
    Length,
}

fn u16_at(b: &[u8], i: usize) -> u16 {
    u16::from_le_bytes([b[i], b[i + 1]])
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

impl Header {
    /// The 64 header bytes.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let c = &self.cfg;
        let mut b = [0u8; HEADER_LEN];
        b[0..4].copy_from_slice(&MAGIC);
        b[4..6].copy_from_slice(&VERSION.to_le_bytes());
        b[6..8].copy_from_slice(&(HEADER_LEN as u16).to_le_bytes());
        b[8..10].copy_from_slice(&c.width.to_le_bytes());
        b[10..12].copy_from_slice(&c.rows.to_le_bytes());
        b[12] = c.n;
        b[13] = c.camera;
        b[14..16].copy_from_slice(&c.saturation.to_le_bytes());
        b[16..20].copy_from_slice(&c.counts_per_pixel.to_bits().to_le_bytes());
        b[20..24].copy_from_slice(&c.fx.to_le_bytes());
        b[24..28].copy_from_slice(&c.lsb_per_turn.to_bits().to_le_bytes());
        b[28..32].copy_from_slice(&c.min_modulation.to_bits().to_le_bytes());
        b[32..34].copy_from_slice(&c.max_noise_gain.to_bits().to_le_bytes());
        b[34..36].copy_from_slice(&c.max_step_rows.to_le_bytes());
        b[36..40].copy_from_slice(&self.frames.to_le_bytes());
        b[40..44].copy_from_slice(&self.intra_period.to_le_bytes());
        b[44..52].copy_from_slice(&self.run_id.to_le_bytes());
        let crc = CRC.checksum(&b[..60]);
        b[60..64].copy_from_slice(&crc.to_le_bytes());
        b
    }

    /// Parses and checks a header: magic, version, length, CRC, reserved bytes, and the
    /// configuration ranges ([`Config::validate`]).
    pub fn decode(b: &[u8]) -> Result<Header, FeedError> {
        if b.len() < HEADER_LEN {
            return Err(FeedError::Length);
        }
        if b[0..4] != MAGIC {
            return Err(FeedError::Magic);
        }
        if u16_at(b, 4) != VERSION {
            return Err(FeedError::Version(u16_at(b, 4)));
        }
        if u16_at(b, 6) as usize != HEADER_LEN {
            return Err(FeedError::HeaderLen(u16_at(b, 6)));
        }
        if CRC.checksum(&b[..60]) != u32_at(b, 60) {
            return Err(FeedError::HeaderCrc);
        }
        if b[52..60].iter().any(|&x| x != 0) {
            return Err(FeedError::Reserved);
        }
        let cfg = Config {
            width: u16_at(b, 8),
            rows: u16_at(b, 10),
            n: b[12],
            camera: b[13],
            saturation: u16_at(b, 14),
            counts_per_pixel: U16F16::from_bits(u32_at(b, 16)),
            fx: u32_at(b, 20),
            lsb_per_turn: U16F16::from_bits(u32_at(b, 24)),
            min_modulation: U20F12::from_bits(u32_at(b, 28)),
            max_noise_gain: U8F8::from_bits(u16_at(b, 32)),
            max_step_rows: u16_at(b, 34),
        };
        cfg.validate().map_err(FeedError::Config)?;
        let intra_period = u32_at(b, 40);
        if intra_period == 0 {
            return Err(FeedError::IntraPeriod);
        }
        Ok(Header {
            cfg,
            frames: u32_at(b, 36),
            intra_period,
            run_id: u64::from_le_bytes([b[44], b[45], b[46], b[47], b[48], b[49], b[50], b[51]]),
        })
    }

    /// Bytes of the reference-phase table and its CRC.
    pub fn table_len(&self) -> usize {
        self.cfg.width as usize * 4 + 4
    }

    /// Bytes of one frame: trigger record and samples.
    pub fn frame_len(&self) -> usize {
        TRIGGER_LEN + self.cfg.rows as usize * self.cfg.width as usize * 2
    }
}

/// Writes the reference-phase table and its CRC into `out` (`4 W + 4` bytes).
pub fn encode_table(ref_phase: &[u32], out: &mut [u8]) -> Result<(), FeedError> {
    let n = ref_phase.len() * 4;
    if out.len() != n + 4 {
        return Err(FeedError::Length);
    }
    for (o, p) in out.chunks_exact_mut(4).zip(ref_phase) {
        o.copy_from_slice(&p.to_le_bytes());
    }
    let crc = CRC.checksum(&out[..n]);
    out[n..].copy_from_slice(&crc.to_le_bytes());
    Ok(())
}

/// Checks the table CRC of `b` (`4 W + 4` bytes) and fills `ref_phase` (`W` entries).
pub fn decode_table(b: &[u8], ref_phase: &mut [u32]) -> Result<(), FeedError> {
    let n = ref_phase.len() * 4;
    if b.len() != n + 4 {
        return Err(FeedError::Length);
    }
    if CRC.checksum(&b[..n]) != u32_at(b, n) {
        return Err(FeedError::TableCrc);
    }
    for (p, c) in ref_phase.iter_mut().zip(b.chunks_exact(4)) {
        *p = u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
    }
    Ok(())
}

/// A frame's trigger record in the feed (16 bytes: `seq` u32, 4 zero bytes, `latch` i64).
impl Trigger {
    pub fn encode(&self) -> [u8; TRIGGER_LEN] {
        let mut b = [0u8; TRIGGER_LEN];
        b[0..4].copy_from_slice(&self.seq.to_le_bytes());
        b[8..16].copy_from_slice(&self.latch.to_le_bytes());
        b
    }

    pub fn decode(b: &[u8; TRIGGER_LEN]) -> Result<Trigger, FeedError> {
        if b[4..8] != [0; 4] {
            return Err(FeedError::Reserved);
        }
        let mut l = [0u8; 8];
        l.copy_from_slice(&b[8..16]);
        Ok(Trigger {
            seq: u32_at(b, 0),
            latch: i64::from_le_bytes(l),
        })
    }
}

/// Decodes a line of little-endian u16 samples (`2 W` bytes) in place of `line`.
pub fn decode_line(b: &[u8], line: &mut [u16]) -> Result<(), FeedError> {
    if b.len() != line.len() * 2 {
        return Err(FeedError::Length);
    }
    for (s, c) in line.iter_mut().zip(b.chunks_exact(2)) {
        *s = u16::from_le_bytes([c[0], c[1]]);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> Header {
        Header {
            cfg: Config {
                width: 2048,
                rows: 40,
                n: 4,
                camera: 2,
                counts_per_pixel: U16F16::from_bits(10 << 16 | 0x4000),
                fx: 1 << 27,
                lsb_per_turn: U16F16::from_num(2000),
                saturation: 4095,
                min_modulation: U20F12::from_num(60),
                max_noise_gain: U8F8::from_num(2),
                max_step_rows: 10,
            },
            frames: 277,
            intra_period: 1,
            run_id: 0x0123_4567_89ab_cdef,
        }
    }

    #[test]
    fn header_round_trip_and_every_flipped_bit_is_caught() {
        let h = header();
        let b = h.encode();
        assert_eq!(Header::decode(&b), Ok(h));
        for bit in 0..HEADER_LEN * 8 {
            let mut c = b;
            c[bit / 8] ^= 1 << (bit % 8);
            assert!(Header::decode(&c).is_err(), "bit {bit}");
        }
        assert_eq!(Header::decode(&b[..63]), Err(FeedError::Length));
    }

    #[test]
    fn header_with_good_crc_but_bad_config_is_refused() {
        let mut h = header();
        h.cfg.n = 9;
        assert_eq!(
            Header::decode(&h.encode()),
            Err(FeedError::Config(super::super::ConfigError::Count))
        );
        let mut h = header();
        h.intra_period = 0;
        assert_eq!(Header::decode(&h.encode()), Err(FeedError::IntraPeriod));
    }

    #[test]
    fn table_and_trigger_round_trip() {
        let t = [0u32, 1, 0xFFFF_FFFF, 0x8000_0000, 12345];
        let mut b = [0u8; 24];
        encode_table(&t, &mut b).unwrap();
        let mut back = [0u32; 5];
        decode_table(&b, &mut back).unwrap();
        assert_eq!(back, t);
        b[7] ^= 4;
        assert_eq!(decode_table(&b, &mut back), Err(FeedError::TableCrc));
        let tr = Trigger {
            seq: 0xFFFF_FFFF,
            latch: -5,
        };
        assert_eq!(Trigger::decode(&tr.encode()), Ok(tr));
        let mut e = tr.encode();
        e[5] = 1;
        assert_eq!(Trigger::decode(&e), Err(FeedError::Reserved));
    }
}
