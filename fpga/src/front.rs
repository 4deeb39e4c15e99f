//! The RTL as the pipeline's front end: [`Fabric`] runs every completed row through the
//! Verilator model of `dpsa_pixel` ([`dpsa_core::offload::FrontEnd`]), and writes what the
//! fabric hands the MCU, row by row, into a *fabric log* that the firmware reads under QEMU in
//! place of the fabric's DMA (`dpsa target-run --front-end`, `docs/fpga.md`).
//!
//! ## What the model is given
//!
//! As on the board: the lines the MCU names ([`FrontEnd::keep`], kept here by pool slot, as
//! the fabric's line pool keeps them: a 12-bit pool clamps samples to 4095 as the core's
//! Mono12p pool does), the window registers of each row (the coefficients, saturation level,
//! modulation gate, the height's rounding) and the row phase, and per column the reference
//! phase and the height scale (Q16.16 LSB per turn, or the column's mantissa). Nothing of the
//! core's per-pixel arithmetic runs here: the heights are the model's.
//!
//! ## The fabric log (`.dpsf`; integers little-endian)
//!
//! A 16-byte header: `"DPSF"`, version `1` (u16), `W` (u16), the recording's run id (u64: the
//! firmware refuses a log made from another recording than its feed). Then one record per
//! row the front end computed, in the order the pipeline asked for them: board row (i64), row
//! flags (u16: `SATURATED`, `LOW_MODULATION` of its pixels), 2 bytes zero, `W` heights (i16,
//! 0 where invalid), `ceil(W/8)` validity bytes (bit `c % 8` of byte `c / 8`): the words the
//! fabric's completion DMA writes ([`record_len`] bytes a row).
//!
//! ## The row codec and its payload log (`.dpsp`)
//!
//! [`Coder`] runs every row the pipeline emits (computed or not) through the Verilator model
//! of `dpsa_codec` ([`dpsa_core::offload::RowCoder`]), so the MCU only frames the payloads
//! (`dpsa_core::sink::CodedSink`). It writes them to the payload log: the header as above with
//! `"DPSP"`, then per row: board row (i64), payload length (u32), the payload.

use std::io::Write;

use dpsa_core::accumulate::Coef;
use dpsa_core::frames::Config;
use dpsa_core::height::{ColumnScale, Scale};
use dpsa_core::offload::{FrontEnd, FrontEndError, Line, RowCoder, RowJob};
use dpsa_core::row::flags;
use dpsa_core::solve::MAX_N;
use dpsa_core::Row;

use crate::cosim::{HeightScale, Out, Pixel, Session, Window, LOW_MODULATION, SATURATED, VALID};
use crate::model::{Model, ModelError};

/// The fabric log's first four bytes.
pub const LOG_MAGIC: [u8; 4] = *b"DPSF";
/// The fabric log's version.
pub const LOG_VERSION: u16 = 1;
/// Bytes of the fabric log's header.
pub const LOG_HEADER_LEN: usize = 16;

/// The payload log's first four bytes.
pub const PAYLOAD_MAGIC: [u8; 4] = *b"DPSP";

fn log_header(magic: [u8; 4], width: u16, run_id: u64) -> [u8; LOG_HEADER_LEN] {
    let mut h = [0u8; LOG_HEADER_LEN];
    h[..4].copy_from_slice(&magic);
    h[4..6].copy_from_slice(&LOG_VERSION.to_le_bytes());
    h[6..8].copy_from_slice(&width.to_le_bytes());
    h[8..16].copy_from_slice(&run_id.to_le_bytes());
    h
}

/// What [`Fabric`] and [`Coder`] share: the log they write (when asked) and their first
/// failure, which sticks (a stage that failed fails every later call at once, and
/// `error` says why).
#[derive(Default)]
struct Trail {
    log: Option<Box<dyn Write>>,
    error: Option<String>,
}

impl Trail {
    /// Writes the log's `header` to `log` and keeps it for the records.
    fn start(&mut self, mut log: Box<dyn Write>, header: &[u8]) -> Result<(), ModelError> {
        log.write_all(header)?;
        self.log = Some(log);
        Ok(())
    }

    /// Whether records are written (build one only then).
    fn logging(&self) -> bool {
        self.log.is_some()
    }

    /// Appends one record to the log, `what` naming it in the error.
    fn record(&mut self, rec: &[u8], what: &str) -> Result<(), String> {
        match self.log.as_mut() {
            Some(log) => log
                .write_all(rec)
                .map_err(|e| format!("writing {what}: {e}")),
            None => Ok(()),
        }
    }

    fn failed(&self) -> bool {
        self.error.is_some()
    }

