//! `dpsa`: simulate recordings, run the fixed-point D-PSA core on them, compare it with an f64
//! reference and the ground truth, decode packet streams, run the firmware under QEMU.
//!
//! This file only dispatches; each subcommand's arguments and printing are in `commands/`.

mod commands;

use clap::Parser;
use commands::{Cli, Cmd};

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
    // The line service handles its own signals (SIGTERM: finish the board in progress); every
    // other command removes its unfinished outputs on SIGINT / SIGTERM.
    if !matches!(args.cmd, Cmd::Line(_)) {
        dpsa_formats::files::remove_unfinished_on_interrupt();
    }
    let progress = !args.quiet;
    let res = match args.cmd {
        #[cfg(feature = "sim")]
        Cmd::Simulate(a) => commands::simulate::run(a, progress),
        #[cfg(feature = "sim")]
        Cmd::Calibrate(a) => commands::calibrate::run(a),
        // 0, or 2 when a --streams stream was damaged or incomplete (commands/board.rs).
        Cmd::Board(a) => commands::board::run(a, progress).map(exit_unless_zero),
        #[cfg(feature = "sim")]
        Cmd::Layout(a) => commands::layout::run(a),
        #[cfg(feature = "sim")]
        Cmd::Reconstruct(a) => commands::reconstruct::run(a, progress),
        #[cfg(feature = "sim")]
        Cmd::Compare(a) => commands::compare::run(a, progress),
        #[cfg(feature = "sim")]
        Cmd::Phase(a) => commands::phase::run(a),
        Cmd::Pads(a) => commands::pads::run(a),
        Cmd::Inspect(a) => commands::inspect::run(a, progress),
        Cmd::Program(a) => commands::program::run(*a),
        #[cfg(feature = "sim")]
        Cmd::Grr(a) => commands::grr::run(a),
        // 0 clean, 2 damaged or incomplete, 3 nothing decodable (commands/decode.rs).
        Cmd::Decode(a) => commands::decode::run(a).map(exit_unless_zero),
        Cmd::Line(a) => commands::line::run(a),
        Cmd::Spc(a) => commands::spc::run(a),
        Cmd::Serve(a) => commands::serve::run(a),
        #[cfg(feature = "sim")]
        Cmd::PrintProcess(a) => commands::print_process::run(a),
        #[cfg(feature = "sim")]
        Cmd::FrameBench(a) => commands::frame_bench::run(a),
        #[cfg(feature = "sim")]
        Cmd::BoardBench(a) => commands::board_bench::run(a),
        #[cfg(feature = "sim")]
        Cmd::PadsBench(a) => commands::pads_bench::run(a),
        #[cfg(feature = "sim")]
        Cmd::CodecBench(a) => commands::codec_bench::run(a, progress),
        #[cfg(feature = "sim")]
        Cmd::FpgaBench(a) => commands::fpga_bench::run(a, progress),
        #[cfg(feature = "sim")]
        Cmd::TargetRun(a) => commands::target_run::run(a, progress),
        #[cfg(feature = "sim")]
        Cmd::Demo(a) => commands::demo::run(a, progress),
    };
    if let Err(e) = res {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
