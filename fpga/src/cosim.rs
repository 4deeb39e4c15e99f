//! Co-simulation: pixels through the Verilator model and through dpsa-core, compared bit for
//! bit.
//!
//! ## The records (the harness's stdin and stdout; integers little-endian)
//!
//! In:
//! - `1u32`, then a window's registers: `n u32`, `q2[8] i32`, `q3[8] i32`, `sat u32`,
//!   `fast u32`, `thr2 u64`, `half u32`, `sh u32`, `rho u32` (the harness drains the pipeline
//!   first, as the MCU writes the registers between rows);
//! - `2u32`, `count u32`, then `count` pixels: `x[8] u16`, `ref_phase u32`, `k u32` (the
//!   harness writes all of a batch's outputs before it reads on);
//! - `0u32`: the end.
//!
//! Out, one 16-byte record a pixel in input order: `v2 i32`, `v3 i32`, `phi u32`, `h i16`,
//! `flags u16` (bit 0 valid, bit 1 saturated, bit 2 low modulation).
//!
//! ## The reference
//!
//! [`expected`]: the core's own functions, pixel by pixel: [`front_end_pixel`] (the
//! accumulate stage's definition), [`Scale::phase_v`] with the window's [`Gate`], then
//! [`Scale::height`] (uniform scale) or [`ColumnScale::height`] (per-column mantissa). The
//! phase and height of an invalid pixel are not compared: the core computes neither.

use std::io::{Read, Write};
use std::sync::mpsc::sync_channel;

use dpsa_core::accumulate::{Coef, V};
use dpsa_core::fixed::types::{U16F16, U20F12, U8F8};
use dpsa_core::height::{ColumnScale, Gate, Invalid, Scale};
use dpsa_core::offload::front_end_pixel;
use dpsa_core::phase::from_rad;
use dpsa_core::solve::{Window as Solved, MAX_N};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::model::{Model, ModelError, Running};

/// Output flag: the pixel has a height.
pub const VALID: u16 = 1;
/// Output flag: a sample was at or above the saturation level.
pub const SATURATED: u16 = 2;
/// Output flag: the modulation is below the threshold.
pub const LOW_MODULATION: u16 = 4;

/// How a window's heights are scaled.
#[derive(Clone, Copy, Debug)]
pub enum HeightScale {
    /// One LSB-per-turn for every column ([`Scale::height`]); the pixel's `k` is the Q16.16
    /// bits.
    Uniform,
    /// A per-column table with this exponent ([`ColumnScale`]); the pixel's `k` is the
    /// column's mantissa.
    Column {
        /// The table's exponent (`0..=15`).
        shift: u8,
    },
}

/// A window: the registers the MCU writes before its rows, as the core's own objects.
#[derive(Clone, Copy, Debug)]
pub struct Window {
    /// The window's coefficients.
    pub coef: Coef,
    /// Saturation level.
    pub sat: u16,
    /// The phase-to-height constants.
    pub scale: Scale,
    /// The modulation gate in the coefficients' units (`scale.gate(coef.frac)`).
    pub gate: Gate,
    /// Uniform or per-column scale.
    pub height: HeightScale,
    /// The row's phase `rho`.
    pub rho: u32,
}

impl Window {
    /// `(half, sh)` of the height's rounding.
    fn rounding(&self) -> (i32, u32) {
        match self.height {
            HeightScale::Uniform => (1 << 15, 16),
            HeightScale::Column { shift } => ColumnScale::new(shift, &[]).rounding(),
        }
    }

    fn encode(&self, out: &mut Vec<u8>) {
        let (half, sh) = self.rounding();
        out.extend(1u32.to_le_bytes());
        out.extend((self.coef.n as u32).to_le_bytes());
        for q in self.coef.q2.iter().chain(&self.coef.q3) {
            out.extend(q.to_le_bytes());
        }
        out.extend((self.sat as u32).to_le_bytes());
        out.extend(self.gate.fast().to_le_bytes());
        out.extend(self.gate.thr2().to_le_bytes());
        out.extend(half.to_le_bytes());
        out.extend(sh.to_le_bytes());
        out.extend(self.rho.to_le_bytes());
    }
}

/// One pixel's inputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pixel {
    /// Samples (those at `j >= n` are ignored by both sides).
    pub x: [u16; MAX_N],
    /// The column's reference phase.
    pub ref_phase: u32,
    /// The column's scale: Q16.16 LSB per turn, or the column's mantissa.
    pub k: u32,
}

