//! `dpsa`: simulate recordings, run the fixed-point D-PSA core on them, compare it with an f64
//! reference and the ground truth, decode packet streams, run the firmware under QEMU.
//!
//! This file only dispatches; each subcommand's arguments and printing are in `cli/`.

mod cli;

use clap::Parser;
use cli::{Cli, Cmd};

/// Ends the program with `code` (after flushing stdout) unless it is 0.
fn exit_unless_zero(code: i32) {
    if code != 0 {
        use std::io::Write as _;
        let _ = std::io::stdout().flush();
        std::process::exit(code);
    }
}

fn main() {
    let args = Cli::parse();
    dpsa_sim::files::remove_unfinished_on_interrupt();
    let progress = !args.quiet;
    let res = match args.cmd {
        Cmd::Simulate(a) => cli::simulate::run(a, progress),
        Cmd::Calibrate(a) => cli::calibrate::run(a),
        // 0, or 2 when a --streams stream was damaged or incomplete (cli/board.rs).
        Cmd::Board(a) => cli::board::run(a, progress).map(exit_unless_zero),
        Cmd::Layout(a) => cli::layout::run(a),
        Cmd::Reconstruct(a) => cli::reconstruct::run(a, progress),
        Cmd::Compare(a) => cli::compare::run(a, progress),
        Cmd::Phase(a) => cli::phase::run(a),
        Cmd::Pads(a) => cli::pads::run(a),
        Cmd::Inspect(a) => cli::inspect::run(a, progress),
        Cmd::Program(a) => cli::program::run(*a),
        Cmd::Grr(a) => cli::grr::run(a),
        // 0 clean, 2 damaged or incomplete, 3 nothing decodable (cli/decode.rs).
        Cmd::Decode(a) => cli::decode::run(a).map(exit_unless_zero),
        Cmd::FrameBench(a) => cli::frame_bench::run(a),
        Cmd::BoardBench(a) => cli::board_bench::run(a),
        Cmd::PadsBench(a) => cli::pads_bench::run(a),
        Cmd::CodecBench(a) => cli::codec_bench::run(a, progress),
        Cmd::TargetRun(a) => cli::target_run::run(a, progress),
        Cmd::Demo(a) => cli::demo::run(a, progress),
    };
    if let Err(e) = res {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
