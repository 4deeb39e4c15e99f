//! The phase + height stage eight pixels at a time: the same integer results as the scalar
//! loop of [`crate::height`] (the firmware's), in a form a vector unit runs.
//!
//! The scalar kernel ([`crate::phase::atan2`], [`Scale::phase_v`], [`ColumnScale::height`])
//! branches per pixel and divides with a `u32` division, which no x86 vector unit has. Here
//! every step is a select, and three steps are restated with the same results:
//!
//! - **`clz(hi)`** from the exponent of an f32 conversion of `hi` with its second-highest
//!   bit cleared (so the rounding cannot carry into the next power of two): `s = 31 -
//!   floor(log2 hi)`. For `hi = 0` the shift count exceeds 31 and shifts to 0: `d = 0x8000`,
//!   `lo << s = 0`, `t = 0`, as the scalar's shift by 32 (a shift by 0) gives.
//! - **`t = floor((lo << s) / d)`** as `((lo << s) as f64 / d as f64)` truncated. Exact: the
//!   numerator is below `2^32` and `d >= 2^15`, so a quotient that is not an integer lies at
//!   least `1 / d >= 2^-16` below the next one, while the f64 division errs by at most
//!   `q 2^-53 < 2^-36` (`q < 2^17`): the truncation lands on the integer the `u32` division
//!   gives.
//! - **The gate** `hi >= fast || exact(x, y)`: the fast compare in every lane, the exact
//!   64-bit test only in lanes below the fast threshold (rare).
//!
//! Three builds beside the scalar loop ([`Kernel`]): `eight`, the branch-free formulation in
//! plain Rust over arrays of eight (the definition, compiled for the target's baseline;
//! [`Kernel::Lanes`]), the same steps in SSE2 intrinsics as two steps of four lanes
//! (x86-64's baseline: [`Kernel::Sse2`]; its module says how it restates what SSE2 lacks),
//! and in AVX2 intrinsics ([`Kernel::Avx2`], chosen at run time when the CPU has it:
//! [`Kernel::best`]). The compiler does not vectorize the plain build (its disassembly is
//! scalar) and the SSE2 build is slower than the scalar loop (measured: [`Kernel::best`]), so
//! [`Kernel::best`] takes the scalar loop where AVX2 is missing, and the firmware keeps it.
//! Tests below prove every kernel gives the same phases,
//! heights, validity bytes and flags as the scalar one on every input class (saturated and
//! invalid pixels, zero and threshold modulation, every octant and axis, the ends of the i32
//! range, odd widths, both height scales); the pipeline's tests run whole rows through each.

// Lane loops index several arrays by the lane: the form the passes are written in on purpose.
#![allow(clippy::needless_range_loop)]

use crate::accumulate::{SATURATED, V};
use crate::flags;
use crate::height::{ColumnScale, Gate, Scale};
use crate::phase::{ATAN, HALF, QUARTER};

/// Which build of the phase + height stage a pipeline runs (the results are the same).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    /// One pixel at a time, branching: the firmware's loop ([`crate::height`]).
    Scalar,
    /// Eight pixels at a time, the plain-Rust definition (`eight`) compiled for the
    /// target's baseline (SSE2 on x86-64, which the compiler leaves scalar).
    Lanes,
    /// Eight pixels at a time, as two steps of four with SSE2 (x86-64's baseline, so every
    /// x86-64 CPU runs it). Only [`Kernel::sse2`] makes one, and only on x86-64.
    Sse2(Sse2),
    /// Eight pixels at a time with AVX2 (x86-64). Only [`Kernel::best`] and
    /// [`Kernel::avx2`] make one, and only on a CPU that has AVX2.
    Avx2(Avx2),
}

/// Proof that this is an x86-64 build (whose baseline has SSE2).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sse2(());

/// Proof that this CPU runs AVX2 (made only by run-time detection).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Avx2(());

impl Kernel {
    /// The AVX2 kernel if this CPU has AVX2 (x86-64 with the `std` feature: run-time
    /// detection), else `None`.
    pub fn avx2() -> Option<Kernel> {
        #[cfg(all(feature = "std", target_arch = "x86_64"))]
        if std::is_x86_feature_detected!("avx2") {
            return Some(Kernel::Avx2(Avx2(())));
        }
        None
    }

    /// The SSE2 kernel on x86-64 (every such CPU has SSE2), else `None`.
    pub fn sse2() -> Option<Kernel> {
        #[cfg(target_arch = "x86_64")]
        return Some(Kernel::Sse2(Sse2(())));
        #[cfg(not(target_arch = "x86_64"))]
        None
    }

    /// The fastest kernel here: AVX2 when detected, else the scalar loop (the firmware's).
    /// The SSE2 and plain eight-lane builds give the same rows but are slower than the
    /// scalar loop on this stage (`cargo bench -p dpsa-core --bench kernel -- phase_height`
    /// on the development machine: scalar 98 - 110, SSE2 80 - 94, plain lanes 58 - 76, AVX2
    /// 133 Mpx/s): four lanes do not pay for the emulated variable shifts, products and
    /// table reads.
    pub fn best() -> Kernel {
        Kernel::avx2().unwrap_or(Kernel::Scalar)
    }

    /// Every kernel this CPU runs, scalar first (for tests and benchmarks).
    pub fn all() -> impl Iterator<Item = Kernel> {
        [
            Some(Kernel::Scalar),
            Some(Kernel::Lanes),
            Kernel::sse2(),
            Kernel::avx2(),
        ]
        .into_iter()
        .flatten()
    }

