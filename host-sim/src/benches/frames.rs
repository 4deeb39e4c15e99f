//! `dpsa frame-bench`: the recording frame formats (16-bit PNG, `.zfr`) on a recording's own
//! frames: bytes per frame and encode / decode throughput, measured in one run (a benchmark,
//! never a test).

use crate::array::frames;
use crate::simulation::recording::{decode_frame, write_frame_png, Recording};
use crate::{Result, SimError};
use serde::Serialize;
use std::time::Instant;

/// One format's figures.
#[derive(Serialize, Clone, Debug)]
pub struct FormatFigures {
    /// Encoded bytes of all the frames.
    pub bytes: u64,
    /// Bytes relative to raw 16-bit samples.
    pub ratio_to_raw: f64,
    /// Encoding rate, Mpx (10^6 samples) per second (PNG: file write and read back).
    pub encode_mpx_per_s: f64,
    /// Decoding rate (with the round-trip check), Mpx per second.
    pub decode_mpx_per_s: f64,
}

/// The report.
#[derive(Serialize, Clone, Debug)]
pub struct FrameBench {
    /// Frames encoded and decoded.
    pub frames: usize,
    /// Samples in those frames (frames x rows x W).
    pub pixels: u64,
    /// Raw size of those samples at 2 bytes each.
    pub raw_bytes: u64,
    /// The 16-bit PNG format.
    pub png: FormatFigures,
    /// The `.zfr` format.
    pub zfr: FormatFigures,
}

/// Encodes and decodes up to `max_frames` frames of `rec` in both formats (single thread).
pub fn run(rec: &Recording, max_frames: usize) -> Result<FrameBench> {
    let n = rec.len().min(max_frames.max(1));
    let loaded: Vec<_> = (0..n).map(|k| rec.frame(k)).collect::<Result<_, _>>()?;
    let (rows, width) = (rec.rows(), rec.width());
    let pixels = (n * rows * width) as u64;
    let tmp = tempfile::tempdir()?;
    let mut figures = Vec::new();
    for zfr in [false, true] {
        let t = Instant::now();
        let mut blobs = Vec::with_capacity(n);
        for (k, f) in loaded.iter().enumerate() {
            if zfr {
                blobs.push(frames::encode(rows, width, &f.data)?);
            } else {
                let p = tmp.path().join(format!("{k}.png"));
                write_frame_png(&p, rows, width, &f.data)?;
                blobs.push(std::fs::read(&p)?);
            }
        }
        let enc = t.elapsed().as_secs_f64();
        let mut m = rec.manifest.clone();
        let ext = if zfr { "zfr" } else { "png" };
        for (k, e) in m.frames.iter_mut().enumerate().take(n) {
            e.file = format!("frames/{k:06}.{ext}");
        }
        let t = Instant::now();
        for (k, b) in blobs.iter().enumerate() {
            let f = decode_frame(&m, k, b, std::path::Path::new(&m.frames[k].file))?;
            if f.data != loaded[k].data {
                return Err(SimError::RoundTrip(format!(
                    "frame {k} does not round-trip"
                )));
            }
        }
        let dec = t.elapsed().as_secs_f64();
        let bytes: u64 = blobs.iter().map(|b| b.len() as u64).sum();
        figures.push(FormatFigures {
            bytes,
            ratio_to_raw: bytes as f64 / (2 * pixels) as f64,
            encode_mpx_per_s: pixels as f64 / enc / 1e6,
            decode_mpx_per_s: pixels as f64 / dec / 1e6,
        });
    }
    let zfr = figures.pop().expect("two formats");
    let png = figures.pop().expect("two formats");
    Ok(FrameBench {
        frames: n,
        pixels,
        raw_bytes: 2 * pixels,
        png,
        zfr,
    })
}
