//! # dpsa-core: fixed-point dynamic phase-shift algorithm (D-PSA)
//!
//! `#![no_std]`, no allocation, no I/O. The same code runs on the Cortex-M7 frame grabber and
//! on the host, and both produce the same bytes.
//!
//! Features (all off by default): `alloc` adds owned, heap-allocated state
//! ([`pipeline::State`], [`packets::codec::ReferenceRow`]) for hosts; `defmt` adds
//! `defmt::Format` for the core's types and errors (all in one file, `src/defmt.rs`); `dsp`
//! runs the accumulate kernel's `SMLAD`, `UQSUB16` and Mono12p unpack as `asm!` on an ARM
//! target (the firmware turns it on), instead of their portable twins, with the same results
//! (`src/dsp.rs`: the only `unsafe` in the crate; checked on the target by
//! [`bench::check_against_twins`]).
//!
//! ## Measurement model (units)
//!
//! A board rides a conveyor under a projector that throws one fixed sinusoidal fringe pattern.
//! Frames are `H` rows x `W` columns (px); image rows run along the motion. Frame `k` carries the
//! encoder count `e_k` (counts) latched at its trigger; the calibration gives `cpp` encoder
//! counts per pixel of travel. On the zero-height reference plane the fringe phase at image row
//! `r`, column `c` is `2 pi f_x r + phi_0(c)` (`f_x` in cycles/px, `phi_0` in rad); a point of
//! height `h` (um) adds `2 pi h / T_z` (`T_z = 1/f_z`, um per fringe turn):
//!
//! ```text
//! I_k(r, c) = B + C cos(2 pi f_x r + phi_0(c) + 2 pi h / T_z) + noise      [DN]
//! ```
//!
//! Frame `k` shows board row `b = r + o_k` at image row `r`, with `o_k = round(e_k / cpp)` (px).
//! A board row is observed in `n` consecutive frames `w..w+n-1` (default 4, 3..=8), at image
//! rows `b - o_{w+j}`, i.e. with the phase shifts `theta_j = -2 pi f_x (o_{w+j} - o_w)` that the
//! encoder makes known. Per pixel the paper's least squares gives
//! `v = (M^T M)^-1 M^T i` with rows `[1, cos theta_j, -sin theta_j]`, then
//! `Phi = atan2(v_3, v_2)`, and the height is
//! `h = wrap(Phi - phi_r) / (2 pi) * T_z` with `phi_r = 2 pi f_x (b - o_w) + phi_0(c)`,
//! written as i16 in units of a configurable LSB (default 0.25 um). `T_z` is one value
//! ([`Config::lsb_per_turn`]) or, with non-telecentric optics, one per column
//! ([`height::ColumnScale`], given to [`Pipeline::with_column_scale`] beside the
//! reference-phase table), so the heights leave the core in the same calibrated LSB in every
//! column. The full rule, including
//! which frames a row uses and every validity flag, is in `docs/model.md`.
//!
//! ## Data flow (one module per stage)
//!
//! frames -> `solve` -> `accumulate` -> [`phase`] -> [`height`] -> [`row`] -> [`packets`] -> [`sink`]
//!
//! - [`frames`]: integer and fixed-point [`frames::Config`], the frame [`frames::Trigger`], encoder latch to row
//!   offset and phase shift ([`frames::Config::shift`]); [`frames::registration`]: which board
//!   rows a frame admits or skips, the slot ring of open rows; [`frames::feed`]: the byte format
//!   a frame grabber is fed (configuration, reference phase, triggers and lines).
//! - `solve` (internal): `P = (M^T M)^-1 M^T` once per window, integer, with the
//!   ill-conditioning test ([`bench::Window`]).
//! - `accumulate` (internal): raw samples of open rows in a line pool; `v = P i` per pixel
//!   ([`bench::Coef`], [`bench::block`]).
//! - [`phase`]: binary angles, integer `atan2`, `sin`/`cos`.
//! - [`height`]: phase to height, validity mask.
//! - [`row`]: the output row ([`Row`], [`RowHeader`]) and its [`flags`].
//! - [`packets`]: CRC-framed row packets, the walk through a damaged stream
//!   ([`packets::Stream`]); [`packets::codec`]: lossless row compression.
//! - [`sink`]: where rows go: the [`Sink`] trait, and [`sink::PacketSink`], which frames rows
//!   into packets over any [`sink::Link`].
//! - [`pipeline`]: the streaming API that runs all of the above line by line.
//!
//! `solve`, `accumulate` and the `asm!` kernel instructions (`dsp`) are internal to the
//! pipeline; [`bench`](mod@bench) re-exports them for the firmware's on-target benchmark and the host's
//! reference comparisons, outside the stable API.
//!
//! ## State memory
//!
//! The caller supplies all state, sized by [`pipeline::Layout`]: a pool of
//! `max_step_rows * n (n-1) / 2` raw lines (`W` x u16), `max_step_rows * n` row slots, one output
//! row, the `W`-entry reference-phase table and, when used, the `W`-entry per-column
//! height-scale table (2 bytes per column, [`pipeline::Layout::with_column_scale`]). No frame is buffered whole (with `alloc`,
//! [`pipeline::State`] allocates it). For the default geometry
//! (`W = 2048`, `n = 4`, `max_step_rows = 10`): 60 lines = 245 760 B, plus 120 B free list,
//! 40 slots x 24 B, 4096 + 256 B output row and 8192 B phase table: 259 384 B in all
//! (263 480 B with a per-column height-scale table).
//!
//! ## Fixed-point error budget (each bound is tested beside its code)
//!
//! | step | format | bound |
//! | --- | --- | --- |
//! | `cos`, `sin` of the shifts | Q1.30, then Q1.24 | `4 * 2^-30`, then `2^-25` |
//! | `P` | Q7.24 (i32) | relative `3e-7 * g^2` vs f64 |
//! | kernel coefficients [`bench::Coef`] | i16, `Q?.frac` (largest `frac <= 24` that fits), row sums exactly 0 | `<= 1/2 + n/2` units of `2^-frac` per entry; largest entry `>= 2^14` (12-bit samples), `>= 2^12` (16-bit) |
//! | `v = P i` per pixel | wrapping i32, DN * 2^frac | exact given the coefficients (no 64-bit arithmetic); the accumulate stage can be offloaded ([`offload`]) |
//! | modulation test [`height::Gate`] | folded into `atan2`'s `max(abs x, abs y)` | identical to `C^2 >= min_modulation^2` |
//! | `atan2` | u32 binary angle | `2e-5` rad |
//! | height | i16 LSB | `<= 0.5` LSB rounding + phase error |
//! | per-column LSB per turn [`height::ColumnScale`] | u16 mantissa `<< shift` = Q16.16 bits (block floating point, one exponent per table) | height `<= 2^(shift-18) + 2^-18` LSB: 0.008 LSB at 2000 LSB per turn |
//!
//! ## Q-formats as types
//!
//! The configuration's Q-formats are [`fixed`] types (re-exported as [`crate::fixed`], so a
//! dependent needs no version of its own): [`Config::counts_per_pixel`] and
//! [`Config::lsb_per_turn`] `U16F16`, [`Config::min_modulation`] `U20F12`,
//! [`Config::max_noise_gain`] `U8F8` (also the limit [`bench::Window::solve`] takes), and
//! [`height::Scale::from_parts`] takes the same types. Their bits are taken once per
//! configuration or window (`to_bits()`), never in a per-pixel loop. What the per-pixel loops
//! read stays a plain integer with its format documented: the `P` entries of
//! [`bench::Window`] (Q7.24 `i32`), the constants inside [`height::Scale`], and binary angles
//! (`u32`, wrapping by design: see [`phase`]).

#![no_std]
// No `unsafe` anywhere but the three `asm!` blocks of `dsp` (`SMLAD`, `UQSUB16` and the
// Mono12p unpack; behind that module's own `allow`, on an ARM target with the `dsp` feature
// only; see that module for why and how it is tested), the SSE2 and AVX2 builds of `lanes`
// and the AVX2 build of `accumulate` (x86-64: their intrinsics' loads and stores, and AVX2
// entered only after run-time detection; see those modules).
#![deny(unsafe_code)]

#[cfg(feature = "alloc")]
extern crate alloc;
// Run-time CPU feature detection only (`lanes::Kernel::avx2`).
#[cfg(feature = "std")]
extern crate std;

pub mod accumulate;
pub mod bench;
pub mod crc32;
#[cfg(feature = "defmt")]
mod defmt;
pub(crate) mod dsp;
mod error;
pub mod frames;
pub mod height;
pub mod lanes;
pub mod offload;
pub mod packets;
pub mod phase;
pub mod pipeline;
pub mod row;
pub mod sink;
pub mod solve;
mod wide;

pub use fixed;
pub use frames::{Config, Trigger};
pub use pipeline::{Layout, Memory, Pipeline};
pub use row::{flags, Row, RowHeader};
pub use sink::Sink;
