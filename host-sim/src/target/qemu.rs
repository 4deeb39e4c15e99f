//! Running the firmware under QEMU and decoding its defmt log.

use super::{firmware::firmware_dir, DEFAULT_TIMEOUT_S, PROGRAM, QEMU, TIMEOUT_ENV};
use crate::{At, Result, SimError};
use serde::Serialize;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// Escapes a value for QEMU's option parser (a comma is written twice).
fn qemu_value(v: &str) -> String {
    v.replace(',', ",,")
}

/// A path as UTF-8, refused if the semihosting command line could not carry it.
fn arg_path(p: &Path) -> Result<String> {
    let s = p.to_str().ok_or_else(|| {
        SimError::Refused(format!(
            "{}: not UTF-8, cannot pass it to the firmware",
            p.display()
        ))
    })?;
    if s.chars().any(char::is_whitespace) {
        return Err(SimError::Refused(format!(
            "{s}: the semihosting command line is split at spaces, so the firmware cannot be given a path \
             containing whitespace (set TMPDIR to a directory without spaces)"
        )));
    }
    Ok(s.to_string())
}

/// The QEMU command that runs `elf` with semihosting arguments `args` (after the program name)
/// and the semihosting console (the defmt log) written to `log`. The one place the QEMU
/// machine and flags are chosen.
pub fn qemu_command(elf: &Path, args: &[String], log: &Path) -> Result<Command> {
    qemu_command_with(elf, args, log, None)
}

/// [`qemu_command`] with the board's UART0 carried to `serial` as a TCP connection (QEMU
/// connects to it; the firmware's `uart:` output link), or none.
pub fn qemu_command_with(
    elf: &Path,
    args: &[String],
    log: &Path,
    serial: Option<std::net::SocketAddr>,
) -> Result<Command> {
    let mut semi = String::from("enable=on,target=native,chardev=dlog");
    for a in std::iter::once(PROGRAM.to_string()).chain(args.iter().cloned()) {
        semi.push_str(",arg=");
        semi.push_str(&qemu_value(&a));
    }
    let log = log
        .to_str()
        .ok_or_else(|| SimError::Refused(format!("{}: not UTF-8", log.display())))?;
    let mut cmd = Command::new(QEMU);
    cmd.args([
        "-machine",
        "mps2-an500",
        "-cpu",
        "cortex-m7",
        "-nographic",
        "-monitor",
        "none",
    ])
    .arg("-serial")
    .arg(match serial {
        Some(a) => format!("tcp:{a},nodelay=on"),
        None => "none".into(),
    })
    .args(["-icount", "shift=0"])
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
    /// The formatted message.
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
    /// Wall time of the QEMU run, until it exited or was killed.
    pub elapsed: Duration,
}

impl Outcome {
    /// Whether the firmware exited with status 0.
    pub fn success(&self) -> bool {
        self.code == Some(0)
    }

    /// The log lines at `ERROR` level.
    pub fn errors(&self) -> impl Iterator<Item = &LogLine> {
        self.log.iter().filter(|l| l.level == "ERROR")
    }

