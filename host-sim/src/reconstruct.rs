//! Runs the fixed-point core (`dpsa-core`) on a recording through its streaming API, exactly
//! as the frame grabber does: frame by frame, line by line, into a packet stream.

use crate::recording::{Manifest, Recording};
use anyhow::{anyhow, Context, Result};
use dpsa_core::{
    packets::{self, codec},
    phase,
    pipeline::{Layout, Pipeline, State},
    sink::{Link, PacketSink},
    Config, Trigger,
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
        max_step_rows: narrow(p.max_step_rows, "max_step_rows")?,
    };
    cfg.validate().map_err(|e| anyhow!("calibration/processing out of range for the core: {e}"))?;
    let ref_phase = cal.reference_phase_rad.iter().map(|&r| phase::from_rad(r)).collect();
    Ok((cfg, ref_phase))
}

/// A [`Link`] over any writer: the packet stream goes to a file, a pipe or memory.
pub struct IoLink<W: Write>(pub W);

impl<W: Write> Link for IoLink<W> {
    type Error = std::io::Error;
    fn send(&mut self, packet: &[u8]) -> std::io::Result<()> {
        self.0.write_all(packet)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.0.flush()
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

/// [`run`] with a chosen codec intra period (1: every packet decodes alone; `intra_period > 1`:
/// rows are predicted from the previous one, smaller but a lost packet costs up to
/// `intra_period - 1` more).
pub fn run_with<W: Write>(rec: &Recording, out: W, intra_period: u32, progress: bool) -> Result<(RunStats, W)> {
    let (cfg, ref_phase) = config(&rec.manifest)?;
    let mut state = State::new(&cfg);
    let mut pipe =
        Pipeline::new(cfg, &ref_phase, state.memory()).map_err(|e| anyhow!("cannot build the pipeline: {e}"))?;
    let w = cfg.width as usize;
    let mut reference = codec::ReferenceRow::new(w);
    let enc = reference
        .encoder(intra_period)
        .ok_or_else(|| anyhow!("width {w} is not supported by the codec"))?;
    let mut buf = vec![0u8; packets::max_packet_len(w)];
    let mut sink = PacketSink::new(IoLink(out), enc, &mut buf);
    let frames = &rec.manifest.frames;
    let bar = progress_bar(progress, frames.len() as u64, "reconstruct");
    let mut high = 0;
    for (k, entry) in frames.iter().enumerate() {
        let frame = rec.frame(k)?;
        let w = frame.width;
        let trigger = Trigger { seq: entry.seq, latch: entry.latch };
        pipe.begin_frame(trigger, &mut sink).map_err(|e| anyhow!("frame {k}: {e}"))?;
        for (r, line) in frame.data.chunks_exact(w).enumerate() {
            pipe.push_line(r as u16, line, &mut sink).map_err(|e| anyhow!("frame {k} line {r}: {e}"))?;
        }
        pipe.end_frame(&mut sink).map_err(|e| anyhow!("frame {k}: {e}"))?;
        high = high.max(pipe.pool_used());
        bar.inc(1);
    }
    pipe.finish(&mut sink).map_err(|e| anyhow!("finish: {e}"))?;
    bar.finish_and_clear();
    sink.flush().context("flushing the packet stream")?;
    let stats = RunStats {
        frames: frames.len(),
        packets: sink.packets(),
        bytes: sink.bytes(),
        state_bytes: Layout::of(&cfg).bytes(),
        pool_high_water: high,
    };
    Ok((stats, sink.into_link().0))
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
