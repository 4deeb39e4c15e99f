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
    let core = config(&rec.manifest)?;
    let cfg = core.cfg;
    let mut state = State::new(&cfg);
    let mut pipe =
        Pipeline::with_column_scale(cfg, &core.ref_phase, core.columns(), state.memory())
            .map_err(|e| SimError::Core(format!("cannot build the pipeline: {e}")))?;
    let w = cfg.width as usize;
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
        None => drive(rec, &mut pipe, fe, &mut sink, &bar)?,
        Some(coder) => {
            let mut coded = CodedSink {
                sink: &mut sink,
                coder,
            };
            drive(rec, &mut pipe, fe, &mut coded, &bar)?
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
/// core, decoded from its own packet (so the rows are exactly what the stream carries), in
/// increasing board-row order; nothing is kept. Gap records (rows no frame showed) are not
/// rows and are not handed over. `each` failing stops the run with its error.
pub fn reconstruct_rows(
    rec: &Recording,
    progress: bool,
    each: impl FnMut(HeightRow) -> Result<()>,
) -> Result<RunStats> {
    let w = rec.manifest.camera.width as usize;
    let link = RowLink {
        reference: codec::ReferenceRow::new(w),
        each,
    };
    Ok(run_link(rec, link, packets::STREAM_INTRA_PERIOD, progress)?.0)
}

/// A [`Link`] that decodes every row packet it is given and passes the row on.
struct RowLink<F> {
    reference: codec::ReferenceRow,
    each: F,
}

impl<F: FnMut(HeightRow) -> Result<()>> Link for RowLink<F> {
    type Error = String;
    fn send(&mut self, bytes: &[u8]) -> std::result::Result<(), String> {
        let (p, _) = packets::decode(bytes)
            .map_err(|e| format!("internal error: the core's own packet does not decode: {e}"))?;
        if p.kind != packets::Kind::Row {
            return Ok(());
        }
        let w = p.header.width as usize;
        let mut heights = vec![0i16; w];
        let mut bits = vec![0u8; w.div_ceil(8)];
        let mut dec = self
            .reference
            .decoder()
            .ok_or_else(|| format!("width {w} is not supported by the codec"))?;
        p.unpack(&mut dec, &mut heights, &mut bits)
            .map_err(|e| format!("internal error: the core's own row does not decode: {e}"))?;
        let row = HeightRow {
            row: p.header.row,
            latch: p.header.latch,
            flags: p.header.flags,
            heights,
            valid: (0..w).map(|c| bits[c / 8] & (1 << (c % 8)) != 0).collect(),
        };
        (self.each)(row).map_err(|e| crate::error::chain(&e))
    }
    fn flush(&mut self) -> std::result::Result<(), String> {
        Ok(())
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
