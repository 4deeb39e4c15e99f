//! The Verilator models of the RTL's top modules (`dpsa_pixel`, `dpsa_codec`): built once per
//! source fingerprint, run as a child process that speaks the records of [`crate::cosim`]
//! (pixel pipeline) or [`crate::codec`] (row-codec encoder) on its stdin and stdout.
//!
//! Why a process and not an in-process model: Verilator compiles the RTL to C++; a small
//! harness (`fpga/sim/harness.cpp`) around it reads and writes plain binary records, so the
//! Rust side needs no C++ toolchain at build time, no `unsafe` FFI and no particular Verilator
//! version beyond what `--build` offers (Debian's 5.006 works). The pipe costs a few bytes a
//! pixel, which the co-simulation's rate (millions of pixels a second) hides.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// Why the model could not be built or run.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// `verilator` is not on `PATH`.
    #[error(
        "verilator not found on PATH: the co-simulation needs it (`bash tests/run.sh` installs \
         Debian's, or `apt-get install verilator`)"
    )]
    NoVerilator,
    /// A source file could not be read.
    #[error("reading {path}: {source}")]
    Source {
        /// The file.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// Verilator or the C++ build failed; its log is kept.
    #[error("building the Verilator model failed (log: {log})")]
    Build {
        /// Verilator's and make's output.
        log: PathBuf,
    },
    /// Running the model failed.
    #[error("running the model: {0}")]
    Run(String),
    /// I/O around the build or the run.
    #[error("{0}")]
    Io(#[from] std::io::Error),
}

/// The files a model is built from.
#[derive(Clone, Debug)]
pub struct Sources {
    /// The top module (`dpsa_pixel` or `dpsa_codec`).
    pub top: String,
    /// Verilog files.
    pub rtl: Vec<PathBuf>,
    /// Files the RTL loads (`$readmemh`), each with the parameter that names it (for
    /// `dpsa_pixel`: `ATAN_HEX`).
    pub data: Vec<(String, PathBuf)>,
    /// The C++ harness.
    pub harness: PathBuf,
}

/// The `.v` files in `dir` whose names start (or, `keep = false`, do not start) with `prefix`.
fn verilog_files(dir: &Path, prefix: &str, keep: bool) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "v"))
                .filter(|p| {
                    let name = p.file_name().map(|n| n.to_string_lossy().into_owned());
                    name.is_some_and(|n| n.starts_with(prefix)) == keep
                })
                .collect()
        })
        .unwrap_or_default();
    files.sort();
    files
}

impl Sources {
    /// The repository's pixel pipeline (`fpga/rtl`, `fpga/sim/harness.cpp`).
    pub fn repo() -> Sources {
        Sources::in_dir(&crate::fpga_dir().join("rtl"))
    }

    /// The pixel pipeline in `rtl` (every `.v` file there but the codec's, and its
    /// `atan.hex`), with the repository's harness: how a test builds a mutated copy of the RTL.
    pub fn in_dir(rtl: &Path) -> Sources {
        Sources {
            top: "dpsa_pixel".into(),
            rtl: verilog_files(rtl, "dpsa_codec", false),
            data: vec![("ATAN_HEX".into(), rtl.join("atan.hex"))],
            harness: crate::fpga_dir().join("sim").join("harness.cpp"),
        }
    }

    /// The repository's row-codec encoder (`fpga/rtl/dpsa_codec*.v`,
    /// `fpga/sim/codec_harness.cpp`).
    pub fn codec_repo() -> Sources {
        Sources::codec_in_dir(&crate::fpga_dir().join("rtl"))
    }

    /// The row-codec encoder in `rtl` (its `dpsa_codec*.v` files) with the repository's codec
    /// harness.
    pub fn codec_in_dir(rtl: &Path) -> Sources {
        Sources {
            top: "dpsa_codec".into(),
            rtl: verilog_files(rtl, "dpsa_codec", true),
            data: Vec::new(),
            harness: crate::fpga_dir().join("sim").join("codec_harness.cpp"),
        }
    }

