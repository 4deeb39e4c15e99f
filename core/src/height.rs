//! Phase to height, and the per-pixel validity mask.

use crate::accumulate::Acc;
use crate::frames::Config;
use crate::phase::atan2;

/// Largest height magnitude written (LSB); `i16::MIN` is never produced.
pub const H_MAX: i32 = i16::MAX as i32;

/// Why a pixel has no height.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Invalid {
    /// A sample was at or above the saturation level.
    Saturated,
    /// Fringe modulation `C` below the threshold.
    LowModulation,
}

/// Constants of the phase-to-height step, derived once from [`Config`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Scale {
    /// Height LSBs per turn, Q16.16.
    k: i64,
    /// `(min_modulation in Q12)^2`: threshold on `C^2` in DN^2 * 2^24.
    min_c2: u64,
}

impl Scale {
    pub fn new(cfg: &Config) -> Scale {
        Scale::from_parts(cfg.lsb_per_turn_q16, cfg.min_modulation_q12)
    }

    /// From LSB per turn (Q16.16) and the modulation threshold (DN, Q20.12).
    pub fn from_parts(lsb_per_turn_q16: u32, min_modulation_q12: u32) -> Scale {
        let m = min_modulation_q12 as u64;
        Scale { k: lsb_per_turn_q16 as i64, min_c2: m.saturating_mul(m) }
    }

    /// The pixel's phase `Phi = atan2(v_3, v_2)` if it is valid (not saturated, modulated).
    ///
    /// Modulation: `v >> 12` is DN in Q12, clamped to i32; `C^2` in u64 Q24 (`< 2^63`).
    #[inline(always)]
    pub fn phase(&self, acc: &Acc) -> Result<u32, Invalid> {
        if acc.saturated {
            return Err(Invalid::Saturated);
        }
        let x = sat_i32(acc.v2 >> 12) as i64;
        let y = sat_i32(acc.v3 >> 12) as i64;
        if ((x * x) as u64 + (y * y) as u64) < self.min_c2 || (x == 0 && y == 0) {
            return Err(Invalid::LowModulation);
        }
        Ok(atan2(acc.v3, acc.v2))
    }

    /// Height of one pixel from its accumulated `v`, relative to the reference phase `phi_r`.
    ///
    /// Formats at each step:
    /// - validity and `Phi = atan2(v_3, v_2)` from [`Scale::phase`] (binary angle, error
    ///   <= 2e-6 rad, see [`crate::phase`]).
    /// - `D = Phi - phi_r`, wrapping, read as i32: `[-pi, pi)` in units of `2 pi / 2^32`.
    /// - `h = round(D * k / 2^48)` with `k` = LSB per turn in Q16.16: i64 product `< 2^62`,
    ///   rounded half up, clamped to `+-32767`.
    #[inline(always)]
    pub fn pixel(&self, acc: &Acc, phi_r: u32) -> Result<i16, Invalid> {
        let d = self.phase(acc)?.wrapping_sub(phi_r) as i32 as i64;
        let h = (d * self.k + (1 << 47)) >> 48;
        Ok(h.clamp(-H_MAX as i64, H_MAX as i64) as i16)
    }
}

fn sat_i32(x: i64) -> i32 {
    x.clamp(i32::MIN as i64 + 1, i32::MAX as i64) as i32
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::phase::from_rad;
    use std::f64::consts::PI;

    fn cfg(lsb_per_turn: f64, min_mod: f64) -> Config {
        Config {
            width: 8,
            rows: 8,
            n: 4,
            camera: 0,
            counts_per_pixel_q16: 1 << 16,
            fx: 1 << 27,
            lsb_per_turn_q16: (lsb_per_turn * 65536.0).round() as u32,
            saturation: 4095,
            min_modulation_q12: (min_mod * 4096.0).round() as u32,
            max_noise_gain_q8: 512,
            max_step: 4,
        }
    }

    fn acc(c: f64, phi: f64) -> Acc {
        let q = (1u64 << 24) as f64;
        Acc { v2: (c * phi.cos() * q) as i64, v3: (c * phi.sin() * q) as i64, saturated: false }
    }

    #[test]
    fn height_matches_f64_within_one_lsb() {
        let s = Scale::new(&cfg(2000.37, 10.0));
        let mut worst = 0f64;
        for k in 0..20_000 {
            let phi = -PI + 2.0 * PI * (k as f64 + 0.5) / 20_000.0;
            let r = 0.77f64;
            let h = s.pixel(&acc(700.0, phi + r), from_rad(r)).unwrap();
            let exact = phi / (2.0 * PI) * 2000.37;
            worst = worst.max((h as f64 - exact).abs());
        }
        // Rounding (0.5) plus phase error (2e-6 rad -> 6e-4 LSB).
        assert!(worst <= 0.5 + 1e-3, "worst {worst}");
    }

    #[test]
    fn wraps_and_clamps() {
        // The largest scale Config accepts (< 2^15 LSB per turn) keeps +-pi inside i16.
        let s = Scale::new(&cfg(32767.99, 0.0));
        let hi = s.pixel(&acc(500.0, 3.14159), 0).unwrap();
        let lo = s.pixel(&acc(500.0, -3.14159), 0).unwrap();
        assert!(hi > 16_380 && lo < -16_380, "{hi} {lo}");
        // Reference subtraction wraps: Phi = -3.1, phi_r = 3.1 -> D = 2 pi - 6.2 = +0.083.
        let s = Scale::new(&cfg(2000.0, 0.0));
        let h = s.pixel(&acc(500.0, -3.1), from_rad(3.1)).unwrap();
        let want = ((2.0 * PI - 6.2) / (2.0 * PI) * 2000.0).round() as i16;
        assert!((h - want).abs() <= 1);
    }

    #[test]
    fn validity() {
        let s = Scale::new(&cfg(2000.0, 40.0));
        assert_eq!(s.pixel(&acc(39.0, 1.0), 0), Err(Invalid::LowModulation));
        assert!(s.pixel(&acc(41.0, 1.0), 0).is_ok());
        assert_eq!(s.pixel(&Acc::default(), 0), Err(Invalid::LowModulation));
        let mut a = acc(700.0, 0.3);
        a.saturated = true;
        assert_eq!(s.pixel(&a, 0), Err(Invalid::Saturated));
        // Extreme accumulators do not overflow.
        let big = Acc { v2: i64::MAX >> 14, v3: i64::MIN >> 14, saturated: false };
        assert!(s.pixel(&big, 0).is_ok());
    }
}