    /// An error describing a failed run: exit status, the error lines of the log (or its last
    /// lines when there are none) and what QEMU printed.
    pub fn failure(&self) -> SimError {
        let status = match self.code {
            Some(c) => format!("the firmware exited with status {c}"),
            None => format!(
                "the firmware did not finish (killed after {:.0} s)",
                self.elapsed.as_secs_f64()
            ),
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
        SimError::Tool(msg)
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
        LogDecoder {
            decoder: table.new_stream_decoder(),
            locations,
            root,
            malformed: 0,
        }
    }

    /// Feeds `bytes` and returns the lines that decoded.
    fn feed(&mut self, bytes: &[u8]) -> Vec<LogLine> {
        self.decoder.received(bytes);
        let mut lines = Vec::new();
        loop {
            match self.decoder.decode() {
                Ok(frame) => {
                    let location = self
                        .locations
                        .as_ref()
                        .and_then(|l| l.get(&frame.index()))
                        .map(|l| {
                            let file = self
                                .root
                                .as_deref()
                                .and_then(|r| l.file.strip_prefix(r).ok())
                                .unwrap_or(&l.file);
                            format!("{}:{}", file.display(), l.line)
                        });
                    let level = frame
                        .level()
                        .map(|l| l.as_str().to_uppercase())
                        .unwrap_or_default();
                    lines.push(LogLine {
                        level,
                        message: frame.display_message().to_string(),
                        location,
                    });
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
                let n = f
                    .read(buf)
                    .at(|| format!("reading {}", self.path.display()))?;
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
    let s = std::env::var(TIMEOUT_ENV)
        .ok()
        .and_then(|v| v.trim().parse().ok())
        .unwrap_or(DEFAULT_TIMEOUT_S);
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
    qemu_with(elf, args, watch, echo, None)
}

/// [`qemu`] with UART0 carried to `serial` ([`qemu_command_with`]).
pub fn qemu_with(
    elf: &Path,
    args: &[String],
    watch: Option<&Path>,
    echo: Echo,
    serial: Option<std::net::SocketAddr>,
) -> Result<Outcome> {
    let elf_bytes =
        std::fs::read(elf).at(|| format!("reading the firmware ELF {}", elf.display()))?;
    // defmt-decoder's own errors are `anyhow` chains: kept as their `{:#}` text.
    let table = defmt_decoder::Table::parse(&elf_bytes)
        .map_err(|e| SimError::Refused(format!("{e:#}")))
        .at(|| format!("reading the defmt table of {}", elf.display()))?
        .ok_or_else(|| {
            SimError::Refused(format!(
                "{} has no .defmt section: not a defmt firmware",
                elf.display()
            ))
        })?;

    let dir = tempfile::Builder::new()
        .prefix("dpsa-qemu")
        .tempdir()
        .at(|| "creating a temporary directory")?;
    // The defmt frames arrive on the semihosting console. QEMU 7.2 (Debian 12) writes what the
    // firmware writes to `:tt` on its own stdout and only SYS_WRITEC/WRITE0 to the console
    // chardev; later versions send both to the chardev. Both are captured and decoded (each
    // with its own stream decoder); QEMU's own messages go to stderr.
    let console_path = dir.path().join("console.log");
    let stdout_path = dir.path().join("qemu.stdout");
    let stderr_path = dir.path().join("qemu.stderr");
    let mut cmd = qemu_command_with(elf, args, &console_path, serial)?;
    cmd.stdout(std::fs::File::create(&stdout_path)?)
        .stderr(std::fs::File::create(&stderr_path)?);
    let start = Instant::now();
    let mut child = cmd.spawn().map_err(|e| {
        if e.kind() == std::io::ErrorKind::NotFound {
            SimError::Tool(format!("{QEMU} not found: install it with `bash firmware/build.sh --install` (Debian package qemu-system-arm)"))
        } else {
            SimError::Tool(format!("starting {QEMU}: {e}"))
        }
    })?;

    let bar = if echo.progress {
        let b = indicatif::ProgressBar::new_spinner();
        if let Ok(style) =
            indicatif::ProgressStyle::with_template("{prefix:>12} {spinner} {elapsed} {msg}")
        {
            b.set_style(style);
        }
        b.set_prefix("qemu");
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let limit = timeout();
    let mut sources = [
        LogSource {
            path: stdout_path,
            file: None,
            dec: LogDecoder::new(&table, &elf_bytes),
        },
        LogSource {
            path: console_path,
            file: None,
            dec: LogDecoder::new(&table, &elf_bytes),
        },
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
    Ok(Outcome {
        code: status.and_then(|s| s.code()),
        log: lines,
        malformed,
        qemu_output,
        elapsed,
    })
}

/// The FPGA front end's logs for a firmware run (`dpsa_fpga::front`): the rows it computed,
/// and the payloads of its row codec when it codes the rows too.
#[derive(Clone, Copy, Debug)]
pub struct FabricLogs<'p> {
    /// The fabric log (computed rows).
    pub rows: &'p Path,
    /// The payload log (every row's payload), if the fabric codes the rows.
    pub payloads: Option<&'p Path>,
}

/// Runs the firmware on a feed file: `dpsa-firmware FEED OUT [BENCH] [fabric=LOG
/// [payloads=LOG]]` (the FPGA front end's rows and its row codec's payloads,
/// `dpsa_fpga::front`). The paths go on the semihosting command
/// line as they are (absolute, without whitespace). A failed run is an error carrying the
/// firmware's error lines.
pub fn run_files(
    elf: &Path,
    feed: &Path,
    out: &Path,
    bench: Option<&Path>,
    fabric: Option<FabricLogs<'_>>,
    echo: Echo,
) -> Result<Outcome> {
    let mut args = vec![arg_path(&absolute(feed)?)?, arg_path(&absolute(out)?)?];
    if let Some(b) = bench {
        args.push(arg_path(&absolute(b)?)?);
    }
    if let Some(f) = fabric {
        args.push(format!("fabric={}", arg_path(&absolute(f.rows)?)?));
        if let Some(p) = f.payloads {
            args.push(format!("payloads={}", arg_path(&absolute(p)?)?));
        }
    }
    let o = qemu(elf, &args, Some(out), echo)?;
    if !o.success() {
        return Err(o.failure());
    }
    Ok(o)
}

/// Runs the firmware on a feed file with its packet stream on UART0, which QEMU carries as a
/// TCP connection to `link` (a frame grabber on the line: `dpsa-firmware FEED uart:`). A
/// failed run is an error carrying the firmware's error lines.
pub fn run_link(
    elf: &Path,
    feed: &Path,
    link: std::net::SocketAddr,
    echo: Echo,
) -> Result<Outcome> {
    let args = vec![arg_path(&absolute(feed)?)?, "uart:".to_string()];
    let o = qemu_with(elf, &args, None, echo, Some(link))?;
    if !o.success() {
        return Err(o.failure());
    }
    Ok(o)
}

fn absolute(p: &Path) -> Result<PathBuf> {
    std::path::absolute(p).at(|| format!("{}: cannot make the path absolute", p.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn qemu_values_double_commas_and_paths_with_spaces_are_refused() {
        assert_eq!(qemu_value("/a,b/c,,d"), "/a,,b/c,,,,d");
        let cmd = qemu_command(
            Path::new("/x/fw.elf"),
            &["/t/r,1".into(), "/t/o".into()],
            Path::new("/l,og"),
        )
        .unwrap();
        let args: Vec<String> = cmd
            .get_args()
            .map(|a| a.to_string_lossy().into_owned())
            .collect();
        let semi = &args[args
            .iter()
            .position(|a| a == "-semihosting-config")
            .unwrap()
            + 1];
        assert!(
            semi.ends_with(",arg=dpsa-firmware,arg=/t/r,,1,arg=/t/o"),
            "{semi}"
        );
        assert!(
            args.contains(&"file,id=dlog,path=/l,,og".to_string()),
            "{args:?}"
        );
        assert!(arg_path(Path::new("/a b/c"))
            .unwrap_err()
            .to_string()
            .contains("whitespace"));
    }
}
