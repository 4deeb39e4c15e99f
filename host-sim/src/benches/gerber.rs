//! `dpsa pads-bench`: the paste-layer reader at scale, as JSON. Synthetic layers of up to 10^6
//! objects (the kinds below) are written to a scratch directory and each is read by a child
//! process of its own (`dpsa pads-bench --one FILE`), so the peak memory it reports (the
//! child's `VmHWM`, Linux) is that of one reading, start-up included.
//!
//! | kind | layer |
//! | --- | --- |
//! | `repeat` | N flashes of a 30 x 20 um pad by one step-and-repeat block, 60 um apart: one column up to 10^5, then ceil(N / 10^5) columns |
//! | `same` | N flashes on one point (one pad) |
//! | `grid` | N flashes on a 0.5 mm grid |
//! | `apertures` | N aperture definitions, one flash each, on a 0.5 mm grid |
//! | `arcs` | N full-circle arc strokes of a 0.1 mm aperture (radius 0.1 mm), on a 0.5 mm grid |
//! | `strokes` | N short line strokes of a 0.1 x 0.05 mm rectangle, on a 0.5 mm grid |
//! | `regions` | N triangular regions (G36/G37) of 0.2 mm, on a 0.5 mm grid (um coordinates, so that 10^6 fit in the file size limit) |

use serde::Serialize;
use std::io::Write;
use std::path::Path;

/// The kinds of synthetic layer, in the order the bench runs them.
pub const KINDS: [&str; 7] = [
    "repeat",
    "same",
    "grid",
    "apertures",
    "arcs",
    "strokes",
    "regions",
];

/// Why the bench could not run (a reading that fails is a result, not this).
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A kind not in [`KINDS`].
    #[error("unknown kind {0:?} (one of repeat, same, grid, apertures, arcs, strokes, regions)")]
    Kind(String),
    /// Writing a layer file, or starting the child, failed.
    #[error("{what}: {source}")]
    Io {
        /// What was being done: the file's path, or the layer or command.
        what: String,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The child failed, or did not print a [`Reading`] as JSON.
    #[error("the child reading {file} failed: {message}")]
    Child {
        /// The layer file the child was given.
        file: String,
        /// The child's exit status and stderr, or why its output did not parse.
        message: String,
    },
}

fn io(what: impl Into<String>) -> impl FnOnce(std::io::Error) -> BenchError {
    let what = what.into();
    move |source| BenchError::Io { what, source }
}

/// Writes a synthetic layer of about `n` objects of `kind` (Gerber, mm); returns how many
/// objects it draws (`repeat` rounds up to whole columns).
pub fn write_layer(kind: &str, n: usize, w: &mut impl Write) -> Result<usize, BenchError> {
    if !KINDS.contains(&kind) {
        return Err(BenchError::Kind(kind.into()));
    }
    let side = (n as f64).sqrt() as usize + 1;
    // mm -> the 4.6 integer format.
    let c = |v: f64| (v * 1e6).round() as i64;
    let at = |i: usize| {
        format!(
            "X{}Y{}",
            c((i % side) as f64 * 0.5),
            c((i / side) as f64 * 0.5)
        )
    };
    let mut body = || -> std::io::Result<usize> {
        let format: &[u8] = if kind == "regions" {
            b"%FSLAX33Y33*%\n"
        } else {
            b"%FSLAX46Y46*%\n"
        };
        w.write_all(format)?;
        w.write_all(b"%MOMM*%\n%ADD10R,0.030000X0.020000*%\n%ADD11C,0.100000*%\n")?;
        w.write_all(b"%ADD12R,0.1X0.05*%\n")?;
        let mut objects = n;
        match kind {
            "repeat" => {
                let nx = n.div_ceil(100_000).max(1);
                let ny = n.div_ceil(nx);
                objects = nx * ny;
                write!(w, "%SRX{nx}Y{ny}I0.06J0.06*%\nD10*\nX0Y0D03*\n%SR*%\n")?
            }
            "same" => {
                w.write_all(b"D10*\n")?;
                for _ in 0..n {
                    w.write_all(b"X1000000Y1000000D03*\n")?;
                }
            }
            "grid" => {
                w.write_all(b"D10*\n")?;
                for i in 0..n {
                    writeln!(w, "{}D03*", at(i))?;
                }
            }
            "apertures" => {
                for i in 0..n {
                    writeln!(w, "%ADD{}R,0.3X0.2*%", 13 + i)?;
                }
                for i in 0..n {
                    writeln!(w, "D{}*\n{}D03*", 13 + i, at(i))?;
                }
            }
            "arcs" => {
                w.write_all(b"D11*\nG75*\n")?;
                for i in 0..n {
                    writeln!(w, "G01{}D02*\nG03{}I{}J0D01*", at(i), at(i), c(0.1))?;
                }
            }
            "strokes" => {
                w.write_all(b"D12*\nG01*\n")?;
                for i in 0..n {
                    let (x, y) = ((i % side) as f64 * 0.5, (i / side) as f64 * 0.5);
                    writeln!(
                        w,
                        "X{}Y{}D02*\nX{}Y{}D01*",
                        c(x),
                        c(y),
                        c(x + 0.2),
                        c(y + 0.1)
                    )?;
                }
            }
            _ => {
                // regions: triangles, um
                w.write_all(b"G01*\n")?;
                for i in 0..n {
                    let (x, y) = ((i % side) * 500, (i / side) * 500);
                    writeln!(
                        w,
                        "G36*X{x}Y{y}D02*X{}D01*Y{}D01*X{x}Y{y}D01*G37*",
                        x + 200,
                        y + 200
                    )?;
                }
            }
        }
        w.write_all(b"M02*\n")?;
        Ok(objects)
    };
    body().map_err(io(format!("writing a {kind} layer")))
}

