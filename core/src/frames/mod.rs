//! Frames in: configuration, frame triggers, encoder latch to row offset and phase shift, and
//! the registration of board rows.
//!
//! The configuration is all integers, converted once from the calibration (on the host, from
//! the recording manifest). The host and the firmware run on the same `Config` values, which
//! is what makes their outputs bit-identical. A Q-format field is a [`fixed`] type
//! (`U16F16`, `U20F12`, `U8F8`): the format is in the type, the bits are the integer the
//! arithmetic uses (`to_bits()`, taken once per configuration, never per pixel). Binary
//! angles (`fx`, the reference phase) stay `u32`: see [`crate::phase`].
//!
//! - [`feed`]: the byte format a frame grabber is fed (configuration, reference phase, frames).
//! - [`registration`]: which board rows a frame admits or skips, and where open rows live.

use crate::height::ColumnScale;
use crate::solve::{MAX_N, MIN_N};
use fixed::types::{U16F16, U20F12, U8F8};

pub mod feed;
pub mod mono12p;
pub mod registration;

/// Largest row offset magnitude ([`Config::offset`] clamps to it): 2^62 rows.
pub const MAX_OFFSET: i64 = 1 << 62;

/// FNV-1a 64 of `bytes` (the hash of [`Config::hash`]; `dpsa` also derives a recording's run
/// identity with it).
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h = Fnv64::new();
    h.bytes(bytes);
    h.0
}

/// FNV-1a, 64 bit (offset basis `0xcbf29ce484222325`, prime `0x100000001b3`).
struct Fnv64(u64);

impl Fnv64 {
    fn new() -> Self {
        Fnv64(0xcbf2_9ce4_8422_2325)
    }
    fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 = (self.0 ^ x as u64).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
}

/// A frame's trigger: the camera's frame counter and the encoder count latched at its trigger.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Trigger {
    /// Camera frame counter (consecutive frames have consecutive values, mod 2^32).
    pub seq: u32,
    /// Encoder count latched by the trigger (counts).
    pub latch: i64,
}

/// Processing configuration (geometry, calibration, thresholds) in integer and fixed-point form.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Config {
    /// Columns `W`.
    pub width: u16,
    /// Rows per frame `H`.
    pub rows: u16,
    /// Observations per board row (3..=8).
    pub n: u8,
    /// Camera id written into packets.
    pub camera: u8,
    /// Encoder counts per pixel of travel (Q16.16, must be > 0).
    pub counts_per_pixel: U16F16,
    /// Fringe phase advance per image row `2 pi f_x`, binary angle.
    pub fx: u32,
    /// Height LSBs per fringe turn `T_z / lsb` (Q16.16, `0 < lsb_per_turn < 32768`).
    pub lsb_per_turn: U16F16,
    /// A sample `>= saturation` (DN) is saturated.
    pub saturation: u16,
    /// Minimum modulation `C` of a valid pixel, DN (Q20.12).
    pub min_modulation: U20F12,
    /// Largest accepted window noise gain (Q8.8, `1..=8`).
    pub max_noise_gain: U8F8,
    /// Largest number of new board rows admitted per frame.
    pub max_step_rows: u16,
}

/// A configuration value out of range.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConfigError {
    /// [`Config::width`] is 0.
    Width,
    /// [`Config::rows`] is 0.
    Rows,
    /// [`Config::n`] is outside `3..=8`.
    Count,
    /// [`Config::counts_per_pixel`] is 0.
    CountsPerPixel,
    /// [`Config::lsb_per_turn`] is 0 or not below 32768.
    LsbPerTurn,
    /// [`Config::max_noise_gain`] is outside `1..=8`.
    NoiseGain,
    /// [`Config::max_step_rows`] is outside `1..=rows`.
    MaxStep,
}

