//! The firmware side of `dpsa`: target recordings, building the firmware, running it under
//! QEMU (`mps2-an500`, Cortex-M7), decoding its defmt log, its ELF sizes and its measurements.
//!
//! The firmware is given its input and output as host paths on the semihosting command line
//! (`dpsa-firmware RECORDING OUT [BENCH]`): it streams `RECORDING` (the target format of
//! [`dpsa_core::frames::feed`], written by [`export`]) line by line through the core, writes the
//! packet stream to `OUT` and, when `BENCH` is given, its measurements as `key value` lines.
//! Its log is defmt over the semihosting console, which QEMU writes to a file; it is decoded
//! here against the ELF's defmt table. Exit status 0 is success.
//!
//! Semihosting joins the arguments with spaces, so the firmware only ever sees paths that this
//! module makes itself (a temporary directory without spaces); the stream is then copied to
//! where the user asked.

use crate::reconstruct::{config, progress_bar};
use crate::recording::Recording;
use anyhow::{anyhow, bail, ensure, Context, Result};
use dpsa_core::frames::{feed, Trigger};
use serde::Serialize;
use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// Name of the firmware program (`argv[0]` on the semihosting command line).
pub const PROGRAM: &str = "dpsa-firmware";

/// QEMU binary that runs the firmware.
pub const QEMU: &str = "qemu-system-arm";

/// Environment variable: QEMU time limit in seconds (default [`DEFAULT_TIMEOUT_S`]).
pub const TIMEOUT_ENV: &str = "DPSA_QEMU_TIMEOUT";
/// Default QEMU time limit, seconds (a firmware that hangs is killed after it).
pub const DEFAULT_TIMEOUT_S: u64 = 1800;

/// Every key the firmware's bench file must hold (integers; ticks are SysTick ticks).
pub const BENCH_KEYS: [&str; 17] = [
    "calib_loop_instructions",
    "calib_ticks",
    "rows_out",
    "pixels_out",
    "ticks_total",
    "ticks_encode",
    "ticks_io",
    "stage_pixels",
    "ticks_accumulate",
    "ticks_phase_height",
    "solves",
    "ticks_solve",
    "stack_high_water",
    "state_bytes",
    "state_total_bytes",
    "width",
    "n",
];

// ---------------------------------------------------------------------------------------------
// Target recordings.

/// Writes `rec` as a target recording (format: [`dpsa_core::frames::feed`]) to `path`. The
/// packet stream the firmware emits from it uses codec intra period `intra_period`.
/// Returns the bytes written.
pub fn export(rec: &Recording, intra_period: u32, path: &Path) -> Result<u64> {
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut w = BufWriter::with_capacity(1 << 20, file);
    let n = export_to(rec, intra_period, &mut w, false)
        .with_context(|| format!("writing the target recording {}", path.display()))?;
    w.flush().with_context(|| format!("writing {}", path.display()))?;
    Ok(n)
}

/// [`export`] into any writer, one frame in memory at a time, with an optional progress bar.
pub fn export_to<W: Write>(rec: &Recording, intra_period: u32, mut out: W, progress: bool) -> Result<u64> {
    ensure!(intra_period >= 1, "the codec intra period must be at least 1");
    let (cfg, ref_phase) = config(&rec.manifest)?;
    let frames = &rec.manifest.frames;
    let header = feed::Header {
        cfg,
        frames: u32::try_from(frames.len()).map_err(|_| anyhow!("{} frames do not fit a target recording", frames.len()))?,
        intra_period,
    };
    // Check that the header reads back as written (the firmware applies the same checks).
    let head = header.encode();
    feed::Header::decode(&head).map_err(|e| anyhow!("the recording's configuration is not valid for the target: {e}"))?;
    out.write_all(&head)?;
    let mut table = vec![0u8; header.table_len()];
    feed::encode_table(&ref_phase, &mut table).map_err(|e| anyhow!("reference-phase table: {e}"))?;
    out.write_all(&table)?;
    let mut written = (head.len() + table.len()) as u64;

    let bar = progress_bar(progress, frames.len() as u64, "export");
    let mut bytes = Vec::with_capacity(header.frame_len());
    for (k, entry) in frames.iter().enumerate() {
        let frame = rec.frame(k)?;
        bytes.clear();
        bytes.extend_from_slice(&Trigger { seq: entry.seq, latch: entry.latch }.encode());
        for s in &frame.data {
            bytes.extend_from_slice(&s.to_le_bytes());
        }
        debug_assert_eq!(bytes.len(), header.frame_len());
        out.write_all(&bytes)?;
        written += bytes.len() as u64;
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(written)
}

// ---------------------------------------------------------------------------------------------
// Building the firmware.

/// The firmware crate (`firmware/` of this repository).
pub fn firmware_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware")
}