    /// A short name (`scalar`, `lanes`, `sse2`, `avx2`).
    pub fn name(&self) -> &'static str {
        match self {
            Kernel::Scalar => "scalar",
            Kernel::Lanes => "lanes",
            Kernel::Sse2(_) => "sse2",
            Kernel::Avx2(_) => "avx2",
        }
    }

    /// [`Scale::row`] (uniform height scale) with this kernel.
    #[allow(clippy::too_many_arguments)]
    pub fn row(
        &self,
        scale: &Scale,
        gate: &Gate,
        v: &[V],
        rho: u32,
        ref_phase: &[u32],
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> u16 {
        let run = Run {
            gate,
            v,
            rho,
            ref_phase,
            mult: Mult::Uniform(scale.k),
            rounding: (1 << 15, 16),
        };
        match self {
            Kernel::Scalar => scale.row(gate, v, rho, ref_phase, heights, valid),
            Kernel::Lanes => lanes(&run, heights, valid),
            Kernel::Sse2(_) => sse2(&run, heights, valid),
            Kernel::Avx2(_) => avx2(&run, heights, valid),
        }
    }

    /// [`Scale::row_columns`] (per-column height scale) with this kernel.
    #[allow(clippy::too_many_arguments)]
    pub fn row_columns(
        &self,
        scale: &Scale,
        gate: &Gate,
        v: &[V],
        rho: u32,
        ref_phase: &[u32],
        columns: &ColumnScale<'_>,
        mantissa: &[u16],
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> u16 {
        let len = v.len().min(mantissa.len());
        let run = Run {
            gate,
            v: &v[..len],
            rho,
            ref_phase,
            mult: Mult::Columns(&mantissa[..len]),
            rounding: columns.rounding(),
        };
        match self {
            Kernel::Scalar => {
                scale.row_columns(gate, v, rho, ref_phase, columns, mantissa, heights, valid)
            }
            Kernel::Lanes => lanes(&run, heights, valid),
            Kernel::Sse2(_) => sse2(&run, heights, valid),
            Kernel::Avx2(_) => avx2(&run, heights, valid),
        }
    }
}

/// One run of columns for the eight-lane builds: the reduced pixels, their reference phases
/// and height scale.
#[derive(Clone, Copy)]
struct Run<'a> {
    gate: &'a Gate,
    v: &'a [V],
    rho: u32,
    ref_phase: &'a [u32],
    mult: Mult<'a>,
    /// `(half, sh)` of the height's rounding.
    rounding: (i32, u32),
}

/// The plain eight-lane build (the target's baseline).
#[inline(never)]
fn lanes(run: &Run<'_>, heights: &mut [i16], valid: &mut [u8]) -> u16 {
    by_lanes(run, heights, valid, eight)
}

/// The AVX2 build (x86-64; elsewhere no [`Kernel::Avx2`] exists, and this is the plain one).
fn avx2(run: &Run<'_>, heights: &mut [i16], valid: &mut [u8]) -> u16 {
    #[cfg(target_arch = "x86_64")]
    return x86::run(run, heights, valid);
    #[cfg(not(target_arch = "x86_64"))]
    lanes(run, heights, valid)
}

/// The SSE2 build (x86-64; elsewhere no [`Kernel::Sse2`] exists, and this is the plain one).
fn sse2(run: &Run<'_>, heights: &mut [i16], valid: &mut [u8]) -> u16 {
    #[cfg(target_arch = "x86_64")]
    return x86_sse2::run(run, heights, valid);
    #[cfg(not(target_arch = "x86_64"))]
    lanes(run, heights, valid)
}

