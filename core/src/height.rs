//! Phase to height, and the per-pixel validity mask.

use crate::accumulate::{Acc, SATURATED, V};
use crate::frames::Config;
use crate::phase::atan2;
use fixed::types::{U16F16, U20F12};

/// Largest height magnitude written (LSB): half a turn at the largest scale `Config` accepts
/// (`< 2^15` LSB per turn); `i16::MIN` is never produced.
pub const H_MAX: i32 = 1 << 14;

/// Why a pixel has no height.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Invalid {
    /// A sample was at or above the saturation level.
    Saturated,
    /// Fringe modulation `C` below the threshold.
    LowModulation,
}

/// Largest exponent of a [`ColumnScale`]: `mantissa << 15 < 2^31`, the range of
/// [`Config::lsb_per_turn`]'s bits that keeps every height inside [`H_MAX`].
pub const MAX_COLUMN_SHIFT: u8 = 15;

/// A per-column height scale: column `c` has its own LSB per turn `k_c` (the non-telecentric
/// optics make the height per fringe turn `T_z(c)` vary over the field), so the heights the
/// core emits are in the same calibrated LSB in every column.
///
/// Format: a block floating point with one exponent for the table. Entry `c` is a `u16`
/// mantissa `m_c`; `k_c`'s Q16.16 bits (the format of [`Config::lsb_per_turn`]) are
/// `m_c << shift`, i.e. `m_c` is `k_c` in LSB per turn with `16 - shift` fractional bits
/// (`shift` is a table-wide run-time value, `0..=`[`MAX_COLUMN_SHIFT`], so no single `fixed`
/// type states it; [`ColumnScale::encode`] takes and [`ColumnScale::lsb_per_turn`] gives the
/// `U16F16` values). Two bytes per column.
///
/// [`ColumnScale::encode`] picks the smallest `shift` whose mantissas fit 16 bits, so the
/// largest mantissa is at least `2^15` (for `shift > 0`) and each `k_c` is rounded to
/// `2^(shift-16)` LSB per turn: at most `2^(shift-17)` LSB per turn off. A height is at most
/// half a turn, so the table's quantisation moves a height by at most `2^(shift-18)` LSB
/// (plus `2^-18` LSB from rounding `k_c` to Q16.16 first): 0.0078 LSB at the default
/// 2000 LSB per turn (`shift = 11`), 0.125 LSB at the largest scale the core accepts
/// (`shift = 15`, `< 32768` LSB per turn; 0.25 LSB for an entry within `2^-16` of 32768,
/// whose mantissa is clamped to 65535). Tested in `column_scale_heights_match_f64`.
///
/// Validity ([`ColumnScale::check`]): one entry per column, `shift <= 15`, and every `k_c`
/// within a factor of two of [`Config::lsb_per_turn`] (`k/2 <= k_c <= 2k`; so never zero): a
/// table further off than that is a wrong or corrupt calibration, not optics.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ColumnScale<'a> {
    shift: u8,
    mantissa: &'a [u16],
}

/// Why a per-column height-scale table was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColumnScaleError {
    /// The table has `got` entries, the configuration `expected` columns.
    Length {
        /// Columns of the configuration.
        expected: u16,
        /// Entries of the table.
        got: usize,
    },
    /// The exponent is above [`MAX_COLUMN_SHIFT`].
    Shift(u8),
    /// Column `column`'s LSB per turn is zero or more than a factor of two away from
    /// [`Config::lsb_per_turn`].
    Range {
        /// The first column out of range.
        column: u16,
    },
}

impl<'a> ColumnScale<'a> {
    /// The table `mantissa` with exponent `shift` (unchecked: see [`ColumnScale::check`]).
    pub const fn new(shift: u8, mantissa: &'a [u16]) -> ColumnScale<'a> {
        ColumnScale { shift, mantissa }
    }

    /// The table's exponent: column `c`'s LSB per turn is `mantissa[c] << shift` in Q16.16
    /// bits.
    pub const fn shift(&self) -> u8 {
        self.shift
    }

    /// The `W` mantissas, one per column.
    pub const fn mantissa(&self) -> &'a [u16] {
        self.mantissa
    }