impl Pixel {
    fn encode(&self, out: &mut Vec<u8>) {
        for x in self.x {
            out.extend(x.to_le_bytes());
        }
        out.extend(self.ref_phase.to_le_bytes());
        out.extend(self.k.to_le_bytes());
    }
}

/// One pixel's outputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Out {
    /// The reduced pixel `[v2, v3]`.
    pub v: V,
    /// Phase, a binary angle (compared only when valid).
    pub phi: u32,
    /// Height (compared only when valid).
    pub h: i16,
    /// [`VALID`], [`SATURATED`], [`LOW_MODULATION`].
    pub flags: u16,
}

impl Out {
    fn decode(b: &[u8]) -> Out {
        let w = |i: usize| [b[i], b[i + 1], b[i + 2], b[i + 3]];
        Out {
            v: [i32::from_le_bytes(w(0)), i32::from_le_bytes(w(4))],
            phi: u32::from_le_bytes(w(8)),
            h: i16::from_le_bytes([b[12], b[13]]),
            flags: u16::from_le_bytes([b[14], b[15]]),
        }
    }

    /// Equal as the core defines a row: `V`, the flags, and the phase and height of a valid
    /// pixel.
    pub fn same(&self, other: &Out) -> bool {
        self.v == other.v
            && self.flags == other.flags
            && (self.flags & VALID == 0 || (self.phi == other.phi && self.h == other.h))
    }
}

/// The core's answer for `px` in window `w` (see the module docs).
pub fn expected(w: &Window, px: &Pixel) -> Out {
    let n = w.coef.n.min(MAX_N);
    let v = front_end_pixel(&w.coef, &px.x[..n], w.sat);
    let phi_r = w.rho.wrapping_add(px.ref_phase);
    match w.scale.phase_v(&w.gate, v) {
        Ok(phi) => {
            let h = match w.height {
                HeightScale::Uniform => w.scale.height(phi, phi_r),
                HeightScale::Column { .. } => {
                    let (half, sh) = w.rounding();
                    ColumnScale::height(phi, phi_r, px.k as u16, half, sh)
                }
            };
            Out {
                v,
                phi,
                h,
                flags: VALID,
            }
        }
        Err(Invalid::Saturated) => Out {
            v,
            phi: 0,
            h: 0,
            flags: SATURATED,
        },
        Err(Invalid::LowModulation) => Out {
            v,
            phi: 0,
            h: 0,
            flags: LOW_MODULATION,
        },
    }
}

/// The classes of pixels the vectors draw from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Class {
    /// A fringe: background, amplitude 20 DN to half the saturation level, noise.
    Fringe,
    /// A fringe whose modulation is near the window's threshold (the gate's exact path).
    NearThreshold,
    /// One sample at or above the saturation level (half of them exactly at it).
    Saturated,
    /// One sample exactly one below the saturation level (not saturated).
    BelowSaturation,
    /// Every sample equal: zero modulation.
    Flat,
    /// Uniformly random samples.
    Random,
    /// Samples from 0, 1, `sat - 1` and 65535.
    Extremes,
}

/// Every class, in the order of [`Class`].
pub const CLASSES: [Class; 7] = [
    Class::Fringe,
    Class::NearThreshold,
    Class::Saturated,
    Class::BelowSaturation,
    Class::Flat,
    Class::Random,
    Class::Extremes,
];

/// Deterministic test vectors: windows of every `n` in 3..=8 (solved from random phase shifts,
/// and one in eight with arbitrary i16 coefficients whose sums wrap), uniform and per-column
/// scales, thresholds from zero up, and pixels of every [`Class`].
pub struct Vectors {
    rng: ChaCha8Rng,
}