/// The SSE2 build: [`eight`] as two steps of four lanes in x86-64's baseline instructions.
///
/// SSE2 lacks what the AVX2 build uses; each is restated with the same results:
///
/// - **unsigned compares, minimum and maximum** through signed compares of the values with
///   their top bit flipped;
/// - **the variable shifts** `hi << s`, `lo << s` as the low words of the products with `2^s`,
///   made as the f32 `2^s` (exponent `s + 127`) truncated to an integer: exact for `s` in
///   `0..=30`, and for `s = 31` the conversion's out-of-range result `0x8000_0000` is `2^31`
///   as a `u32`; lanes whose `s` lies outside `0..=31` (`hi = 0`, or a discarded saturated
///   lane) get 0, as the AVX2 shift by more than 31 gives;
/// - **32 x 32-bit products**: `_mm_mul_epu32` on the even and odd lanes; the low words are
///   the wrapping product, and the signed high word is the unsigned one less `b` where `a <
///   0` and less `a` where `b < 0` (mod `2^32`);
/// - **the table reads** as four scalar reads (the indices are at most 256: read as 16-bit
///   lanes).
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod x86_sse2 {
    use super::*;
    use core::arch::x86_64::*;

    /// Lanes per SSE2 step.
    const Q: usize = 4;

    pub(super) fn run(run: &Run<'_>, heights: &mut [i16], valid: &mut [u8]) -> u16 {
        by_lanes(run, heights, valid, |g, step| {
            // SAFETY: x86-64's baseline has SSE2 (this module is compiled for x86-64 only).
            unsafe { eight_sse2(g, step) }
        })
    }

    /// `a > b` as unsigned 32-bit lanes.
    #[target_feature(enable = "sse2")]
    #[inline]
    fn gt_u32(a: __m128i, b: __m128i) -> __m128i {
        let top = _mm_set1_epi32(i32::MIN);
        _mm_cmpgt_epi32(_mm_xor_si128(a, top), _mm_xor_si128(b, top))
    }

    /// `a` where `m` is all ones, else `b`.
    #[target_feature(enable = "sse2")]
    #[inline]
    fn select(m: __m128i, a: __m128i, b: __m128i) -> __m128i {
        _mm_or_si128(_mm_and_si128(m, a), _mm_andnot_si128(m, b))
    }

    /// `|v|` as unsigned 32-bit lanes (`i32::MIN` gives `2^31`).
    #[target_feature(enable = "sse2")]
    #[inline]
    fn abs(v: __m128i) -> __m128i {
        let s = _mm_srai_epi32::<31>(v);
        _mm_sub_epi32(_mm_xor_si128(v, s), s)
    }

    /// The 64-bit products of the even lanes and of the odd lanes (unsigned).
    #[target_feature(enable = "sse2")]
    #[inline]
    fn products(a: __m128i, b: __m128i) -> (__m128i, __m128i) {
        (
            _mm_mul_epu32(a, b),
            _mm_mul_epu32(_mm_srli_epi64::<32>(a), _mm_srli_epi64::<32>(b)),
        )
    }

    /// The low words of the lanes' products (the wrapping product, signed or not).
    #[target_feature(enable = "sse2")]
    #[inline]
    pub(super) fn mul_lo(a: __m128i, b: __m128i) -> __m128i {
        let (even, odd) = products(a, b);
        _mm_unpacklo_epi32(
            _mm_shuffle_epi32::<0b00_00_10_00>(even),
            _mm_shuffle_epi32::<0b00_00_10_00>(odd),
        )
    }

    /// The high words of the lanes' signed 64-bit products.
    #[target_feature(enable = "sse2")]
    #[inline]
    pub(super) fn mul_hi_i32(a: __m128i, b: __m128i) -> __m128i {
        let (even, odd) = products(a, b);
        let high = _mm_unpacklo_epi32(
            _mm_shuffle_epi32::<0b00_00_11_01>(even),
            _mm_shuffle_epi32::<0b00_00_11_01>(odd),
        );
        let fix_a = _mm_and_si128(_mm_srai_epi32::<31>(a), b);
        let fix_b = _mm_and_si128(_mm_srai_epi32::<31>(b), a);
        _mm_sub_epi32(_mm_sub_epi32(high, fix_a), fix_b)
    }

    /// Four lanes of [`eight`](super::eight): the phases, the heights (before packing), and
    /// the saturated and fast-gate lanes as bits.
    #[target_feature(enable = "sse2")]
    #[inline]
    #[allow(clippy::too_many_arguments)]
    fn four(
        x: __m128i,
        y: __m128i,
        rp: __m128i,
        mv: __m128i,
        rho: u32,
        half: i32,
        sh: u32,
        fast_thr: u32,
    ) -> (__m128i, __m128i, u32, u32) {
        let zero = _mm_setzero_si128();
        let ones = _mm_set1_epi32(-1);
        let saturated = _mm_cmpeq_epi32(x, _mm_set1_epi32(SATURATED));
        let (ax, ay) = (abs(x), abs(y));
        // swap = ax < ay.
        let swap = gt_u32(ay, ax);
        let hi = select(swap, ay, ax);
        let lo = select(swap, ax, ay);
        let fast = _mm_xor_si128(gt_u32(_mm_set1_epi32(fast_thr as i32), hi), ones);
        // s = 31 - floor(log2 hi) from the f32 exponent of hi without its second bit.
        let top = _mm_andnot_si128(_mm_srli_epi32::<1>(hi), hi);
        let bits = _mm_castps_si128(_mm_cvtepi32_ps(top));
        let e = _mm_sub_epi32(_mm_srli_epi32::<23>(bits), _mm_set1_epi32(127));
        let s = _mm_sub_epi32(_mm_set1_epi32(31), e);
        // 2^s (0 where s is outside 0..=31: those lanes shift to 0).
        let in_range = gt_u32(_mm_set1_epi32(32), s);
        let pf = _mm_castsi128_ps(_mm_slli_epi32::<23>(_mm_add_epi32(s, _mm_set1_epi32(127))));
        let pow = _mm_and_si128(_mm_cvttps_epi32(pf), in_range);
        let hs = mul_lo(hi, pow);
        let ls = mul_lo(lo, pow);
        let d = _mm_or_si128(_mm_srli_epi32::<16>(hs), _mm_set1_epi32(0x8000));
        // u32 -> f64 exactly: (ls - 2^31) as i32, then + 2^31; two lanes per division.
        let flip = _mm_xor_si128(ls, _mm_set1_epi32(i32::MIN));
        let two31 = _mm_set1_pd(2_147_483_648.0);
        let n01 = _mm_add_pd(_mm_cvtepi32_pd(flip), two31);
        let n23 = _mm_add_pd(_mm_cvtepi32_pd(_mm_unpackhi_epi64(flip, flip)), two31);
        let d01 = _mm_cvtepi32_pd(d);
        let d23 = _mm_cvtepi32_pd(_mm_unpackhi_epi64(d, d));
        let t = _mm_unpacklo_epi64(
            _mm_cvttpd_epi32(_mm_div_pd(n01, d01)),
            _mm_cvttpd_epi32(_mm_div_pd(n23, d23)),
        );
        // 0 <= t < 2^17: the signed minimum is the unsigned one.
        let lim = _mm_set1_epi32(1 << 16);
        let t = select(_mm_cmpgt_epi32(t, lim), lim, t);
        let i = _mm_srli_epi32::<8>(t);
        let f = _mm_and_si128(t, _mm_set1_epi32(0xFF));
        // i <= 256: its low 16 bits are the index (ATAN has 258 entries).
        let idx = [
            _mm_extract_epi16::<0>(i) as usize,
            _mm_extract_epi16::<2>(i) as usize,
            _mm_extract_epi16::<4>(i) as usize,
            _mm_extract_epi16::<6>(i) as usize,
        ]
        .map(|k| k.min(256));
        let ta = _mm_setr_epi32(
            ATAN[idx[0]] as i32,
            ATAN[idx[1]] as i32,
            ATAN[idx[2]] as i32,
            ATAN[idx[3]] as i32,
        );
        let tb = _mm_setr_epi32(
            ATAN[idx[0] + 1] as i32,
            ATAN[idx[1] + 1] as i32,
            ATAN[idx[2] + 1] as i32,
            ATAN[idx[3] + 1] as i32,
        );
        let step = mul_lo(_mm_sub_epi32(tb, ta), f);
        let oct = _mm_add_epi32(
            ta,
            _mm_srli_epi32::<8>(_mm_add_epi32(step, _mm_set1_epi32(1 << 7))),
        );
        let ang = select(
            swap,
            _mm_sub_epi32(_mm_set1_epi32(QUARTER as i32), oct),
            oct,
        );
        let ang = select(
            _mm_cmpgt_epi32(zero, x),
            _mm_sub_epi32(_mm_set1_epi32(HALF as i32), ang),
            ang,
        );
        let phi = select(_mm_cmpgt_epi32(zero, y), _mm_sub_epi32(zero, ang), ang);
        // Height: the high word of the signed 32 x 32 -> 64 product.
        let dd = _mm_sub_epi32(phi, _mm_add_epi32(_mm_set1_epi32(rho as i32), rp));
        let p = mul_hi_i32(dd, mv);
        let h = _mm_sra_epi32(
            _mm_add_epi32(p, _mm_set1_epi32(half)),
            _mm_cvtsi32_si128(sh as i32),
        );
        let sat_bits = _mm_movemask_ps(_mm_castsi128_ps(saturated)) as u32;
        let fast_bits = _mm_movemask_ps(_mm_castsi128_ps(fast)) as u32;
        (phi, h, sat_bits, fast_bits)
    }

    /// [`eight`](super::eight) in SSE2 instructions (the same integer results; see the
    /// module docs of this build).
    #[target_feature(enable = "sse2")]
    #[inline]
    pub(super) fn eight_sse2(gate: &Gate, step: &Step) -> Eight {
        let v = &step.v;
        let mut r = Eight {
            phi: [0; L],
            heights: [0; L],
            good: [false; L],
            saturated: [false; L],
        };
        for q in 0..L / Q {
            let k = q * Q;
            // SAFETY: unaligned 16-byte loads of four pixels' `[x, y]` pairs (32 bytes of the
            // 64 in `v` from pixel `k`, `k + Q <= L`) and of four words of `ref_phase` and `m`;
            // 16-byte stores into local arrays of 16 bytes.
            let (phi, h, sat_bits, fast_bits) = unsafe {
                let a = _mm_loadu_si128(v.as_ptr().add(k).cast());
                let b = _mm_loadu_si128(v.as_ptr().add(k + 2).cast());
                // a = x0 y0 x1 y1, b = x2 y2 x3 y3.
                let x = _mm_castps_si128(_mm_shuffle_ps::<0b10_00_10_00>(
                    _mm_castsi128_ps(a),
                    _mm_castsi128_ps(b),
                ));
                let y = _mm_castps_si128(_mm_shuffle_ps::<0b11_01_11_01>(
                    _mm_castsi128_ps(a),
                    _mm_castsi128_ps(b),
                ));
                let rp = _mm_loadu_si128(step.ref_phase.as_ptr().add(k).cast());
                let mv = _mm_loadu_si128(step.m.as_ptr().add(k).cast());
                let (phi, h, sb, fb) = four(x, y, rp, mv, step.rho, step.half, step.sh, gate.fast);
                let mut phis = [0u32; Q];
                _mm_storeu_si128(phis.as_mut_ptr().cast(), phi);
                let mut hs = [0i16; 2 * Q];
                // Within i16 (see `Scale::height`, `ColumnScale::height`): the saturating
                // pack is the scalar's truncation.
                _mm_storeu_si128(hs.as_mut_ptr().cast(), _mm_packs_epi32(h, h));
                (phis, hs, sb, fb)
            };
            r.phi[k..k + Q].copy_from_slice(&phi);
            r.heights[k..k + Q].copy_from_slice(&h[..Q]);
            settle(
                gate,
                &v[k..k + Q],
                sat_bits,
                fast_bits,
                &mut r.saturated[k..k + Q],
                &mut r.good[k..k + Q],
            );
        }
        r
    }
}