    /// FNV-1a over a version of the build's layout, the top module's name, the parameters'
    /// names and every file's name and bytes: the build cache's key.
    fn fingerprint(&self) -> Result<u64, ModelError> {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        let mut eat = |b: &[u8]| {
            for &x in b {
                h ^= x as u64;
                h = h.wrapping_mul(0x0000_0100_0000_01b3);
            }
        };
        // The build's layout (its own copies of the data files), then the sources.
        eat(b"dpsa-fpga model 2");
        eat(self.top.as_bytes());
        for (param, _) in &self.data {
            eat(param.as_bytes());
        }
        let files = self.data.iter().map(|(_, p)| p);
        for p in self.rtl.iter().chain(files).chain([&self.harness]) {
            let bytes = std::fs::read(p).map_err(|source| ModelError::Source {
                path: p.clone(),
                source,
            })?;
            eat(p.file_name().map(|n| n.as_encoded_bytes()).unwrap_or(b""));
            eat(&bytes);
        }
        Ok(h)
    }
}

/// A built model: the harness executable.
#[derive(Clone, Debug)]
pub struct Model {
    exe: PathBuf,
}

impl Model {
    /// Builds (or finds, under `cache`, an earlier build of the same sources) the model.
    pub fn build(src: &Sources, cache: &Path) -> Result<Model, ModelError> {
        if src.rtl.is_empty() {
            return Err(ModelError::Run("no Verilog sources".into()));
        }
        let key = src.fingerprint()?;
        let dir = cache.join(format!("{key:016x}"));
        let exe = dir.join("model");
        if exe.is_file() {
            return Ok(Model { exe });
        }
        if Command::new("verilator")
            .arg("--version")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_err()
        {
            return Err(ModelError::NoVerilator);
        }
        // Built beside the final place, then renamed into it: a build cut off half-way is
        // never taken for a model.
        std::fs::create_dir_all(cache)?;
        let tmp = cache.join(format!("building-{:016x}-{}", key, std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        std::fs::create_dir_all(&tmp)?;
        let log = tmp.join("build.log");
        let abs = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
        let mut cmd = Command::new("verilator");
        cmd.args(["--cc", "--exe", "--build", "-O3", "-j", "2"])
            .args(["--top-module", &src.top, "-Wall"]);
        // The data files are read when the model starts, so the model keeps its own copies
        // (a test's mutated sources live in a temporary folder that is gone by the time a
        // later run finds the model in the cache): copied into the build folder, named by
        // their final place.
        for (i, (param, file)) in src.data.iter().enumerate() {
            let name = format!("data{i}-{param}");
            std::fs::copy(file, tmp.join(&name)).map_err(|source| ModelError::Source {
                path: file.clone(),
                source,
            })?;
            cmd.arg(format!("-G{param}=\"{}\"", abs(&dir.join(&name)).display()));
        }
        cmd.arg("-Mdir").arg(&tmp).args(["-o", "model"]);
        for f in &src.rtl {
            cmd.arg(abs(f));
        }
        cmd.arg(abs(&src.harness));
        let out = cmd.output()?;
        std::fs::write(&log, [&out.stdout[..], &out.stderr[..]].concat())?;
        if !out.status.success() || !tmp.join("model").is_file() {
            return Err(ModelError::Build { log });
        }
        match std::fs::rename(&tmp, &dir) {
            Ok(()) => {}
            // Another process finished the same build first: theirs is as good.
            Err(_) if exe.is_file() => {
                let _ = std::fs::remove_dir_all(&tmp);
            }
            Err(e) => return Err(e.into()),
        }
        Ok(Model { exe })
    }

    /// The repository's pixel-pipeline model, in the workspace's `target/fpga-model`.
    pub fn repo() -> Result<Model, ModelError> {
        Model::build(&Sources::repo(), &cache_dir())
    }

    /// The repository's row-codec encoder model, in the workspace's `target/fpga-model`.
    pub fn codec_repo() -> Result<Model, ModelError> {
        Model::build(&Sources::codec_repo(), &cache_dir())
    }

    /// Starts the model with piped stdin, stdout and stderr.
    pub(crate) fn start(&self) -> Result<Running, ModelError> {
        let mut child = Command::new(&self.exe)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()?;
        let (Some(stdin), Some(stdout)) = (child.stdin.take(), child.stdout.take()) else {
            let _ = child.kill();
            return Err(ModelError::Run("the model's pipes are missing".into()));
        };
        Ok(Running {
            child,
            stdin: Some(stdin),
            stdout,
        })
    }
}

/// A running model: its pipes, and how a run ends (the model's stderr in every error).
pub(crate) struct Running {
    child: std::process::Child,
    /// `None` once handed to a writer thread ([`Running::take_stdin`]) or closed.
    stdin: Option<std::process::ChildStdin>,
    stdout: std::process::ChildStdout,
}

impl Running {
    /// Stops the model and describes the failure, with what it printed on stderr.
    fn failed(&mut self, what: &str, e: impl std::fmt::Display) -> ModelError {
        let _ = self.child.kill();
        ModelError::Run(format!("{what}: {e} {}", self.stderr()))
    }

    fn stderr(&mut self) -> String {
        let mut err = String::new();
        if let Some(mut s) = self.child.stderr.take() {
            let _ = std::io::Read::read_to_string(&mut s, &mut err);
        }
        err
    }

    /// Sends `b` (and flushes).
    pub(crate) fn send(&mut self, b: &[u8]) -> Result<(), ModelError> {
        use std::io::Write;
        let res = match self.stdin.as_mut() {
            Some(s) => s.write_all(b).and_then(|_| s.flush()),
            None => Err(std::io::ErrorKind::BrokenPipe.into()),
        };
        res.map_err(|e| self.failed("writing to the model", e))
    }

    /// Reads exactly `b.len()` bytes of output.
    pub(crate) fn read(&mut self, b: &mut [u8]) -> Result<(), ModelError> {
        std::io::Read::read_exact(&mut self.stdout, b)
            .map_err(|e| self.failed("reading the model's output", e))
    }

    /// Stops the model with `why` (its output made no sense).
    pub(crate) fn refuse(&mut self, why: String) -> ModelError {
        let _ = self.child.kill();
        ModelError::Run(why)
    }

    /// The input pipe, for a writer thread (the batch runs write ahead while they read).
    pub(crate) fn take_stdin(&mut self) -> Option<std::process::ChildStdin> {
        self.stdin.take()
    }

    /// The output pipe.
    pub(crate) fn stdout(&mut self) -> &mut std::process::ChildStdout {
        &mut self.stdout
    }

    /// Ends the run: the end record (tag 0) if this side still holds the input, then the
    /// model must exit cleanly. `read`: the first error reading its output, `wrote`: how a
    /// writer thread ended, if the run had them.
    pub(crate) fn finish(
        mut self,
        read: Option<std::io::Error>,
        wrote: Option<std::thread::Result<std::io::Result<()>>>,
    ) -> Result<(), ModelError> {
        if self.stdin.is_some() {
            self.send(&0u32.to_le_bytes())?;
            self.stdin = None;
        }
        let status = self.child.wait()?;
        if let Some(e) = read {
            let err = self.stderr();
            return Err(ModelError::Run(format!(
                "reading the model's output: {e} {err}"
            )));
        }
        match wrote {
            None | Some(Ok(Ok(()))) => {}
            Some(Ok(Err(e))) => {
                let err = self.stderr();
                return Err(ModelError::Run(format!("writing to the model: {e} {err}")));
            }
            Some(Err(_)) => return Err(ModelError::Run("the vector writer panicked".into())),
        }
        if !status.success() {
            let err = self.stderr();
            return Err(ModelError::Run(format!(
                "the model exited with {status}: {err}"
            )));
        }
        Ok(())
    }
}

/// Where built models are kept: `$CARGO_TARGET_DIR/fpga-model`, else the workspace's
/// `target/fpga-model`.
pub fn cache_dir() -> PathBuf {
    match std::env::var_os("CARGO_TARGET_DIR") {
        Some(t) => PathBuf::from(t).join("fpga-model"),
        None => crate::fpga_dir()
            .join("..")
            .join("target")
            .join("fpga-model"),
    }
}