    /// Column `c`'s LSB per turn (`None` past the table).
    pub fn lsb_per_turn(&self, c: usize) -> Option<U16F16> {
        let m = *self.mantissa.get(c)?;
        Some(U16F16::from_bits(
            (m as u32)
                .checked_shl(self.shift as u32)
                .unwrap_or(u32::MAX),
        ))
    }

    /// Checks the table against `cfg` (see [`ColumnScale`]).
    pub fn check(&self, cfg: &Config) -> Result<(), ColumnScaleError> {
        self.check_parts(cfg.width, cfg.lsb_per_turn)
    }

    /// [`ColumnScale::check`] with the two values of the configuration it reads: the width
    /// `W` and the uniform LSB per turn.
    pub fn check_parts(&self, w: u16, lsb_per_turn: U16F16) -> Result<(), ColumnScaleError> {
        if self.mantissa.len() != w as usize {
            return Err(ColumnScaleError::Length {
                expected: w,
                got: self.mantissa.len(),
            });
        }
        if self.shift > MAX_COLUMN_SHIFT {
            return Err(ColumnScaleError::Shift(self.shift));
        }
        let k = lsb_per_turn.to_bits() as u64;
        for (c, &m) in self.mantissa.iter().enumerate() {
            // Q16.16 bits, < 2^31 (shift <= 15); compared in u64, no overflow.
            let kc = (m as u64) << self.shift;
            if kc == 0 || 2 * kc < k || kc > 2 * k {
                return Err(ColumnScaleError::Range { column: c as u16 });
            }
        }
        Ok(())
    }

    /// Encodes per-column LSB per turn (Q16.16) into mantissas (`mantissa.len()` must equal
    /// `lsb_per_turn.len()`) and returns the exponent: the smallest `shift` for which every
    /// `round(k_c / 2^shift)` (half up) fits 16 bits. Refuses zero entries and entries at or
    /// above `2^15` LSB per turn (the range of [`Config::lsb_per_turn`]); the band around
    /// the configuration's value is [`ColumnScale::check`]'s.
    pub fn encode(lsb_per_turn: &[U16F16], mantissa: &mut [u16]) -> Result<u8, ColumnScaleError> {
        if mantissa.len() != lsb_per_turn.len() {
            return Err(ColumnScaleError::Length {
                expected: lsb_per_turn.len().min(u16::MAX as usize) as u16,
                got: mantissa.len(),
            });
        }
        let mut max = 0u32;
        for (c, k) in lsb_per_turn.iter().enumerate() {
            let b = k.to_bits();
            if b == 0 || b >= 1 << 31 {
                return Err(ColumnScaleError::Range { column: c as u16 });
            }
            max = max.max(b);
        }
        // Rounding `max` up may carry into bit 16: take the next exponent then. At the
        // largest exponent the mantissa is clamped to 65535 instead (only entries within
        // 2^-16 of 32768 LSB per turn reach it: their error is then below one unit,
        // `2^(shift-16)` LSB per turn, instead of half).
        let round = |b: u32, s: u32| -> u64 {
            if s == 0 {
                b as u64
            } else {
                ((b as u64) + (1 << (s - 1))) >> s
            }
        };
        let mut shift = 0u32;
        while shift < MAX_COLUMN_SHIFT as u32 && round(max, shift) > u16::MAX as u64 {
            shift += 1;
        }
        for (m, k) in mantissa.iter_mut().zip(lsb_per_turn) {
            *m = round(k.to_bits(), shift).min(u16::MAX as u64) as u16;
        }
        Ok(shift as u8)
    }

    /// Height of phase `phi` against `phi_r` with mantissa `m` (see [`Scale::height`]):
    /// `h = round(D m 2^shift / 2^48) = round(D m / 2^(48 - shift))`, `D` the wrapped
    /// difference (i32, units of `2 pi / 2^32`). `|D m| < 2^47`: one 32 x 32 -> 64 product whose
    /// high word carries the result, `((D m >> 32) + 2^(15 - shift)) >> (16 - shift)` (the same
    /// identity as [`Scale::height`], valid for `shift <= 16`). Equal to [`Scale::height`] with
    /// `k = m << shift`.
    #[inline(always)]
    pub fn height(phi: u32, phi_r: u32, m: u16, half: i32, sh: u32) -> i16 {
        let d = phi.wrapping_sub(phi_r) as i32 as i64;
        let hi = ((d * m as i64) >> 32) as i32;
        ((hi + half) >> sh) as i16
    }

