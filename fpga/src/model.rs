//! The Verilator model of `dpsa_pixel`: built once per source fingerprint, run as a child
//! process that speaks the records of [`crate::cosim`] on its stdin and stdout.
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
    /// Verilog files (the top module is `dpsa_pixel`).
    pub rtl: Vec<PathBuf>,
    /// The `$readmemh` table the RTL loads (`ATAN_HEX`).
    pub atan_hex: PathBuf,
    /// The C++ harness.
    pub harness: PathBuf,
}

impl Sources {
    /// The repository's own sources (`fpga/rtl`, `fpga/sim`).
    pub fn repo() -> Sources {
        Sources::in_dir(&crate::fpga_dir().join("rtl"))
    }

    /// The RTL in `rtl` (every `.v` file there and its `atan.hex`), with the repository's
    /// harness: how a test builds a mutated copy of the RTL.
    pub fn in_dir(rtl: &Path) -> Sources {
        let mut files: Vec<PathBuf> = std::fs::read_dir(rtl)
            .map(|d| {
                d.filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.extension().is_some_and(|x| x == "v"))
                    .collect()
            })
            .unwrap_or_default();
        files.sort();
        Sources {
            rtl: files,
            atan_hex: rtl.join("atan.hex"),
            harness: crate::fpga_dir().join("sim").join("harness.cpp"),
        }
    }

    /// FNV-1a over every file's name and bytes: the build cache's key.
    fn fingerprint(&self) -> Result<u64, ModelError> {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        let mut eat = |b: &[u8]| {
            for &x in b {
                h ^= x as u64;
                h = h.wrapping_mul(0x0000_0100_0000_01b3);
            }
        };
        for p in self.rtl.iter().chain([&self.atan_hex, &self.harness]) {
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
        // The model reads its table at run time from the path it was built with: a copy kept
        // in the cache beside it (named by the key, which covers the table's bytes), so a model
        // never depends on the source folder living on (the mutation tests' folders do not).
        let hex = abs(&cache.join(format!("{key:016x}.atan.hex")));
        std::fs::copy(&src.atan_hex, &hex).map_err(|source| ModelError::Source {
            path: src.atan_hex.clone(),
            source,
        })?;
        let mut cmd = Command::new("verilator");
        cmd.args(["--cc", "--exe", "--build", "-O3", "-j", "2"])
            .args(["--top-module", "dpsa_pixel", "-Wall"])
            .arg(format!("-GATAN_HEX=\"{}\"", hex.display()))
            .arg("-Mdir")
            .arg(&tmp)
            .args(["-o", "model"]);
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

    /// The repository's model, in the workspace's `target/fpga-model`.
    pub fn repo() -> Result<Model, ModelError> {
        Model::build(&Sources::repo(), &cache_dir())
    }

    /// Starts the model with piped stdin and stdout.
    pub(crate) fn spawn(&self) -> Result<std::process::Child, ModelError> {
        Ok(Command::new(&self.exe)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()?)
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