    /// A call's result as the pipeline sees it, its failure kept.
    fn stick<T>(&mut self, r: Result<T, String>) -> Result<T, FrontEndError> {
        r.map_err(|e| {
            self.error = Some(e);
            FrontEndError::Failed
        })
    }

    /// Flushes and closes the log.
    fn flush(&mut self) -> Result<(), ModelError> {
        if let Some(mut log) = self.log.take() {
            log.flush()?;
        }
        Ok(())
    }
}

/// Bytes of one row record of the fabric log for rows of `width` pixels.
pub fn record_len(width: usize) -> usize {
    12 + 2 * width + width.div_ceil(8)
}

/// The Verilator model as a front end (see the module docs).
pub struct Fabric {
    session: Session,
    cfg: Config,
    scale: Scale,
    height: HeightScale,
    ref_phase: Vec<u32>,
    /// Per column: Q16.16 LSB per turn, or the column's mantissa.
    k: Vec<u32>,
    /// Whether the pool keeps 12-bit (Mono12p) lines.
    packed: bool,
    pool: Vec<Vec<u16>>,
    trail: Trail,
    /// Rows and pixels computed.
    pub rows: u64,
    /// Pixels computed.
    pub pixels: u64,
    outs: Vec<Out>,
    px: Vec<Pixel>,
}

impl Fabric {
    /// A front end for `cfg` with its reference-phase table and optional per-column height
    /// scale.
    pub fn new(
        model: &Model,
        cfg: Config,
        ref_phase: &[u32],
        columns: Option<ColumnScale<'_>>,
    ) -> Result<Fabric, ModelError> {
        let w = cfg.width as usize;
        if ref_phase.len() < w {
            return Err(ModelError::Run(format!(
                "the reference-phase table has {} entries for width {w}",
                ref_phase.len()
            )));
        }
        let scale = Scale::new(&cfg);
        let (height, k) = match &columns {
            None => (
                HeightScale::Uniform,
                vec![scale.lsb_per_turn_bits() as u32; w],
            ),
            Some(t) => {
                let m = t.mantissa();
                if m.len() < w {
                    return Err(ModelError::Run(format!(
                        "the height-scale table has {} entries for width {w}",
                        m.len()
                    )));
                }
                (
                    HeightScale::Column { shift: t.shift() },
                    m[..w].iter().map(|&x| x as u32).collect(),
                )
            }
        };
        Ok(Fabric {
            session: Session::start(model)?,
            cfg,
            scale,
            height,
            ref_phase: ref_phase[..w].to_vec(),
            k,
            packed: dpsa_core::Layout::of(&cfg).packed,
            pool: Vec::new(),
            trail: Trail::default(),
            rows: 0,
            pixels: 0,
            outs: Vec::new(),
            px: Vec::new(),
        })
    }

    /// Writes the fabric log of this run to `log` (its header now, a record per row), for
    /// the recording `run_id`.
    pub fn log_to(&mut self, log: Box<dyn Write>, run_id: u64) -> Result<(), ModelError> {
        self.trail
            .start(log, &log_header(LOG_MAGIC, self.cfg.width, run_id))
    }

    /// The first failure of the model or the log, if any (a failed row is reported to the
    /// pipeline as [`FrontEndError::Failed`]; this says why).
    pub fn error(&self) -> Option<&str> {
        self.trail.error.as_deref()
    }

    /// Ends the model's run and flushes the log.
    pub fn finish(mut self) -> Result<(), ModelError> {
        self.trail.flush()?;
        self.session.finish()
    }

    fn samples(&self, line: Line<'_>) -> Vec<u16> {
        let mut l = vec![0u16; self.cfg.width as usize];
        line.samples_into(&mut l, self.packed);
        l
    }

