//! The firmware side of `dpsa`: feeds, building the firmware, running it under
//! QEMU (`mps2-an500`, Cortex-M7), decoding its defmt log, its ELF sizes and its measurements.
//!
//! The firmware is given its input and output as host paths on the semihosting command line
//! (`dpsa-firmware FEED OUT [BENCH]`): it streams `FEED` (the format of
//! [`dpsa_core::frames::feed`], written by [`write_feed`]) line by line through the core, writes the
//! packet stream to `OUT` and, when `BENCH` is given, its measurements as `key value` lines.
//! Its log is defmt over the semihosting console, which QEMU writes to a file; it is decoded
//! here against the ELF's defmt table. Exit status 0 is success.
//!
//! Semihosting joins the arguments with spaces, so the firmware only ever sees paths that this
//! module makes itself (a temporary directory without spaces); the stream is then copied to
//! where the user asked.

pub mod bench;
pub mod elf;
pub mod feed;
pub mod firmware;
pub mod qemu;

pub use bench::*;
pub use elf::*;
pub use feed::*;
pub use firmware::*;
pub use qemu::*;

use crate::simulation::recording::Recording;
use crate::{At, Result};
use std::collections::BTreeMap;
use std::io::{BufWriter, Write};
use std::path::Path;

/// Name of the firmware program (`argv[0]` on the semihosting command line).
pub const PROGRAM: &str = "dpsa-firmware";

/// QEMU binary that runs the firmware.
pub const QEMU: &str = "qemu-system-arm";

/// Environment variable: QEMU time limit in seconds (default [`DEFAULT_TIMEOUT_S`]).
pub const TIMEOUT_ENV: &str = "DPSA_QEMU_TIMEOUT";
/// Default QEMU time limit, seconds (a firmware that hangs is killed after it).
pub const DEFAULT_TIMEOUT_S: u64 = 1800;

/// What [`run`] returns: the firmware's packet stream, the QEMU run and the measurements.
#[derive(Clone, Debug)]
pub struct TargetOutput {
    /// The packet stream the firmware wrote.
    pub stream: Vec<u8>,
    /// How the QEMU run ended (exit code, decoded log).
    pub outcome: Outcome,
    /// The firmware's measurements (`--bench`), key by key.
    pub bench: Option<BTreeMap<String, i64>>,
}

/// Options of [`run`].
#[derive(Clone, Copy, Debug)]
pub struct RunOptions {
    /// Codec intra period of the stream (the host default is
    /// [`dpsa_core::packets::STREAM_INTRA_PERIOD`]).
    pub intra_period: u32,
    /// Ask the firmware for its measurements.
    pub bench: bool,
    /// What the run reports on stderr (log lines, spinner).
    pub echo: Echo,
    /// Send the packet stream over the board's UART, carried by QEMU as a TCP connection to
    /// this address (a frame grabber on the line), instead of writing it to a file: the
    /// returned stream is then empty.
    pub link: Option<std::net::SocketAddr>,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            intra_period: dpsa_core::packets::STREAM_INTRA_PERIOD,
            bench: false,
            echo: Echo::default(),
            link: None,
        }
    }
}

/// Runs the firmware `elf` under QEMU on the recording `rec`: exports it to a temporary feed, runs QEMU and returns the packet stream (and the measurements with `bench`).
pub fn run(rec: &Recording, elf: &Path, opts: RunOptions) -> Result<TargetOutput> {
    run_with_fabric(rec, elf, opts, None)
}

/// [`run`] with the FPGA front end: the firmware takes its rows from the fabric's logs
/// (`dpsa_fpga::front`, written by the RTL's models on the same recording) instead of
/// computing them (and, with a payload log, framing the fabric's payloads instead of coding).
pub fn run_with_fabric(
    rec: &Recording,
    elf: &Path,
    opts: RunOptions,
    fabric: Option<FabricLogs<'_>>,
) -> Result<TargetOutput> {
    let dir = tempfile::Builder::new()
        .prefix("dpsa-target")
        .tempdir()
        .at(|| "creating a temporary directory")?;
    let feed_path = dir.path().join("feed.dpsr");
    let out_path = dir.path().join("stream.dpsa");
    let bench_path = dir.path().join("bench.txt");
    {
        let file = std::fs::File::create(&feed_path)?;
        let mut w = BufWriter::with_capacity(1 << 20, file);
        write_feed_to(rec, opts.intra_period, &mut w, opts.echo.progress)?;
        w.flush()?;
    }
    if let (Some(_), Some(_)) = (opts.link, fabric) {
        return Err(crate::SimError::Refused(
            "the front end's fabric log and the line's link are not run together".into(),
        ));
    }
    if let Some(link) = opts.link {
        let outcome = run_link(elf, &feed_path, link, opts.echo)?;
        return Ok(TargetOutput {
            stream: Vec::new(),
            outcome,
            bench: None,
        });
    }
    let outcome = run_files(
        elf,
        &feed_path,
        &out_path,
        opts.bench.then_some(bench_path.as_path()),
        fabric,
        opts.echo,
    )?;
    let stream = std::fs::read(&out_path).at(|| "reading the packet stream the firmware wrote")?;
    let bench = if opts.bench {
        let text =
            std::fs::read_to_string(&bench_path).at(|| "reading the firmware's bench file")?;
        Some(parse_bench(&text)?)
    } else {
        None
    };
    Ok(TargetOutput {
        stream,
        outcome,
        bench,
    })
}