    /// The rounding constant and right shift of [`ColumnScale::height`]:
    /// `(2^(15 - shift), 16 - shift)` (`shift` clamped to [`MAX_COLUMN_SHIFT`]).
    #[inline(always)]
    pub fn rounding(&self) -> (i32, u32) {
        let s = self.shift.min(MAX_COLUMN_SHIFT) as u32;
        (1 << (15 - s), 16 - s)
    }
}

/// Constants of the phase-to-height step, derived once from [`Config`].
///
/// Both fields are read for every pixel ([`Scale::height`], [`Scale::phase_v`]), so they are
/// the raw integers the per-pixel arithmetic multiplies and compares, with their Q-formats
/// stated here; the fixed-point types end at [`Scale::from_parts`] (`to_bits()` once per
/// pipeline):
/// - `k`: height LSBs per turn, Q16.16 in an `i32` (the bits of [`Config::lsb_per_turn`],
///   `< 2^31`), the factor of the signed 32 x 32 -> 64 product in [`Scale::height`];
/// - `min_c2`: the square of [`Config::min_modulation`]'s Q20.12 bits, a threshold on
///   `C^2` in DN^2 with 24 fractional bits (Q40.24 in a `u64`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Scale {
    /// Height LSBs per turn, Q16.16.
    pub(crate) k: i32,
    /// `min_modulation^2`, Q40.24: threshold on `C^2` in DN^2 * 2^24.
    min_c2: u64,
}

/// The modulation test of one window, in the units of its reduced pixels (`frac` fractional
/// bits, see [`crate::accumulate::V`]), from [`Scale::gate`].
///
/// A pixel `[x, y]` is modulated when `C^2 = x^2 + y^2 >= thr2` and `C^2 > 0`, with
/// `thr2 = ceil(m^2 2^(2 frac) / 2^24)` for the threshold's Q20.12 bits `m`: exactly
/// `C >= min_modulation` (for `frac = 12`, the old `c2 >= m^2`). The per-pixel test is folded
/// into the phase kernel: `atan2` computes `hi = max(|x|, |y|)` anyway, and `hi >= fast`
/// (`fast = max(1, ceil(sqrt(thr2)))`) already proves `C^2 >= hi^2 >= thr2`; only pixels
/// below it take the exact 64-bit test. Same result as the exact test for every input
/// (tested), one compare for the common case.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Gate {
    /// `hi >= fast` proves the pixel modulated.
    pub(crate) fast: u32,
    /// Threshold on `x^2 + y^2`.
    pub(crate) thr2: u64,
}

impl Gate {
    /// The exact test (see [`Gate`]).
    #[inline(always)]
    fn modulated_exact(&self, x: i32, y: i32) -> bool {
        let c2 = (x as i64 * x as i64) as u64 + (y as i64 * y as i64) as u64;
        c2 >= self.thr2 && c2 != 0
    }

    /// The folded test: `hi = max(|x|, |y|)`.
    #[inline(always)]
    fn modulated(&self, x: i32, y: i32, hi: u32) -> bool {
        hi >= self.fast || self.slow(x, y)
    }

    #[inline(always)]
    fn slow(&self, x: i32, y: i32) -> bool {
        self.modulated_exact(x, y)
    }

    /// The fast-path bound `fast` (`hi >= fast` proves a pixel modulated): a window register
    /// of a front end that runs the gate ([`crate::offload`]).
    pub fn fast(&self) -> u32 {
        self.fast
    }

    /// The threshold on `C^2 = v_2^2 + v_3^2`: a window register of a front end that runs
    /// the gate ([`crate::offload`]).
    pub fn thr2(&self) -> u64 {
        self.thr2
    }
}

/// `ceil(sqrt(v))` (bitwise; once per window).
fn isqrt_ceil(v: u64) -> u64 {
    let (mut r, mut bit) = (0u64, 1u64 << 31);
    while bit != 0 {
        let t = r | bit;
        if t * t <= v {
            r = t;
        }
        bit >>= 1;
    }
    if r * r < v {
        r + 1
    } else {
        r
    }
}

