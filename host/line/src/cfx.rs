//! The CFX spool: one IPC-CFX `UnitsInspected` message per inspected board
//! (`dpsa_inspect::report::cfx`, as `dpsa inspect` writes it), a file `RUNID.json` written
//! whole or not at all (a temporary file renamed into place), so that whatever picks the
//! spool up (a CFX publisher, a MES bridge) never reads half a message. An incomplete board
//! gets none. Beside it, `RUNID.printer.json`: the printer correction the loop proposed after
//! the board (`dpsa.SPI.PrinterCorrectionProposed`, `docs/spc.md`).

use crate::LineError;
use std::path::{Path, PathBuf};

/// Writes `message` as `spool/RUNID.json` atomically; returns its path. A message already
/// there for this board is never replaced.
pub fn spool(dir: &Path, run_id: u64, message: &serde_json::Value) -> Result<PathBuf, LineError> {
    spool_named(dir, &format!("{run_id:016x}.json"), message)
}

/// Writes `message` as `spool/NAME` atomically (the printer's proposal after a board is
/// `RUNID.printer.json`); returns its path. A file already there is never replaced.
pub fn spool_named(
    dir: &Path,
    name: &str,
    message: &serde_json::Value,
) -> Result<PathBuf, LineError> {
    let path = dir.join(name);
    if path.exists() {
        return Err(LineError::Refused(format!(
            "{} exists: the board was inspected before",
            path.display()
        )));
    }
    let text = serde_json::to_string_pretty(message).map_err(|e| LineError::Io(e.to_string()))?;
    dpsa_formats::files::write_bytes(&path, text.as_bytes())?;
    Ok(path)
}
