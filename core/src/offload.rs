//! The accumulate-stage offload interface: where a front end (an FPGA, or the camera's own
//! logic) can take over `v = P i`, and the core finishes the row.
//!
//! The per-pixel work splits at the reduced pixel [`V`]:
//!
//! ```text
//! samples x_j (u16) --[accumulate: front end or core]--> V = [v_2, v_3] --[phase, height, mask: core]--> row
//! ```
//!
//! ## What the core hands the front end (once per window)
//!
//! A [`Coef`] ([`Coef::of`] of the window's [`crate::solve::Window`]): for each observation
//! `j < n`, two i16 coefficients `q2[j]`, `q3[j]` (each row sums to exactly zero) and their
//! number of fractional bits `frac`; and the saturation level. In hardware these are `2n`
//! 16-bit registers per window, loaded when the last frame's encoder latch arrives.
//!
//! ## What the front end hands back (per pixel of a completed board row)
//!
//! `V = [v_2, v_3]` with `v_2 = sum_j q2[j] x_j`, `v_3 = sum_j q3[j] x_j`, in two's complement
//! 32-bit arithmetic (any intermediate wrap is harmless: for non-saturated samples the exact
//! sums are below `2^31` in magnitude, see [`Coef`]); or `[`[`SATURATED`]`, 0]` when any
//! `x_j >= saturation`. Samples may be read as `x_j` or as `x_j - 2^15` (the zero row sums
//! cancel any common offset). [`front_end_pixel`] is the reference model: a front end is
//! correct when it gives the same `V` for every input; the core's own accumulate stage
//! ([`crate::accumulate::block`]) is tested against the same model.
//!
//! A front end with wider accumulators may instead hand over the normal-equation sums of its
//! own solve; they enter here once reduced to this `V` (the phase stage needs only the ratio
//! `v_3 / v_2` and the modulation in the units of `frac`).
//!
//! ## What the core does with it
//!
//! [`finish_row`]: the modulation gate of the window ([`Scale::gate`] of `coef.frac`), the phase,
//! the height against the reference phase `rho + phi_0(c)`, the validity mask and the row
//! flags: exactly what [`crate::pipeline::Pipeline`] runs after its own accumulate stage, so an
//! offloaded row is bit-identical to a row computed on the core (tested below).
//!
//! ## A front end that takes every per-pixel stage ([`FrontEnd`])
//!
//! The FPGA front end (`fpga/`, `docs/fpga.md`) goes further: it keeps the camera's lines in
//! its own line pool and computes whole rows (accumulate, gate, phase, height, validity). The
//! MCU keeps everything that is not per pixel: the registration of frames by their encoder
//! latches, the window solve, which rows are admitted, killed or flagged, the stream. The
//! pipeline runs that split with [`crate::pipeline::Pipeline::push_to_front_end`]: for each
//! line it decides exactly as on the core, but instead of copying a line into its pool it
//! tells the front end which pool slot keeps it ([`FrontEnd::keep`]; the slot bookkeeping,
//! and so the `OVERFLOW` decisions, stay the pipeline's), and instead of computing a
//! completed row it hands the front end a [`RowJob`] ([`FrontEnd::row`]). A front end is
//! correct when its rows equal the core's: the pipeline's tests run a software front end
//! through this seam against the pipeline's own rows, and `fpga/` runs the RTL through it.

use crate::accumulate::{Coef, SATURATED, V};
use crate::height::{Gate, Scale};

/// A camera line as the pipeline receives it.
#[derive(Clone, Copy, Debug)]
pub enum Line<'l> {
    /// `W` samples as u16.
    Wide(&'l [u16]),
    /// Mono12p bytes as a 12-bit camera sends them ([`crate::frames::mono12p`]).
    Packed(&'l [u8]),
}

impl Line<'_> {
    /// The samples a front end keeps of this line, into `out` (`W` of them): a 12-bit pool
    /// (`packed_pool`, [`crate::Layout::packed`]) holds wide samples clamped to 4095, as the
    /// pool's Mono12p does; packed bytes are unpacked. A line shorter than `out` leaves the
    /// rest of `out` at 0.
    pub fn samples_into(&self, out: &mut [u16], packed_pool: bool) {
        out.fill(0);
        match *self {
            Line::Wide(l) => {
                for (o, &x) in out.iter_mut().zip(l) {
                    *o = if packed_pool { x.min(4095) } else { x };
                }
            }
            Line::Packed(b) => {
                if b.len() >= crate::frames::mono12p::packed_len(out.len()) {
                    crate::frames::mono12p::unpack(b, out);
                }
            }
        }
    }
}

/// A completed row for a [`FrontEnd`]: which kept lines, which window, which row phase.
#[derive(Clone, Copy, Debug)]
pub struct RowJob<'j> {
    /// Board row.
    pub row: i64,
    /// The pool slots of observations `0 .. n - 1` (the last observation is the line
    /// delivered with the job).
    pub slots: &'j [u16],
    /// The window's coefficients (the registers the MCU writes once per frame).
    pub coef: &'j Coef,
    /// The window's modulation gate, in the coefficients' units.
    pub gate: &'j Gate,
    /// The row phase `rho` ([`crate::Config::row_phase`]).
    pub rho: u32,
}

/// Why a front end gave no row.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrontEndError {
    /// The front end's row is not the row asked for (a lost or reordered completion).
    WrongRow {
        /// The row asked for.
        asked: i64,
        /// The row the front end delivered.
        got: i64,
    },
    /// The front end failed or stopped (no row came).
    Failed,
}

