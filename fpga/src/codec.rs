//! Co-simulation of the row codec's encoder (`fpga/rtl/dpsa_codec.v`): streams of rows through
//! the Verilator model and through [`dpsa_core::packets::codec::Encoder`], the payloads compared
//! byte for byte.
//!
//! ## The records (the harness's stdin and stdout; integers little-endian)
//!
//! In (`fpga/sim/codec_harness.cpp`):
//! - `1u32`, `width u32`, `K u32`, `stall u32`: a new stream (the encoder's command 2, as
//!   [`Encoder::new`]); `stall != 0` makes the harness insert pseudo-random gaps in the pixel
//!   stream and drop `out_ready` pseudo-randomly during the stream's rows;
//! - `2u32`, `K u32`: [`Encoder::set_intra_period`] (command 0);
//! - `3u32`: [`Encoder::reset`] (command 1);
//! - `4u32`, then `width` heights (i16) and `ceil(width / 8)` validity bytes: a row;
//! - `5u32`: flush the output; `0u32`: the end.
//!
//! Out, per row: `len u32`, `clocks u32` (first pixel offered to last word accepted),
//! `status u32` (bit 0: word count not `ceil(len / 4)`, bit 1: non-zero bytes past `len`), then
//! the `len` payload bytes.
//!
//! ## The vectors
//!
//! [`stream`]: a stream's width (the first streams take the widths of [`WIDTHS`], the others
//! random ones), intra period (0, 1, 2, 5 or random), and rows of mixed styles: heights smooth
//! (a board with small noise, repeated from row to row so predicted rows pay off), noisy, with
//! step edges, extremes, alternating extremes (a residual of -32768 at every pixel: the raw
//! fallback), copies of the previous row; validity all, none, random density, long runs,
//! alternating (the plain mask), the previous row's, the previous with a few flips. Resets and
//! changes of the intra period fall between rows at random.

use std::io::{Read, Write};
use std::sync::mpsc::sync_channel;

use dpsa_core::packets::codec::{max_len, Encoder};
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::model::{Model, ModelError, Running};

/// Widths every run covers first (the corner cases of the packing and of `MAX_WIDTH`).
pub const WIDTHS: [usize; 12] = [1, 2, 7, 8, 9, 31, 33, 63, 64, 65, 2048, 8192];

/// One step of a stream.
#[derive(Clone, Debug)]
pub enum Op {
    /// A new stream of `width` pixels a row, intra period `k`; `stall`: back-pressure and gaps.
    Stream {
        /// Row width.
        width: usize,
        /// Intra period.
        k: u32,
        /// Gaps in the input and output handshakes.
        stall: bool,
    },
    /// A new intra period.
    SetK(u32),
    /// Forget the reference.
    Reset,
    /// A row: heights and validity bytes.
    Row(Vec<i16>, Vec<u8>),
}

impl Op {
    fn encode(&self, out: &mut Vec<u8>) {
        match self {
            Op::Stream { width, k, stall } => {
                for v in [1, *width as u32, *k, u32::from(*stall)] {
                    out.extend(v.to_le_bytes());
                }
            }
            Op::SetK(k) => {
                out.extend(2u32.to_le_bytes());
                out.extend(k.to_le_bytes());
            }
            Op::Reset => out.extend(3u32.to_le_bytes()),
            Op::Row(h, v) => {
                out.extend(4u32.to_le_bytes());
                for x in h {
                    out.extend(x.to_le_bytes());
                }
                out.extend(v);
            }
        }
    }
}

/// The expected result of one row.
#[derive(Clone, Debug)]
pub struct Expect {
    /// The core's payload.
    pub payload: Vec<u8>,
    /// Width.
    pub width: usize,
    /// Valid pixels.
    pub valid: usize,
    /// Escaped Rice codes in the coded body (0 for a raw row).
    pub escapes: u64,
    /// The row went through the stalling harness.
    pub stall: bool,
}

/// A stream's ops and its rows' expected results.
pub struct Stream {
    /// The ops, in order.
    pub ops: Vec<Op>,
    /// One per [`Op::Row`].
    pub expect: Vec<Expect>,
}

