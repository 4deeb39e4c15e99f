//! The numpy float64 least-squares phase of one camera's frames, run and timed in the same
//! `dpsa board-bench` as the fixed-point core: the baseline the issue names ("numpy LS reached
//! ~60 Mpx/s here"). The script is `numpy_dpsa.py` beside this file; it gets the frames, the
//! registration (board row, entry frame, window offsets per row, from the reference's `plan`)
//! and `f_x` through a temporary directory, and times only its compute.

use crate::reference::dpsa::{offsets, plan};
use crate::simulation::recording::Recording;
use crate::{At, Result, SimError};
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::process::Command;

const SCRIPT: &str = include_str!("numpy_dpsa.py");

/// What the script measured.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NumpyRun {
    /// Phase pixels computed (rows with a complete window x W).
    pub pixels: u64,
    /// Compute time (gather, pseudo-inverse, solve, atan2), s.
    pub seconds: f64,
    /// `pixels / seconds` / 1e6: phase Mpx per second.
    pub mpx_s: f64,
}

/// Runs the numpy baseline on `rec` (its frames preloaded or read here) with `python`.
pub fn run(rec: &Recording, python: &str) -> Result<NumpyRun> {
    let m = &rec.manifest;
    let n = usize::from(m.processing.n);
    let o = offsets(m)
        .ok_or_else(|| SimError::refused("the recording's latches give no registration"))?;
    let dir = tempfile::tempdir().at(|| "a temporary directory for the numpy baseline")?;
    let mut rows: Vec<u8> = Vec::new();
    let mut count = 0u64;
    for p in plan(m) {
        let Some(w) = p.first_frame.filter(|&w| p.flags == 0 && w + n <= o.len()) else {
            continue;
        };
        rows.extend_from_slice(&p.row.to_le_bytes());
        rows.extend_from_slice(&(w as i64).to_le_bytes());
        for ok in &o[w..w + n] {
            rows.extend_from_slice(&ok.to_le_bytes());
        }
        count += 1;
    }
    if count == 0 {
        return Err(SimError::refused("no board row has a complete window"));
    }
    std::fs::write(dir.path().join("rows.i64"), &rows)?;
    let mut f = std::io::BufWriter::new(std::fs::File::create(dir.path().join("frames.u16"))?);
    for k in 0..rec.len() {
        let fr = rec.frame(k)?;
        for v in &fr.data {
            f.write_all(&v.to_le_bytes())?;
        }
    }
    f.flush()?;
    drop(f);
    let meta = serde_json::json!({
        "frames": rec.len(),
        "rows_per_frame": rec.rows(),
        "width": rec.width(),
        "n": n,
        "f_x": 1.0 / m.calibration.fringe_period_px,
    });
    std::fs::write(dir.path().join("meta.json"), meta.to_string())?;
    let script = dir.path().join("numpy_dpsa.py");
    std::fs::write(&script, SCRIPT)?;
    let out = Command::new(python)
        .arg(&script)
        .arg(dir.path())
        .output()
        .at(|| format!("running {python}"))?;
    if !out.status.success() {
        return Err(SimError::Tool(format!(
            "{python} {}: {}",
            script.display(),
            String::from_utf8_lossy(&out.stderr).trim()
        )));
    }
    serde_json::from_slice(&out.stdout).at(|| {
        format!(
            "the numpy baseline printed {:?}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}
