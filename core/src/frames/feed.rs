//! The feed: frames and calibration as one little-endian byte stream, as a camera feeds a frame
//! grabber.
//!
//! This is what a frame grabber receives, in the order it receives it: the integer
//! [`Config`], the reference-phase table and, optionally, the per-column height-scale table
//! (its calibration), then every frame as a trigger record (sequence number, latched encoder
//! count) followed by `H` lines of `W` u16 samples. `dpsa` writes it from a recording directory; the QEMU board of the firmware
//! streams it line by line. Both ends use this module, so they agree by construction.
//!
//! ```text
//! header (64 B)   0 "DPSR"  4 version u16 = 1  6 header length u16 = 64
//!                 8 W u16  10 H u16  12 n u8  13 camera u8  14 saturation u16
//!                16 counts_per_pixel U16F16  20 fx u32  24 lsb_per_turn U16F16
//!                28 min_modulation U20F12  32 max_noise_gain U8F8  34 max_step_rows u16
//!                36 frames u32  40 intra period u32  44 run id u64
//!                52 flags u8 (bit 0: a height-scale table follows; bit 1: lines are
//!                   Mono12p; others zero)
//!                53 height-scale exponent u8 (0..=15; zero without the table)  54..60 zero
//!                60 CRC-32 (ISO-HDLC) of bytes 0..60
//! ref phase      W x u32 binary angles, then CRC-32 of those 4W bytes
//! height scale   only with flag bit 0: W x u16 mantissas (column c: LSB per turn, Q16.16
//!                bits = mantissa << exponent; see `height::ColumnScale`), then CRC-32 of
//!                those 2W bytes
//! frame k        16 B trigger record: 0 seq u32, 4 zero u32, 8 latch i64
//!                then H lines, row-major: W x u16 samples each, or with flag bit 1
//!                Mono12p, 3 ceil(W/2) bytes each (`frames::mono12p`)
//! ```
//!
//! Mono12p lines (flag bit 1) are what a 12-bit camera sends; a feed may use them only when
//! `saturation <= 4095` (every sample that decides a pixel fits 12 bits): the pipeline then
//! keeps them as they arrive ([`crate::Pipeline::push_packed_line`]).
//!
//! Feeds written before the height-scale table existed hold zeros in bytes 52..60 (then
//! reserved): they read as feeds without the table, whose heights use the uniform
//! `lsb_per_turn`. The version stays 1.
//!
//! The sample data carries no checksum (a camera link checks its own lines); a short file is
//! caught by the reader as a truncation at a named frame and line.

use super::{Config, Trigger};
use crate::crc32;
use crate::height::{ColumnScale, ColumnScaleError, MAX_COLUMN_SHIFT};
use fixed::types::{U16F16, U20F12, U8F8};

/// Magic of a feed.
pub const MAGIC: [u8; 4] = *b"DPSR";
/// Format version.
pub const VERSION: u16 = 1;
/// Bytes of the feed header.
pub const HEADER_LEN: usize = 64;
/// Bytes of a frame's trigger record.
pub const TRIGGER_LEN: usize = 16;

/// What the header says besides the configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Header {
    /// The pipeline configuration.
    pub cfg: Config,
    /// Frames that follow.
    pub frames: u32,
    /// Codec intra period of the packet stream to emit (1: every packet decodes alone).
    pub intra_period: u32,
    /// Run identity for the packet stream's header (`dpsa` writes the recording's identity,
    /// so a camera's firmware and the host tag the same board alike). Feeds written before it
    /// existed hold 0 here, their reserved bytes.
    pub run_id: u64,
    /// `Some(exponent)` when a per-column height-scale table follows the reference-phase
    /// table ([`crate::height::ColumnScale`]); `None`: every column uses
    /// `cfg.lsb_per_turn`.
    pub column_scale: Option<u8>,
    /// Lines are Mono12p ([`super::mono12p`]), not u16 (only with `saturation <= 4095`).
    pub mono12p: bool,
}