/// Where `firmware/build.sh` leaves the release ELF (it always builds into `firmware/target`).
pub fn default_elf_path() -> PathBuf {
    firmware_dir().join("target/thumbv7em-none-eabihf/release").join(PROGRAM)
}

/// The firmware ELF. `build`: run `firmware/build.sh` (it builds what is out of date and prints
/// the ELF path as its last line of stdout; its log goes to stderr, which is forwarded). Without
/// `build`: the ELF where the last build left it ([`default_elf_path`]), which must exist.
pub fn firmware_elf(build: bool) -> Result<PathBuf> {
    if !build {
        let p = default_elf_path();
        ensure!(
            p.is_file(),
            "no firmware ELF at {}: build it with `bash firmware/build.sh` (add --install to install \
             the cross toolchain and QEMU) or pass --elf",
            p.display()
        );
        return Ok(p);
    }
    let script = firmware_dir().join("build.sh");
    ensure!(script.is_file(), "{} is missing", script.display());
    let mut child = Command::new("bash")
        .arg(&script)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .context("starting bash firmware/build.sh")?;
    // Forward the build log line by line (through eprintln, so a test harness captures it)
    // and keep its tail for the error message.
    let stderr = child.stderr.take().expect("piped stderr");
    let log = std::thread::spawn(move || {
        let mut tail = std::collections::VecDeque::new();
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            eprintln!("{line}");
            if tail.len() == 40 {
                tail.pop_front();
            }
            tail.push_back(line);
        }
        tail.into_iter().collect::<Vec<_>>().join("\n")
    });
    let mut stdout = String::new();
    child.stdout.take().expect("piped stdout").read_to_string(&mut stdout)?;
    let status = child.wait()?;
    let tail = log.join().unwrap_or_default();
    ensure!(
        status.success(),
        "bash firmware/build.sh failed ({status}); if the cross toolchain or QEMU is missing, run \
         `bash firmware/build.sh --install`. Last lines of its log:\n{tail}"
    );
    let last = stdout.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("").trim();
    let elf = PathBuf::from(last);
    ensure!(
        elf.is_absolute() && elf.is_file(),
        "firmware/build.sh succeeded but its last line of output is not the path of an ELF: {last:?}"
    );
    Ok(elf)
}

// ---------------------------------------------------------------------------------------------
// ELF sizes.

/// Sizes of the firmware image, bytes.
#[derive(Clone, Debug, Default, Serialize, PartialEq, Eq)]
pub struct ElfSizes {
    /// Bytes loaded into flash: every allocated section with contents (vector table, code,
    /// read-only data, the `.data` and `.itcm` load images).
    pub flash: u64,
    /// Static RAM: `.data + .bss + .uninit` (the `.state` region is not counted).
    pub static_ram: u64,
    pub sections: Sections,
}

/// Section sizes, bytes (a section absent from the ELF is 0).
#[derive(Clone, Debug, Default, Serialize, PartialEq, Eq)]
pub struct Sections {
    pub vector_table: u64,
    pub text: u64,
    pub rodata: u64,
    pub data: u64,
    pub bss: u64,
    pub uninit: u64,
    /// Hot code run from ITCM (its load image is in flash too).
    pub itcm: u64,
    /// NOLOAD region of the configuration-sized buffers (capacity reserved by the link).
    pub state: u64,
}

