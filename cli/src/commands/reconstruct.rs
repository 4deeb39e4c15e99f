//! `dpsa reconstruct`: the core through its streaming API, into a packet stream.

use super::{open, out};
use anyhow::{anyhow, Result};
use dpsa_sim::files::{self, AtomicFile, Input, Tee};
use dpsa_sim::{images, reconstruct, stream};
use std::io::{BufWriter, Write};
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct Args {
    /// Recording directory.
    dir: PathBuf,
    /// Packet stream output file (written to a temporary file beside it and renamed into place
    /// when complete; may not be inside the recording).
    #[arg(long)]
    out: PathBuf,
    /// Also write a 16-bit height PNG here (h + 32768 in LSB, 0 = invalid) and a
    /// false-colour PNG beside it (`*.colour.png`). The name must end in `.png`.
    #[arg(long)]
    png: Option<PathBuf>,
    /// Codec intra period: 1 (default) makes every packet decodable on its own, so a
    /// damaged packet loses only itself; K > 1 predicts rows from the previous one
    /// (smaller, but a lost packet costs up to K - 1 more rows).
    #[arg(long, default_value_t = dpsa_core::packets::STREAM_INTRA_PERIOD,
          value_parser = intra_period)]
    intra_period: u32,
    /// Array calibration file (`dpsa calibrate`): use camera `--camera`'s encoder scale,
    /// fringe period, reference-phase table and height per turn instead of the manifest's.
    #[arg(long)]
    cal: Option<PathBuf>,
    /// Camera of `--cal` (default: the manifest's camera id).
    #[arg(long, requires = "cal")]
    camera: Option<u8>,
}

/// Parses `--intra-period`: a whole number of rows, at least 1 (0 would never force an intra
/// row, so one lost packet would cost the rest of the stream).
pub(super) fn intra_period(s: &str) -> std::result::Result<u32, String> {
    match s.parse::<u32>() {
        Ok(0) => Err(
            "the codec intra period must be at least 1 (1: every row decodes on its \
                      own; K: an intra row at least every K rows)"
                .into(),
        ),
        Ok(k) => Ok(k),
        Err(_) => Err(format!(
            "the codec intra period must be a whole number of rows from 1 to {}",
            u32::MAX
        )),
    }
}

pub fn run(a: Args, progress: bool) -> Result<()> {
    dpsa_sim::kind::expect(&a.dir, "DIR", dpsa_sim::kind::Kind::Recording, &[])?;
    if let Some(c) = &a.cal {
        dpsa_sim::kind::expect(c, "--cal", dpsa_sim::kind::Kind::Calibration, &[])?;
    }
    // Every output is checked before any work.
    let inputs = [Input::Dir(&a.dir)];
    files::refuse_overwrite("--out", &a.out, &inputs)?;
    if let Some(png) = &a.png {
        files::require_png("--png", png)?;
        let colour = images::colour_path(png);
        files::refuse_overwrite("--png", png, &inputs)?;
        files::refuse_overwrite("--png", &colour, &inputs)?;
        files::refuse_same(("--out", &a.out), ("--png", png))?;
        files::refuse_same(("--out", &a.out), ("--png's false-colour file", &colour))?;
    }
    let mut rec = open(&a.dir)?;
    if let Some(path) = &a.cal {
        files::refuse_same(("--out", &a.out), ("--cal", path))?;
        super::apply_cal(&mut rec, path, a.camera)?;
    }
    let file = AtomicFile::create(&a.out)?;
    let mut tee = Tee::new(BufWriter::new(file), a.png.is_some());
    let res = reconstruct::run_with(&rec, &mut tee, a.intra_period, progress).map(|(s, _)| s);
    let res = res.and_then(|stats| {
        tee.flush()?;
        Ok(stats)
    });
    let stats = match (res, tee.error.take()) {
        (Ok(s), _) => s,
        (Err(_), Some(io)) => {
            return Err(anyhow!("{} {}", a.out.display(), files::write_cause(&io)))
        }
        (Err(e), None) => return Err(e.into()),
    };
    let Tee { inner, copy, .. } = tee;
    let file = inner
        .into_inner()
        .map_err(|e| files::write_error(&a.out, e.into_error()))?;
    file.commit()?;
    out!(
        "{} packets, {} bytes -> {}",
        stats.packets,
        stats.bytes,
        a.out.display()
    );
    if let (Some(png), Some(bytes)) = (a.png, copy) {
        let (map, _) = stream::decode_stream(&bytes, rec.manifest.calibration.height_lsb_um);
        let colour = images::write_pngs(&map, &png)?;
        out!(
            "heights -> {}, false colour -> {}",
            png.display(),
            colour.display()
        );
    }
    Ok(())
}