impl Vectors {
    /// Vectors from `seed`.
    pub fn new(seed: u64) -> Vectors {
        Vectors {
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// A window with `n` observations.
    pub fn window(&mut self, n: usize) -> Window {
        let r = &mut self.rng;
        let sat = match r.random_range(0..4) {
            0 => 4095,
            1 => 65535,
            2 => 1000,
            _ => r.random_range(64..=65535),
        };
        let coef = if r.random_range(0..8) == 0 {
            let mut q2 = [0i32; MAX_N];
            let mut q3 = [0i32; MAX_N];
            for j in 0..MAX_N {
                q2[j] = r.random_range(-32767..=32767);
                q3[j] = r.random_range(-32767..=32767);
            }
            Coef {
                n,
                q2,
                q3,
                frac: r.random_range(0..=24),
            }
        } else {
            loop {
                let mut th = [0u32; MAX_N];
                let step = std::f64::consts::TAU / n as f64;
                for (j, t) in th.iter_mut().enumerate().take(n) {
                    *t = from_rad(-(j as f64) * step * r.random_range(0.6..1.4));
                }
                let Ok(s) = Solved::solve(&th[..n], U8F8::from_num(8)) else {
                    continue;
                };
                if let Some(c) = Coef::of(&s, sat) {
                    break c;
                }
            }
        };
        let lsb = U16F16::from_num(r.random_range(1.0..32767.0));
        let min_mod = match r.random_range(0..4) {
            0 => U20F12::ZERO,
            _ => U20F12::from_num(r.random_range(0.0..64.0)),
        };
        let scale = Scale::from_parts(lsb, min_mod);
        let gate = scale.gate(coef.frac);
        let height = if r.random_range(0..2) == 0 {
            HeightScale::Uniform
        } else {
            HeightScale::Column {
                shift: r.random_range(0..=15),
            }
        };
        Window {
            coef,
            sat,
            scale,
            gate,
            height,
            rho: r.random(),
        }
    }

    /// A pixel of class `c` for window `w`.
    pub fn pixel(&mut self, w: &Window, c: Class) -> Pixel {
        let r = &mut self.rng;
        let n = w.coef.n;
        let sat = w.sat as f64;
        let mut x: [u16; MAX_N] = r.random();
        let fringe = |r: &mut ChaCha8Rng, amp: f64, x: &mut [u16; MAX_N]| {
            let b = r.random_range(0.0..sat);
            let phi = r.random_range(0.0..std::f64::consts::TAU);
            let step = std::f64::consts::TAU / n as f64;
            for (j, s) in x.iter_mut().enumerate().take(n) {
                let v = b + amp * (phi - j as f64 * step).cos() + r.random_range(-2.0..2.0);
                *s = v.round().clamp(0.0, (w.sat - 1) as f64) as u16;
            }
        };
        match c {
            Class::Fringe => {
                let amp = r.random_range(20.0..(sat / 2.0).max(21.0));
                fringe(r, amp, &mut x)
            }
            Class::NearThreshold => {
                let amp = w.min_modulation_dn() * r.random_range(0.3..2.0);
                fringe(r, amp, &mut x)
            }
            Class::Saturated => {
                let amp = r.random_range(0.0..sat / 2.0);
                fringe(r, amp, &mut x);
                let j = r.random_range(0..n);
                x[j] = if r.random() {
                    w.sat
                } else {
                    r.random_range(w.sat..=u16::MAX)
                };
            }
            Class::BelowSaturation => {
                let amp = r.random_range(0.0..sat / 2.0);
                fringe(r, amp, &mut x);
                x[r.random_range(0..n)] = w.sat - 1;
            }
            Class::Flat => {
                let v = r.random_range(0..w.sat);
                x[..n].fill(v);
            }
            Class::Random => {}
            Class::Extremes => {
                for s in x.iter_mut() {
                    *s = [0, 1, w.sat.saturating_sub(1), u16::MAX][r.random_range(0..4)];
                }
            }
        }
        let k = match w.height {
            HeightScale::Uniform => w.scale.lsb_per_turn_bits() as u32,
            HeightScale::Column { .. } => r.random::<u16>() as u32,
        };
        Pixel {
            x,
            ref_phase: r.random(),
            k,
        }
    }
}

impl Window {
    /// The modulation threshold in DN (a fringe of this amplitude has `C^2 = thr2`).
    fn min_modulation_dn(&self) -> f64 {
        (self.gate.thr2() as f64).sqrt() / 2f64.powi(self.coef.frac as i32)
    }
}

/// What a co-simulation run found.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Report {
    /// Pixels compared.
    pub pixels: u64,
    /// Pixels whose outputs differ.
    pub mismatches: u64,
    /// Windows (register sets).
    pub windows: u64,
    /// Pixels per `n` (index `n`).
    pub by_n: [u64; MAX_N + 1],
    /// Pixels the core found valid, saturated, low-modulation.
    pub valid: u64,
    /// Saturated pixels.
    pub saturated: u64,
    /// Low-modulation pixels.
    pub low_modulation: u64,
    /// Valid pixels decided by the gate's exact path (`hi < fast`).
    pub exact_gate: u64,
    /// The first few mismatches, described.
    pub first: Vec<String>,
}

/// Runs `pixels` pixels of [`Vectors::new`]`(seed)` (windows of `per_window` pixels, `n`
/// cycling over 3..=8, classes cycling) through `model` and the core.
pub fn run(model: &Model, seed: u64, pixels: u64, per_window: u64) -> Result<Report, ModelError> {
    let mut running = model.start()?;
    let Some(mut stdin) = running.take_stdin() else {
        return Err(ModelError::Run("the model's input is closed".into()));
    };
    let per_window = per_window.max(1);
    // The writer sends each chunk's windows and expected outputs ahead (bounded: a few chunks).
    let (tx, rx) = sync_channel::<Vec<(Window, Pixel, Out)>>(4);
    let writer = std::thread::spawn(move || -> std::io::Result<()> {
        let mut vec = Vectors::new(seed);
        let mut done = 0u64;
        let mut wi = 0u64;
        let mut buf = Vec::new();
        while done < pixels {
            let w = vec.window(3 + (wi % 6) as usize);
            wi += 1;
            let count = per_window.min(pixels - done);
            buf.clear();
            w.encode(&mut buf);
            buf.extend(2u32.to_le_bytes());
            buf.extend((count as u32).to_le_bytes());
            let mut chunk = Vec::with_capacity(count as usize);
            for i in 0..count {
                let px = vec.pixel(&w, CLASSES[((done + i) % CLASSES.len() as u64) as usize]);
                px.encode(&mut buf);
                chunk.push((w, px, expected(&w, &px)));
            }
            done += count;
            if tx.send(chunk).is_err() {
                break;
            }
            stdin.write_all(&buf)?;
        }
        stdin.write_all(&0u32.to_le_bytes())?;
        stdin.flush()
    });
    let mut rep = Report::default();
    let mut rec = [0u8; 16];
    let mut last_window = None;
    let mut read_err = None;
    'chunks: for chunk in rx.iter() {
        for (w, px, want) in chunk {
            if let Err(e) = running.stdout().read_exact(&mut rec) {
                read_err = Some(e);
                break 'chunks;
            }
            let got = Out::decode(&rec);
            if last_window != Some(w.rho) {
                rep.windows += 1;
                last_window = Some(w.rho);
            }
            rep.pixels += 1;
            rep.by_n[w.coef.n] += 1;
            match want.flags {
                VALID => {
                    rep.valid += 1;
                    let hi = want.v[0].unsigned_abs().max(want.v[1].unsigned_abs());
                    if hi < w.gate.fast() {
                        rep.exact_gate += 1;
                    }
                }
                SATURATED => rep.saturated += 1,
                _ => rep.low_modulation += 1,
            }
            if !got.same(&want) {
                rep.mismatches += 1;
                if rep.first.len() < 8 {
                    rep.first.push(format!(
                        "n {} x {:?} ref {:#x} k {} rho {:#x}: model {:?}, core {:?}",
                        w.coef.n, px.x, px.ref_phase, px.k, w.rho, got, want
                    ));
                }
            }
        }
    }
    drop(rx);
    let wrote = writer.join();
    running.finish(read_err, Some(wrote))?;
    Ok(rep)
}