/// Section sizes of a firmware ELF.
pub fn elf_sizes(elf: &[u8]) -> Result<ElfSizes> {
    use object::{Object, ObjectSection, SectionFlags, SectionKind};
    let file = object::File::parse(elf).context("parsing the firmware ELF")?;
    let mut out = ElfSizes::default();
    for s in file.sections() {
        let name = s.name().unwrap_or("");
        let size = s.size();
        let alloc = match s.flags() {
            SectionFlags::Elf { sh_flags } => sh_flags & u64::from(object::elf::SHF_ALLOC) != 0,
            _ => false,
        };
        let nobits = matches!(s.kind(), SectionKind::UninitializedData | SectionKind::UninitializedTls)
            || name == ".state";
        if alloc && !nobits {
            out.flash += size;
        }
        let is = |prefix: &str| name == prefix || name.starts_with(&format!("{prefix}."));
        let t = &mut out.sections;
        match () {
            _ if is(".vector_table") => t.vector_table += size,
            _ if is(".text") => t.text += size,
            _ if is(".rodata") => t.rodata += size,
            _ if is(".data") => t.data += size,
            _ if is(".bss") => t.bss += size,
            _ if is(".uninit") => t.uninit += size,
            _ if is(".itcm") => t.itcm += size,
            _ if is(".state") => t.state += size,
            _ => {}
        }
    }
    let t = &out.sections;
    out.static_ram = t.data + t.bss + t.uninit;
    ensure!(t.text > 0 || t.itcm > 0, "the ELF has no code sections: is it the firmware?");
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// QEMU.

/// Escapes a value for QEMU's option parser (a comma is written twice).
fn qemu_value(v: &str) -> String {
    v.replace(',', ",,")
}

/// A path as UTF-8, refused if the semihosting command line could not carry it.
fn arg_path(p: &Path) -> Result<String> {
    let s = p.to_str().ok_or_else(|| anyhow!("{}: not UTF-8, cannot pass it to the firmware", p.display()))?;
    ensure!(
        !s.chars().any(char::is_whitespace),
        "{s}: the semihosting command line is split at spaces, so the firmware cannot be given a path \
         containing whitespace (set TMPDIR to a directory without spaces)"
    );
    Ok(s.to_string())
}

/// The QEMU command that runs `elf` with semihosting arguments `args` (after the program name)
/// and the semihosting console (the defmt log) written to `log`. The one place the QEMU
/// machine and flags are chosen.
pub fn qemu_command(elf: &Path, args: &[String], log: &Path) -> Result<Command> {
    let mut semi = String::from("enable=on,target=native,chardev=dlog");
    for a in std::iter::once(PROGRAM.to_string()).chain(args.iter().cloned()) {
        semi.push_str(",arg=");
        semi.push_str(&qemu_value(&a));
    }
    let log = log.to_str().ok_or_else(|| anyhow!("{}: not UTF-8", log.display()))?;
    let mut cmd = Command::new(QEMU);
    cmd.args(["-machine", "mps2-an500", "-cpu", "cortex-m7", "-nographic", "-monitor", "none"])
        .args(["-serial", "none", "-icount", "shift=0"])
        .arg("-semihosting-config")
        .arg(semi)
        .arg("-chardev")
        .arg(format!("file,id=dlog,path={}", qemu_value(log)))
        .arg("-kernel")
        .arg(elf)
        .stdin(Stdio::null());
    Ok(cmd)
}

/// One decoded line of the firmware's defmt log.
#[derive(Clone, Debug, Serialize, PartialEq, Eq)]
pub struct LogLine {
    /// `TRACE`, `DEBUG`, `INFO`, `WARN`, `ERROR`, or empty for `println`.
    pub level: String,
    pub message: String,
    /// Source location (`file:line`) when the ELF has debug information for it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub location: Option<String>,
}

impl std::fmt::Display for LogLine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.level.is_empty() {
            write!(f, "{}", self.message)?;
        } else {
            write!(f, "{:<5} {}", self.level, self.message)?;
        }
        if let Some(l) = &self.location {
            write!(f, "  ({l})")?;
        }
        Ok(())
    }
}

/// What a QEMU run produced.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// Exit code of QEMU (the firmware's exit status); `None` if it was killed (time limit).
    pub code: Option<i32>,
    /// The decoded defmt log.
    pub log: Vec<LogLine>,
    /// Log frames that did not decode (damaged, or a table that does not match the ELF).
    pub malformed: usize,
    /// What QEMU itself printed (its own errors, e.g. a bad option or a missing file).
    pub qemu_output: String,
    pub elapsed: Duration,
}

impl Outcome {
    pub fn success(&self) -> bool {
        self.code == Some(0)
    }

    /// The log lines at `ERROR` level.
    pub fn errors(&self) -> impl Iterator<Item = &LogLine> {
        self.log.iter().filter(|l| l.level == "ERROR")
    }

    /// An error describing a failed run: exit status, the error lines of the log (or its last
    /// lines when there are none) and what QEMU printed.
    pub fn failure(&self) -> anyhow::Error {
        let status = match self.code {
            Some(c) => format!("the firmware exited with status {c}"),
            None => format!("the firmware did not finish (killed after {:.0} s)", self.elapsed.as_secs_f64()),
        };
        let mut lines: Vec<String> = self.errors().map(|l| l.to_string()).collect();
        if lines.is_empty() {
            let skip = self.log.len().saturating_sub(10);
            lines = self.log[skip..].iter().map(|l| l.to_string()).collect();
        }
        let mut msg = status;
        if lines.is_empty() {
            msg.push_str(" and logged nothing");
        } else {
            msg.push_str(":\n");
            msg.push_str(&lines.join("\n"));
        }
        if self.malformed > 0 {
            msg.push_str(&format!("\n({} log frames did not decode)", self.malformed));
        }
        let q = self.qemu_output.trim();
        if !q.is_empty() {
            msg.push_str("\nqemu: ");
            msg.push_str(q);
        }
        anyhow!(msg)
    }
}

