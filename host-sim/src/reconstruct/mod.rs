//! Runs the fixed-point core (`dpsa-core`) on a recording through its streaming API, exactly
//! as the frame grabber does: frame by frame, line by line, into a packet stream.

pub use dpsa_stream::config;
pub mod sink;

pub use config::config;
pub use sink::IoLink;

use crate::heightmap::{HeightMap, HeightRow};
use crate::progress::progress_bar;
use crate::simulation::recording::Recording;
use crate::{Result, SimError};
use dpsa_core::{
    offload::{FrontEnd, Line, RowCoder},
    packets::{self, codec},
    pipeline::{Pipeline, State},
    sink::{CodedSink, Link, PacketSink, Sink},
};
use dpsa_stream::config::CoreConfig;
use std::io::Write;

/// Summary of one reconstruction run.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RunStats {
    /// Frames fed to the core.
    pub frames: usize,
    /// Packets written (every kind).
    pub packets: u64,
    /// Bytes of packet stream written.
    pub bytes: u64,
    /// Bytes of the core's pipeline state (line pool, row slots, tables).
    pub state_bytes: usize,
    /// Most line slots in use at the end of any frame.
    pub pool_high_water: usize,
}

/// Streams every frame of `rec` through the core into `out` as a packet stream (compressed
/// payloads, intra period [`packets::STREAM_INTRA_PERIOD`]).
pub fn run<W: Write>(rec: &Recording, out: W, progress: bool) -> Result<(RunStats, W)> {
    run_with(rec, out, packets::STREAM_INTRA_PERIOD, progress)
}

/// [`run`] with a chosen codec intra period (1: every packet decodes alone; `intra_period > 1`:
/// rows are predicted from the previous one, smaller but a lost packet costs up to
/// `intra_period - 1` more). 0 is refused.
pub fn run_with<W: Write>(
    rec: &Recording,
    out: W,
    intra_period: u32,
    progress: bool,
) -> Result<(RunStats, W)> {
    let (stats, link) = run_link(rec, IoLink(out), intra_period, progress)?;
    Ok((stats, link.0))
}

/// Runs the core on every frame of `rec` into a [`PacketSink`] over `link`.
pub fn run_link<L: Link>(
    rec: &Recording,
    link: L,
    intra_period: u32,
    progress: bool,
) -> Result<(RunStats, L)>
where
    L::Error: std::fmt::Display,
{
    run_link_with(rec, link, intra_period, progress, None, None)
}

/// [`run_with`] with the per-pixel stages in the front end `fe`
/// ([`dpsa_core::offload::FrontEnd`], `Pipeline::push_to_front_end`): the frame grabber with
/// its FPGA front end, the core keeping the registration, the windows and the stream.
/// With `coder`, the front end's row codec codes every row ([`RowCoder`], `CodedSink`).
pub fn run_front_end<W: Write>(
    rec: &Recording,
    out: W,
    intra_period: u32,
    fe: &mut dyn FrontEnd,
    coder: Option<&mut dyn RowCoder>,
    progress: bool,
) -> Result<(RunStats, W)> {
    let (stats, link) = run_link_with(rec, IoLink(out), intra_period, progress, Some(fe), coder)?;
    Ok((stats, link.0))
}

fn run_link_with<L: Link>(
    rec: &Recording,
    link: L,
    intra_period: u32,
    progress: bool,
    fe: Option<&mut dyn FrontEnd>,
    coder: Option<&mut dyn RowCoder>,
) -> Result<(RunStats, L)>
where
    L::Error: std::fmt::Display,
{
    if intra_period < 1 {
        return Err(SimError::Refused(
            "the codec intra period must be at least 1 (got 0)".into(),
        ));
    }
    with_pipeline(rec, |core, pipe| {
        let w = core.cfg.width as usize;
        let mut reference = codec::ReferenceRow::new(w);
        let enc = reference
            .encoder(intra_period)
            .ok_or_else(|| SimError::Core(format!("width {w} is not supported by the codec")))?;
        let mut buf = vec![0u8; packets::max_packet_len(w)];
        let mut sink = PacketSink::new(link, enc, &mut buf);
        sink.set_run_id(rec.run_id());
        let frames = &rec.manifest.frames;
        let bar = progress_bar(progress, frames.len() as u64, "reconstruct");
        let high = match coder {
            None => drive(rec, pipe, fe, &mut sink, &bar)?,
            Some(coder) => {
                let mut coded = CodedSink {
                    sink: &mut sink,
                    coder,
                };
                drive(rec, pipe, fe, &mut coded, &bar)?
            }
        };
        bar.finish_and_clear();
        sink.flush()
            .map_err(|e| SimError::Core(format!("flushing the packet stream: {e}")))?;
        let stats = RunStats {
            frames: rec.manifest.frames.len(),
            packets: sink.packets(),
            bytes: sink.bytes(),
            state_bytes: core.layout().bytes(),
            pool_high_water: high,
        };
        Ok((stats, sink.into_link()))
    })
}