/// Pixels per batch a [`Session`] sends before it reads their outputs (the pipes then never
/// hold more than 24 KiB one way and 16 KiB the other).
const SESSION_BATCH: usize = 1024;

/// One running model, row by row: a window's registers, then its pixels, their outputs back
/// ([`crate::front::Fabric`] runs whole rows through it).
pub struct Session {
    running: Running,
    buf: Vec<u8>,
}

impl Session {
    /// Starts `model`.
    pub fn start(model: &Model) -> Result<Session, ModelError> {
        Ok(Session {
            running: model.start()?,
            buf: Vec::new(),
        })
    }

    /// Loads window `w` and runs `px` through it; their outputs, in order, into `out`.
    pub fn pixels(
        &mut self,
        w: &Window,
        px: &[Pixel],
        out: &mut Vec<Out>,
    ) -> Result<(), ModelError> {
        out.clear();
        let mut rec = [0u8; 16];
        for (i, batch) in px.chunks(SESSION_BATCH).enumerate() {
            self.buf.clear();
            if i == 0 {
                w.encode(&mut self.buf);
            }
            self.buf.extend(2u32.to_le_bytes());
            self.buf.extend((batch.len() as u32).to_le_bytes());
            for p in batch {
                p.encode(&mut self.buf);
            }
            self.running.send(&self.buf)?;
            for _ in batch {
                self.running.read(&mut rec)?;
                out.push(Out::decode(&rec));
            }
        }
        Ok(())
    }

    /// Ends the model's run: it must exit cleanly.
    pub fn finish(self) -> Result<(), ModelError> {
        self.running.finish(None, None)
    }
}