/// Decodes the defmt log as it grows (the table comes from the firmware ELF).
struct LogDecoder<'t> {
    decoder: Box<dyn defmt_decoder::StreamDecoder + Send + Sync + 't>,
    locations: Option<defmt_decoder::Locations>,
    /// The repository root: source locations are shown relative to it.
    root: Option<PathBuf>,
    malformed: usize,
}

impl<'t> LogDecoder<'t> {
    fn new(table: &'t defmt_decoder::Table, elf: &[u8]) -> Self {
        let locations = table.get_locations(elf).ok().filter(|l| !l.is_empty());
        let root = firmware_dir().parent().and_then(|p| p.canonicalize().ok());
        LogDecoder { decoder: table.new_stream_decoder(), locations, root, malformed: 0 }
    }

    /// Feeds `bytes` and returns the lines that decoded.
    fn feed(&mut self, bytes: &[u8]) -> Vec<LogLine> {
        self.decoder.received(bytes);
        let mut lines = Vec::new();
        loop {
            match self.decoder.decode() {
                Ok(frame) => {
                    let location = self.locations.as_ref().and_then(|l| l.get(&frame.index())).map(|l| {
                        let file = self.root.as_deref().and_then(|r| l.file.strip_prefix(r).ok()).unwrap_or(&l.file);
                        format!("{}:{}", file.display(), l.line)
                    });
                    let level = frame.level().map(|l| l.as_str().to_uppercase()).unwrap_or_default();
                    lines.push(LogLine { level, message: frame.display_message().to_string(), location });
                }
                Err(defmt_decoder::DecodeError::UnexpectedEof) => break,
                Err(defmt_decoder::DecodeError::Malformed) => self.malformed += 1,
            }
        }
        lines
    }
}

/// A file QEMU appends defmt frames to, read as it grows.
struct LogSource<'t> {
    path: PathBuf,
    file: Option<std::fs::File>,
    dec: LogDecoder<'t>,
}

impl LogSource<'_> {
    /// Decodes what was appended since the last call.
    fn read(&mut self, buf: &mut [u8]) -> Result<Vec<LogLine>> {
        if self.file.is_none() {
            self.file = std::fs::File::open(&self.path).ok();
        }
        let mut out = Vec::new();
        if let Some(f) = self.file.as_mut() {
            loop {
                let n = f.read(buf).with_context(|| format!("reading {}", self.path.display()))?;
                if n == 0 {
                    break;
                }
                out.extend(self.dec.feed(&buf[..n]));
            }
        }
        Ok(out)
    }
}

/// QEMU time limit ([`TIMEOUT_ENV`], default [`DEFAULT_TIMEOUT_S`]).
pub fn timeout() -> Duration {
    let s = std::env::var(TIMEOUT_ENV).ok().and_then(|v| v.trim().parse().ok()).unwrap_or(DEFAULT_TIMEOUT_S);
    Duration::from_secs(s.max(1))
}

/// How a run reports on stderr.
#[derive(Clone, Copy, Debug, Default)]
pub struct Echo {
    /// Print every decoded log line (prefixed `target: `) as it arrives.
    pub log: bool,
    /// A spinner with the elapsed time and the bytes of `watch` so far.
    pub progress: bool,
}