/// A front end's row codec: it codes every row the pipeline emits, in order, into the payload
/// the stream's own codec would make ([`crate::packets::codec::Encoder`] with the stream's
/// intra period), so the MCU only frames it ([`crate::sink::CodedSink`]).
pub trait RowCoder {
    /// Codes `row` into `payload` (at least [`crate::packets::codec::max_len`]`(W)` bytes);
    /// returns its length.
    fn code(&mut self, row: &crate::Row<'_>, payload: &mut [u8]) -> Result<usize, FrontEndError>;
}

/// A front end that takes over the per-pixel stages of whole rows (see the module docs).
pub trait FrontEnd {
    /// The line just delivered is an observation of a row still open: keep it in pool slot
    /// `slot` until a [`RowJob`] names it (a slot may be reused after that row).
    fn keep(&mut self, slot: u16, line: Line<'_>);
    /// Computes the row of `job`, `last` being its final observation: heights into `heights`
    /// (`W`, zero where invalid) and validity bits into `valid` (`ceil(W/8)` bytes, both
    /// zeroed on entry); returns the row flags of its pixels ([`crate::flags::SATURATED`],
    /// [`crate::flags::LOW_MODULATION`]), as [`finish_row`] does.
    fn row(
        &mut self,
        job: &RowJob<'_>,
        last: Line<'_>,
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> Result<u16, FrontEndError>;
}

/// The reference model of the front end's per-pixel output (see the module docs): exact i64
/// sums, reduced to i32 (exact for non-saturated samples).
pub fn front_end_pixel(coef: &Coef, samples: &[u16], saturation: u16) -> V {
    let n = coef.n.min(samples.len());
    if samples[..n].iter().any(|&x| x >= saturation) {
        return [SATURATED, 0];
    }
    let dot =
        |q: &[i32]| -> i32 { (0..n).map(|j| q[j] as i64 * samples[j] as i64).sum::<i64>() as i32 };
    [dot(&coef.q2), dot(&coef.q3)]
}

/// Finishes a row from the front end's `V`s: phase, height and validity of `v.len()` pixels
/// starting at a multiple of 8 (as [`Scale::block`]); returns the row flags seen.
pub fn finish_row(
    scale: &Scale,
    coef: &Coef,
    v: &[V],
    rho: u32,
    ref_phase: &[u32],
    heights: &mut [i16],
    valid: &mut [u8],
) -> u16 {
    let gate = scale.gate(coef.frac);
    scale.block(&gate, v, rho, ref_phase, heights, valid)
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::accumulate;
    use crate::phase::from_rad;
    use crate::solve::Window;
    use fixed::types::{U16F16, U20F12, U8F8};
    use std::vec::Vec;

    /// A row through the offload seam (front-end model -> finish_row) equals the core's own
    /// accumulate + phase stages, bit for bit, including saturated and unmodulated pixels.
    #[test]
    fn offloaded_rows_equal_core_rows() {
        let w = 203;
        for (th, sat) in [
            (&[0.0f64, -1.9, -3.7, -5.8][..], 4095u16),
            (&[0.0, -1.2, -2.5, -3.6, -5.0][..], 65535),
            (&[0.0, -2.1, -4.2][..], 1000),
        ] {
            let n = th.len();
            let bam: Vec<u32> = th.iter().map(|&t| from_rad(t)).collect();
            let win = Window::solve(&bam, U8F8::from_num(8)).unwrap();
            let coef = Coef::of(&win, sat).unwrap();
            let scale = Scale::from_parts(U16F16::from_num(2000), U20F12::from_num(40));
            let lines: Vec<Vec<u16>> = (0..n)
                .map(|j| {
                    (0..w)
                        .map(|c| {
                            let phi = 0.37 * c as f64 + th[j];
                            // Every 17th pixel unmodulated, every 23rd saturated.
                            let amp = if c % 17 == 0 { 5.0 } else { 300.0 };
                            let x = 500.0 + amp * phi.cos();
                            if c % 23 == 0 && j == 1 {
                                sat
                            } else {
                                x.round() as u16
                            }
                        })
                        .collect()
                })
                .collect();
            let refp: Vec<u32> = (0..w).map(|c| from_rad(0.01 * c as f64)).collect();
            let rho = from_rad(0.3);
            // Front end: its own sums.
            let v: Vec<V> = (0..w)
                .map(|c| {
                    let s: Vec<u16> = (0..n).map(|j| lines[j][c]).collect();
                    front_end_pixel(&coef, &s, sat)
                })
                .collect();
            let (mut h1, mut m1) = (std::vec![0i16; w], std::vec![0u8; w.div_ceil(8)]);
            let f1 = finish_row(&scale, &coef, &v, rho, &refp, &mut h1, &mut m1);
            // Core: the pipeline's stages.
            let ls: Vec<&[u16]> = lines.iter().map(|l| &l[..]).collect();
            let mut vc = std::vec![[0i32; 2]; w];
            accumulate::block(&coef, &ls, 0, sat, &mut vc);
            assert_eq!(v, vc, "front-end model vs core accumulate");
            let (mut h2, mut m2) = (std::vec![0i16; w], std::vec![0u8; w.div_ceil(8)]);
            let gate = scale.gate(coef.frac);
            let f2 = scale.row(&gate, &vc, rho, &refp, &mut h2, &mut m2);
            assert_eq!((h1, m1, f1), (h2, m2, f2));
            assert_eq!(f1, crate::flags::SATURATED | crate::flags::LOW_MODULATION);
        }
    }
}