/// The AVX2 build, entered only through a [`Kernel::Avx2`] (whose existence proves the CPU
/// has it).
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod x86 {
    use super::*;

    pub(super) fn run(run: &Run<'_>, heights: &mut [i16], valid: &mut [u8]) -> u16 {
        // SAFETY: reached only through `Kernel::Avx2`, made only after run-time detection
        // found AVX2 (`Kernel::avx2`); the function is otherwise safe (slices only).
        unsafe { run_avx2(run, heights, valid) }
    }

    #[target_feature(enable = "avx2")]
    fn run_avx2(run: &Run<'_>, heights: &mut [i16], valid: &mut [u8]) -> u16 {
        // SAFETY: inlined into this AVX2 function.
        let e = |g: &Gate, step: &Step| unsafe { eight_avx2(g, step) };
        by_lanes(run, heights, valid, e)
    }

    /// [`eight`](super::eight) for the tests, as its own AVX2 function.
    #[cfg(test)]
    #[target_feature(enable = "avx2")]
    pub(super) fn eight_avx2_alone(gate: &Gate, step: &Step) -> Eight {
        // SAFETY: inside an AVX2 function.
        unsafe { eight_avx2(gate, step) }
    }

    /// [`eight`](super::eight) in AVX2 instructions, step for step (the same integer
    /// results; the module docs give why the f32 exponent and the f64 division are exact).
    /// Always inlined, so that it compiles inside its AVX2 caller (a `#[target_feature]`
    /// function cannot be forced inline, and a call per eight pixels cost a third of the
    /// stage).
    ///
    /// # Safety
    /// Only inside a `#[target_feature(enable = "avx2")]` function (which the CPU runs).
    #[inline(always)]
    unsafe fn eight_avx2(gate: &Gate, step: &Step) -> Eight {
        let Step {
            v,
            ref_phase,
            m,
            rho,
            half,
            sh,
        } = *step;
        use core::arch::x86_64::*;
        // SAFETY: the caller runs AVX2 (the intrinsics); every load, store and gather stays
        // inside its array (said at each).
        unsafe {
            // Unaligned 32-byte loads from arrays of 64 (`v`) and 32 bytes.
            let (a, b, rp, mv) = {
                (
                    _mm256_loadu_si256(v.as_ptr().cast()),
                    _mm256_loadu_si256(v.as_ptr().add(4).cast()),
                    _mm256_loadu_si256(ref_phase.as_ptr().cast()),
                    _mm256_loadu_si256(m.as_ptr().cast()),
                )
            };
            // Deinterleave: a = x0 y0 .. x3 y3, b = x4 y4 .. x7 y7.
            let idx = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
            let a = _mm256_permutevar8x32_epi32(a, idx);
            let b = _mm256_permutevar8x32_epi32(b, idx);
            let x = _mm256_permute2x128_si256::<0x20>(a, b);
            let y = _mm256_permute2x128_si256::<0x31>(a, b);
            let saturated = _mm256_cmpeq_epi32(x, _mm256_set1_epi32(SATURATED));
            let ax = _mm256_abs_epi32(x);
            let ay = _mm256_abs_epi32(y);
            let hi = _mm256_max_epu32(ax, ay);
            let lo = _mm256_min_epu32(ax, ay);
            let ones = _mm256_set1_epi32(-1);
            // swap = ax < ay: hi is not ax.
            let swap = _mm256_xor_si256(_mm256_cmpeq_epi32(hi, ax), ones);
            let fastv = _mm256_set1_epi32(gate.fast as i32);
            let fast = _mm256_cmpeq_epi32(_mm256_max_epu32(hi, fastv), hi);
            // s = 31 - floor(log2 hi) from the f32 exponent of hi without its second bit.
            let top = _mm256_andnot_si256(_mm256_srli_epi32::<1>(hi), hi);
            let bits = _mm256_castps_si256(_mm256_cvtepi32_ps(top));
            let e = _mm256_sub_epi32(_mm256_srli_epi32::<23>(bits), _mm256_set1_epi32(127));
            // Counts above 31 shift to 0 (hi = 0, or a discarded saturated lane).
            let s = _mm256_sub_epi32(_mm256_set1_epi32(31), e);
            let hs = _mm256_sllv_epi32(hi, s);
            let ls = _mm256_sllv_epi32(lo, s);
            let d = _mm256_or_si256(_mm256_srli_epi32::<16>(hs), _mm256_set1_epi32(0x8000));
            // u32 -> f64 exactly: (ls - 2^31) as i32, then + 2^31.
            let flip = _mm256_xor_si256(ls, _mm256_set1_epi32(i32::MIN));
            let two31 = _mm256_set1_pd(2_147_483_648.0);
            let n_lo = _mm256_add_pd(_mm256_cvtepi32_pd(_mm256_castsi256_si128(flip)), two31);
            let n_hi = _mm256_add_pd(
                _mm256_cvtepi32_pd(_mm256_extracti128_si256::<1>(flip)),
                two31,
            );
            let d_lo = _mm256_cvtepi32_pd(_mm256_castsi256_si128(d));
            let d_hi = _mm256_cvtepi32_pd(_mm256_extracti128_si256::<1>(d));
            let t = _mm256_set_m128i(
                _mm256_cvttpd_epi32(_mm256_div_pd(n_hi, d_hi)),
                _mm256_cvttpd_epi32(_mm256_div_pd(n_lo, d_lo)),
            );
            let t = _mm256_min_epu32(t, _mm256_set1_epi32(1 << 16));
            let i = _mm256_srli_epi32::<8>(t);
            let f = _mm256_and_si256(t, _mm256_set1_epi32(0xFF));
            // i <= 256 and ATAN has 258 entries: both gathers read inside the table.
            let (ta, tb) = {
                (
                    _mm256_i32gather_epi32::<4>(ATAN.as_ptr().cast(), i),
                    _mm256_i32gather_epi32::<4>(ATAN.as_ptr().add(1).cast(), i),
                )
            };
            let step = _mm256_mullo_epi32(_mm256_sub_epi32(tb, ta), f);
            let oct = _mm256_add_epi32(
                ta,
                _mm256_srli_epi32::<8>(_mm256_add_epi32(step, _mm256_set1_epi32(1 << 7))),
            );
            let zero = _mm256_setzero_si256();
            let ang = _mm256_blendv_epi8(
                oct,
                _mm256_sub_epi32(_mm256_set1_epi32(QUARTER as i32), oct),
                swap,
            );
            let ang = _mm256_blendv_epi8(
                ang,
                _mm256_sub_epi32(_mm256_set1_epi32(HALF as i32), ang),
                _mm256_cmpgt_epi32(zero, x),
            );
            let phi = _mm256_blendv_epi8(
                ang,
                _mm256_sub_epi32(zero, ang),
                _mm256_cmpgt_epi32(zero, y),
            );
            // Height: the high word of the signed 32 x 32 -> 64 product, even and odd lanes.
            let dd = _mm256_sub_epi32(phi, _mm256_add_epi32(_mm256_set1_epi32(rho as i32), rp));
            let pe = _mm256_mul_epi32(dd, mv);
            let po = _mm256_mul_epi32(_mm256_srli_epi64::<32>(dd), _mm256_srli_epi64::<32>(mv));
            let p = _mm256_blend_epi32::<0b1010_1010>(_mm256_srli_epi64::<32>(pe), po);
            let h = _mm256_sra_epi32(
                _mm256_add_epi32(p, _mm256_set1_epi32(half)),
                _mm_cvtsi32_si128(sh as i32),
            );
            // Within i16 (see `Scale::height`, `ColumnScale::height`): the saturating pack is the
            // scalar's truncation.
            let packed = _mm256_permute4x64_epi64::<0b00_00_10_00>(_mm256_packs_epi32(h, h));
            let mut heights = [0i16; L];
            // A 16-byte store into an array of 16 bytes.
            _mm_storeu_si128(heights.as_mut_ptr().cast(), _mm256_castsi256_si128(packed));
            let sat_bits = _mm256_movemask_ps(_mm256_castsi256_ps(saturated)) as u32;
            let fast_bits = _mm256_movemask_ps(_mm256_castsi256_ps(fast)) as u32;
            let mut phis = [0u32; L];
            // A 32-byte store into an array of 32 bytes.
            _mm256_storeu_si256(phis.as_mut_ptr().cast(), phi);
            let mut r = Eight {
                phi: phis,
                heights,
                good: [false; L],
                saturated: [false; L],
            };
            settle(gate, &v, sat_bits, fast_bits, &mut r.saturated, &mut r.good);
            r
        }
    }
}

