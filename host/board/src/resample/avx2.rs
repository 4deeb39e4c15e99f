//! [`Taps::pixel`]'s common case four pixels at a time in AVX2 (x86-64, after run-time
//! detection): a pixel in the rows at hand whose four neighbours are valid, of a camera with
//! no lost row and no variance grid. The same operations in the same order on the same
//! `f64` and `f32` values (the vector instructions round as the scalar ones do, and no
//! multiplication and addition are fused), so the same values to the bit; a group of four
//! with any other pixel is left to [`Taps::pixel`].

// The module is the crate's one place of unsafe code besides its call: intrinsics that read
// and write through pointers, after run-time detection.
#![allow(unsafe_code)]

use super::Taps;
use std::arch::x86_64::*;

/// Whether [`run`] can take `taps`' pixels: no variance, no lost row, indices within `i32`,
/// and the rows at hand and the heights per turn as large as their sizes say.
pub(super) fn takes(taps: &Taps) -> bool {
    let fits = |n: usize| n >= 1 && n <= i32::MAX as usize;
    taps.vs.is_none()
        && !taps.any_lost
        && fits(taps.w)
        && fits(taps.rows)
        && taps
            .rows
            .checked_mul(taps.w)
            .is_some_and(|n| n <= taps.hs.len())
        && taps.period.len() >= taps.w
}