impl Scale {
    /// The modulation gate for reduced pixels with `frac` fractional bits (`<= 24`).
    pub fn gate(&self, frac: u32) -> Gate {
        let frac = frac.min(24);
        let m2 = self.min_c2 as u128;
        let thr2 = ((m2 << (2 * frac)) + (1u128 << 24) - 1) >> 24;
        let thr2 = thr2.min(u64::MAX as u128) as u64;
        // hi <= 2^31 < u32::MAX: a threshold above (2^32 - 1)^2 never takes the fast path.
        let fast = isqrt_ceil(thr2).clamp(1, u32::MAX as u64) as u32;
        Gate { fast, thr2 }
    }

    /// The scale of a configuration ([`Config::lsb_per_turn`], [`Config::min_modulation`]).
    pub fn new(cfg: &Config) -> Scale {
        Scale::from_parts(cfg.lsb_per_turn, cfg.min_modulation)
    }

    /// From LSB per turn and the modulation threshold (DN).
    pub fn from_parts(lsb_per_turn: U16F16, min_modulation: U20F12) -> Scale {
        let m = min_modulation.to_bits() as u64;
        // `Config::validate` keeps LSB per turn below 2^31; the clamp covers direct callers.
        Scale {
            k: lsb_per_turn.to_bits().min(i32::MAX as u32) as i32,
            min_c2: m.saturating_mul(m),
        }
    }

    /// Height LSBs per turn, the Q16.16 bits (`< 2^31`): the factor a front end that runs
    /// the height stage multiplies by ([`Scale::height`], [`crate::offload`]).
    pub fn lsb_per_turn_bits(&self) -> i32 {
        self.k
    }

    /// The pixel's phase `Phi = atan2(v_3, v_2)` if it is valid (not saturated, modulated).
    #[inline(always)]
    pub fn phase(&self, acc: &Acc) -> Result<u32, Invalid> {
        self.phase_v(&self.gate(12), acc.reduce())
    }

    /// [`Scale::phase`] of a reduced pixel `[v_2, v_3]` in the units of `gate`.
    ///
    /// Modulation: `C^2 = v_2^2 + v_3^2 >= thr2` (see [`Gate`], folded into the phase
    /// kernel); zero modulation is always invalid.
    #[inline(always)]
    pub fn phase_v(&self, gate: &Gate, v: V) -> Result<u32, Invalid> {
        let [x, y] = v;
        if x == SATURATED {
            return Err(Invalid::Saturated);
        }
        let hi = x.unsigned_abs().max(y.unsigned_abs());
        if !gate.modulated(x, y, hi) {
            return Err(Invalid::LowModulation);
        }
        Ok(atan2(y, x))
    }

    /// Height from a phase and the reference phase `phi_r` (binary angles):
    /// - `D = Phi - phi_r`, wrapping, read as i32: `[-pi, pi)` in units of `2 pi / 2^32`.
    /// - `h = round(D * k / 2^48)` with `k` = LSB per turn in Q16.16 (`< 2^31`): one
    ///   32 x 32 -> 64 product (`|D k| < 2^62`), rounded half up. Since `|D| <= 2^31` and
    ///   `k < 2^31`, `|h| <= 2^14`: always inside i16 (and never `i16::MIN`), no clamp needed.
    #[inline(always)]
    pub fn height(&self, phi: u32, phi_r: u32) -> i16 {
        // `(X + 2^47) >> 48 = ((X >> 32) + 2^15) >> 16` for any integer X (the low word
        // cannot carry across a multiple of 2^16 once 2^15 is added to the high word), so only
        // the high word of the product is needed (`SMULL`, one add, one shift).
        let d = phi.wrapping_sub(phi_r) as i32 as i64;
        let hi = ((d * self.k as i64) >> 32) as i32;
        ((hi + (1 << 15)) >> 16) as i16
    }

    /// Height of one pixel from its accumulated `v`, relative to the reference phase `phi_r`:
    /// validity and phase from [`Scale::phase`] (error at most
    /// [`crate::phase::ATAN2_MAX_ERR_RAD`]), then [`Scale::height`].
    #[inline(always)]
    pub fn pixel(&self, acc: &Acc, phi_r: u32) -> Result<i16, Invalid> {
        Ok(self.height(self.phase(acc)?, phi_r))
    }