/// Runs `elf` under QEMU with semihosting arguments `args` (host paths, after the program name).
/// Decodes the defmt log as it arrives. `watch`: a file whose size the spinner shows (the
/// packet stream). Fails only when QEMU cannot be run or the log cannot be decoded at all; the
/// firmware's own failure is in [`Outcome::code`].
pub fn qemu(elf: &Path, args: &[String], watch: Option<&Path>, echo: Echo) -> Result<Outcome> {
    let elf_bytes = std::fs::read(elf).with_context(|| format!("reading the firmware ELF {}", elf.display()))?;
    let table = defmt_decoder::Table::parse(&elf_bytes)
        .with_context(|| format!("reading the defmt table of {}", elf.display()))?
        .ok_or_else(|| anyhow!("{} has no .defmt section: not a defmt firmware", elf.display()))?;

    let dir = tempfile::Builder::new().prefix("dpsa-qemu").tempdir().context("creating a temporary directory")?;
    // The defmt frames arrive on the semihosting console. QEMU 7.2 (Debian 12) writes what the
    // firmware writes to `:tt` on its own stdout and only SYS_WRITEC/WRITE0 to the console
    // chardev; later versions send both to the chardev. Both are captured and decoded (each
    // with its own stream decoder); QEMU's own messages go to stderr.
    let console_path = dir.path().join("console.log");
    let stdout_path = dir.path().join("qemu.stdout");
    let stderr_path = dir.path().join("qemu.stderr");
    let mut cmd = qemu_command(elf, args, &console_path)?;
    cmd.stdout(std::fs::File::create(&stdout_path)?).stderr(std::fs::File::create(&stderr_path)?);
    let start = Instant::now();
    let mut child = cmd.spawn().map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            anyhow!("{QEMU} not found: install it with `bash firmware/build.sh --install` (Debian package qemu-system-arm)")
        } else {
            anyhow!("starting {QEMU}: {e}")
        }
    })?;

    let bar = if echo.progress {
        let b = indicatif::ProgressBar::new_spinner();
        if let Ok(style) = indicatif::ProgressStyle::with_template("{prefix:>12} {spinner} {elapsed} {msg}") {
            b.set_style(style);
        }
        b.set_prefix("qemu");
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let limit = timeout();
    let mut sources = [
        LogSource { path: stdout_path, file: None, dec: LogDecoder::new(&table, &elf_bytes) },
        LogSource { path: console_path, file: None, dec: LogDecoder::new(&table, &elf_bytes) },
    ];
    let mut lines = Vec::new();
    let mut buf = vec![0u8; 1 << 16];
    let mut drain = |sources: &mut [LogSource], lines: &mut Vec<LogLine>| -> Result<()> {
        for src in sources.iter_mut() {
            for l in src.read(&mut buf)? {
                if echo.log {
                    bar.suspend(|| eprintln!("target: {l}"));
                }
                lines.push(l);
            }
        }
        Ok(())
    };
    let status: Option<ExitStatus> = loop {
        if let Some(s) = child.try_wait()? {
            break Some(s);
        }
        drain(&mut sources, &mut lines)?;
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        if let Some(w) = watch {
            if let Ok(m) = std::fs::metadata(w) {
                bar.set_message(format!("{} bytes out", m.len()));
            }
        }
        bar.tick();
        std::thread::sleep(Duration::from_millis(20));
    };
    drain(&mut sources, &mut lines)?;
    bar.finish_and_clear();
    let elapsed = start.elapsed();
    let qemu_output = std::fs::read_to_string(&stderr_path).unwrap_or_default();
    let malformed = sources.iter().map(|s| s.dec.malformed).sum();
    Ok(Outcome { code: status.and_then(|s| s.code()), log: lines, malformed, qemu_output, elapsed })
}

/// Runs the firmware on a target recording file: `dpsa-firmware RECORDING OUT [BENCH]`. The
/// paths go on the semihosting command line as they are (absolute, without whitespace). A
/// failed run is an error carrying the firmware's error lines.
pub fn run_files(elf: &Path, recording: &Path, out: &Path, bench: Option<&Path>, echo: Echo) -> Result<Outcome> {
    let mut args = vec![arg_path(&absolute(recording)?)?, arg_path(&absolute(out)?)?];
    if let Some(b) = bench {
        args.push(arg_path(&absolute(b)?)?);
    }
    let o = qemu(elf, &args, Some(out), echo)?;
    if !o.success() {
        return Err(o.failure());
    }
    Ok(o)
}

fn absolute(p: &Path) -> Result<PathBuf> {
    std::path::absolute(p).with_context(|| format!("{}: cannot make the path absolute", p.display()))
}

/// What [`run`] returns.
#[derive(Clone, Debug)]
pub struct TargetOutput {
    /// The packet stream the firmware wrote.
    pub stream: Vec<u8>,
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
    pub echo: Echo,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions { intra_period: dpsa_core::packets::STREAM_INTRA_PERIOD, bench: false, echo: Echo::default() }
    }
}

