//! Runs the fixed-point core (`dpsa-core`) on a recording through its streaming API, exactly
//! as the frame grabber does: frame by frame, line by line, into a packet stream.

use crate::recording::{Manifest, Recording};
use anyhow::{anyhow, Context, Result};
use dpsa_core::{
    packets::{self, codec},
    phase,
    pipeline::{Layout, Memory, Pipeline, Slot},
    Config, Row, Sink,
};
use indicatif::{ProgressBar, ProgressStyle};
use std::io::Write;

/// Integer core configuration and reference-phase table from a manifest.
///
/// This is the one place where calibration floats become the integers both the host and the
/// firmware run on: `cpp` in Q16.16, `2 pi f_x` and `phi_0(c)` as binary angles, LSB per turn
/// in Q16.16, the modulation threshold in Q12, the noise-gain limit in Q8.
pub fn config(m: &Manifest) -> Result<(Config, Vec<u32>)> {
    let cal = &m.calibration;
    let p = &m.processing;
    let to_u32 = |x: f64, what: &str| -> Result<u32> {
        let r = x.round();
        if r.is_finite() && (0.0..=u32::MAX as f64).contains(&r) {
            Ok(r as u32)
        } else {
            Err(anyhow!("{what} = {x} is out of range for the fixed-point core"))
        }
    };
    let narrow = |x: u32, what: &str| -> Result<u16> {
        u16::try_from(x).map_err(|_| anyhow!("{what} = {x} exceeds 65535"))
    };
    let cfg = Config {
        width: narrow(m.camera.width, "camera.width")?,
        rows: narrow(m.camera.rows, "camera.rows")?,
        n: p.n,
        camera: m.camera.id,
        counts_per_pixel_q16: to_u32(cal.counts_per_pixel * 65536.0, "counts_per_pixel")?,
        fx: (4_294_967_296.0 / cal.fringe_period_px).round() as u64 as u32,
        lsb_per_turn_q16: to_u32(cal.height_per_turn_um / cal.height_lsb_um * 65536.0, "lsb per turn")?,
        saturation: m.camera.saturation,
        min_modulation_q12: to_u32(p.min_modulation * 4096.0, "min_modulation")?,
        max_noise_gain_q8: narrow(to_u32(p.max_noise_gain * 256.0, "max_noise_gain")?, "max_noise_gain")?,
        max_step: narrow(p.max_step_rows, "max_step_rows")?,
    };
    cfg.validate().map_err(|e| anyhow!("calibration/processing out of range for the core: {e:?}"))?;
    let ref_phase = cal.reference_phase_rad.iter().map(|&r| phase::from_rad(r)).collect();
    Ok((cfg, ref_phase))
}

/// Owned state for a [`Pipeline`], sized by [`Layout`].
pub struct State {
    lines: Vec<u16>,
    free: Vec<u16>,
    slots: Vec<Slot>,
    heights: Vec<i16>,
    valid: Vec<u8>,
}

impl State {
    pub fn new(cfg: &Config) -> State {
        let l = Layout::of(cfg);
        State {
            lines: vec![0; l.pool_lines * l.width],
            free: vec![0; l.pool_lines],
            slots: vec![Slot::default(); l.slots],
            heights: vec![0; l.width],
            valid: vec![0; l.width.div_ceil(8)],
        }
    }

    pub fn memory(&mut self) -> Memory<'_> {
        Memory {
            lines: &mut self.lines,
            free: &mut self.free,
            slots: &mut self.slots,
            heights: &mut self.heights,
            valid: &mut self.valid,
        }
    }
}

/// Codec reference rows (the previous row) for one end of a stream.
pub struct CodecState {
    heights: Vec<i16>,
    valid: Vec<u8>,
}

impl CodecState {
    pub fn new(width: usize) -> CodecState {
        CodecState { heights: vec![0; width], valid: vec![0; width.div_ceil(8)] }
    }

    /// An encoder with intra period `k` (the stream default is [`packets::STREAM_INTRA_PERIOD`]).
    pub fn encoder(&mut self, k: u32) -> Result<codec::Encoder<'_>> {
        let w = self.heights.len();
        let mut e = codec::Encoder::new(&mut self.heights, &mut self.valid, w)
            .ok_or_else(|| anyhow!("width {w} is not supported by the codec"))?;
        e.set_intra_period(k);
        Ok(e)
    }

    pub fn decoder(&mut self) -> Option<codec::Decoder<'_>> {
        let w = self.heights.len();
        codec::Decoder::new(&mut self.heights, &mut self.valid, w)
    }
}

