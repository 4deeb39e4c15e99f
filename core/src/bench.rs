//! The core's internal stages, for benchmarks and reference comparisons only: **not a stable
//! API**.
//!
//! The per-window solve ([`Window`]), the accumulate kernel (`v = P i`: [`Coef`], [`block`],
//! [`block_packed`], [`pixel_v`], the i64 reference [`pixel`]) and the DSP instruction checks
//! ([`check_against_twins`]) are internal to the streaming [`Pipeline`](crate::Pipeline),
//! which is the supported way to run them. They are re-exported here, and only here, for
//! the firmware's on-target benchmark (`firmware/src/bench.rs`: the stages timed apart, the
//! solve timed, the `asm!` instructions checked against their portable twins), the core's
//! host benchmark (`benches/kernel.rs`) and the host's f64 reference comparisons. Names,
//! signatures and formats here may change with any release.

pub use crate::accumulate::{
    block, block_packed, block_packed_with, block_with, pixel, pixel_v, Acc, Coef, SATURATED, V,
};
pub use crate::dsp::{check_against_twins, checks};
pub use crate::solve::{SolveError, Window, MAX_N, MIN_N, P_FRAC};