/// Runs the firmware `elf` under QEMU on the recording `rec`: exports it to a temporary target
/// recording, runs QEMU and returns the packet stream (and the measurements with `bench`).
pub fn run(rec: &Recording, elf: &Path, opts: RunOptions) -> Result<TargetOutput> {
    let dir = tempfile::Builder::new().prefix("dpsa-target").tempdir().context("creating a temporary directory")?;
    let rec_path = dir.path().join("recording.dpsr");
    let out_path = dir.path().join("stream.dpsa");
    let bench_path = dir.path().join("bench.txt");
    {
        let file = std::fs::File::create(&rec_path)?;
        let mut w = BufWriter::with_capacity(1 << 20, file);
        export_to(rec, opts.intra_period, &mut w, opts.echo.progress)?;
        w.flush()?;
    }
    let outcome = run_files(elf, &rec_path, &out_path, opts.bench.then_some(bench_path.as_path()), opts.echo)?;
    let stream = std::fs::read(&out_path).context("reading the packet stream the firmware wrote")?;
    let bench = if opts.bench {
        let text = std::fs::read_to_string(&bench_path).context("reading the firmware's bench file")?;
        Some(parse_bench(&text)?)
    } else {
        None
    };
    Ok(TargetOutput { stream, outcome, bench })
}

// ---------------------------------------------------------------------------------------------
// Measurements.

/// Parses a bench file: one `key value` pair (an integer) per line; blank lines are ignored.
pub fn parse_bench(text: &str) -> Result<BTreeMap<String, i64>> {
    let mut out = BTreeMap::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let mut it = line.split_whitespace();
        let (Some(k), Some(v), None) = (it.next(), it.next(), it.next()) else {
            bail!("bench file line {}: expected `key value`, got {line:?}", i + 1);
        };
        let v: i64 = v.parse().with_context(|| format!("bench file line {}: {k}: {v:?} is not an integer", i + 1))?;
        if out.insert(k.to_string(), v).is_some() {
            bail!("bench file line {}: {k} given twice", i + 1);
        }
    }
    Ok(out)
}

/// Instructions per output pixel, by stage.
#[derive(Clone, Debug, Serialize)]
pub struct PerPixel {
    /// The whole pipeline (accumulate, solve, phase, height, mask, encode), I/O excluded.
    pub total: f64,
    /// Raw samples into the line pool and `v = P i` per pixel.
    pub accumulate: f64,
    /// Phase, height and the validity mask.
    pub phase_height: f64,
    /// Packet framing and row compression.
    pub encode: f64,
}

/// RAM figures, bytes.
#[derive(Clone, Debug, Serialize)]
pub struct Ram {
    /// `.data + .bss + .uninit` of the ELF.
    #[serde(rename = "static")]
    pub static_: u64,
    /// Core pipeline state for this recording's configuration (`Layout::bytes`).
    pub state: u64,
    /// Every configuration-sized buffer of the firmware (core state, codec reference row,
    /// line and packet buffers).
    pub state_total: u64,
    /// Deepest stack use measured by the firmware.
    pub stack_high_water: u64,
}

/// The firmware's measured figures (`dpsa target-run --bench --json`).
#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    pub instructions_per_pixel: PerPixel,
    /// One-off cost of `P` for one window (the integer solve).
    pub instructions_per_window_solve: f64,
    pub ram_bytes: Ram,
    /// Bytes the firmware occupies in flash.
    pub flash_bytes: u64,
    /// Retired instructions per SysTick tick, calibrated by the firmware (40 on mps2 at
    /// `-icount shift=0`).
    pub instructions_per_tick: f64,
    pub width: i64,
    pub n: i64,
    pub rows_out: i64,
    pub pixels_out: i64,
    /// Pixels the per-stage loops (accumulate, phase + height) were timed over.
    pub stage_pixels: i64,
    pub solves: i64,
    /// Instructions spent in semihosting file I/O (context: QEMU's host I/O, not the board's).
    pub io_instructions: f64,
    pub elf_sections: Sections,
    /// The bench file as the firmware wrote it.
    pub raw: BTreeMap<String, i64>,
}