fn gauss(r: &mut ChaCha8Rng) -> f64 {
    let u: f64 = r.random_range(1e-12..1.0);
    let v: f64 = r.random_range(0.0..1.0);
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

fn intra_period(r: &mut ChaCha8Rng) -> u32 {
    match r.random_range(0..6) {
        0 => 0,
        1 => 1,
        2 => 2,
        3 => 5,
        _ => r.random_range(3..40),
    }
}

fn mask(w: usize, f: impl Fn(usize) -> bool) -> Vec<u8> {
    let mut m = vec![0u8; w.div_ceil(8)];
    for c in 0..w {
        if f(c) {
            m[c / 8] |= 1 << (c % 8);
        }
    }
    m
}

fn bit(m: &[u8], c: usize) -> bool {
    m[c / 8] >> (c % 8) & 1 != 0
}

/// Stream number `index` of a run with seed `rng`: about `pixels` pixels (at least 4 rows).
pub fn stream(r: &mut ChaCha8Rng, index: usize, pixels: usize) -> Stream {
    let w = match WIDTHS.get(index) {
        Some(&w) => w,
        None => match r.random_range(0..10) {
            0..=4 => r.random_range(1..=100),
            5..=7 => r.random_range(101..=2048),
            _ => r.random_range(2049..=8192),
        },
    };
    let k = [0, 1, 2, 5][index % 4];
    let k = if index < 2 * WIDTHS.len() {
        k
    } else {
        intra_period(r)
    };
    let stall = index % 4 == 3;
    let rows = (pixels / w).clamp(4, 400);
    let mut ops = vec![Op::Stream { width: w, k, stall }];
    // A board profile the smooth rows share: a slope, bumps, a few deposits.
    let base = f64::from(r.random_range(-20000i32..20000));
    let slope = r.random_range(-2.0..2.0);
    let deposits: Vec<(usize, usize, f64)> = (0..r.random_range(0..6))
        .map(|_| {
            let s = r.random_range(0..w);
            (
                s,
                (s + r.random_range(1..200)).min(w),
                r.random_range(200.0..900.0),
            )
        })
        .collect();
    let profile: Vec<f64> = (0..w)
        .map(|c| {
            let mut h = base + slope * c as f64 + 40.0 * (c as f64 / 37.0).sin();
            for &(s, e, a) in &deposits {
                if (s..e).contains(&c) {
                    h += a;
                }
            }
            h
        })
        .collect();
    let (mut prev_h, mut prev_v) = (vec![0i16; w], mask(w, |_| true));
    let (mut hstyle, mut vstyle) = (0u32, 0u32);
    for row in 0..rows {
        match r.random_range(0..100) {
            0..=2 => ops.push(Op::Reset),
            3..=5 => ops.push(Op::SetK(intra_period(r))),
            _ => {}
        }
        // Styles persist for a few rows.
        if row == 0 || r.random_range(0..4) == 0 {
            hstyle = match r.random_range(0..20) {
                0..=8 => 0,
                9..=10 => 1,
                11..=12 => 2,
                13..=14 => 3,
                15..=16 => 4,
                _ => 5,
            };
        }
        if row == 0 || r.random_range(0..4) == 0 {
            vstyle = match r.random_range(0..20) {
                0..=6 => 0,
                7 => 1,
                8..=10 => 2,
                11..=12 => 3,
                13..=14 => 4,
                15..=17 => 5,
                _ => 6,
            };
        }
        let sigma = [0.0, 1.0, 4.0, 8.0][row % 4];
        let h: Vec<i16> = match hstyle {
            0 => (0..w)
                .map(|c| {
                    (profile[c] + sigma * gauss(r))
                        .round()
                        .clamp(-32768.0, 32767.0) as i16
                })
                .collect(),
            1 => (0..w).map(|_| r.random::<i16>()).collect(),
            2 => {
                let mut level = r.random::<i16>() as f64;
                (0..w)
                    .map(|_| {
                        if r.random_range(0..64) == 0 {
                            level = f64::from(r.random::<i16>());
                        }
                        (level + sigma * gauss(r)).round().clamp(-32768.0, 32767.0) as i16
                    })
                    .collect()
            }
            3 => (0..w)
                .map(|_| [i16::MIN, i16::MAX, 0, -1][r.random_range(0..4)])
                .collect(),
            4 => {
                let b: i16 = r.random();
                (0..w)
                    .map(|c| if c % 2 == 1 { b ^ i16::MIN } else { b })
                    .collect()
            }
            _ => prev_h
                .iter()
                .map(|&x| x.wrapping_add(r.random_range(-2..=2)))
                .collect(),
        };
        let v = match vstyle {
            0 => mask(w, |_| true),
            1 => mask(w, |_| false),
            2 => {
                let p = r.random_range(0.0..1.0);
                let bits: Vec<bool> = (0..w).map(|_| r.random_bool(p)).collect();
                mask(w, |c| bits[c])
            }
            3 => {
                let mut bits = Vec::with_capacity(w);
                let mut val = r.random_bool(0.7);
                while bits.len() < w {
                    let n = r.random_range(1..400);
                    bits.extend(std::iter::repeat_n(val, n));
                    val = !val;
                }
                mask(w, |c| bits[c])
            }
            4 => {
                let period = 1 + row % 2;
                let phase = r.random_range(0..2);
                mask(w, |c| (c / period + phase) % 2 == 0)
            }
            5 => prev_v.clone(),
            _ => {
                let mut m = prev_v.clone();
                for _ in 0..r.random_range(1..5) {
                    let c = r.random_range(0..w);
                    m[c / 8] ^= 1 << (c % 8);
                }
                m
            }
        };
        // Invalid pixels' heights are ignored by the coder: give them noise.
        let h: Vec<i16> = h
            .iter()
            .enumerate()
            .map(|(c, &x)| if bit(&v, c) { x } else { r.random() })
            .collect();
        prev_h.clone_from(&h);
        prev_v.clone_from(&v);
        ops.push(Op::Row(h, v));
    }
    let expect = expected(&ops);
    Stream { ops, expect }
}

/// The core's payloads for `ops` (one [`Op::Stream`] first), with each row's statistics.
pub fn expected(ops: &[Op]) -> Vec<Expect> {
    let Some(Op::Stream { width: w, k, stall }) = ops.first() else {
        return Vec::new();
    };
    let (w, stall) = (*w, *stall);
    let (mut rh, mut rv) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
    let mut enc = Encoder::new(&mut rh, &mut rv, w, *k).expect("width in range");
    let mut mirror = Mirror::new(w);
    let mut buf = vec![0u8; max_len(w)];
    let mut out = Vec::new();
    for op in &ops[1..] {
        match op {
            Op::Stream { .. } => break,
            Op::SetK(k) => enc.set_intra_period(*k),
            Op::Reset => enc.reset(),
            Op::Row(h, v) => {
                let n = enc.encode(h, v, &mut buf).expect("buffers sized");
                let payload = buf[..n].to_vec();
                let escapes = mirror.row(payload[0], h, v);
                out.push(Expect {
                    payload,
                    width: w,
                    valid: (0..w).filter(|&c| bit(v, c)).count(),
                    escapes,
                    stall,
                });
            }
        }
    }
    out
}

/// The predictor and the adaptation of the module docs of `dpsa_core::packets::codec`, written
/// again to count escapes (a class the vectors must reach); follows the payloads' flags.
struct Mirror {
    u: Vec<i32>,
}

impl Mirror {
    fn new(w: usize) -> Mirror {
        Mirror { u: vec![0; w] }
    }

    /// Escapes of a row coded with header flags `flags`; updates the reference.
    fn row(&mut self, flags: u8, h: &[i16], v: &[u8]) -> u64 {
        let w = h.len();
        let (raw, pred) = (flags & 2 != 0, flags & 1 != 0);
        let mut r = vec![0i32; w];
        let mut acc = [448u32; 3];
        let mut escapes = 0;
        let u = |c: isize| self.u[c.clamp(0, w as isize - 1) as usize];
        for c in 0..w {
            let ci = c as isize;
            let x = i32::from(h[c]);
            if !bit(v, c) {
                r[c] = if pred && !raw {
                    self.u[c]
                } else if c > 0 {
                    r[c - 1]
                } else {
                    0
                };
                continue;
            }
            r[c] = x;
            let (p, t) = if pred {
                let a = if c > 0 { r[c - 1] } else { u(0) };
                let (b, uu, d) = (u(ci), u(ci - 1), u(ci + 1));
                let g = (a - uu).abs() + (uu - b).abs() + (b - d).abs();
                if g < 128 {
                    ((a + b + uu + d + 2) >> 2, usize::from(g >= 48))
                } else {
                    let (mn, mx) = (a.min(b), a.max(b));
                    let m = if uu >= mx {
                        mn
                    } else if uu <= mn {
                        mx
                    } else {
                        a + b - uu
                    };
                    (m, 2)
                }
            } else {
                let a = if c > 0 { r[c - 1] } else { 0 };
                let aa = if c > 1 { r[c - 2] } else { 0 };
                let g = (a - aa).abs();
                if g < 48 {
                    ((a + aa + 1) >> 1, usize::from(g >= 16))
                } else {
                    (a, 2)
                }
            };
            let e = i32::from((x - p) as i16);
            let z = ((e << 1) ^ (e >> 31)) as u32;
            let k = 32 - (acc[t] >> 6).leading_zeros();
            if z >> k >= 16 && !raw {
                escapes += 1;
            }
            acc[t] = acc[t] - (acc[t] >> 5) + z;
        }
        self.u = r;
        escapes
    }
}

/// What a run found.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Report {
    /// Streams (encoder restarts).
    pub streams: u64,
    /// Rows compared.
    pub rows: u64,
    /// Pixels in them.
    pub pixels: u64,
    /// Valid pixels.
    pub valid_pixels: u64,
    /// Rows the core wrote raw.
    pub raw_rows: u64,
    /// Coded rows with a plain validity mask.
    pub plain_rows: u64,
    /// Coded predicted rows.
    pub predicted_rows: u64,
    /// Coded intra rows.
    pub intra_rows: u64,
    /// Rows without a valid pixel.
    pub empty_rows: u64,
    /// Escaped Rice codes in coded rows.
    pub escapes: u64,
    /// Resets between rows.
    pub resets: u64,
    /// Changes of the intra period between rows.
    pub period_changes: u64,
    /// Rows run with stalls (input gaps, output back-pressure).
    pub stalled_rows: u64,
    /// Distinct widths.
    pub widths: u64,
    /// Clocks of the rows without stalls, minus their widths: coded rows.
    pub extra_clocks_coded: u64,
    /// Payload words of the coded rows without stalls.
    pub words_coded: u64,
    /// Coded rows without stalls.
    pub rows_coded_unstalled: u64,
    /// Clocks of the raw rows without stalls, minus their widths.
    pub extra_clocks_raw: u64,
    /// Pixels of the raw rows without stalls.
    pub pixels_raw_unstalled: u64,
    /// Raw rows without stalls.
    pub rows_raw_unstalled: u64,
    /// Rows whose payload differs from the core's (or whose padding or word count is wrong).
    pub mismatches: u64,
    /// The first few mismatches, described.
    pub first: Vec<String>,
}