/// Lanes per step.
const L: usize = 8;

/// The height scale of the pixels: `h = (((phi - phi_r) m) >> 32 + half) >> sh` with `m` the
/// uniform [`Scale`]'s `k` (`half = 2^15`, `sh = 16`: [`Scale::height`]) or a column's
/// mantissa ([`ColumnScale::height`]).
#[derive(Clone, Copy)]
enum Mult<'a> {
    Uniform(i32),
    Columns(&'a [u16]),
}

/// The stage over a run of columns (a multiple of 8 from its start, as [`Scale::block`]):
/// eight pixels per step ([`eight`]), the tail padded to eight. Same contract and results as
/// the scalar `block_by`.
#[inline(always)]
fn by_lanes(
    run: &Run<'_>,
    heights: &mut [i16],
    valid: &mut [u8],
    eight: impl Fn(&Gate, &Step) -> Eight,
) -> u16 {
    let Run {
        gate,
        v,
        rho,
        ref_phase,
        mult,
        rounding: (half, sh),
    } = *run;
    let len = v
        .len()
        .min(ref_phase.len())
        .min(heights.len())
        .min(valid.len() * 8);
    let (mut saturated, mut low) = (false, false);
    let mut k0 = 0;
    while k0 < len {
        let n = L.min(len - k0);
        // The tail is padded with unmodulated pixels, whose lanes are discarded.
        let mut vc = [[0i32; 2]; L];
        let mut rc = [0u32; L];
        let mut m = [0i32; L];
        vc[..n].copy_from_slice(&v[k0..k0 + n]);
        rc[..n].copy_from_slice(&ref_phase[k0..k0 + n]);
        match mult {
            Mult::Uniform(k) => m = [k; L],
            Mult::Columns(t) => {
                for (ml, &tl) in m.iter_mut().zip(&t[k0..k0 + n]) {
                    *ml = i32::from(tl);
                }
            }
        }
        let r = eight(
            gate,
            &Step {
                v: vc,
                ref_phase: rc,
                m,
                rho,
                half,
                sh,
            },
        );
        let mut byte = 0u8;
        for (l, h) in heights[k0..k0 + n].iter_mut().enumerate() {
            if r.good[l] {
                *h = r.heights[l];
            }
            byte |= (r.good[l] as u8) << l;
        }
        valid[k0 / 8] = byte;
        // Padding lanes are zero pixels: unmodulated, never counted.
        for l in 0..n {
            saturated |= r.saturated[l];
            low |= !r.saturated[l] & !r.good[l];
        }
        k0 += L;
    }
    (if saturated { flags::SATURATED } else { 0 }) | (if low { flags::LOW_MODULATION } else { 0 })
}