/// Turns the firmware's bench file and the ELF sizes into figures. Every ratio needs a
/// positive denominator.
pub fn bench_report(raw: &BTreeMap<String, i64>, elf: &ElfSizes) -> Result<BenchReport> {
    let missing: Vec<&str> = BENCH_KEYS.iter().copied().filter(|k| !raw.contains_key(*k)).collect();
    ensure!(missing.is_empty(), "the firmware's bench file lacks {}", missing.join(", "));
    let get = |k: &str| raw[k];
    let positive = |k: &str| -> Result<f64> {
        let v = get(k);
        ensure!(v > 0, "bench {k} = {v}, expected > 0");
        Ok(v as f64)
    };
    let unsigned = |k: &str| -> Result<u64> { u64::try_from(get(k)).map_err(|_| anyhow!("bench {k} = {} is negative", get(k))) };
    let ipt = positive("calib_loop_instructions")? / positive("calib_ticks")?;
    let ticks = |k: &str| -> Result<f64> { Ok(unsigned(k)? as f64 * ipt) };
    let pixels = positive("pixels_out")?;
    let stage = positive("stage_pixels")?;
    let solves = positive("solves")?;
    Ok(BenchReport {
        instructions_per_pixel: PerPixel {
            total: ticks("ticks_total")? / pixels,
            accumulate: ticks("ticks_accumulate")? / stage,
            phase_height: ticks("ticks_phase_height")? / stage,
            encode: ticks("ticks_encode")? / pixels,
        },
        instructions_per_window_solve: ticks("ticks_solve")? / solves,
        ram_bytes: Ram {
            static_: elf.static_ram,
            state: unsigned("state_bytes")?,
            state_total: unsigned("state_total_bytes")?,
            stack_high_water: unsigned("stack_high_water")?,
        },
        flash_bytes: elf.flash,
        instructions_per_tick: ipt,
        width: get("width"),
        n: get("n"),
        rows_out: get("rows_out"),
        pixels_out: get("pixels_out"),
        stage_pixels: get("stage_pixels"),
        solves: get("solves"),
        io_instructions: ticks("ticks_io")?,
        elf_sections: elf.sections.clone(),
        raw: raw.clone(),
    })
}

impl BenchReport {
    /// A few lines for people.
    pub fn summary(&self) -> String {
        let p = &self.instructions_per_pixel;
        let r = &self.ram_bytes;
        let s = &self.elf_sections;
        format!(
            "Cortex-M7 (QEMU, {:.2} instructions per SysTick tick), W = {}, n = {}, {} pixels out\n\
             instructions per pixel: {:.1} total (accumulate {:.1}, phase + height {:.1}, encode {:.1})\n\
             instructions per window solve: {:.0} ({} solves)\n\
             flash {} bytes (text {}, rodata {}, data {}, itcm {}); static RAM {} bytes (data {}, bss {}, uninit {})\n\
             core state {} bytes, all config-sized buffers {} bytes, stack high water {} bytes",
            self.instructions_per_tick, self.width, self.n, self.pixels_out,
            p.total, p.accumulate, p.phase_height, p.encode,
            self.instructions_per_window_solve, self.solves,
            self.flash_bytes, s.text, s.rodata, s.data, s.itcm, r.static_, s.data, s.bss, s.uninit,
            r.state, r.state_total, r.stack_high_water
        )
    }
}

// ---------------------------------------------------------------------------------------------
// `dpsa target-run`.

/// Options of `dpsa target-run`.
#[derive(Clone, Debug)]
pub struct CliArgs<'a> {
    /// Where to write the packet stream.
    pub out: Option<&'a Path>,
    pub intra_period: u32,
    /// The firmware ELF; `None`: build it ([`firmware_elf`]).
    pub elf: Option<PathBuf>,
    pub bench: bool,
    pub json: bool,
    /// Progress bars on stderr (the decoded log is always printed there).
    pub progress: bool,
}

