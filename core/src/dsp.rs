//! The Cortex-M7's packed 16-bit instructions the accumulate kernel needs, each with its
//! portable twin.
//!
//! A word holds two 16-bit lanes: *bottom* (bits 0..16) and *top* (bits 16..32). The kernel
//! ([`crate::accumulate::block`]) reads two neighbouring pixels of a line as one word and
//! multiplies pairs of samples by pairs of coefficients:
//!
//! | function | M7 instruction | what it computes |
//! | --- | --- | --- |
//! | [`smlad`] | `SMLAD` | `acc + a.b * b.b + a.t * b.t` (signed lanes, wrapping i32) |
//! | [`uqsub16`] | `UQSUB16` | per lane `max(a - b, 0)` (unsigned lanes) |
//! | [`unpack12`] | `UBFX`, `UBFX`, `ORR` | a Mono12p pair (24 bits) as two lanes |
//! | [`pack_bottoms`] | `PKHBT` | `[a.b, b.b]` |
//! | [`pack_tops`] | `PKHTB` | `[a.t, b.t]` |
//!
//! The two packing functions are plain Rust that LLVM turns into `PKHBT`/`PKHTB` by itself.
//! LLVM does not form `SMLAD` or `UQSUB16` from scalar code (and the `core::arch::arm`
//! intrinsics are unstable), so with the `dsp` feature on an ARM target those two are one
//! `asm!` instruction each, and [`unpack12`] is three (see there why): the only `unsafe` in
//! `dpsa-core`. Everywhere else (the host, the
//! tests) the portable twin runs. They compute the same function of their inputs by the
//! instruction set's definition (ARMv7-M ARM, A7.7.112 SMLAD: the products and the sum are
//! exact, the result is the low 32 bits; A7.7.127 UQSUB16: unsigned saturating lane
//! difference). The firmware checks each against its twin on the target
//! (`dpsa target-run --dsp-check`, run by `tests/firmware.rs`: every lane value class, random
//! words), and the byte-identical host and firmware streams check them in use.

/// `acc + a.b * b.b + a.t * b.t`: both lanes read as i16, the sum wrapping in 32 bits (`SMLAD`;
/// it also sets the sticky `Q` flag on a signed overflow, which nothing here reads).
#[inline(always)]
pub fn smlad(a: u32, b: u32, acc: i32) -> i32 {
    #[cfg(all(feature = "dsp", target_arch = "arm"))]
    {
        target::smlad(a, b, acc)
    }
    #[cfg(not(all(feature = "dsp", target_arch = "arm")))]
    {
        smlad_portable(a, b, acc)
    }
}

/// Per 16-bit lane, `a - b` if `a >= b`, else 0 (unsigned; `UQSUB16`).
#[inline(always)]
pub fn uqsub16(a: u32, b: u32) -> u32 {
    #[cfg(all(feature = "dsp", target_arch = "arm"))]
    {
        target::uqsub16(a, b)
    }
    #[cfg(not(all(feature = "dsp", target_arch = "arm")))]
    {
        uqsub16_portable(a, b)
    }
}

/// A Mono12p pair (the low 24 bits of `v`: `x0 | x1 << 12`) as two 16-bit lanes
/// `[x0, x1]`; the top byte of `v` is ignored. Three instructions (`UBFX`, `UBFX`, `ORR`); as
/// `asm!` on the target because the compiler, seeing only 24 bits used, would otherwise split
/// the caller's one 32-bit load into three byte loads.
#[inline(always)]
pub fn unpack12(v: u32) -> u32 {
    #[cfg(all(feature = "dsp", target_arch = "arm"))]
    {
        target::unpack12(v)
    }
    #[cfg(not(all(feature = "dsp", target_arch = "arm")))]
    {
        unpack12_portable(v)
    }
}

/// The portable twin of [`unpack12`].
#[inline(always)]
pub fn unpack12_portable(v: u32) -> u32 {
    (v & 0xFFF) | ((v >> 12) & 0xFFF) << 16
}

/// The portable twin of [`smlad`].
#[inline(always)]
pub fn smlad_portable(a: u32, b: u32, acc: i32) -> i32 {
    let p = (a as i16 as i32).wrapping_mul(b as i16 as i32);
    let q = ((a as i32) >> 16).wrapping_mul((b as i32) >> 16);
    acc.wrapping_add(p).wrapping_add(q)
}

/// The portable twin of [`uqsub16`].
#[inline(always)]
pub fn uqsub16_portable(a: u32, b: u32) -> u32 {
    let lo = (a as u16).saturating_sub(b as u16) as u32;
    let hi = ((a >> 16) as u16).saturating_sub((b >> 16) as u16) as u32;
    lo | hi << 16
}

/// `[a.b, b.b]`: `a`'s bottom lane in the bottom, `b`'s bottom lane in the top (`PKHBT`).
#[inline(always)]
pub fn pack_bottoms(a: u32, b: u32) -> u32 {
    (a & 0xFFFF) | (b << 16)
}

/// `[a.t, b.t]`: `a`'s top lane in the bottom, `b`'s top lane in the top (`PKHTB`).
#[inline(always)]
pub fn pack_tops(a: u32, b: u32) -> u32 {
    (b & 0xFFFF_0000) | (a >> 16)
}

/// Two i16 values as one word: `lo` in the bottom lane, `hi` in the top.
#[inline(always)]
pub const fn pair(lo: i32, hi: i32) -> u32 {
    (lo as u16 as u32) | ((hi as u16 as u32) << 16)
}

