//! Statistical process control of the printing process, from the pads the line stores.
//!
//! The paste printer is the process; every pad of every board is a measurement of it. This
//! crate turns the stored pads of a run of boards into what a process engineer qualifies a
//! print with: per pad, component, package family and board the mean, the within and overall
//! sigma, `Cp`/`Cpk` and `Pp`/`Ppk` against the program's limits ([`capability`]); control
//! charts, I-MR per pad and X-bar/S with the board as the subgroup ([`chart`]); Western
//! Electric's and Nelson's run rules ([`rules`]); and alarms (which rule, which pads or
//! components, since which board: [`study`]); and the print's placement on each board (shift,
//! turn, stretch: `dpsa_inspect::print`, fitted by every inspection) and the correction it
//! proposes to the printer (`dpsa_line::printer`, the loop the line runs live); when to clean the stencil
//! ([`stencil`]); how often each rule fires by chance ([`arl`]); and the measurement system
//! itself, a gauge R&R by ANOVA ([`msa`]).
//! [`plot`] draws the charts as SVG and PNG.
//!
//! It reads no store itself (the `dpsa spc` command does, through `dpsa-line`): the
//! statistics are plain functions of numbers, tested against an independent numpy
//! implementation of `tests/REFERENCE.md` to 1e-9 relative and against published worked
//! examples. Why by hand and not an SPC crate: `docs/spc.md`.

pub mod arl;
pub mod capability;
pub mod chart;
pub mod constants;
pub mod load;
pub mod msa;
pub mod output;
pub mod plot;
pub mod rules;
pub mod stencil;
pub mod study;