    /// The phase + height + mask stage over a run of columns starting at a multiple of 8:
    /// pixel `k` has reduced `v[k]` and reference phase `rho + ref_phase[k]`. Writes
    /// `heights[k]` of valid pixels (others are left alone) and the validity bytes
    /// `valid[k / 8]` (whole bytes, bit `k % 8`); returns the per-pixel row flags seen.
    /// Heights at the uniform scale `k` ([`Scale::height`]).
    #[inline(always)]
    pub fn block(
        &self,
        gate: &Gate,
        v: &[V],
        rho: u32,
        ref_phase: &[u32],
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> u16 {
        let cols = core::iter::repeat(());
        let h = |phi: u32, phi_r: u32, _: ()| self.height(phi, phi_r);
        self.block_by(gate, v, rho, ref_phase, cols, h, heights, valid)
    }

    /// [`Scale::block`] with a per-column scale: `mantissa[k]` (the [`ColumnScale`] entries
    /// of these columns, exponent from `columns`) replaces the uniform `k`
    /// ([`ColumnScale::height`]): one table load per pixel instead of a constant.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub fn block_columns(
        &self,
        gate: &Gate,
        v: &[V],
        rho: u32,
        ref_phase: &[u32],
        columns: &ColumnScale<'_>,
        mantissa: &[u16],
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> u16 {
        let (half, sh) = columns.rounding();
        let h = |phi: u32, phi_r: u32, m: u16| ColumnScale::height(phi, phi_r, m, half, sh);
        let len = v.len().min(mantissa.len());
        let cols = mantissa[..len].iter().copied();
        self.block_by(gate, &v[..len], rho, ref_phase, cols, h, heights, valid)
    }

    /// The loop of [`Scale::block`] and [`Scale::block_columns`]: `cols` yields each
    /// column's scale (nothing for the uniform one), `height` turns a phase, a reference
    /// phase and that scale into the height.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn block_by<K, I: Iterator<Item = K>>(
        &self,
        gate: &Gate,
        v: &[V],
        rho: u32,
        ref_phase: &[u32],
        cols: I,
        height: impl Fn(u32, u32, K) -> i16,
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> u16 {
        let len = v
            .len()
            .min(ref_phase.len())
            .min(heights.len())
            .min(valid.len() * 8);
        let (v, ref_phase, heights) = (&v[..len], &ref_phase[..len], &mut heights[..len]);
        let mut fl = 0u16;
        let mut byte = 0u32;
        // `cols` is never shorter than `len` (endless, or cut to `v` by the caller).
        let pixels = v.iter().zip(ref_phase).zip(heights.iter_mut()).zip(cols);
        for (k, (((&vk, &rk), hk), ck)) in pixels.enumerate() {
            match self.phase_v(gate, vk) {
                Ok(phi) => {
                    *hk = height(phi, rho.wrapping_add(rk), ck);
                    byte |= 1 << (k & 7);
                }
                Err(Invalid::Saturated) => fl |= crate::flags::SATURATED,
                Err(Invalid::LowModulation) => fl |= crate::flags::LOW_MODULATION,
            }
            if k & 7 == 7 {
                valid[k >> 3] = byte as u8;
                byte = 0;
            }
        }
        if len & 7 != 0 {
            valid[len >> 3] = byte as u8;
        }
        fl
    }

    /// [`Scale::block`] as its own (never inlined) function, for timing the stage alone.
    #[inline(never)]
    pub fn row(
        &self,
        gate: &Gate,
        v: &[V],
        rho: u32,
        ref_phase: &[u32],
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> u16 {
        self.block(gate, v, rho, ref_phase, heights, valid)
    }

    /// [`Scale::block_columns`] as its own (never inlined) function, for timing the stage.
    #[inline(never)]
    #[allow(clippy::too_many_arguments)]
    pub fn row_columns(
        &self,
        gate: &Gate,
        v: &[V],
        rho: u32,
        ref_phase: &[u32],
        columns: &ColumnScale<'_>,
        mantissa: &[u16],
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> u16 {
        self.block_columns(gate, v, rho, ref_phase, columns, mantissa, heights, valid)
    }
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
            counts_per_pixel: U16F16::ONE,
            fx: 1 << 27,
            lsb_per_turn: U16F16::from_bits((lsb_per_turn * 65536.0).round() as u32),
            saturation: 4095,
            min_modulation: U20F12::from_bits((min_mod * 4096.0).round() as u32),
            max_noise_gain: fixed::types::U8F8::from_num(2),
            max_step_rows: 4,
        }
    }

    fn acc(c: f64, phi: f64) -> Acc {
        let q = (1u64 << 24) as f64;
        Acc {
            v2: (c * phi.cos() * q) as i64,
            v3: (c * phi.sin() * q) as i64,
            saturated: false,
        }
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
        // Rounding (0.5) plus the phase error bound (2e-5 rad -> 0.0064 LSB at 2000 LSB/turn).
        let bound = 0.5 + crate::phase::ATAN2_MAX_ERR_RAD / (2.0 * PI) * 2000.37;
        assert!(worst <= bound, "worst {worst} > {bound}");
    }

    #[test]
    fn wraps_and_clamps() {
        // The largest scale Config accepts (< 2^15 LSB per turn) keeps +-pi inside i16.
        let s = Scale::new(&cfg(32767.99, 0.0));
        // 1e-4 rad inside +-pi: further from the cut than the phase error bound.
        let hi = s.pixel(&acc(500.0, PI - 1e-4), 0).unwrap();
        let lo = s.pixel(&acc(500.0, -PI + 1e-4), 0).unwrap();
        assert!(hi > 16_380 && lo < -16_380, "{hi} {lo}");
        // The extreme difference (-pi exactly) at the largest scale stays inside H_MAX.
        let s_max = Scale::from_parts(U16F16::MAX, U20F12::ZERO);
        for (phi, r) in [
            (0x8000_0000u32, 0u32),
            (0, 0x8000_0000),
            (0x7FFF_FFFF, 0),
            (0, 0x7FFF_FFFF),
        ] {
            assert!((s_max.height(phi, r) as i32).abs() <= H_MAX);
        }
        // The high-word form equals the rounded 64-bit product everywhere.
        let mut seed = 0x1234_5678_9ABC_DEF1u64;
        for i in 0..200_000u64 {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            let (phi, k) = (seed as u32, ((seed >> 32) as u32 >> (i % 17)) & 0x7FFF_FFFF);
            let s = Scale {
                k: k as i32,
                min_c2: 0,
            };
            let d = phi as i32 as i64;
            let want = ((d * k as i64 + (1 << 47)) >> 48) as i16;
            assert_eq!(s.height(phi, 0), want, "{phi} {k}");
        }
        // Reference subtraction wraps: Phi = -3.1, phi_r = 3.1 -> D = 2 pi - 6.2 = +0.083.
        let s = Scale::new(&cfg(2000.0, 0.0));
        let h = s.pixel(&acc(500.0, -3.1), from_rad(3.1)).unwrap();
        let want = ((2.0 * PI - 6.2) / (2.0 * PI) * 2000.0).round() as i16;
        assert!((h - want).abs() <= 1);
    }

    #[test]
    fn folded_gate_is_the_exact_test() {
        let mut seed = 0x9E37_79B9_7F4A_7C15u64;
        let mut rnd = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed
        };
        for min_mod in [0.0, 0.3, 1.0, 10.0, 40.0, 333.7, 4095.0, 65535.0, 1048575.0] {
            let s = Scale::new(&cfg(2000.0, min_mod));
            for frac in [0u32, 3, 11, 12, 13, 15, 19, 24] {
                let g = s.gate(frac);
                // The threshold in these units, from f64: C >= min_mod.
                let t = (min_mod * 4096.0f64).round() / 4096.0 * (1u64 << frac) as f64;
                let around = [g.fast as i64, t as i64];
                for k in 0..20_000 {
                    let (x, y) = match k % 3 {
                        0 => (rnd() as i32, rnd() as i32),
                        1 => {
                            let c = around[k % 2] + (rnd() % 5) as i64 - 2;
                            let a = (rnd() % 6283) as f64 / 1000.0;
                            (
                                (c as f64 * a.cos()).round().clamp(-2e9, 2e9) as i32,
                                (c as f64 * a.sin()).round().clamp(-2e9, 2e9) as i32,
                            )
                        }
                        _ => ((rnd() % 9) as i32 - 4, (rnd() % 9) as i32 - 4),
                    };
                    if x == SATURATED {
                        continue;
                    }
                    let hi = x.unsigned_abs().max(y.unsigned_abs());
                    assert_eq!(g.modulated(x, y, hi), g.modulated_exact(x, y), "{x} {y}");
                    let c = ((x as f64).powi(2) + (y as f64).powi(2)).sqrt();
                    if (c - t).abs() > 1e-6 * t.max(1.0) {
                        assert_eq!(g.modulated_exact(x, y), c >= t && c > 0.0, "{x} {y} {t}");
                    }
                }
            }
        }
        assert_eq!(isqrt_ceil(0), 0);
        assert_eq!(isqrt_ceil(15), 4);
        assert_eq!(isqrt_ceil(16), 4);
        assert_eq!(isqrt_ceil(17), 5);
        assert_eq!(isqrt_ceil(1 << 62), 1 << 31);
    }