/// The instructions themselves: three `asm!` blocks, `SMLAD` and `UQSUB16` one instruction
/// each, the Mono12p unpack three (`UBFX`, `UBFX`, `ORR`). Each is register to register only:
/// no memory, no stack, inputs and outputs in general registers. That is all their safety
/// needs.
#[cfg(all(feature = "dsp", target_arch = "arm"))]
#[allow(unsafe_code)]
mod target {
    #[inline(always)]
    pub fn smlad(a: u32, b: u32, acc: i32) -> i32 {
        let r: i32;
        // SAFETY: SMLAD reads three registers and writes one; it touches no memory or stack.
        // It may set the APSR Q bit, so `preserves_flags` is not claimed.
        unsafe {
            core::arch::asm!(
                "smlad {r}, {a}, {b}, {acc}",
                r = lateout(reg) r,
                a = in(reg) a,
                b = in(reg) b,
                acc = in(reg) acc,
                options(pure, nomem, nostack),
            );
        }
        r
    }

    #[inline(always)]
    pub fn unpack12(v: u32) -> u32 {
        let r: u32;
        let t: u32;
        // SAFETY: three register instructions (two bit-field extracts and an or); no memory,
        // stack or flags.
        unsafe {
            core::arch::asm!(
                "ubfx {t}, {v}, #12, #12",
                "ubfx {r}, {v}, #0, #12",
                "orr {r}, {r}, {t}, lsl #16",
                r = out(reg) r,
                t = out(reg) t,
                v = in(reg) v,
                options(pure, nomem, nostack, preserves_flags),
            );
        }
        let _ = t;
        r
    }

    #[inline(always)]
    pub fn uqsub16(a: u32, b: u32) -> u32 {
        let r: u32;
        // SAFETY: UQSUB16 reads two registers and writes one; no memory, stack or flags.
        unsafe {
            core::arch::asm!(
                "uqsub16 {r}, {a}, {b}",
                r = lateout(reg) r,
                a = in(reg) a,
                b = in(reg) b,
                options(pure, nomem, nostack, preserves_flags),
            );
        }
        r
    }
}

/// Lane values that exercise every class of both instructions: zero, one, the i16 and u16
/// extremes and their neighbours (signs, the i16 wrap, the saturating floor).
pub const LANE_CLASSES: [u16; 12] = [
    0, 1, 2, 0x7FFE, 0x7FFF, 0x8000, 0x8001, 0xFFFE, 0xFFFF, 0x0FFF, 0x1000, 0xC000,
];

/// Input triples [`check_against_twins`] runs with `random` random ones (each checks all
/// three functions).
pub const fn checks(random: u32) -> u32 {
    let n = LANE_CLASSES.len() as u32;
    n * n * n * n + random
}

/// Compares `smlad`, `uqsub16` and `unpack12` with their twins on every pair of `LANE_CLASSES`
/// words and `random` more inputs (xorshift from `seed`); returns the number of mismatches.
/// The firmware runs it on the target; on the host it compares the twins with themselves
/// (and the unit tests below check the twins against wide arithmetic).
pub fn check_against_twins(random: u32, seed: u32) -> u32 {
    let mut bad = 0;
    let mut one = |a: u32, b: u32, acc: i32| {
        bad += u32::from(smlad(a, b, acc) != smlad_portable(a, b, acc));
        bad += u32::from(uqsub16(a, b) != uqsub16_portable(a, b));
        bad += u32::from(unpack12(a ^ b) != unpack12_portable(a ^ b));
    };
    let words = |i: usize| {
        let n = LANE_CLASSES.len();
        LANE_CLASSES[i % n] as u32 | (LANE_CLASSES[i / n] as u32) << 16
    };
    let n2 = LANE_CLASSES.len() * LANE_CLASSES.len();
    for i in 0..n2 {
        for j in 0..n2 {
            let acc = [0i32, i32::MAX, i32::MIN, -1][(i + j) % 4];
            one(words(i), words(j), acc);
        }
    }
    let mut s = seed | 1;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 17;
        s ^= s << 5;
        s
    };
    for _ in 0..random {
        let (a, b, acc) = (next(), next(), next() as i32);
        one(a, b, acc);
    }
    bad
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The twins against wide (i64 / i32) arithmetic on every class pair.
    #[test]
    fn twins_match_wide_arithmetic() {
        for &a0 in &LANE_CLASSES {
            for &a1 in &LANE_CLASSES {
                for &b0 in &LANE_CLASSES {
                    for &b1 in &LANE_CLASSES {
                        let (a, b) = (a0 as u32 | (a1 as u32) << 16, b0 as u32 | (b1 as u32) << 16);
                        for acc in [0i32, 1, -1, i32::MAX, i32::MIN] {
                            let wide = acc as i64
                                + a0 as i16 as i64 * b0 as i16 as i64
                                + a1 as i16 as i64 * b1 as i16 as i64;
                            assert_eq!(smlad_portable(a, b, acc), wide as i32);
                        }
                        let lane = |x: u16, y: u16| (x as i32 - y as i32).max(0) as u32;
                        assert_eq!(uqsub16_portable(a, b), lane(a0, b0) | lane(a1, b1) << 16);
                    }
                }
            }
        }
        assert_eq!(pack_bottoms(0x1111_2222, 0x3333_4444), 0x4444_2222);
        assert_eq!(pack_tops(0x1111_2222, 0x3333_4444), 0x3333_1111);
        assert_eq!(pair(-1, 2), 0x0002_FFFF);
        assert_eq!(check_against_twins(1000, 7), 0);
        assert_eq!(unpack12_portable(0xAB12_3456), 0x0123_0456);
    }
}