/// A sink that frames rows into compressed packets and writes them to `out`.
pub struct PacketSink<'e, W: Write> {
    out: W,
    enc: codec::Encoder<'e>,
    buf: Vec<u8>,
    /// Packets and bytes written.
    pub packets: u64,
    pub bytes: u64,
}

impl<'e, W: Write> PacketSink<'e, W> {
    pub fn new(out: W, enc: codec::Encoder<'e>) -> Self {
        let w = enc.width();
        PacketSink { out, enc, buf: vec![0; packets::max_packet_len(w)], packets: 0, bytes: 0 }
    }

    pub fn into_inner(self) -> W {
        self.out
    }
}

impl<W: Write> Sink for PacketSink<'_, W> {
    type Error = std::io::Error;
    fn row(&mut self, row: &Row<'_>) -> Result<(), Self::Error> {
        let n = packets::encode(row, &mut self.enc, &mut self.buf)
            .map_err(|e| std::io::Error::other(format!("packet encode: {e:?}")))?;
        self.out.write_all(&self.buf[..n])?;
        self.packets += 1;
        self.bytes += n as u64;
        Ok(())
    }
}

/// Summary of one reconstruction run.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RunStats {
    pub frames: usize,
    pub packets: u64,
    pub bytes: u64,
    pub state_bytes: usize,
    pub pool_high_water: usize,
}

/// Streams every frame of `rec` through the core into `out` as a packet stream (compressed
/// payloads, intra period [`packets::STREAM_INTRA_PERIOD`]).
pub fn run<W: Write>(rec: &Recording, out: W, progress: bool) -> Result<(RunStats, W)> {
    run_with(rec, out, packets::STREAM_INTRA_PERIOD, progress)
}

/// [`run`] with a chosen codec intra period `k` (1: every packet decodes alone; `k > 1`: rows
/// are predicted from the previous one, smaller but a lost packet costs up to `k - 1` more).
pub fn run_with<W: Write>(rec: &Recording, out: W, k: u32, progress: bool) -> Result<(RunStats, W)> {
    let (cfg, ref_phase) = config(&rec.manifest)?;
    let mut state = State::new(&cfg);
    let mut pipe = Pipeline::new(cfg, &ref_phase, state.memory())
        .map_err(|e| anyhow!("cannot build the pipeline: {e:?}"))?;
    let mut codec_state = CodecState::new(cfg.width as usize);
    let mut sink = PacketSink::new(out, codec_state.encoder(k)?);
    let frames = &rec.manifest.frames;
    let bar = progress_bar(progress, frames.len() as u64, "reconstruct");
    let mut high = 0;
    for (k, entry) in frames.iter().enumerate() {
        let frame = rec.frame(k)?;
        let w = frame.width;
        pipe.begin_frame(entry.seq, entry.latch, &mut sink).map_err(|e| anyhow!("frame {k}: {e:?}"))?;
        for (r, line) in frame.data.chunks_exact(w).enumerate() {
            pipe.push_line(r as u16, line, &mut sink).map_err(|e| anyhow!("frame {k} line {r}: {e:?}"))?;
        }
        pipe.end_frame(&mut sink).map_err(|e| anyhow!("frame {k}: {e:?}"))?;
        high = high.max(pipe.pool_used());
        bar.inc(1);
    }
    pipe.finish(&mut sink).map_err(|e| anyhow!("finish: {e:?}"))?;
    bar.finish_and_clear();
    sink.out.flush().context("flushing the packet stream")?;
    let stats = RunStats {
        frames: frames.len(),
        packets: sink.packets,
        bytes: sink.bytes,
        state_bytes: Layout::of(&cfg).bytes(),
        pool_high_water: high,
    };
    Ok((stats, sink.into_inner()))
}

/// A progress bar on stderr, hidden when `show` is false or stderr is not a terminal.
pub fn progress_bar(show: bool, len: u64, what: &str) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(len);
    if let Ok(style) = ProgressStyle::with_template("{prefix:>12} [{bar:40}] {pos}/{len} {elapsed}") {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(what.to_string());
    bar
}