/// Header byte 52: flag bit of the height-scale table.
const FLAG_SCALE_TABLE: u8 = 1;
/// Header byte 52: flag bit of Mono12p lines.
const FLAG_MONO12P: u8 = 2;

/// A malformed header or table.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FeedError {
    /// The magic is not `DPSR`: not a feed.
    Magic,
    /// A feed version other than [`VERSION`].
    Version(u16),
    /// A header length other than [`HEADER_LEN`].
    HeaderLen(u16),
    /// The header CRC does not match.
    HeaderCrc,
    /// Reserved bytes not zero.
    Reserved,
    /// The configuration in the header is out of range.
    Config(super::ConfigError),
    /// Intra period 0.
    IntraPeriod,
    /// The reference-phase table's CRC does not match.
    TableCrc,
    /// The per-column height-scale table's CRC does not match.
    ScaleCrc,
    /// The per-column height-scale table (or its exponent) is out of range.
    ColumnScale(ColumnScaleError),
    /// A buffer of the wrong size.
    Length,
    /// Mono12p lines with a saturation level above 4095.
    Mono12p,
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
        if let Some(shift) = self.column_scale {
            b[52] = FLAG_SCALE_TABLE;
            b[53] = shift;
        }
        if self.mono12p {
            b[52] |= FLAG_MONO12P;
        }
        let crc = crc32::checksum(&b[..60]);
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
        if crc32::checksum(&b[..60]) != u32_at(b, 60) {
            return Err(FeedError::HeaderCrc);
        }
        let column_scale = match b[52] & !FLAG_MONO12P {
            0 if b[53] == 0 => None,
            FLAG_SCALE_TABLE if b[53] <= MAX_COLUMN_SHIFT => Some(b[53]),
            FLAG_SCALE_TABLE => {
                return Err(FeedError::ColumnScale(ColumnScaleError::Shift(b[53])));
            }
            _ => return Err(FeedError::Reserved),
        };
        let mono12p = b[52] & FLAG_MONO12P != 0;
        if b[54..60].iter().any(|&x| x != 0) {
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
        if mono12p && cfg.saturation > super::mono12p::MAX {
            return Err(FeedError::Mono12p);
        }
        let intra_period = u32_at(b, 40);
        if intra_period == 0 {
            return Err(FeedError::IntraPeriod);
        }
        Ok(Header {
            cfg,
            frames: u32_at(b, 36),
            intra_period,
            run_id: u64::from_le_bytes([b[44], b[45], b[46], b[47], b[48], b[49], b[50], b[51]]),
            column_scale,
            mono12p,
        })
    }

    /// Bytes of the reference-phase table and its CRC.
    pub fn table_len(&self) -> usize {
        self.cfg.width as usize * 4 + 4
    }

    /// Bytes of the per-column height-scale table and its CRC (0 without the table).
    pub fn scale_table_len(&self) -> usize {
        match self.column_scale {
            Some(_) => self.cfg.width as usize * 2 + 4,
            None => 0,
        }
    }

    /// Byte offset of the first frame: header and tables.
    pub fn frames_at(&self) -> usize {
        HEADER_LEN + self.table_len() + self.scale_table_len()
    }

    /// Bytes of one line: `2 W`, or `3 ceil(W/2)` for Mono12p.
    pub fn line_len(&self) -> usize {
        let w = self.cfg.width as usize;
        if self.mono12p {
            super::mono12p::packed_len(w)
        } else {
            2 * w
        }
    }

    /// Bytes of one frame: trigger record and lines.
    pub fn frame_len(&self) -> usize {
        TRIGGER_LEN + self.cfg.rows as usize * self.line_len()
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
    let crc = crc32::checksum(&out[..n]);
    out[n..].copy_from_slice(&crc.to_le_bytes());
    Ok(())
}

/// Checks the table CRC of `b` (`4 W + 4` bytes) and fills `ref_phase` (`W` entries).
pub fn decode_table(b: &[u8], ref_phase: &mut [u32]) -> Result<(), FeedError> {
    let n = ref_phase.len() * 4;
    if b.len() != n + 4 {
        return Err(FeedError::Length);
    }
    if crc32::checksum(&b[..n]) != u32_at(b, n) {
        return Err(FeedError::TableCrc);
    }
    for (p, c) in ref_phase.iter_mut().zip(b.chunks_exact(4)) {
        *p = u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
    }
    Ok(())
}