    /// Q16.16 bits of `x` LSB per turn, rounded.
    fn q16(x: f64) -> U16F16 {
        U16F16::from_bits((x * 65536.0).round() as u32)
    }

    #[test]
    fn column_scale_heights_match_f64() {
        // Per-column LSB per turn varying +-2 % (as the optics make T_z vary), at the default
        // scale and at the largest the core accepts. Heights against f64 `D / 2 pi * k_c`
        // with the exact (unquantised) k_c: max error within rounding + atan2 + the table's
        // bound 2^(shift-18) + 2^-18; rms near the 1/sqrt(12) of rounding alone.
        for nominal in [2000.0f64, 400.0, 32000.0] {
            let w = 257usize;
            let exact: std::vec::Vec<f64> = (0..w)
                .map(|c| nominal * (1.0 + 0.02 * (c as f64 * 0.37).sin()))
                .collect();
            let k: std::vec::Vec<U16F16> = exact.iter().map(|&x| q16(x)).collect();
            let mut m = std::vec![0u16; w];
            let shift = ColumnScale::encode(&k, &mut m).unwrap();
            let t = ColumnScale::new(shift, &m);
            let mut c0 = cfg(nominal, 10.0);
            c0.width = w as u16;
            t.check(&c0).unwrap();
            let s = Scale::new(&c0);
            let (half, sh) = t.rounding();
            let quant = (1u64 << shift) as f64 / (1u64 << 18) as f64 + 1.0 / (1u64 << 18) as f64;
            let phase = crate::phase::ATAN2_MAX_ERR_RAD / (2.0 * PI) * nominal * 1.02;
            let bound = 0.5 + phase + quant;
            let (mut worst, mut sq, mut n, mut worst_q) = (0f64, 0f64, 0usize, 0f64);
            for (c, &kc) in exact.iter().enumerate() {
                for j in 0..400 {
                    let phi = -PI + 2.0 * PI * (j as f64 + 0.31) / 400.0;
                    let r = 0.77 + 0.01 * c as f64;
                    let p = s.phase(&acc(700.0, phi + r)).unwrap();
                    let h = ColumnScale::height(p, from_rad(r), m[c], half, sh);
                    let want = phi / (2.0 * PI) * kc;
                    let e = h as f64 - want;
                    worst = worst.max(e.abs());
                    sq += e * e;
                    n += 1;
                    // The table alone: the exact product with the table's k_c against the
                    // exact one, same phase.
                    let d = p.wrapping_sub(from_rad(r)) as i32 as f64 / 4_294_967_296.0;
                    let kt = t.lsb_per_turn(c).unwrap().to_num::<f64>();
                    worst_q = worst_q.max((d * (kt - kc)).abs());
                }
            }
            let rms = (sq / n as f64).sqrt();
            assert!(worst <= bound, "{nominal}: worst {worst} > {bound}");
            assert!(
                worst_q <= quant,
                "{nominal}: table error {worst_q} > {quant}"
            );
            assert!(rms < 0.3, "{nominal}: rms {rms}");
            if nominal == 2000.0 {
                // Far below one LSB at the default scale.
                assert_eq!(shift, 11);
                assert!(quant < 0.008 && worst_q < 0.008, "{quant} {worst_q}");
            }
        }
    }