/// One reading of a layer, in the process that read it.
#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct Reading {
    /// Pads read, or `None` when the reader refused the layer (`error`).
    pub pads: Option<usize>,
    /// The reader's error, when it refused the layer.
    pub error: Option<String>,
    /// Wall time of `read_file`, s.
    pub read_s: f64,
    /// The process's peak resident memory (`VmHWM`), MB (10^6 bytes); `None` off Linux.
    pub peak_rss_mb: Option<f64>,
}

/// Reads `path` here and now (`dpsa pads-bench --one`).
pub fn read_one(path: &Path) -> Reading {
    let t = std::time::Instant::now();
    let r = crate::inspection::gerber::read_file(path);
    let read_s = t.elapsed().as_secs_f64();
    let (pads, error) = match r {
        Ok(layer) => (Some(layer.pads.len()), None),
        Err(e) => (None, Some(e.to_string())),
    };
    Reading {
        pads,
        error,
        read_s,
        peak_rss_mb: peak_rss_mb(),
    }
}

/// `VmHWM` of this process, MB.
fn peak_rss_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line
        .trim_start_matches("VmHWM:")
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb * 1024.0 / 1e6)
}

/// One case of the bench.
#[derive(Clone, Debug, Serialize)]
pub struct Case {
    /// The layer kind (one of [`KINDS`]).
    pub kind: String,
    /// Objects the layer draws (flashes, strokes, regions; copies of a step and repeat).
    pub objects: usize,
    /// Size of the layer file, bytes.
    pub file_bytes: u64,
    /// What the child measured (its keys sit beside these in the JSON).
    #[serde(flatten)]
    pub reading: Reading,
}

/// Writes each kind's layer of `n` objects into `dir` and reads it with `exe pads-bench
/// --one FILE` (the `dpsa` binary).
pub fn run(exe: &Path, kinds: &[String], n: usize, dir: &Path) -> Result<Vec<Case>, BenchError> {
    let mut cases = Vec::new();
    for kind in kinds {
        let path = dir.join(format!("{kind}-{n}.gbr"));
        let objects;
        {
            let f = std::fs::File::create(&path).map_err(io(path.display().to_string()))?;
            let mut w = std::io::BufWriter::new(f);
            objects = write_layer(kind, n, &mut w)?;
            w.flush().map_err(io(path.display().to_string()))?;
        }
        let file_bytes = std::fs::metadata(&path)
            .map_err(io(path.display().to_string()))?
            .len();
        let out = std::process::Command::new(exe)
            .args(["--quiet", "pads-bench", "--one"])
            .arg(&path)
            .output()
            .map_err(io(format!("running {}", exe.display())))?;
        let child = |message: String| BenchError::Child {
            file: path.display().to_string(),
            message,
        };
        if !out.status.success() {
            return Err(child(format!(
                "{}: {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            )));
        }
        let reading: Reading =
            serde_json::from_slice(&out.stdout).map_err(|e| child(e.to_string()))?;
        let _ = std::fs::remove_file(&path);
        cases.push(Case {
            kind: kind.clone(),
            objects,
            file_bytes,
            reading,
        });
    }
    Ok(cases)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every kind writes a layer the reader takes, with the pads its geometry makes.
    #[test]
    fn small_layers_read_with_their_pads() {
        for kind in KINDS {
            let mut text = Vec::new();
            write_layer(kind, 50, &mut text).unwrap();
            let layer = crate::inspection::gerber::read_str(std::str::from_utf8(&text).unwrap())
                .unwrap_or_else(|e| panic!("{kind}: {e}"));
            let want = if kind == "same" { 1 } else { 50 };
            assert_eq!(write_layer(kind, 50, &mut Vec::new()).unwrap(), 50);
            assert_eq!(layer.pads.len(), want, "{kind}");
        }
        assert!(matches!(
            write_layer("nope", 1, &mut Vec::new()),
            Err(BenchError::Kind(_))
        ));
    }
}