/// Writes the per-column height-scale mantissas and their CRC into `out` (`2 W + 4` bytes).
pub fn encode_scale_table(mantissa: &[u16], out: &mut [u8]) -> Result<(), FeedError> {
    let n = mantissa.len() * 2;
    if out.len() != n + 4 {
        return Err(FeedError::Length);
    }
    for (o, m) in out.chunks_exact_mut(2).zip(mantissa) {
        o.copy_from_slice(&m.to_le_bytes());
    }
    let crc = crc32::checksum(&out[..n]);
    out[n..].copy_from_slice(&crc.to_le_bytes());
    Ok(())
}

/// Checks the height-scale table `b` (`2 W + 4` bytes) of a feed with `header` (which must
/// announce the table): CRC, then the values against the configuration
/// ([`ColumnScale::check`]); fills `mantissa` (`W` entries).
pub fn decode_scale_table(
    b: &[u8],
    header: &Header,
    mantissa: &mut [u16],
) -> Result<(), FeedError> {
    let Some(shift) = header.column_scale else {
        return Err(FeedError::Length);
    };
    let n = mantissa.len() * 2;
    if b.len() != n + 4 || mantissa.len() != header.cfg.width as usize {
        return Err(FeedError::Length);
    }
    if crc32::checksum(&b[..n]) != u32_at(b, n) {
        return Err(FeedError::ScaleCrc);
    }
    for (m, c) in mantissa.iter_mut().zip(b.chunks_exact(2)) {
        *m = u16::from_le_bytes([c[0], c[1]]);
    }
    ColumnScale::new(shift, mantissa)
        .check(&header.cfg)
        .map_err(FeedError::ColumnScale)
}

/// A frame's trigger record in the feed (16 bytes: `seq` u32, 4 zero bytes, `latch` i64).
impl Trigger {
    /// The 16-byte record of this trigger.
    pub fn encode(&self) -> [u8; TRIGGER_LEN] {
        let mut b = [0u8; TRIGGER_LEN];
        b[0..4].copy_from_slice(&self.seq.to_le_bytes());
        b[8..16].copy_from_slice(&self.latch.to_le_bytes());
        b
    }