    #[test]
    fn column_scale_equal_to_the_uniform_one_changes_nothing() {
        // A table whose every k_c is the configuration's k (low bits zero so the mantissa is
        // exact) gives the very heights of the uniform scale, for any phase pair.
        let k = U16F16::from_bits(2000 << 16);
        let mut m = [0u16; 8];
        let shift = ColumnScale::encode(&[k; 8], &mut m).unwrap();
        assert_eq!((m[0] as u32) << shift, k.to_bits());
        let t = ColumnScale::new(shift, &m);
        let s = Scale::from_parts(k, U20F12::ZERO);
        let (half, sh) = t.rounding();
        let mut seed = 0x0DDC_0FFE_E123_4567u64;
        for _ in 0..200_000 {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            let (phi, r) = (seed as u32, (seed >> 32) as u32);
            assert_eq!(
                ColumnScale::height(phi, r, m[0], half, sh),
                s.height(phi, r)
            );
        }
        // And the same for every mantissa and exponent against the rounded 64-bit product.
        for _ in 0..200_000 {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            let (phi, mm, shift) = (seed as u32, (seed >> 32) as u16, (seed >> 48) as u8 % 16);
            let t = ColumnScale::new(shift, &[]);
            let (half, sh) = t.rounding();
            let kk = (mm as i64) << shift;
            let want = ((phi as i32 as i64 * kk + (1 << 47)) >> 48) as i16;
            assert_eq!(ColumnScale::height(phi, 0, mm, half, sh), want);
            assert!((want as i32).abs() <= H_MAX);
        }
    }

