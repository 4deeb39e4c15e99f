//! Building the firmware ELF.

use super::PROGRAM;
use crate::{At, Result, SimError};
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// The firmware crate (`firmware/` of this repository).
pub fn firmware_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware")
}

/// Where `firmware/build.sh` leaves the release ELF (it always builds into `firmware/target`).
pub fn default_elf_path() -> PathBuf {
    firmware_dir()
        .join("target/thumbv7em-none-eabihf/release")
        .join(PROGRAM)
}

/// The firmware ELF. `build`: run `firmware/build.sh` (it builds what is out of date and prints
/// the ELF path as its last line of stdout; its log goes to stderr, which is forwarded). Without
/// `build`: the ELF where the last build left it ([`default_elf_path`]), which must exist.
pub fn firmware_elf(build: bool) -> Result<PathBuf> {
    if !build {
        let p = default_elf_path();
        if !p.is_file() {
            return Err(SimError::Tool(format!(
                "no firmware ELF at {}: build it with `bash firmware/build.sh` (add --install to install \
                 the cross toolchain and QEMU) or pass --elf",
                p.display()
            )));
        }
        return Ok(p);
    }
    let script = firmware_dir().join("build.sh");
    if !script.is_file() {
        return Err(SimError::Tool(format!("{} is missing", script.display())));
    }
    let mut child = Command::new("bash")
        .arg(&script)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .at(|| "starting bash firmware/build.sh")?;
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
    child
        .stdout
        .take()
        .expect("piped stdout")
        .read_to_string(&mut stdout)?;
    let status = child.wait()?;
    let tail = log.join().unwrap_or_default();
    if !status.success() {
        return Err(SimError::Tool(format!(
            "bash firmware/build.sh failed ({status}); if the cross toolchain or QEMU is missing, run \
             `bash firmware/build.sh --install`. Last lines of its log:\n{tail}"
        )));
    }
    let last = stdout
        .lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("")
        .trim();
    let elf = PathBuf::from(last);
    if !(elf.is_absolute() && elf.is_file()) {
        return Err(SimError::Tool(format!(
            "firmware/build.sh succeeded but its last line of output is not the path of an ELF: {last:?}"
        )));
    }
    Ok(elf)
}