    /// The trigger of a 16-byte record ([`FeedError::Reserved`] when bytes 4..8 are not zero).
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
            column_scale: None,
            mono12p: false,
        }
    }

    #[test]
    fn header_round_trip_and_every_flipped_bit_is_caught() {
        for column_scale in [None, Some(0), Some(11), Some(15)] {
            let h = Header {
                column_scale,
                ..header()
            };
            let b = h.encode();
            assert_eq!(Header::decode(&b), Ok(h));
            for bit in 0..HEADER_LEN * 8 {
                let mut c = b;
                c[bit / 8] ^= 1 << (bit % 8);
                assert!(Header::decode(&c).is_err(), "bit {bit}");
            }
            assert_eq!(Header::decode(&b[..63]), Err(FeedError::Length));
        }
    }

    /// Re-seals a header whose bytes were edited (a new CRC), to test the checks behind it.
    fn reseal(mut b: [u8; HEADER_LEN]) -> [u8; HEADER_LEN] {
        let crc = crc32::checksum(&b[..60]);
        b[60..64].copy_from_slice(&crc.to_le_bytes());
        b
    }

    #[test]
    fn old_feeds_read_and_table_bytes_are_checked() {
        // A feed of before the table: bytes 52..60 zero, the layout of version 1 unchanged.
        let h = header();
        let b = h.encode();
        assert!(b[52..60].iter().all(|&x| x == 0));
        let d = Header::decode(&b).unwrap();
        assert_eq!((d.column_scale, d.scale_table_len()), (None, 0));
        assert_eq!(d.frames_at(), HEADER_LEN + 2048 * 4 + 4);
        let t = Header {
            column_scale: Some(11),
            ..h
        };
        assert_eq!(t.frames_at(), HEADER_LEN + 2048 * 4 + 4 + 2048 * 2 + 4);
        // An exponent without the flag, an unknown flag, a too large exponent, later bytes.
        let mut e = b;
        e[53] = 3;
        assert_eq!(Header::decode(&reseal(e)), Err(FeedError::Reserved));
        let mut e = b;
        e[52] = 4;
        assert_eq!(Header::decode(&reseal(e)), Err(FeedError::Reserved));
        // Mono12p lines: flag bit 1, three bytes per pair; only up to a saturation of 4095.
        let mut e = b;
        e[52] = 2;
        let m = Header::decode(&reseal(e)).unwrap();
        assert!(m.mono12p && h.cfg.saturation <= 4095);
        assert_eq!((m.line_len(), h.line_len()), (3 * 1024, 2 * 2048));
        assert_eq!(m.frame_len(), TRIGGER_LEN + 40 * 3 * 1024);
        assert_eq!(Header::decode(&m.encode()), Ok(m));
        let mut c = h;
        c.cfg.saturation = 4096;
        c.mono12p = true;
        assert_eq!(Header::decode(&c.encode()), Err(FeedError::Mono12p));
        let mut e = b;
        e[52] = 1;
        e[53] = 16;
        assert_eq!(
            Header::decode(&reseal(e)),
            Err(FeedError::ColumnScale(ColumnScaleError::Shift(16)))
        );
        let mut e = b;
        e[57] = 1;
        assert_eq!(Header::decode(&reseal(e)), Err(FeedError::Reserved));
    }

    #[test]
    fn scale_table_round_trip_and_refusals() {
        let mut h = header();
        h.cfg.width = 6;
        // 2000 LSB per turn, columns +-2 %: exponent 11, mantissas near 64000.
        let k: [U16F16; 6] =
            core::array::from_fn(|c| U16F16::from_num(2000.0 * (0.98 + 0.008 * c as f64)));
        let mut m = [0u16; 6];
        let shift = ColumnScale::encode(&k, &mut m).unwrap();
        h.column_scale = Some(shift);
        let h = Header::decode(&h.encode()).unwrap();
        let mut b = [0u8; 16];
        assert_eq!(h.scale_table_len(), b.len());
        encode_scale_table(&m, &mut b).unwrap();
        let mut back = [0u16; 6];
        decode_scale_table(&b, &h, &mut back).unwrap();
        assert_eq!(back, m);
        // Every flipped bit is a CRC error.
        for bit in 0..b.len() * 8 {
            let mut c = b;
            c[bit / 8] ^= 1 << (bit % 8);
            assert_eq!(
                decode_scale_table(&c, &h, &mut back),
                Err(FeedError::ScaleCrc),
                "bit {bit}"
            );
        }
        // Wrong lengths; a header without the table.
        assert_eq!(
            decode_scale_table(&b[..15], &h, &mut back),
            Err(FeedError::Length)
        );
        assert_eq!(
            decode_scale_table(&b, &h, &mut [0u16; 5]),
            Err(FeedError::Length)
        );
        let plain = Header {
            column_scale: None,
            ..h
        };
        assert_eq!(
            decode_scale_table(&b, &plain, &mut back),
            Err(FeedError::Length)
        );
        // A zero entry and an absurd one (3x the configuration's scale), with a good CRC.
        for (col, bad) in [(2usize, 0u16), (4, 0xFFFF)] {
            let mut mm = m;
            mm[col] = bad;
            let mut h3 = h;
            h3.cfg.lsb_per_turn = U16F16::from_num(if bad == 0 { 2000 } else { 700 });
            encode_scale_table(&mm, &mut b).unwrap();
            assert_eq!(
                decode_scale_table(&b, &h3, &mut back),
                Err(FeedError::ColumnScale(ColumnScaleError::Range {
                    column: if bad == 0 { col as u16 } else { 0 }
                }))
            );
        }
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