/// What one step of every build takes: eight reduced pixels, their reference phases and
/// height multipliers, and the height's rounding (see [`Mult`]).
#[derive(Clone, Copy)]
struct Step {
    v: [V; L],
    ref_phase: [u32; L],
    m: [i32; L],
    rho: u32,
    half: i32,
    sh: u32,
}

/// The validity of lanes `v` from their saturated and fast-gate bits (bit `l` for lane `l`):
/// a lane neither saturated nor above the gate's fast threshold takes the exact test (rare).
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
fn settle(
    gate: &Gate,
    v: &[V],
    sat_bits: u32,
    fast_bits: u32,
    saturated: &mut [bool],
    good: &mut [bool],
) {
    for (l, ((px, sat), ok)) in v.iter().zip(saturated).zip(good).enumerate() {
        let fast = fast_bits >> l & 1 != 0;
        *sat = sat_bits >> l & 1 != 0;
        *ok = !*sat
            && (fast || {
                let c2 =
                    (px[0] as i64 * px[0] as i64) as u64 + (px[1] as i64 * px[1] as i64) as u64;
                c2 >= gate.thr2 && c2 != 0
            });
    }
}

/// Eight pixels' phases, heights and validity.
struct Eight {
    /// The phases (binary angles; meaningful where `good`): what the tests compare, finer
    /// than a height.
    #[cfg_attr(not(test), allow(dead_code))]
    phi: [u32; L],
    heights: [i16; L],
    good: [bool; L],
    saturated: [bool; L],
}