/// Runs streams of [`stream`] (seeded with `seed`, about `per_stream` pixels each) through
/// `model` and the core until `pixels` pixels went through.
pub fn run(model: &Model, seed: u64, pixels: u64, per_stream: usize) -> Result<Report, ModelError> {
    let mut running = model.start()?;
    let Some(mut stdin) = running.take_stdin() else {
        return Err(ModelError::Run("the model's input is closed".into()));
    };
    let (tx, rx) = sync_channel::<(Vec<Expect>, u64, u64)>(4);
    let writer = std::thread::spawn(move || -> std::io::Result<()> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut done = 0u64;
        let mut index = 0;
        let mut buf = Vec::new();
        while done < pixels {
            let s = stream(&mut rng, index, per_stream);
            index += 1;
            buf.clear();
            let (mut resets, mut changes) = (0, 0);
            for op in &s.ops {
                op.encode(&mut buf);
                match op {
                    Op::Reset => resets += 1,
                    Op::SetK(_) => changes += 1,
                    _ => {}
                }
            }
            buf.extend(5u32.to_le_bytes());
            done += s.expect.iter().map(|e| e.width as u64).sum::<u64>();
            if tx.send((s.expect, resets, changes)).is_err() {
                break;
            }
            stdin.write_all(&buf)?;
        }
        stdin.write_all(&0u32.to_le_bytes())?;
        stdin.flush()
    });
    let mut rep = Report::default();
    let mut widths = std::collections::BTreeSet::new();
    let mut read_err = None;
    let mut hdr = [0u8; 12];
    'streams: for (expect, resets, changes) in rx.iter() {
        rep.streams += 1;
        rep.resets += resets;
        rep.period_changes += changes;
        for e in expect {
            if let Err(err) = running.stdout().read_exact(&mut hdr) {
                read_err = Some(err);
                break 'streams;
            }
            let word = |i: usize| u32::from_le_bytes([hdr[i], hdr[i + 1], hdr[i + 2], hdr[i + 3]]);
            let (len, clocks, status) = (word(0) as usize, u64::from(word(4)), word(8));
            let mut got = vec![0u8; len];
            if let Err(err) = running.stdout().read_exact(&mut got) {
                read_err = Some(err);
                break 'streams;
            }
            widths.insert(e.width);
            rep.rows += 1;
            rep.pixels += e.width as u64;
            rep.valid_pixels += e.valid as u64;
            rep.escapes += e.escapes;
            rep.empty_rows += u64::from(e.valid == 0);
            let flags = e.payload[0];
            let raw = flags == 2;
            if raw {
                rep.raw_rows += 1;
            } else {
                rep.plain_rows += u64::from(flags & 4 != 0);
                if flags & 1 != 0 {
                    rep.predicted_rows += 1;
                } else {
                    rep.intra_rows += 1;
                }
            }
            if e.stall {
                rep.stalled_rows += 1;
            } else {
                let extra = clocks.saturating_sub(e.width as u64);
                if raw {
                    rep.extra_clocks_raw += extra;
                    rep.pixels_raw_unstalled += e.width as u64;
                    rep.rows_raw_unstalled += 1;
                } else {
                    rep.extra_clocks_coded += extra;
                    rep.words_coded += len.div_ceil(4) as u64;
                    rep.rows_coded_unstalled += 1;
                }
            }
            if got != e.payload || status != 0 {
                rep.mismatches += 1;
                if rep.first.len() < 8 {
                    let at = got
                        .iter()
                        .zip(&e.payload)
                        .position(|(a, b)| a != b)
                        .unwrap_or(got.len().min(e.payload.len()));
                    rep.first.push(format!(
                        "stream {} row {} width {} flags {:#04x}: model {} bytes, core {}, status \
                         {status}, first difference at byte {at}: model {:02x?}, core {:02x?}",
                        rep.streams,
                        rep.rows,
                        e.width,
                        flags,
                        len,
                        e.payload.len(),
                        &got[at.min(got.len())..(at + 8).min(got.len())],
                        &e.payload[at.min(e.payload.len())..(at + 8).min(e.payload.len())],
                    ));
                }
            }
        }
    }
    drop(rx);
    rep.widths = widths.len() as u64;
    let wrote = writer.join();
    running.finish(read_err, Some(wrote))?;
    Ok(rep)
}