/// The run's pixels at camera rows `bs` (from the camera's row 0) and columns `cs` (at most
/// 64) four at a time, into `heights`, `period` and `weight` (each at least as long as
/// `bs`) where all four of a group take [`Taps::pixel`]'s common case (their values exactly
/// its `Pixel::Valid`'s); the others' bits set in the mask returned, for [`Taps::pixel`].
///
/// # Safety
///
/// The processor runs AVX2 ([`Instructions::avx2`](dpsa_formats::instructions::Instructions::avx2)), and [`takes`] is true of `taps`.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn run(
    taps: &Taps,
    bs: &[f64],
    cs: &[f64],
    heights: &mut [f32],
    period: &mut [f32],
    weight: &mut [f32],
) -> u64 {
    let n = bs.len().min(cs.len()).min(64);
    assert!(heights.len() >= n && period.len() >= n && weight.len() >= n);
    let mut left = if n == 64 { u64::MAX } else { (1u64 << n) - 1 };
    let row0 = _mm256_set1_pd(taps.row0_f);
    let zero = _mm256_setzero_pd();
    let one = _mm256_set1_pd(1.0);
    let (last_b, last_c) = (_mm256_set1_pd(taps.last_b), _mm256_set1_pd(taps.last_c));
    let half = _mm256_set1_pd(0.5);
    let inv_feather = _mm256_set1_pd(taps.inv_feather);
    let (w_lo, w_hi) = (_mm256_set1_pd(1e-3), one);
    let one_i = _mm_set1_epi32(1);
    // `takes`: both fit i32.
    let rows_last = _mm_set1_epi32((taps.rows - 1) as i32);
    let cols_last = _mm_set1_epi32((taps.w - 1) as i32);
    let w64 = _mm256_set1_epi64x(taps.w as i64);
    let abs = _mm_castsi128_ps(_mm_set1_epi32(0x7fff_ffff));
    let inf = _mm_set1_ps(f32::INFINITY);
    let (hs, ps) = (taps.hs.as_ptr(), taps.period.as_ptr());
    for j in (0..n - n % 4).step_by(4) {
        // SAFETY: `j + 4 <= n`, within `bs`, `cs` and the outputs.
        let (b, c) = unsafe {
            (
                _mm256_sub_pd(_mm256_loadu_pd(bs.as_ptr().add(j)), row0),
                _mm256_loadu_pd(cs.as_ptr().add(j)),
            )
        };
        // In the rows at hand (ordered comparisons: NaN is out).
        let inside = _mm256_and_pd(
            _mm256_and_pd(
                _mm256_cmp_pd::<_CMP_GE_OQ>(b, zero),
                _mm256_cmp_pd::<_CMP_GE_OQ>(c, zero),
            ),
            _mm256_and_pd(
                _mm256_cmp_pd::<_CMP_LE_OQ>(b, last_b),
                _mm256_cmp_pd::<_CMP_LE_OQ>(c, last_c),
            ),
        );
        if _mm256_movemask_pd(inside) != 0b1111 {
            continue;
        }
        // Non-negative and at most the last row and column: truncation is the floor, as
        // `Taps::pixel`'s conversion through i64 (the values fit i32).
        let (b0, c0) = (_mm256_cvttpd_epi32(b), _mm256_cvttpd_epi32(c));
        let fb = _mm256_sub_pd(b, _mm256_cvtepi32_pd(b0));
        let fc = _mm256_sub_pd(c, _mm256_cvtepi32_pd(c0));
        let b1 = _mm_min_epi32(_mm_add_epi32(b0, one_i), rows_last);
        let c1 = _mm_min_epi32(_mm_add_epi32(c0, one_i), cols_last);
        let r0 = _mm256_mul_epi32(_mm256_cvtepi32_epi64(b0), w64);
        let r1 = _mm256_mul_epi32(_mm256_cvtepi32_epi64(b1), w64);
        let (c0l, c1l) = (_mm256_cvtepi32_epi64(c0), _mm256_cvtepi32_epi64(c1));
        // SAFETY: every index is a row of `0..rows` times `w` plus a column of `0..w`, below
        // `rows * w <= hs.len()` (`takes`); the columns are below `w <= period.len()`.
        let (h00, h01, h10, h11, p0, p1) = unsafe {
            (
                _mm256_i64gather_ps::<4>(hs, _mm256_add_epi64(r0, c0l)),
                _mm256_i64gather_ps::<4>(hs, _mm256_add_epi64(r0, c1l)),
                _mm256_i64gather_ps::<4>(hs, _mm256_add_epi64(r1, c0l)),
                _mm256_i64gather_ps::<4>(hs, _mm256_add_epi64(r1, c1l)),
                _mm_i32gather_ps::<4>(ps, c0),
                _mm_i32gather_ps::<4>(ps, c1),
            )
        };
        // `(h00 + h01 + h10 + h11).is_finite()`, in f32 in that order.
        let sum = _mm_add_ps(_mm_add_ps(_mm_add_ps(h00, h01), h10), h11);
        if _mm_movemask_ps(_mm_cmplt_ps(_mm_and_ps(sum, abs), inf)) != 0b1111 {
            continue;
        }
        let (h00, h01, h10, h11) = (
            _mm256_cvtps_pd(h00),
            _mm256_cvtps_pd(h01),
            _mm256_cvtps_pd(h10),
            _mm256_cvtps_pd(h11),
        );
        let top = _mm256_add_pd(h00, _mm256_mul_pd(fc, _mm256_sub_pd(h01, h00)));
        let bottom = _mm256_add_pd(h10, _mm256_mul_pd(fc, _mm256_sub_pd(h11, h10)));
        let h = _mm256_add_pd(top, _mm256_mul_pd(fb, _mm256_sub_pd(bottom, top)));
        let t = _mm256_add_pd(
            _mm256_mul_pd(_mm256_cvtps_pd(p0), _mm256_sub_pd(one, fc)),
            _mm256_mul_pd(_mm256_cvtps_pd(p1), fc),
        );
        // `(c.min(last_c - c) + 0.5) * inv_feather`, clamped to [1e-3, 1].
        let edge = _mm256_add_pd(_mm256_min_pd(c, _mm256_sub_pd(last_c, c)), half);
        let wt = _mm256_min_pd(_mm256_max_pd(_mm256_mul_pd(edge, inv_feather), w_lo), w_hi);
        // SAFETY: `j + 4 <= n`, within the outputs (asserted above).
        unsafe {
            _mm_storeu_ps(heights.as_mut_ptr().add(j), _mm256_cvtpd_ps(h));
            _mm_storeu_ps(period.as_mut_ptr().add(j), _mm256_cvtpd_ps(t));
            _mm_storeu_ps(weight.as_mut_ptr().add(j), _mm256_cvtpd_ps(wt));
        }
        left &= !(0b1111u64 << j);
    }
    left
}