/// The core's pipeline for `rec` (its configuration, tables and state), handed to `f`.
fn with_pipeline<T>(
    rec: &Recording,
    f: impl FnOnce(&CoreConfig, &mut Pipeline<'_>) -> Result<T>,
) -> Result<T> {
    let core = config(&rec.manifest)?;
    let mut state = State::new(&core.cfg);
    let mut pipe =
        Pipeline::with_column_scale(core.cfg, &core.ref_phase, core.columns(), state.memory())
            .map_err(|e| SimError::Core(format!("cannot build the pipeline: {e}")))?;
    f(&core, &mut pipe)
}

/// Every frame of `rec` through `pipe` (its per-pixel stages in `fe` when given) into `sink`;
/// returns the most line slots in use at the end of any frame.
fn drive<S: Sink>(
    rec: &Recording,
    pipe: &mut Pipeline<'_>,
    mut fe: Option<&mut dyn FrontEnd>,
    sink: &mut S,
    bar: &indicatif::ProgressBar,
) -> Result<usize>
where
    S::Error: std::fmt::Display,
{
    let mut high = 0;
    for (k, entry) in rec.manifest.frames.iter().enumerate() {
        let frame = rec.frame(k)?;
        let w = frame.width;
        pipe.begin_frame(entry.trigger(), sink)
            .map_err(|e| SimError::Core(format!("frame {k}: {e}")))?;
        for (r, line) in frame.data.chunks_exact(w).enumerate() {
            match fe.as_deref_mut() {
                None => pipe.push_line(r as u16, line, sink),
                Some(fe) => pipe.push_to_front_end(r as u16, Line::Wide(line), fe, sink),
            }
            .map_err(|e| SimError::Core(format!("frame {k} line {r}: {e}")))?;
        }
        pipe.end_frame(sink)
            .map_err(|e| SimError::Core(format!("frame {k}: {e}")))?;
        high = high.max(pipe.pool_used());
        bar.inc(1);
    }
    pipe.finish(sink)
        .map_err(|e| SimError::Core(format!("finish: {e}")))?;
    Ok(high)
}

/// Runs the fixed-point core on a recording and hands each row to `each` as it leaves the
/// core, in increasing board-row order; nothing is kept. Gap records (rows no frame showed)
/// are not rows and are not handed over. `each` failing stops the run with its error.
///
/// The rows are taken from the pipeline as its sink receives them, not coded into packets and
/// decoded again: the row codec is lossless, so they are the rows the core's stream carries
/// (`reconstruct_and_decode_every_documented_intra_period` in `cli/tests/intra_period.rs`
/// holds that, header and pixels, for every intra period), and the round trip cost about a
/// third of the host core's time (issue 22). Returns the frames fed.
pub fn reconstruct_rows(
    rec: &Recording,
    progress: bool,
    each: impl FnMut(HeightRow) -> Result<()>,
) -> Result<usize> {
    with_pipeline(rec, |_, pipe| {
        let bar = progress_bar(progress, rec.manifest.frames.len() as u64, "reconstruct");
        let mut sink = RowSink { each, error: None };
        let run = drive(rec, pipe, None, &mut sink, &bar);
        bar.finish_and_clear();
        // `each`'s own error, not the pipeline's report of a failed sink.
        if let Some(e) = sink.error {
            return Err(e);
        }
        run?;
        Ok(rec.manifest.frames.len())
    })
}

/// A [`Sink`] that hands every row on as a [`HeightRow`].
struct RowSink<F> {
    each: F,
    /// What `each` reported when it failed (the pipeline stops at the failed row).
    error: Option<SimError>,
}

/// A [`RowSink`]'s failure as the pipeline reports it (the error itself is kept in the sink).
#[derive(Debug)]
struct RowsStopped;

impl std::fmt::Display for RowsStopped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("the rows' consumer stopped")
    }
}