/// `dpsa target-run`: runs the firmware on `rec`, writes the stream to `args.out` and returns
/// what to print (a summary, or one JSON object with `--json`). The decoded log goes to stderr.
pub fn cli(rec: &Recording, args: CliArgs<'_>) -> Result<String> {
    let elf = match args.elf {
        Some(e) => e,
        None => firmware_elf(true)?,
    };
    let elf_bytes = std::fs::read(&elf).with_context(|| format!("reading {}", elf.display()))?;
    let sizes = elf_sizes(&elf_bytes).with_context(|| format!("firmware ELF {}", elf.display()))?;
    let opts = RunOptions { intra_period: args.intra_period, bench: args.bench, echo: Echo { log: true, progress: args.progress } };
    let run = run(rec, &elf, opts)?;
    if let Some(out) = args.out {
        std::fs::write(out, &run.stream).with_context(|| format!("writing {}", out.display()))?;
    }
    let (map, rep) = crate::packets::decode_stream(&run.stream, rec.manifest.calibration.height_lsb_um);
    let report = run.bench.as_ref().map(|raw| bench_report(raw, &sizes)).transpose()?;
    let seconds = run.outcome.elapsed.as_secs_f64();
    if args.json {
        let mut v = match &report {
            Some(r) => serde_json::to_value(r)?,
            None => serde_json::json!({
                "flash_bytes": sizes.flash,
                "ram_bytes": { "static": sizes.static_ram },
                "elf_sections": sizes.sections,
            }),
        };
        v["stream"] = serde_json::json!({
            "bytes": run.stream.len(),
            "packets": rep.ok,
            "corrupt": rep.corrupt,
            "rows": map.rows.len(),
            "file": args.out.map(|p| p.display().to_string()),
        });
        v["elf"] = serde_json::json!(elf.display().to_string());
        v["qemu_seconds"] = serde_json::json!(seconds);
        return Ok(serde_json::to_string_pretty(&v)?);
    }
    let dest = args.out.map(|p| format!(" -> {}", p.display())).unwrap_or_default();
    let mut text = format!(
        "target: {} packets ({} corrupt), {} bytes{dest}; {seconds:.1} s in QEMU\n",
        rep.ok,
        rep.corrupt,
        run.stream.len()
    );
    match &report {
        Some(r) => text.push_str(&r.summary()),
        None => text.push_str(&format!("firmware: flash {} bytes, static RAM {} bytes", sizes.flash, sizes.static_ram)),
    }
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn raw() -> BTreeMap<String, i64> {
        let mut m: BTreeMap<String, i64> = BENCH_KEYS.iter().map(|k| (k.to_string(), 1)).collect();
        for (k, v) in [
            ("calib_loop_instructions", 4000),
            ("calib_ticks", 100),
            ("pixels_out", 1000),
            ("ticks_total", 500),
            ("ticks_encode", 50),
            ("stage_pixels", 200),
            ("ticks_accumulate", 20),
            ("ticks_phase_height", 40),
            ("solves", 4),
            ("ticks_solve", 30),
        ] {
            m.insert(k.into(), v);
        }
        m
    }

    #[test]
    fn bench_figures_are_ticks_times_instructions_per_tick_over_pixels() {
        let r = bench_report(&raw(), &ElfSizes { flash: 9, static_ram: 7, ..Default::default() }).unwrap();
        assert_eq!(r.instructions_per_tick, 40.0);
        assert_eq!(r.instructions_per_pixel.total, 20.0);
        assert_eq!(r.instructions_per_pixel.encode, 2.0);
        assert_eq!(r.instructions_per_pixel.accumulate, 4.0);
        assert_eq!(r.instructions_per_pixel.phase_height, 8.0);
        assert_eq!(r.instructions_per_window_solve, 300.0);
        assert_eq!((r.flash_bytes, r.ram_bytes.static_), (9, 7));
        let v = serde_json::to_value(&r).unwrap();
        assert_eq!(v["ram_bytes"]["static"], 7);
        assert_eq!(v["instructions_per_pixel"]["total"], 20.0);
    }

    #[test]
    fn bench_file_errors() {
        let mut m = raw();
        m.remove("ticks_solve");
        let e = bench_report(&m, &ElfSizes::default()).unwrap_err().to_string();
        assert!(e.contains("ticks_solve"), "{e}");
        let mut m = raw();
        m.insert("calib_ticks".into(), 0);
        let e = bench_report(&m, &ElfSizes::default()).unwrap_err().to_string();
        assert!(e.contains("calib_ticks"), "{e}");
        assert_eq!(parse_bench("a 1\n\nb -2\n").unwrap(), BTreeMap::from([("a".into(), 1), ("b".into(), -2)]));
        assert!(parse_bench("a 1 2").is_err());
        assert!(parse_bench("a x").unwrap_err().to_string().contains("line 1"));
        assert!(parse_bench("a 1\na 2").unwrap_err().to_string().contains("twice"));
    }

    #[test]
    fn qemu_values_double_commas_and_paths_with_spaces_are_refused() {
        assert_eq!(qemu_value("/a,b/c,,d"), "/a,,b/c,,,,d");
        let cmd = qemu_command(Path::new("/x/fw.elf"), &["/t/r,1".into(), "/t/o".into()], Path::new("/l,og")).unwrap();
        let args: Vec<String> = cmd.get_args().map(|a| a.to_string_lossy().into_owned()).collect();
        let semi = &args[args.iter().position(|a| a == "-semihosting-config").unwrap() + 1];
        assert!(semi.ends_with(",arg=dpsa-firmware,arg=/t/r,,1,arg=/t/o"), "{semi}");
        assert!(args.contains(&"file,id=dlog,path=/l,,og".to_string()), "{args:?}");
        assert!(arg_path(Path::new("/a b/c")).unwrap_err().to_string().contains("whitespace"));
    }
}