/// [`Scale::phase_v`] and the height of eight pixels, each step a pass over the lanes with no
/// branch (see the module docs for the restated steps), so that the compiler turns every pass
/// into vector instructions; the exact modulation test, needed only by pixels below the
/// gate's fast threshold, is done for those lanes alone.
#[inline(always)]
fn eight(gate: &Gate, step: &Step) -> Eight {
    let Step {
        v,
        ref_phase,
        m,
        rho,
        half,
        sh,
    } = *step;
    let mut x = [0i32; L];
    let mut y = [0i32; L];
    for l in 0..L {
        x[l] = v[l][0];
        y[l] = v[l][1];
    }
    let mut hi = [0u32; L];
    let mut lo = [0u32; L];
    let mut swap = [false; L];
    let mut saturated = [false; L];
    let mut fast = [false; L];
    for l in 0..L {
        let (ax, ay) = (x[l].unsigned_abs(), y[l].unsigned_abs());
        swap[l] = ax < ay;
        hi[l] = ax.max(ay);
        lo[l] = ax.min(ay);
        saturated[l] = x[l] == SATURATED;
        fast[l] = hi[l] >= gate.fast;
    }
    // t = floor((lo << s) / d), s = clz(hi) from the f32 exponent of hi with its second bit
    // cleared (so the conversion cannot round up to the next power of two). hi = 0 gives
    // s >= 32 and shifts to 0, hence d = 0x8000 and t = 0, as the scalar's shift by 32 (a
    // shift by 0) does. A saturated lane (hi = 2^31) computes garbage that is discarded.
    let mut t = [0u32; L];
    for l in 0..L {
        let top = hi[l] & !(hi[l] >> 1);
        let e = ((top as i32 as f32).to_bits() >> 23) as i32 - 127;
        let s = (31 - e) as u32;
        let hs = if s < 32 { hi[l] << (s & 31) } else { 0 };
        let ls = if s < 32 { lo[l] << (s & 31) } else { 0 };
        let d = (hs >> 16) | 0x8000;
        t[l] = ((ls as f64 / d as f64) as i32 as u32).min(1 << 16);
    }
    let mut phi = [0u32; L];
    for l in 0..L {
        let i = ((t[l] >> 8) as usize).min(256);
        let f = t[l] & 0xFF;
        let (a, b) = (ATAN[i], ATAN[i + 1]);
        let oct = a + (((b - a) * f + (1 << 7)) >> 8);
        let ang = if swap[l] { QUARTER - oct } else { oct };
        let ang = if x[l] < 0 {
            HALF.wrapping_sub(ang)
        } else {
            ang
        };
        phi[l] = if y[l] < 0 { ang.wrapping_neg() } else { ang };
    }
    let mut heights = [0i16; L];
    for l in 0..L {
        let d = phi[l].wrapping_sub(rho.wrapping_add(ref_phase[l])) as i32 as i64;
        let p = ((d * m[l] as i64) >> 32) as i32;
        heights[l] = ((p + half) >> sh) as i16;
    }
    let mut good = [false; L];
    for l in 0..L {
        good[l] = !saturated[l] & fast[l];
    }
    if fast.iter().zip(&saturated).any(|(&f, &s)| !f & !s) {
        for l in 0..L {
            if !fast[l] && !saturated[l] {
                let c2 = (x[l] as i64 * x[l] as i64) as u64 + (y[l] as i64 * y[l] as i64) as u64;
                good[l] = c2 >= gate.thr2 && c2 != 0;
            }
        }
    }
    Eight {
        phi,
        heights,
        good,
        saturated,
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::frames::Config;
    use fixed::types::{U16F16, U20F12, U8F8};
    use std::vec;
    use std::vec::Vec;

    fn scale(min_mod: f64) -> Scale {
        Scale::new(&Config {
            width: 8,
            rows: 8,
            n: 4,
            camera: 0,
            counts_per_pixel: U16F16::ONE,
            fx: 1 << 27,
            lsb_per_turn: U16F16::from_num(2000.37),
            saturation: 4095,
            min_modulation: U20F12::from_num(min_mod),
            max_noise_gain: U8F8::from_num(2),
            max_step_rows: 4,
        })
    }

    /// A small LCG (no dependency for a test).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self) -> u32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 32) as u32
        }
    }

    /// Reduced pixels of every class: saturated, zero, tiny, at the gate's threshold, on the
    /// axes and diagonals, extremes of the i32 range, and random magnitudes at every scale.
    fn pixels(r: &mut Lcg, n: usize, thr: i32) -> Vec<V> {
        (0..n)
            .map(|_| {
                let m = |r: &mut Lcg| {
                    let sh = r.next() % 32;
                    ((r.next() as i32) >> sh).max(i32::MIN + 1)
                };
                match r.next() % 12 {
                    0 => [SATURATED, m(r)],
                    1 => [0, 0],
                    2 => [
                        thr.saturating_sub(1).saturating_add((r.next() % 3) as i32),
                        (r.next() % 3) as i32 - 1,
                    ],
                    3 => {
                        let a = m(r);
                        [a, a]
                    }
                    4 => {
                        let a = m(r);
                        [a, -a]
                    }
                    5 => [0, m(r)],
                    6 => [m(r), 0],
                    7 => [i32::MAX, i32::MIN + 1],
                    8 => [i32::MIN + 1, i32::MAX],
                    _ => [m(r), m(r)],
                }
            })
            .collect()
    }

    #[test]
    fn every_kernel_gives_the_scalar_rows() {
        let mut r = Lcg(0x5eed);
        let kernels: Vec<Kernel> = Kernel::all().collect();
        assert!(
            kernels.len() >= 2,
            "at least the scalar and the lanes kernels"
        );
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            assert!(kernels.iter().any(|k| matches!(k, Kernel::Avx2(_))));
        }
        for case in 0..600 {
            // Odd widths and widths of whole and partial lane groups, starting at 0.
            let len = match case % 6 {
                0 => 1 + (r.next() % 7) as usize,
                1 => 8,
                2 => 64,
                _ => 1 + (r.next() % 200) as usize,
            };
            let min_mod = [0.0, 0.5, 10.0, 300.0, 40_000.0][case % 5];
            let s = scale(min_mod);
            let frac = [0, 7, 12, 20, 24][(case / 5) % 5];
            let gate = s.gate(frac);
            let thr = gate.fast.min(i32::MAX as u32) as i32;
            let v = pixels(&mut r, len, thr);
            let rho = r.next();
            let ref_phase: Vec<u32> = (0..len).map(|_| r.next()).collect();
            let shift = (r.next() % 4) as u8;
            let mantissa: Vec<u16> = (0..len)
                .map(|_| (1000 + r.next() % 60_000) as u16)
                .collect();
            let columns = ColumnScale::new(shift, &mantissa);
            let before: Vec<i16> = (0..len).map(|_| r.next() as i16).collect();
            let run = |k: Kernel, per_column: bool| {
                let mut h = before.clone();
                let mut m = vec![0xA5u8; len.div_ceil(8)];
                let f = if per_column {
                    k.row_columns(
                        &s, &gate, &v, rho, &ref_phase, &columns, &mantissa, &mut h, &mut m,
                    )
                } else {
                    k.row(&s, &gate, &v, rho, &ref_phase, &mut h, &mut m)
                };
                (h, m, f)
            };
            for per_column in [false, true] {
                let want = run(Kernel::Scalar, per_column);
                for &k in &kernels[1..] {
                    assert_eq!(
                        run(k, per_column),
                        want,
                        "kernel {} against scalar: case {case}, width {len}, per-column {per_column}",
                        k.name()
                    );
                }
            }
        }
    }

    /// The phases themselves (a height hides a phase error below its LSB): every lane of
    /// every kernel's eight-pixel step against the scalar `Scale::phase_v`.
    #[test]
    #[allow(unsafe_code)]
    fn every_kernel_gives_the_scalar_phase() {
        let mut r = Lcg(0xfeed);
        let s = scale(10.0);
        let m = [1 << 16; L];
        for case in 0..20_000 {
            let gate = s.gate([0, 12, 24][case % 3]);
            let thr = gate.fast.min(i32::MAX as u32) as i32;
            let px = pixels(&mut r, L, thr);
            let v: [V; L] = px.try_into().unwrap();
            let rp = [0u32; L];
            let step = Step {
                v,
                ref_phase: rp,
                m,
                rho: 0,
                half: 1 << 15,
                sh: 16,
            };
            let mut got = std::vec![eight(&gate, &step)];
            #[cfg(target_arch = "x86_64")]
            // SAFETY: x86-64's baseline has SSE2.
            got.push(unsafe { x86_sse2::eight_sse2(&gate, &step) });
            #[cfg(target_arch = "x86_64")]
            if Kernel::avx2().is_some() {
                // SAFETY: the CPU has AVX2 (detected just above).
                got.push(unsafe { x86::eight_avx2_alone(&gate, &step) });
            }
            for e in &got {
                for l in 0..L {
                    let want = s.phase_v(&gate, v[l]);
                    assert_eq!(e.good[l], want.is_ok(), "case {case} lane {l}: {:?}", v[l]);
                    if let Ok(phi) = want {
                        assert_eq!(e.phi[l], phi, "case {case} lane {l}: {:?}", v[l]);
                    }
                }
            }
        }
    }

    /// The SSE2 build's products against i64 ones, every sign (the pipeline's multipliers are
    /// never negative, so the rows alone would not see the signed high word's corrections).
    #[test]
    #[cfg(target_arch = "x86_64")]
    #[allow(unsafe_code)]
    fn the_sse2_products_are_the_i64_products() {
        use core::arch::x86_64::*;
        let mut r = Lcg(99);
        let lanes = |v: __m128i| {
            let mut o = [0i32; 4];
            // SAFETY: a 16-byte store into an array of 16 bytes.
            unsafe { _mm_storeu_si128(o.as_mut_ptr().cast(), v) };
            o
        };
        for case in 0..100_000 {
            let pick = |r: &mut Lcg| match case % 4 {
                0 => r.next() as i32,
                1 => [i32::MIN, i32::MAX, -1, 0, 1][(r.next() % 5) as usize],
                _ => (r.next() as i32) >> (r.next() % 32),
            };
            let a: [i32; 4] = core::array::from_fn(|_| pick(&mut r));
            let b: [i32; 4] = core::array::from_fn(|_| pick(&mut r));
            // SAFETY: x86-64's baseline has SSE2.
            let (lo, hi) = unsafe {
                let va = _mm_setr_epi32(a[0], a[1], a[2], a[3]);
                let vb = _mm_setr_epi32(b[0], b[1], b[2], b[3]);
                (x86_sse2::mul_lo(va, vb), x86_sse2::mul_hi_i32(va, vb))
            };
            for l in 0..4 {
                let p = a[l] as i64 * b[l] as i64;
                assert_eq!(lanes(lo)[l], p as i32, "{} x {}", a[l], b[l]);
                assert_eq!(lanes(hi)[l], (p >> 32) as i32, "{} x {}", a[l], b[l]);
            }
        }
    }

    #[test]
    fn the_f64_division_is_the_integer_division() {
        // Every divisor d in 2^15..2^16 against numerators around its multiples and at the
        // ends of the u32 range: floor(n / d) either way.
        let mut r = Lcg(7);
        for d in (1u32 << 15)..(1 << 16) {
            for _ in 0..4 {
                let q = r.next() % (1 << 17);
                for n in [
                    (q as u64 * d as u64).saturating_sub(1),
                    q as u64 * d as u64,
                    q as u64 * d as u64 + d as u64 - 1,
                    u32::MAX as u64,
                ] {
                    let n = n.min(u32::MAX as u64) as u32;
                    assert_eq!((n as f64 / d as f64) as u32, n / d, "{n} / {d}");
                }
            }
        }
    }

    #[test]
    fn the_exponent_is_the_leading_zeros() {
        // Every hi below 2^31 (the lanes' range) at the ends of each power of two.
        for b in 0..31 {
            for hi in [1u32 << b, (1u32 << b) | 1, (2u32 << b) - 1] {
                let e = (((hi as i32 as f64).to_bits() >> 52) as u32).wrapping_sub(1023);
                assert_eq!(31 - e, hi.leading_zeros(), "hi {hi:#x}");
            }
        }
    }
}