impl<F: FnMut(HeightRow) -> Result<()>> Sink for RowSink<F> {
    type Error = RowsStopped;
    fn row(&mut self, row: &dpsa_core::Row<'_>) -> std::result::Result<(), RowsStopped> {
        let w = row.header.width as usize;
        let r = HeightRow {
            row: row.header.row,
            latch: row.header.latch,
            flags: row.header.flags,
            heights: row.heights[..w.min(row.heights.len())].to_vec(),
            valid: (0..w).map(|c| row.is_valid(c)).collect(),
        };
        (self.each)(r).map_err(|e| {
            self.error = Some(e);
            RowsStopped
        })
    }
}

/// Runs the fixed-point core on a recording and returns the packet stream bytes.
pub fn reconstruct_bytes(rec: &Recording, progress: bool) -> Result<(RunStats, Vec<u8>)> {
    run(rec, Vec::new(), progress)
}

/// Runs the fixed-point core and decodes its own stream into a height map.
pub fn reconstruct_map(rec: &Recording, progress: bool) -> Result<(RunStats, Vec<u8>, HeightMap)> {
    let (stats, bytes) = reconstruct_bytes(rec, progress)?;
    let (map, rep) = crate::stream::decode_stream(&bytes, rec.manifest.calibration.height_lsb_um);
    if rep.corrupt != 0 {
        return Err(SimError::Internal(format!(
            "the core's own stream has {} bad packets",
            rep.corrupt
        )));
    }
    Ok((stats, bytes, map))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simulation::scene::{Scene, Stall};
    use crate::simulation::simulate::simulate;

    /// A small recording with jitter, a stall and saturated deposits (rows of every flag the
    /// scene can make).
    fn recording(dir: &std::path::Path) -> Recording {
        let scene = Scene {
            width: 40,
            board_length: 300,
            deposits: 10,
            jitter_pct: 30.0,
            saturation: Some(2500),
            stalls: vec![Stall {
                frame: 12,
                frames: 3,
            }],
            ..Scene::default()
        };
        let out = dir.join("rec");
        simulate(&scene, 3, &out, false).unwrap();
        Recording::open(&out).unwrap()
    }

    /// The rows handed on are those of the core's own stream, decoded: header and pixels.
    #[test]
    fn the_rows_are_the_streams_rows() {
        let dir = tempfile::tempdir().unwrap();
        let rec = recording(dir.path());
        let mut rows = Vec::new();
        let frames = reconstruct_rows(&rec, false, |r| {
            rows.push(r);
            Ok(())
        })
        .unwrap();
        assert_eq!(frames, rec.manifest.frames.len());
        let (_, bytes) = reconstruct_bytes(&rec, false).unwrap();
        let (map, rep) =
            crate::stream::decode_stream(&bytes, rec.manifest.calibration.height_lsb_um);
        assert_eq!(rep.corrupt, 0);
        assert!(rows.len() > 200, "{} rows", rows.len());
        assert_eq!(map.rows.len(), rows.len());
        for (a, b) in map.rows.iter().zip(&rows) {
            assert_eq!(
                (a.row, a.latch, a.flags, &a.valid, &a.heights),
                (b.row, b.latch, b.flags, &b.valid, &b.heights)
            );
        }
        // Saturated and invalid pixels and flagged rows are among them.
        assert!(rows.iter().any(|r| r.flags != 0), "no flagged row");
        assert!(rows.iter().any(|r| r.valid.iter().any(|v| !v)));
    }

    /// A consumer that fails stops the run with its own error, and is given no row after.
    #[test]
    fn a_failing_consumer_stops_the_run_with_its_error() {
        let dir = tempfile::tempdir().unwrap();
        let rec = recording(dir.path());
        let mut seen = 0;
        let e = reconstruct_rows(&rec, false, |_| {
            seen += 1;
            if seen == 5 {
                Err(SimError::refused("the fifth row"))
            } else {
                Ok(())
            }
        })
        .unwrap_err();
        assert_eq!(seen, 5);
        assert!(e.to_string().contains("the fifth row"), "{e}");
    }
}