/// [`Sampler::seen_at`](super::Sampler::seen_at)'s common case four pixels at a time: every
/// pixel of the run (`(column, its share of the camera row)` pairs) between row places `s`
/// and `s + 1`, at `p` (the place of row `s`, rows) with `q` (`1 / (place of s + 1 - p)`),
/// seen at camera row `s + (b_row - share - p) q` and column `column - across(row)`, the
/// row places' `across` interpolated (0 past their end, the last one past the last but
/// one); the same operations in the same order as the scalar form, so the same values. The
/// pixels past the last whole four are left as they are; returns how many were written.
///
/// # Safety
///
/// The processor runs AVX2 ([`Instructions::avx2`](dpsa_formats::instructions::Instructions::avx2)); `s` is a row of `across` (so the rows found are
/// at least `s >= 0`), which has fewer than `i32::MAX` rows.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn seen_in_one(
    (s, p, q): (usize, f64, f64),
    b_row: f64,
    run: &[(f64, f64)],
    across: &[f64],
    bs: &mut [f64],
    cs: &mut [f64],
) -> usize {
    let n = run.len().min(bs.len()).min(cs.len());
    let n4 = n - n % 4;
    assert!(s < across.len() && across.len() < i32::MAX as usize);
    let s = _mm256_set1_pd(s as i64 as f64);
    let (p, q, b_row) = (_mm256_set1_pd(p), _mm256_set1_pd(q), _mm256_set1_pd(b_row));
    let one = _mm256_set1_pd(1.0);
    let len = _mm_set1_epi32(across.len() as i32);
    let one_i = _mm_set1_epi32(1);
    let zero = _mm256_setzero_pd();
    for j in (0..n4).step_by(4) {
        // SAFETY: `j + 4 <= n`: pairs `j..j + 4` of `run` (eight f64), values `j..j + 4` of
        // `bs` and `cs`.
        let (x0, x1) = unsafe {
            let at = run.as_ptr().add(j).cast::<f64>();
            (_mm256_loadu_pd(at), _mm256_loadu_pd(at.add(4)))
        };
        // [c0 a0 c1 a1], [c2 a2 c3 a3] -> [c0 c2 c1 c3], [a0 a2 a1 a3] -> in order.
        let cc = _mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_unpacklo_pd(x0, x1));
        let along = _mm256_permute4x64_pd::<0b11_01_10_00>(_mm256_unpackhi_pd(x0, x1));
        let t = _mm256_sub_pd(b_row, along);
        let b = _mm256_add_pd(s, _mm256_mul_pd(_mm256_sub_pd(t, p), q));
        // `b >= s >= 0` (`t >= p`), below `i32::MAX`: truncation is the floor.
        let i = _mm256_cvttpd_epi32(b);
        let f = _mm256_sub_pd(b, _mm256_cvtepi32_pd(i));
        let i1 = _mm_add_epi32(i, one_i);
        let has = |k: __m128i| _mm256_castsi256_pd(_mm256_cvtepi32_epi64(_mm_cmpgt_epi32(len, k)));
        // SAFETY: only the rows below `across.len()` are read (the masks).
        let (a0, a1) = unsafe {
            let a0 = _mm256_mask_i32gather_pd::<8>(zero, across.as_ptr(), i, has(i));
            (
                a0,
                _mm256_mask_i32gather_pd::<8>(a0, across.as_ptr(), i1, has(i1)),
            )
        };
        let shift = _mm256_add_pd(
            _mm256_mul_pd(a0, _mm256_sub_pd(one, f)),
            _mm256_mul_pd(a1, f),
        );
        let c = _mm256_sub_pd(cc, shift);
        // SAFETY: as above.
        unsafe {
            _mm256_storeu_pd(bs.as_mut_ptr().add(j), b);
            _mm256_storeu_pd(cs.as_mut_ptr().add(j), c);
        }
    }
    n4
}