    fn compute(
        &mut self,
        job: &RowJob<'_>,
        last: Line<'_>,
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> Result<u16, String> {
        let w = self.cfg.width as usize;
        let n = job.coef.n;
        if job.slots.len() + 1 != n || n > MAX_N {
            return Err(format!(
                "a row of {} kept lines for n = {n}",
                job.slots.len()
            ));
        }
        let last = self.samples(last);
        let mut lines: Vec<&[u16]> = Vec::with_capacity(n);
        for &s in job.slots {
            match self.pool.get(s as usize) {
                Some(l) if l.len() == w => lines.push(l),
                _ => return Err(format!("pool slot {s} holds no line")),
            }
        }
        if last.len() != w {
            return Err(format!("a final line of {} samples", last.len()));
        }
        lines.push(&last);
        let coef: Coef = *job.coef;
        let win = Window {
            coef,
            sat: self.cfg.saturation,
            scale: self.scale,
            gate: *job.gate,
            height: self.height,
            rho: job.rho,
        };
        self.px.clear();
        for c in 0..w {
            let mut x = [0u16; MAX_N];
            for (j, l) in lines.iter().enumerate() {
                x[j] = l[c];
            }
            self.px.push(Pixel {
                x,
                ref_phase: self.ref_phase[c],
                k: self.k[c],
            });
        }
        self.session
            .pixels(&win, &self.px, &mut self.outs)
            .map_err(|e| e.to_string())?;
        let mut fl = 0u16;
        for (c, o) in self.outs.iter().enumerate() {
            if o.flags & VALID != 0 {
                heights[c] = o.h;
                valid[c / 8] |= 1 << (c % 8);
            } else {
                heights[c] = 0;
            }
            if o.flags & SATURATED != 0 {
                fl |= flags::SATURATED;
            }
            if o.flags & LOW_MODULATION != 0 {
                fl |= flags::LOW_MODULATION;
            }
        }
        self.rows += 1;
        self.pixels += w as u64;
        if self.trail.logging() {
            let mut rec = Vec::with_capacity(record_len(w));
            rec.extend(job.row.to_le_bytes());
            rec.extend(fl.to_le_bytes());
            rec.extend([0u8; 2]);
            for h in &heights[..w] {
                rec.extend(h.to_le_bytes());
            }
            rec.extend(&valid[..w.div_ceil(8)]);
            self.trail.record(&rec, "the fabric log")?;
        }
        Ok(fl)
    }
}

impl FrontEnd for Fabric {
    fn keep(&mut self, slot: u16, line: Line<'_>) {
        let l = self.samples(line);
        let s = slot as usize;
        if self.pool.len() <= s {
            self.pool.resize(s + 1, Vec::new());
        }
        self.pool[s] = l;
    }

    fn row(
        &mut self,
        job: &RowJob<'_>,
        last: Line<'_>,
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> Result<u16, FrontEndError> {
        if self.trail.failed() {
            return Err(FrontEndError::Failed);
        }
        let r = self.compute(job, last, heights, valid);
        self.trail.stick(r)
    }
}

/// The row codec's Verilator model as the front end's coder (see the module docs).
pub struct Coder {
    session: crate::codec::Session,
    width: usize,
    trail: Trail,
    payload: Vec<u8>,
    /// Rows coded.
    pub rows: u64,
    /// Payload bytes.
    pub bytes: u64,
    /// Clocks the model took, summed over the rows (first pixel in to last word out).
    pub clocks: u64,
}

impl Coder {
    /// A coder for rows of `width` pixels with intra period `intra_period` (the stream's).
    pub fn new(model: &Model, width: usize, intra_period: u32) -> Result<Coder, ModelError> {
        Ok(Coder {
            session: crate::codec::Session::start(model, width, intra_period)?,
            width,
            trail: Trail::default(),
            payload: Vec::new(),
            rows: 0,
            bytes: 0,
            clocks: 0,
        })
    }

    /// Writes the payload log to `log` for the recording `run_id`.
    pub fn log_to(&mut self, log: Box<dyn Write>, run_id: u64) -> Result<(), ModelError> {
        self.trail
            .start(log, &log_header(PAYLOAD_MAGIC, self.width as u16, run_id))
    }

    /// The first failure of the model or the log, if any.
    pub fn error(&self) -> Option<&str> {
        self.trail.error.as_deref()
    }

    /// Ends the model's run and flushes the log.
    pub fn finish(mut self) -> Result<(), ModelError> {
        self.trail.flush()?;
        self.session.finish()
    }

    fn code_row(&mut self, row: &Row<'_>, payload: &mut [u8]) -> Result<usize, String> {
        self.session
            .row(row.heights, row.valid, &mut self.payload)
            .map_err(|e| e.to_string())?;
        let len = self.payload.len();
        let room = payload.len();
        let dst = payload
            .get_mut(..len)
            .ok_or_else(|| format!("a payload of {len} bytes for a buffer of {room}"))?;
        dst.copy_from_slice(&self.payload);
        self.rows += 1;
        self.bytes += len as u64;
        self.clocks += u64::from(self.session.clocks);
        if self.trail.logging() {
            let mut rec = Vec::with_capacity(12 + len);
            rec.extend(row.header.row.to_le_bytes());
            rec.extend((len as u32).to_le_bytes());
            rec.extend(&self.payload);
            self.trail.record(&rec, "the payload log")?;
        }
        Ok(len)
    }
}

impl RowCoder for Coder {
    fn code(&mut self, row: &Row<'_>, payload: &mut [u8]) -> Result<usize, FrontEndError> {
        if self.trail.failed() {
            return Err(FrontEndError::Failed);
        }
        let r = self.code_row(row, payload);
        self.trail.stick(r)
    }
}