/// One running codec model, row by row: the row codec of [`crate::front::Coder`].
pub struct Session {
    running: Running,
    width: usize,
    buf: Vec<u8>,
    /// Clocks of the last row (first pixel offered to last word accepted).
    pub clocks: u32,
}

impl Session {
    /// Starts `model` on a stream of rows of `width` pixels with intra period `k` (as
    /// [`Encoder::new`]).
    pub fn start(model: &Model, width: usize, k: u32) -> Result<Session, ModelError> {
        let mut running = model.start()?;
        let mut b = Vec::new();
        Op::Stream {
            width,
            k,
            stall: false,
        }
        .encode(&mut b);
        running.send(&b)?;
        Ok(Session {
            running,
            width,
            buf: b,
            clocks: 0,
        })
    }

    /// Codes one row (`width` heights, `ceil(width / 8)` validity bytes); its payload into
    /// `out`.
    pub fn row(
        &mut self,
        heights: &[i16],
        valid: &[u8],
        out: &mut Vec<u8>,
    ) -> Result<(), ModelError> {
        let (w, nb) = (self.width, self.width.div_ceil(8));
        if heights.len() < w || valid.len() < nb {
            return Err(ModelError::Run(format!("a row shorter than the width {w}")));
        }
        self.buf.clear();
        self.buf.extend(4u32.to_le_bytes());
        for h in &heights[..w] {
            self.buf.extend(h.to_le_bytes());
        }
        self.buf.extend(&valid[..nb]);
        self.buf.extend(5u32.to_le_bytes());
        self.running.send(&self.buf)?;
        let mut hdr = [0u8; 12];
        self.running.read(&mut hdr)?;
        let word = |i: usize| u32::from_le_bytes([hdr[i], hdr[i + 1], hdr[i + 2], hdr[i + 3]]);
        let (len, clocks, status) = (word(0) as usize, word(4), word(8));
        if len > max_len(w) || status != 0 {
            return Err(self.running.refuse(format!(
                "the codec model gave a payload of {len} bytes with status {status:#x}"
            )));
        }
        out.resize(len, 0);
        self.running.read(out)?;
        self.clocks = clocks;
        Ok(())
    }

    /// Ends the model's run: it must exit cleanly.
    pub fn finish(self) -> Result<(), ModelError> {
        self.running.finish(None, None)
    }
}