impl Config {
    /// Checks every field against the ranges the arithmetic relies on.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.width == 0 {
            return Err(ConfigError::Width);
        }
        if self.rows == 0 {
            return Err(ConfigError::Rows);
        }
        if !(MIN_N..=MAX_N).contains(&(self.n as usize)) {
            return Err(ConfigError::Count);
        }
        if self.counts_per_pixel.to_bits() == 0 {
            return Err(ConfigError::CountsPerPixel);
        }
        let lsb_per_turn = self.lsb_per_turn.to_bits();
        if lsb_per_turn == 0 || lsb_per_turn >= 1 << 31 {
            return Err(ConfigError::LsbPerTurn);
        }
        if !(256..=2048).contains(&self.max_noise_gain.to_bits()) {
            return Err(ConfigError::NoiseGain);
        }
        if self.max_step_rows == 0 || self.max_step_rows > self.rows {
            return Err(ConfigError::MaxStep);
        }
        Ok(())
    }

    /// Board-row offset of a frame: `floor(latch / cpp + 1/2)`, exact in integers, clamped to
    /// `[-MAX_OFFSET, MAX_OFFSET]` (so `offset + rows` and differences of offsets never
    /// overflow an i64, whatever the latch and `cpp`; an offset that far out is an encoder
    /// fault anyway).
    pub fn offset(&self, latch: i64) -> i64 {
        let q = (self.counts_per_pixel.to_bits() as i128).max(1);
        let num = ((latch as i128) << 17) + q;
        crate::wide::div_floor(num, 2 * q as u128).clamp(-(MAX_OFFSET as i128), MAX_OFFSET as i128)
            as i64
    }

    /// FNV-1a 64 of the configuration and the reference-phase table, the stream header's
    /// `config_hash`: the fields in declaration order (`width`, `rows` u16; `n`, `camera` u8;
    /// `counts_per_pixel`, `fx`, `lsb_per_turn` u32; `saturation` u16; `min_modulation`
    /// u32; `max_noise_gain`, `max_step_rows` u16; the fixed-point fields by their bits), then
    /// the `W` reference phases as u32, all little-endian.
    pub fn hash(&self, ref_phase: &[u32]) -> u64 {
        self.hash_with(ref_phase, None)
    }

    /// [`Config::hash`] with the per-column height scale: `None` gives exactly
    /// [`Config::hash`]; `Some(table)` continues it with the table's exponent (one byte) and
    /// its `W` mantissas as u16, little-endian.
    pub fn hash_with(&self, ref_phase: &[u32], columns: Option<&ColumnScale<'_>>) -> u64 {
        let mut h = Fnv64::new();
        h.bytes(&self.width.to_le_bytes());
        h.bytes(&self.rows.to_le_bytes());
        h.bytes(&[self.n, self.camera]);
        h.bytes(&self.counts_per_pixel.to_bits().to_le_bytes());
        h.bytes(&self.fx.to_le_bytes());
        h.bytes(&self.lsb_per_turn.to_bits().to_le_bytes());
        h.bytes(&self.saturation.to_le_bytes());
        h.bytes(&self.min_modulation.to_bits().to_le_bytes());
        h.bytes(&self.max_noise_gain.to_bits().to_le_bytes());
        h.bytes(&self.max_step_rows.to_le_bytes());
        for p in ref_phase {
            h.bytes(&p.to_le_bytes());
        }
        if let Some(t) = columns {
            h.bytes(&[t.shift()]);
            for m in t.mantissa() {
                h.bytes(&m.to_le_bytes());
            }
        }
        h.0
    }

    /// Fringe phase advance over `rows` image rows, `2 pi f_x rows`, as a binary angle (wrapping).
    #[inline(always)]
    pub fn row_phase(&self, rows: i64) -> u32 {
        (rows as u32).wrapping_mul(self.fx)
    }

    /// Phase shift of a frame whose row offset is `offset_delta` rows past the window's first
    /// frame: `theta_j = -(o_j - o_0) 2 pi f_x`, as a binary angle.
    #[inline(always)]
    pub fn shift(&self, offset_delta: i64) -> u32 {
        self.row_phase(offset_delta).wrapping_neg()
    }

    /// The shifts `theta_j` of a window from its frames' row offsets `o_0 .. o_{n-1}`
    /// (`shifts.len() >= offsets.len()`; the first `offsets.len()` entries are written).
    #[inline(always)]
    pub fn shifts(&self, offsets: &[i64], shifts: &mut [u32]) {
        let o0 = offsets.first().copied().unwrap_or(0);
        for (s, &o) in shifts.iter_mut().zip(offsets) {
            *s = self.shift(o.wrapping_sub(o0));
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    fn cfg(cpp: f64) -> Config {
        Config {
            width: 8,
            rows: 8,
            n: 4,
            camera: 0,
            counts_per_pixel: U16F16::from_bits((cpp * 65536.0) as u32),
            fx: 1 << 27,
            lsb_per_turn: U16F16::from_num(2000),
            saturation: 4095,
            min_modulation: U20F12::ZERO,
            max_noise_gain: U8F8::from_num(2),
            max_step_rows: 4,
        }
    }

    #[test]
    fn offset_rounds_half_up_like_f64() {
        for &cpp in &[10.25, 1.0, 0.5, 7.015625, 3.0 + 1.0 / 65536.0] {
            let c = cfg(cpp);
            let cppq = c.counts_per_pixel.to_bits() as f64 / 65536.0;
            for e in -5000i64..5000 {
                let want = (e as f64 / cppq + 0.5).floor() as i64;
                assert_eq!(c.offset(e), want, "cpp {cpp} e {e}");
            }
        }
    }

    #[test]
    fn offset_extremes_do_not_overflow() {
        let c = cfg(1.0 / 65536.0);
        assert_eq!(c.offset(i64::MAX >> 17), (i64::MAX >> 17) << 16);
        assert_eq!(c.offset(i64::MIN), -MAX_OFFSET);
        assert_eq!(c.offset(i64::MAX), MAX_OFFSET);
        let c = cfg(1e-3);
        assert_eq!(c.offset(i64::MAX), MAX_OFFSET);
    }

    #[test]
    fn hash_covers_config_and_table() {
        let c = cfg(10.25);
        let h = c.hash(&[1, 2, 3]);
        assert_ne!(h, c.hash(&[1, 2, 4]));
        let mut d = c;
        d.max_step_rows = 3;
        assert_ne!(h, d.hash(&[1, 2, 3]));
        // FNV-1a 64 of nothing is the offset basis; of "a" the published value.
        let mut f = Fnv64::new();
        assert_eq!(f.0, 0xcbf29ce484222325);
        f.bytes(b"a");
        assert_eq!(f.0, 0xaf63dc4c8601ec8c);
    }
}
