//! Feeds: a recording in the target format, as a camera delivers it to the frame grabber.

use crate::progress::progress_bar;
use crate::reconstruct::config;
use crate::simulation::recording::Recording;
use crate::{At, Result, SimError};
use dpsa_core::frames::feed;
use std::io::{BufWriter, Write};
use std::path::Path;

/// Writes `rec` as a feed (format: [`dpsa_core::frames::feed`]) to `path`. The
/// packet stream the firmware emits from it uses codec intra period `intra_period`.
/// Returns the bytes written.
pub fn write_feed(rec: &Recording, intra_period: u32, path: &Path) -> Result<u64> {
    let file = std::fs::File::create(path).at(|| format!("creating {}", path.display()))?;
    let mut w = BufWriter::with_capacity(1 << 20, file);
    let n = write_feed_to(rec, intra_period, &mut w, false)
        .at(|| format!("writing the feed {}", path.display()))?;
    w.flush().at(|| format!("writing {}", path.display()))?;
    Ok(n)
}

/// [`write_feed`] into any writer, one frame in memory at a time, with an optional progress bar.
pub fn write_feed_to<W: Write>(
    rec: &Recording,
    intra_period: u32,
    mut out: W,
    progress: bool,
) -> Result<u64> {
    if intra_period < 1 {
        return Err(SimError::refused(
            "the codec intra period must be at least 1",
        ));
    }
    let core = config(&rec.manifest)?;
    let (cfg, ref_phase) = (core.cfg, &core.ref_phase);
    let frames = &rec.manifest.frames;
    let header = feed::Header {
        cfg,
        frames: u32::try_from(frames.len())
            .map_err(|_| SimError::Refused(format!("{} frames do not fit a feed", frames.len())))?,
        intra_period,
        run_id: rec.run_id(),
        column_scale: core.column_scale.as_ref().map(|(shift, _)| *shift),
        // A 12-bit configuration's lines go as a 12-bit camera sends them (Mono12p); samples
        // above 4095 (none in a 12-bit recording) would be sent as 4095, still saturated.
        mono12p: cfg.saturation <= dpsa_core::frames::mono12p::MAX,
    };
    // Check that the header reads back as written (the firmware applies the same checks).
    let head = header.encode();
    feed::Header::decode(&head).map_err(|e| {
        SimError::Core(format!(
            "the recording's configuration is not valid for the target: {e}"
        ))
    })?;
    out.write_all(&head)?;
    let mut table = vec![0u8; header.table_len()];
    feed::encode_table(ref_phase, &mut table)
        .map_err(|e| SimError::Core(format!("reference-phase table: {e}")))?;
    out.write_all(&table)?;
    let mut written = (head.len() + table.len()) as u64;
    if let Some((_, mantissa)) = &core.column_scale {
        let mut t = vec![0u8; header.scale_table_len()];
        feed::encode_scale_table(mantissa, &mut t)
            .map_err(|e| SimError::Core(format!("height-scale table: {e}")))?;
        // Read back as the firmware will (CRC and range).
        let mut back = vec![0u16; mantissa.len()];
        feed::decode_scale_table(&t, &header, &mut back).map_err(|e| {
            SimError::Core(format!(
                "the per-column height scale is not valid for the target: {e}"
            ))
        })?;
        out.write_all(&t)?;
        written += t.len() as u64;
    }

    let bar = progress_bar(progress, frames.len() as u64, "export");
    let mut bytes = Vec::with_capacity(header.frame_len());
    for (k, entry) in frames.iter().enumerate() {
        let frame = rec.frame(k)?;
        bytes.clear();
        bytes.extend_from_slice(&entry.trigger().encode());
        if header.mono12p {
            let (w, lb) = (cfg.width as usize, header.line_len());
            for line in frame.data.chunks_exact(w) {
                let at = bytes.len();
                bytes.resize(at + lb, 0);
                dpsa_core::frames::mono12p::pack(line, &mut bytes[at..]);
            }
        } else {
            for s in &frame.data {
                bytes.extend_from_slice(&s.to_le_bytes());
            }
        }
        debug_assert_eq!(bytes.len(), header.frame_len());
        out.write_all(&bytes)?;
        written += bytes.len() as u64;
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(written)
}