    #[test]
    fn column_scale_encode_and_check() {
        // Exponent: the smallest that fits 16 bits, so the largest mantissa is >= 2^15.
        for top in [1.0f64, 1.5, 255.99, 2000.0, 2047.99, 2048.0, 32767.99] {
            let k = [q16(top), q16(top * 0.97), q16(top * 0.5)];
            let mut m = [0u16; 3];
            let shift = ColumnScale::encode(&k, &mut m).unwrap();
            assert!(shift <= MAX_COLUMN_SHIFT);
            assert!(shift == 0 || m[0] >= 1 << 15, "{top}: {shift} {m:?}");
            for (kk, &mm) in k.iter().zip(&m) {
                let back = (mm as u64) << shift;
                let err = (back as i64 - kk.to_bits() as i64).unsigned_abs();
                // Half a unit, or just under one unit for a mantissa clamped at 65535.
                let unit = 1u64 << shift;
                assert!(err <= unit / 2 || (mm == u16::MAX && err < unit), "{top}");
            }
        }
        let mut m = [0u16; 2];
        assert_eq!(
            ColumnScale::encode(&[q16(5.0), U16F16::ZERO], &mut m),
            Err(ColumnScaleError::Range { column: 1 })
        );
        assert_eq!(
            ColumnScale::encode(&[U16F16::from_bits(1 << 31)], &mut m[..1]),
            Err(ColumnScaleError::Range { column: 0 })
        );
        assert!(matches!(
            ColumnScale::encode(&[q16(5.0)], &mut m),
            Err(ColumnScaleError::Length { .. })
        ));
        // check: length, exponent, zero, outside k/2 ..= 2k.
        let c = cfg(2000.0, 0.0); // width 8
        let k = c.lsb_per_turn.to_bits();
        let good = [(k >> 11) as u16; 8];
        assert_eq!(ColumnScale::new(11, &good).check(&c), Ok(()));
        assert_eq!(
            ColumnScale::new(11, &good[..7]).check(&c),
            Err(ColumnScaleError::Length {
                expected: 8,
                got: 7
            })
        );
        assert_eq!(
            ColumnScale::new(16, &good).check(&c),
            Err(ColumnScaleError::Shift(16))
        );
        let mut bad = good;
        bad[3] = 0;
        assert_eq!(
            ColumnScale::new(11, &bad).check(&c),
            Err(ColumnScaleError::Range { column: 3 })
        );
        // Exactly k/2 and 2k pass; one step beyond fails.
        let (lo, hi) = ((k / 2) >> 12, (2 * k) >> 12);
        assert_eq!((lo << 12, hi << 12), (k / 2, 2 * k));
        for (v, ok) in [(lo, true), (lo - 1, false), (hi, true), (hi + 1, false)] {
            let mut t = [(k >> 12) as u16; 8];
            t[5] = v as u16;
            let r = ColumnScale::new(12, &t).check(&c);
            assert_eq!(r.is_ok(), ok, "{v}: {r:?}");
        }
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
        let big = Acc {
            v2: i64::MAX >> 14,
            v3: i64::MIN >> 14,
            saturated: false,
        };
        assert!(s.pixel(&big, 0).is_ok());
    }
}
