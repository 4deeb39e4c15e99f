//! Lossless row codec: a compressed payload for one height row (heights + validity).
//!
//! One row of `W` pixels (`1 ..= `[`MAX_WIDTH`]) is coded at a time. The coder may use the
//! previous row of the same stream (the *reference*), kept by both ends in caller memory
//! (`W` x i16 heights + `ceil(W/8)` validity bytes). Per pixel the work is integer only: a
//! 4-neighbour predictor, a zigzag map and an adaptive Golomb-Rice code (no division, no
//! multiplication); runs of invalid pixels cost nothing per pixel.
//!
//! ## Loss recovery (the reference rule)
//!
//! Every payload says whether it is *intra* (decodable alone) or *predicted* (needs the
//! reference: the row the decoder decoded last). Each payload carries an 8-bit sequence number
//! that the encoder increments by one per row (mod 256), whatever the row kind.
//!
//! - The [`Encoder`] codes a row intra when it has no reference (after [`Encoder::new`] and
//!   [`Encoder::reset`]) and at least every `K` rows (the intra period, an argument of
//!   [`Encoder::new`]; [`Encoder::set_intra_period`] changes it): row `i` after an intra row is
//!   intra when `i == K`, so at
//!   most `K - 1` predicted rows follow an intra row. `K = 1` codes every row intra; `K = 0`
//!   never forces an intra row (only the first row after a reset is intra).
//! - The [`Decoder`] accepts a predicted row only if it holds a reference and the row's
//!   sequence number is the reference's plus one (mod 256); otherwise it returns
//!   [`CodecError::MissingReference`] and forgets its reference. After any error it also
//!   forgets its reference (the reference buffer may be half overwritten). Intra rows are
//!   always accepted and become the new reference.
//!
//! So a receiver that loses (or drops for a bad CRC) a packet gets `MissingReference` for the
//! following predicted rows, without having to notice the loss itself, and is back in step at
//! the next intra row, at most `K - 1` rows later. Calling [`Decoder::reset`] on a detected loss
//! is harmless but not needed. (The sequence check misses a loss of exactly a multiple of 256
//! consecutive packets; reset the decoder on a gap in board rows to cover that too.) An encoder
//! that learns of a loss on a return channel can call [`Encoder::reset`] to send an intra row
//! at once.
//!
//! ## Payload format
//!
//! Two header bytes, then either a raw body or a coded body.
//!
//! | byte | field |
//! | --- | --- |
//! | 0 | flags: bit 0 `P` (predicted from the reference), bit 1 `RAW`, bit 2 `PLAIN_MASK`; bits 3..7 are 0 |
//! | 1 | sequence number (u8, +1 per row mod 256) |
//!
//! Valid flag values: `0x02` (raw, intra), `0x00`/`0x04` (coded intra), `0x01`/`0x05` (coded
//! predicted). Anything else is [`CodecError::Corrupt`].
//!
//! **Raw body** (`RAW`): exactly the raw packet payload (codec 0 in [`super`]): `ceil(W/8)`
//! validity bytes (bit `c % 8` of byte `c / 8`, 1 = valid, padding bits 0), then `W` heights as
//! i16 little-endian (0 where invalid). The payload is then `2 + ceil(W/8) + 2 W` bytes, which
//! is [`max_len`].
//!
//! **Coded body**: a bit stream, most significant bit of each byte first, with the last byte
//! padded with 0 bits; its length is exactly the bits used rounded up to whole bytes (a decoder
//! rejects extra bytes or non-zero padding). It holds the validity section, then one
//! Rice code per valid pixel, left to right.
//!
//! *Validity section.* Let `ref(c)` be the reference's validity bit of pixel `c` for a predicted
//! row and 1 for an intra row, and `m(c) = valid(c) XOR ref(c)` (so for an intra row `m` marks
//! the invalid pixels, for a predicted row the changes from the previous row).
//! - `PLAIN_MASK = 1`: `W` bits, `valid(0)` first (the validity bits themselves, not `m`).
//! - `PLAIN_MASK = 0`: `m` as alternating runs, starting with a run of 0s (which may be empty).
//!   A run that starts at pixel 0 is coded `gamma(r + 1)`, every later run `gamma(r)` (`r >= 1`).
//!   So when `m(0) = 1` the empty first run is `gamma(1)` and the run of 1s after it, which also
//!   starts at pixel 0, is `gamma(r + 1)` as well. Runs alternate until the lengths sum to `W`
//!   (a run past `W` is corrupt). `gamma(v)`, `v >= 1`, is Elias gamma:
//!   `floor(log2 v)` 0 bits, then `v` in binary in `floor(log2 v) + 1` bits, most significant
//!   (a 1) first. A row equal to its reference mask (e.g. all valid, intra) is one run.
//!
//! The encoder writes plain bits when the runs would take more than `W` bits.
//!
//! *Pixels.* Valid pixels are coded left to right; invalid ones cost nothing. Two rows of i16
//! values take part: `U`, the reference heights (predicted rows only), and `R`, the current
//! row's *filled* heights: `R[c]` is the height of a valid pixel; for an invalid pixel it is
//! `R[c-1]` in an intra or raw row (0 for `c = 0`) and `U[c]` in a predicted row. `R` becomes the
//! next row's `U`, and the row's validity the next reference mask (so an invalid predicted row
//! leaves the reference heights as they were). Out-of-row neighbours: intra: `R[-1] = R[-2] = 0`;
//! predicted: `R[-1] = U[-1] = U[0]`, `U[W] = U[W-1]`. All arithmetic below is on exact integers
//! (i32 suffices); `>>` is an arithmetic shift.
//!
//! - Predicted row, pixel `c`: `a = R[c-1]`, `b = U[c]`, `u = U[c-1]`, `d = U[c+1]`;
//!   `g = |a-u| + |u-b| + |b-d|`. If `g < 128`: `pred = (a + b + u + d + 2) >> 2` and context
//!   `t = 0` if `g < 48`, `t = 1` otherwise. If `g >= 128`: `pred = MED(a, b, u)` (LOCO-I:
//!   `min(a,b)` if `u >= max(a,b)`, `max(a,b)` if `u <= min(a,b)`, else `a + b - u`), `t = 2`.
//! - Intra row, pixel `c`: `a = R[c-1]`, `aa = R[c-2]`, `g = |a - aa|`. If `g < 48`:
//!   `pred = (a + aa + 1) >> 1`, `t = 0` if `g < 16` else `t = 1`; otherwise `pred = a`, `t = 2`.
//!
//! The residual `e = (x - pred) mod 2^16`, as i16 (it wraps like JPEG-LS: every `x` in
//! `-32768 ..= 32767` is coded, and decoded as `(pred + e) mod 2^16`), is mapped to
//! `z = 2e` for `e >= 0`, `-2e - 1` for `e < 0` (`0 ..= 65535`) and written as a Rice code with
//! the parameter `k` of context `t`.
//!
//! *Rice code with parameter `k`* (`0 ..= 15`): `n = z >> k`. If `n < 16`: `n` 0 bits, a 1 bit,
//! then the low `k` bits of `z` (at most 31 bits). Otherwise (escape): 16 0 bits, then `z` in 16
//! bits. A decoder rejects a non-escape code with `(n << k) | low > 65535` as corrupt.
//!
//! *Adaptation.* Each context `t = 0, 1, 2` has an accumulator `A` (u32), set to `448` at the
//! start of every row (`k = 3`). A pixel in context `t` uses `k = bitlen(A >> 6)`, the number of
//! significant bits (`bitlen(0) = 0`), i.e. the smallest `k` with `2^(k+1) > A / 32`: `A` is
//! about 32 times the recent mean of `z`. After coding `z`: `A = A - (A >> 5) + z`. `A` stays
//! below `2^21`, so `k <= 15`.
//!
//! ## Size bounds
//!
//! The encoder codes the row and keeps the coded body only if it is no longer than the raw
//! body; otherwise it writes the row raw (intra). So every payload is at most
//! [`max_len`]`(W) = 2 + ceil(W/8) + 2 W` bytes: **the worst-case expansion over the raw
//! (codec 0) payload is 2 bytes**. (A coded row costs at most about 17 bits per valid pixel, so
//! the raw fallback takes adversarial data, e.g. a residual of -32768 at every pixel; random
//! i16 noise codes at about 16.5 bits per pixel.) A row without a valid pixel costs 5 bytes for
//! `W < 4095` and at most 6 bytes up to `W = 8192`.
//!
//! ## Rates (synthetic data, see the tests)
//!
//! `W = 2048`, intra period 32, a flat board with Gaussian noise of 8 LSB rms: 5.36 bits per
//! pixel, 2.7 % above the zeroth-order entropy of the predictor's residuals (5.22 bits); with
//! 14 % of the area under solder deposits of 240..800 LSB with sharp walls: 5.38 bits
//! (+2.9 %), 3.16 : 1 against the 17 raw bits per pixel. The noise alone has
//! `log2(8 sqrt(2 pi e)) = 5.05` bits of entropy per pixel, the floor for any lossless coder.
//! Other predictors on the same noise: left neighbour 5.71, MED 5.74, `(a + b) / 2` 5.50 bits.
//! The Rice code itself costs 1.5-3.5 % over the entropy of Gaussian residuals, even with the
//! best `k`.
//!
//! ## Speed
//!
//! Per valid pixel: 4 neighbour loads (one new), 3 absolute differences, the average or MED,
//! zigzag, `k` from one `clz`, one Rice code into a 32-bit bit buffer (a word store every 32
//! bits), one accumulator update, one store to the reference row. The runs of valid pixels are
//! coded by two out-of-line loops, one per row kind, that keep the bit writer and (intra) the
//! three contexts' accumulators in locals, one copy of the coder per context and two pixels a
//! step, so that the compiler holds them in registers. Compiled for `thumbv7em-none-eabihf`
//! (`dpsa target-run --bench`: QEMU-retired instructions per output pixel of the whole packet
//! encode, codec, framing and CRC-32): about 43 for intra rows (the stream default; the
//! CRC-32 about 3 of them, the copy into the reference row about 2) and 73 with intra period 8.
//! Reaching 8 instructions per pixel would need a different format (e.g. `k` per block of
//! pixels instead of per pixel, and a predictor that allows 2-pixel DSP instructions).

use core::cell::Cell;

/// Largest supported row width.
pub const MAX_WIDTH: usize = 8192;
/// Bytes of the payload header.
pub const HEADER_LEN: usize = 2;

/// Flag: the row is predicted from the reference.
const F_PRED: u8 = 1;
/// Flag: raw body.
const F_RAW: u8 = 2;
/// Flag: the validity section is `W` plain bits.
const F_PLAIN_MASK: u8 = 4;

/// Unary limit of the Rice code: quotients from here on are escaped.
const QMAX: u32 = 16;
/// Predicted rows: gradient below which the 4-neighbour average is used.
const T_FLAT: i32 = 128;
/// Predicted rows: context split inside the flat class.
const T_CTX: i32 = 48;
/// Intra rows: gradient below which the 2-neighbour average is used.
const T_FLAT_I: i32 = 48;
/// Intra rows: context split inside the flat class.
const T_CTX_I: i32 = 16;
/// Contexts.
const NCTX: usize = 3;
/// Decay of the Rice accumulators: `A += z - (A >> SHIFT)`.
const SHIFT: u32 = 5;
/// Initial accumulator (`k = 3`).
const A_INIT: u32 = 14 << SHIFT;

/// Raw body bytes (equal to the raw packet payload of codec 0).
pub const fn raw_len(width: usize) -> usize {
    width.div_ceil(8) + 2 * width
}

/// Largest payload for a row of `width` pixels: header + raw body. Size encoder buffers with it.
pub const fn max_len(width: usize) -> usize {
    HEADER_LEN + raw_len(width)
}

/// Why a row could not be coded or decoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CodecError {
    /// An output buffer is smaller than [`max_len`] (encoder) or a row buffer shorter than `W`
    /// heights / `ceil(W/8)` validity bytes.
    BufferTooSmall,
    /// The payload ends before the row does.
    Truncated,
    /// The payload is not a valid coding of a `W`-pixel row.
    Corrupt,
    /// A predicted row without the reference it was coded against (after a reset, a lost row,
    /// or an earlier error). Decoding resumes at the next intra row.
    MissingReference,
}

/// How a payload is coded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RowKind {
    /// Raw body (always intra).
    Raw,
    /// Coded, no reference needed.
    Intra,
    /// Coded against the previous row.
    Predicted,
}

/// Kind and sequence number of a payload, from its header alone.
pub fn peek(payload: &[u8]) -> Result<(RowKind, u8), CodecError> {
    match payload {
        [f, seq, ..] => match *f {
            F_RAW => Ok((RowKind::Raw, *seq)),
            0 | F_PLAIN_MASK => Ok((RowKind::Intra, *seq)),
            F_PRED | 0x05 => Ok((RowKind::Predicted, *seq)),
            _ => Err(CodecError::Corrupt),
        },
        _ => Err(CodecError::Truncated),
    }
}

/// Reference-row state shared by the encoder and the decoder.
struct Reference<'a> {
    heights: &'a mut [i16],
    valid: &'a mut [u8],
    width: usize,
    present: bool,
    seq: u8,
}

impl<'a> Reference<'a> {
    fn new(heights: &'a mut [i16], valid: &'a mut [u8], width: usize) -> Option<Self> {
        let nb = width.div_ceil(8);
        if width == 0 || width > MAX_WIDTH || heights.len() < width || valid.len() < nb {
            return None;
        }
        Some(Self {
            heights: &mut heights[..width],
            valid: &mut valid[..nb],
            width,
            present: false,
            seq: 0,
        })
    }

    /// Stores the row's validity (padding bits cleared) as the reference mask.
    fn set_valid(&mut self, valid: &[u8]) {
        self.valid.copy_from_slice(&valid[..self.valid.len()]);
        clear_padding(self.valid, self.width);
    }
}

/// Mask of the used bits of the last validity byte.
fn last_byte_mask(width: usize) -> u8 {
    match width % 8 {
        0 => 0xFF,
        r => (1u8 << r) - 1,
    }
}

fn clear_padding(mask: &mut [u8], width: usize) {
    if let Some(last) = mask.last_mut() {
        *last &= last_byte_mask(width);
    }
}

#[inline(always)]
fn bit(mask: &[u8], c: usize) -> bool {
    mask[c / 8] >> (c % 8) & 1 != 0
}

/// Bits `32 i .. 32 i + 32` of a mask (bit `c % 8` of byte `c / 8`), 0 past its end.
#[inline(always)]
fn word(mask: &[u8], i: usize) -> u32 {
    let s = 4 * i;
    match mask.get(s..s + 4) {
        Some(b) => u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        None => word_tail(mask, s),
    }
}

/// [`word`] at the end of the mask (fewer than 4 bytes from `s`): once per row, out of line.
#[inline(never)]
fn word_tail(mask: &[u8], s: usize) -> u32 {
    mask.iter()
        .skip(s)
        .enumerate()
        .fold(0, |v, (j, &b)| v | u32::from(b) << (8 * j))
}

/// First index in `from .. w` whose bit (`word_at(c / 32)`, bit `c % 32`) differs from
/// `value`, or `w`. Bits past `w` are ignored.
#[inline(always)]
fn run_end(word_at: impl Fn(usize) -> u32, from: usize, w: usize, value: bool) -> usize {
    let flip = if value { !0 } else { 0 };
    let mut c = from;
    while c < w {
        let other = (word_at(c / 32) ^ flip) >> (c % 32);
        if other != 0 {
            return (c + other.trailing_zeros() as usize).min(w);
        }
        c = (c / 32 + 1) * 32;
    }
    w
}

/// Sets bits `s .. e` of `mask`.
fn set_bits(mask: &mut [u8], s: usize, e: usize) {
    let mut c = s;
    while c < e {
        let lo = c % 8;
        let hi = (e - (c - lo)).min(8);
        let ones = ((1u16 << hi) - (1u16 << lo)) as u8;
        mask[c / 8] |= ones;
        c = c - lo + 8;
    }
}

#[inline(always)]
fn zigzag(e: i16) -> u32 {
    u32::from(((e << 1) ^ (e >> 15)) as u16)
}

#[inline(always)]
fn unzigzag(z: u32) -> i16 {
    let z = z as u16;
    ((z >> 1) as i16) ^ -((z & 1) as i16)
}

#[inline(always)]
fn med(a: i32, b: i32, u: i32) -> i32 {
    let (mn, mx) = if a < b { (a, b) } else { (b, a) };
    if u >= mx {
        mn
    } else if u <= mn {
        mx
    } else {
        a + b - u
    }
}

/// Predicted-row predictor: `(pred, context)` from left, up, up-left, up-right.
#[inline(always)]
fn predict_p(a: i32, b: i32, u: i32, d: i32) -> (i32, usize) {
    let g = (a - u).abs() + (u - b).abs() + (b - d).abs();
    if g < T_FLAT {
        ((a + b + u + d + 2) >> 2, usize::from(g >= T_CTX))
    } else {
        (med(a, b, u), 2)
    }
}

/// Intra-row predictor: `(pred, context)` from the two left neighbours.
#[inline(always)]
fn predict_i(a: i32, aa: i32) -> (i32, usize) {
    let g = (a - aa).abs();
    if g < T_FLAT_I {
        ((a + aa + 1) >> 1, usize::from(g >= T_CTX_I))
    } else {
        (a, 2)
    }
}

/// Adaptive Rice parameters of the contexts: `A` is a running sum of `z` with decay `2^-SHIFT`,
/// about `2^SHIFT` times the recent mean of `z`.
struct Model {
    a: [u32; NCTX],
}

impl Model {
    fn new() -> Self {
        Self { a: [A_INIT; NCTX] }
    }

    /// `k = bitlen(A >> (SHIFT + 1))`: the smallest `k` with `2^(k+1) > A / 2^SHIFT`. Since
    /// `A < 2^(16 + SHIFT)`, `k <= 15`.
    #[inline(always)]
    fn k(&self, q: usize) -> u32 {
        k_of(self.a[q])
    }

    #[inline(always)]
    fn update(&mut self, q: usize, z: u32) {
        self.a[q] = self.a[q] - (self.a[q] >> SHIFT) + z;
    }
}

/// `k = bitlen(A >> (SHIFT + 1))` of an accumulator `A` (see [`Model::k`]).
#[inline(always)]
fn k_of(a: u32) -> u32 {
    32 - (a >> (SHIFT + 1)).leading_zeros()
}

/// MSB-first bit writer with a 32-bit accumulator; stores whole words, counts past the end
/// of `out` without writing.
struct BitWriter<'o> {
    out: &'o mut [u8],
    pos: usize,
    /// Pending bits, left-aligned.
    acc: u32,
    /// Free bits in `acc` (`1 ..= 32`).
    free: u32,
}

impl<'o> BitWriter<'o> {
    fn new(out: &'o mut [u8]) -> Self {
        Self {
            out,
            pos: 0,
            acc: 0,
            free: 32,
        }
    }

    /// Appends the low `len` bits of `v` (`1 <= len <= 32`, `v < 2^len`).
    #[inline(always)]
    fn put(&mut self, v: u32, len: u32) {
        // len < free: the bits fit with one to spare (one signed subtraction and its flags).
        let left = self.free as i32 - len as i32;
        if left > 0 {
            self.free = left as u32;
            self.acc |= v << self.free;
        } else {
            let spill = left.unsigned_abs();
            self.store(self.acc | (v >> spill));
            self.free = 32 - spill;
            // v << (32 - spill), 0 for spill = 0.
            self.acc = (v << 1) << (31 - spill);
        }
    }

    /// Stores a full word (if it fits).
    #[inline(always)]
    fn store(&mut self, word: u32) {
        if let Some(dst) = self
            .out
            .get_mut(self.pos..)
            .and_then(|d| d.first_chunk_mut())
        {
            *dst = word.to_be_bytes();
        }
        self.pos += 4;
    }

    fn bits(&self) -> usize {
        self.pos * 8 + (32 - self.free) as usize
    }

    #[inline(always)]
    fn put_rice(&mut self, z: u32, k: u32) {
        let q = z >> k;
        if q < QMAX {
            // A 1 bit then the low k bits of z: z - (q << k) + (1 << k).
            self.put(z.wrapping_sub(q.wrapping_sub(1) << k), q + 1 + k);
        } else {
            // 16 zero bits, then z in 16 bits.
            self.put(z, 32);
        }
    }

    /// Elias gamma of `v >= 1`, `v < 2^16`.
    fn put_gamma(&mut self, v: u32) {
        let nb = 32 - v.leading_zeros();
        self.put(v, 2 * nb - 1);
    }

    /// Pads to a byte; the byte length, or `None` if it did not fit.
    fn finish(self) -> Option<usize> {
        let nbytes = (32 - self.free).div_ceil(8) as usize;
        let dst = self.out.get_mut(self.pos..self.pos + nbytes)?;
        dst.copy_from_slice(&self.acc.to_be_bytes()[..nbytes]);
        Some(self.pos + nbytes)
    }
}

/// MSB-first bit reader; reads 0 bits past the end and remembers how far it went.
struct BitReader<'i> {
    data: &'i [u8],
    pos: usize,
    acc: u64,
    n: u32,
}

impl<'i> BitReader<'i> {
    fn new(data: &'i [u8]) -> Self {
        Self {
            data,
            pos: 0,
            acc: 0,
            n: 0,
        }
    }

    /// Ensures at least 32 bits in the accumulator.
    #[inline(always)]
    fn refill(&mut self) {
        if self.n <= 32 {
            if let Some(b) = self.data.get(self.pos..self.pos + 4) {
                let w = u32::from_be_bytes([b[0], b[1], b[2], b[3]]);
                self.acc |= u64::from(w) << (32 - self.n);
                self.n += 32;
                self.pos += 4;
            } else {
                while self.n <= 56 {
                    let b = self.data.get(self.pos).copied().unwrap_or(0);
                    self.acc |= u64::from(b) << (56 - self.n);
                    self.n += 8;
                    self.pos += 1;
                }
            }
        }
    }

    /// Next `len <= 32` bits (needs `len <= n`).
    #[inline(always)]
    fn peek(&self, len: u32) -> u32 {
        (self.acc >> 1 >> (63 - len)) as u32
    }

    #[inline(always)]
    fn skip(&mut self, len: u32) {
        self.acc <<= len;
        self.n -= len;
    }

    fn consumed_bits(&self) -> usize {
        self.pos * 8 - self.n as usize
    }

    fn overrun(&self) -> bool {
        self.consumed_bits() > self.data.len() * 8
    }

    #[inline(always)]
    fn rice(&mut self, k: u32) -> Result<u32, CodecError> {
        self.refill();
        let q = self.acc.leading_zeros();
        if q >= QMAX {
            self.skip(QMAX);
            let z = self.peek(16);
            self.skip(16);
            Ok(z)
        } else {
            self.skip(q + 1);
            let z = (q << k) | self.peek(k);
            self.skip(k);
            if z > 0xFFFF {
                Err(CodecError::Corrupt)
            } else {
                Ok(z)
            }
        }
    }

    /// Elias gamma, at most `max`.
    fn gamma(&mut self, max: u32) -> Result<u32, CodecError> {
        self.refill();
        let z = self.acc.leading_zeros();
        if z >= 32 - max.leading_zeros() {
            return Err(CodecError::Corrupt);
        }
        self.skip(z);
        let v = self.peek(z + 1);
        self.skip(z + 1);
        if v > max {
            return Err(CodecError::Corrupt);
        }
        Ok(v)
    }

    /// Checks that the stream ended exactly here (zero padding to the last byte).
    fn finish(mut self) -> Result<(), CodecError> {
        if self.overrun() {
            return Err(CodecError::Truncated);
        }
        let used = self.consumed_bits();
        let pad = (8 - used % 8) % 8;
        self.refill();
        if used.div_ceil(8) != self.data.len() || self.peek(pad as u32) != 0 {
            return Err(CodecError::Corrupt);
        }
        Ok(())
    }
}

/// Row encoder. Holds the reference row in caller memory.
pub struct Encoder<'a> {
    r: Reference<'a>,
    intra_period: u32,
    /// Predicted rows still allowed before the next intra row.
    budget: u32,
    next_seq: u8,
}

impl<'a> Encoder<'a> {
    /// An encoder for rows of `width` (`1 ..= MAX_WIDTH`) pixels keeping its reference in
    /// `prev_heights` (`>= width`) and `prev_valid` (`>= ceil(width/8)` bytes); `None` if the
    /// width or a buffer does not fit. `intra_period` is the intra period `K` (see the module
    /// docs; a packet stream uses [`super::STREAM_INTRA_PERIOD`]).
    pub fn new(
        prev_heights: &'a mut [i16],
        prev_valid: &'a mut [u8],
        width: usize,
        intra_period: u32,
    ) -> Option<Self> {
        Some(Self {
            r: Reference::new(prev_heights, prev_valid, width)?,
            intra_period,
            budget: 0,
            next_seq: 0,
        })
    }

    /// Sets the intra period `K` (see the module docs). A shorter period takes effect at once:
    /// no more than `K - 1` predicted rows follow the last intra row.
    pub fn set_intra_period(&mut self, intra_period: u32) {
        self.intra_period = intra_period;
        self.budget = self.budget.min(intra_period.saturating_sub(1));
    }

    /// Forgets the reference: the next row is intra.
    pub fn reset(&mut self) {
        self.r.present = false;
    }

    /// The intra period `K`.
    pub fn intra_period(&self) -> u32 {
        self.intra_period
    }

    /// Row width.
    pub fn width(&self) -> usize {
        self.r.width
    }

    /// Codes one row into `out`; returns the payload length (at most [`max_len`]).
    ///
    /// `heights`: `W` values (those of invalid pixels are ignored); `valid`: `ceil(W/8)` bytes,
    /// bit `c % 8` of byte `c / 8` set for a valid pixel (padding bits ignored). `out` must hold
    /// [`max_len`]`(W)` bytes, else [`CodecError::BufferTooSmall`] (and nothing changes).
    pub fn encode(
        &mut self,
        heights: &[i16],
        valid: &[u8],
        out: &mut [u8],
    ) -> Result<usize, CodecError> {
        let w = self.r.width;
        let nb = w.div_ceil(8);
        if heights.len() < w || valid.len() < nb || out.len() < max_len(w) {
            return Err(CodecError::BufferTooSmall);
        }
        let (heights, valid) = (&heights[..w], &valid[..nb]);
        let (hdr, body) = out.split_at_mut(HEADER_LEN);
        let body = &mut body[..raw_len(w)];
        let seq = self.next_seq;
        self.next_seq = seq.wrapping_add(1);
        let predicted = self.r.present && (self.intra_period == 0 || self.budget > 0);

        let coded = encode_body(&mut self.r, predicted, heights, valid, body);
        let len = match coded {
            Some((plain, len)) => {
                hdr[0] = (u8::from(predicted) * F_PRED) | (u8::from(plain) * F_PLAIN_MASK);
                len
            }
            None => {
                hdr[0] = F_RAW;
                write_raw(&mut self.r, heights, valid, body)
            }
        };
        hdr[1] = seq;
        self.r.set_valid(valid);
        self.r.present = true;
        if predicted && coded.is_some() {
            self.budget = self.budget.saturating_sub(1);
        } else {
            self.budget = self.intra_period.saturating_sub(1);
        }
        Ok(HEADER_LEN + len)
    }
}

/// Codes pixel `x` against `pred` in context `q`.
#[inline(always)]
fn code(bw: &mut BitWriter<'_>, model: &mut Model, q: usize, pred: i32, x: i16) {
    let z = zigzag((i32::from(x) - pred) as i16);
    let k = model.k(q);
    model.update(q, z);
    bw.put_rice(z, k);
}

/// [`code`] out of line: the last pixel of a predicted run, the odd pixel of an intra run.
#[inline(never)]
fn code_one(bw: &mut BitWriter<'_>, model: &mut Model, q: usize, pred: i32, x: i16) {
    code(bw, model, q, pred, x);
}

/// Codes a run of valid pixels `xs` of an intra row; `a`, `aa`: the filled heights `R[c-1]`,
/// `R[c-2]` left of the run. [`predict_i`] and [`code`], with the bit writer and the contexts'
/// accumulators in locals (registers) and one copy of the coder per context.
#[inline(never)]
fn code_intra_run(bw: &mut BitWriter<'_>, model: &mut Model, xs: &[i16], mut a: i32, aa: i32) {
    let mut w = BitWriter {
        out: &mut *bw.out,
        ..*bw
    };
    let [mut a0, mut a1, mut a2] = model.a;
    // The gradient a - aa, carried instead of aa.
    let mut d = a - aa;
    macro_rules! pixel {
        ($x:expr) => {
            let x = i32::from($x);
            // |d| < T_FLAT_I: the average (a + aa + 1) >> 1 = a - (d >> 1).
            if (d + (T_FLAT_I - 1)) as u32 <= 2 * (T_FLAT_I - 1) as u32 {
                let e = x - (a - (d >> 1));
                if (d + (T_CTX_I - 1)) as u32 <= 2 * (T_CTX_I - 1) as u32 {
                    code_acc(&mut w, &mut a0, e);
                } else {
                    code_acc(&mut w, &mut a1, e);
                }
            } else {
                code_acc(&mut w, &mut a2, x - a);
            }
            (a, d) = (x, x - a);
        };
    }
    // Two pixels a step (no moves between the steps' registers).
    let mut pairs = xs.chunks_exact(2);
    for p in &mut pairs {
        pixel!(p[0]);
        pixel!(p[1]);
    }
    model.a = [a0, a1, a2];
    (bw.pos, bw.acc, bw.free) = (w.pos, w.acc, w.free);
    if let [x] = pairs.remainder() {
        let (p, q) = predict_i(a, a - d);
        code_one(bw, model, q, p, *x);
    }
}

/// [`code`] with the context's accumulator `ctx`: the residual `e` is taken mod 2^16.
#[inline(always)]
fn code_acc(bw: &mut BitWriter<'_>, ctx: &mut u32, e: i32) {
    let e = i32::from(e as i16);
    // zigzag of the i16 residual, in 0 ..= 65535.
    let z = ((e << 1) ^ (e >> 31)) as u32;
    let k = k_of(*ctx);
    *ctx = *ctx - (*ctx >> SHIFT) + z;
    bw.put_rice(z, k);
}

/// Codes a run of valid pixels `xs` (pixels `c .. c + xs.len()`) of a predicted row with
/// [`predict_p`] and [`code`]; `refh`: the reference heights `U` of the whole row, overwritten
/// by the run's `R` one pixel behind where they are read.
#[inline(never)]
fn code_predicted_run(
    bw: &mut BitWriter<'_>,
    model: &mut Model,
    xs: &[i16],
    refh: &mut [i16],
    c: usize,
) {
    let mut w = BitWriter {
        out: &mut *bw.out,
        ..*bw
    };
    let mut m = Model { a: model.a };
    let e = c + xs.len();
    // a = R[c-1] = U[c-1] (pixel c-1 is invalid, or c = 0: U[0]), u = U[c-1].
    let mut a = i32::from(refh[c.saturating_sub(1)]);
    let mut u = a;
    // d of the run's last pixel: U[e] (invalid, not overwritten) or U[W-1].
    let tail = i32::from(refh[e.min(refh.len() - 1)]);
    let mut run = refh[c..e].iter_mut();
    let (Some(mut r), Some((&x_last, xs))) = (run.next(), xs.split_last()) else {
        return;
    };
    let mut b = i32::from(*r);
    for (&x, dn) in xs.iter().zip(run) {
        let d = i32::from(*dn);
        let (p, q) = predict_p(a, b, u, d);
        code(&mut w, &mut m, q, p, x);
        *r = x;
        r = dn;
        (a, u, b) = (i32::from(x), b, d);
    }
    *r = x_last;
    model.a = m.a;
    (bw.pos, bw.acc, bw.free) = (w.pos, w.acc, w.free);
    let (p, q) = predict_p(a, b, u, tail);
    code_one(bw, model, q, p, x_last);
}

/// Codes the body; `Some((plain_mask, bytes))`, or `None` if it would exceed the raw body
/// (the reference heights are then half updated: the caller rewrites them).
fn encode_body(
    r: &mut Reference<'_>,
    predicted: bool,
    heights: &[i16],
    valid: &[u8],
    body: &mut [u8],
) -> Option<(bool, usize)> {
    let w = r.width;
    let ref_valid: &[u8] = r.valid;
    let m = |i: usize| {
        if predicted {
            word(valid, i) ^ word(ref_valid, i)
        } else {
            !word(valid, i)
        }
    };

    // Validity section: runs of m, or W plain bits if the runs cost more.
    let mut bw = BitWriter::new(body);
    let mut c = 0;
    let mut value = false;
    while c < w && bw.bits() <= w {
        let e = run_end(m, c, w, value);
        bw.put_gamma((e - c + usize::from(c == 0)) as u32);
        c = e;
        value = !value;
    }
    let plain = bw.bits() > w;
    if plain {
        bw = BitWriter::new(bw.out);
        for (i, &byte) in valid.iter().enumerate() {
            let len = (w - 8 * i).min(8) as u32;
            bw.put(u32::from(byte.reverse_bits() >> (8 - len)), len);
        }
    }

    // Pixels, run by run of validity.
    let mut model = Model::new();
    let refh = &mut *r.heights;
    let mut c = 0;
    while c < w {
        let v = bit(valid, c);
        let e = run_end(|i| word(valid, i), c, w, v);
        match (v, predicted) {
            (true, true) => code_predicted_run(&mut bw, &mut model, &heights[c..e], refh, c),
            (true, false) => {
                let a = if c >= 1 { i32::from(refh[c - 1]) } else { 0 };
                let aa = if c >= 2 { i32::from(refh[c - 2]) } else { 0 };
                code_intra_run(&mut bw, &mut model, &heights[c..e], a, aa);
                refh[c..e].copy_from_slice(&heights[c..e]);
            }
            (false, true) => {}
            (false, false) => {
                let fill = if c >= 1 { refh[c - 1] } else { 0 };
                refh[c..e].fill(fill);
            }
        }
        c = e;
    }
    bw.finish().map(|len| (plain, len))
}

/// Writes the raw body and makes the row the reference (intra fill rule); returns its length.
fn write_raw(r: &mut Reference<'_>, heights: &[i16], valid: &[u8], body: &mut [u8]) -> usize {
    let w = r.width;
    let nb = w.div_ceil(8);
    let (mask, hs) = body.split_at_mut(nb);
    mask.copy_from_slice(valid);
    clear_padding(mask, w);
    let mut fill = 0i16;
    for (c, (dst, (&x, rh))) in hs
        .chunks_exact_mut(2)
        .zip(heights.iter().zip(r.heights.iter_mut()))
        .enumerate()
    {
        let x = if bit(valid, c) {
            fill = x;
            x
        } else {
            0
        };
        dst.copy_from_slice(&x.to_le_bytes());
        *rh = fill;
    }
    nb + 2 * w
}

/// Decodes one pixel coded against `pred` in context `q`.
#[inline(always)]
fn decode_px(
    br: &mut BitReader<'_>,
    model: &mut Model,
    q: usize,
    pred: i32,
) -> Result<i16, CodecError> {
    match br.rice(model.k(q)) {
        Ok(z) => {
            model.update(q, z);
            Ok((pred + i32::from(unzigzag(z))) as i16)
        }
        Err(e) => Err(if br.overrun() {
            CodecError::Truncated
        } else {
            e
        }),
    }
}

/// Row decoder. Holds the reference row in caller memory.
pub struct Decoder<'a> {
    r: Reference<'a>,
    /// The reference's state outside this decoder (a [`ReferenceRow`]'s): kept up to date after
    /// every row, so that the next decoder over the same memory takes up where this one left
    /// off. `None` for a decoder over plain slices.
    home: Option<&'a mut RefState>,
}

/// Whether a reference is held and its sequence number: the part of a decoder's reference that
/// is not in the row memory.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct RefState {
    present: bool,
    seq: u8,
}

impl<'a> Decoder<'a> {
    /// A decoder for rows of `width` pixels; buffers and `None` as for [`Encoder::new`].
    pub fn new(
        prev_heights: &'a mut [i16],
        prev_valid: &'a mut [u8],
        width: usize,
    ) -> Option<Self> {
        Some(Self {
            r: Reference::new(prev_heights, prev_valid, width)?,
            home: None,
        })
    }

    /// Forgets the reference: predicted rows fail with [`CodecError::MissingReference`] until
    /// the next intra row.
    pub fn reset(&mut self) {
        self.r.present = false;
        self.save();
    }

    /// Copies the reference's state to its home, if it has one.
    fn save(&mut self) {
        if let Some(h) = self.home.as_deref_mut() {
            *h = RefState {
                present: self.r.present,
                seq: self.r.seq,
            };
        }
    }

    /// Row width.
    pub fn width(&self) -> usize {
        self.r.width
    }

    /// Whether the decoder holds a reference (the next predicted row in sequence can decode).
    pub fn has_reference(&self) -> bool {
        self.r.present
    }

    /// Decodes one payload into `heights` (`W`, 0 where invalid) and `valid` (`ceil(W/8)`
    /// bytes, padding bits 0). On error the outputs hold garbage and the reference is dropped.
    pub fn decode(
        &mut self,
        input: &[u8],
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> Result<(), CodecError> {
        let w = self.r.width;
        let nb = w.div_ceil(8);
        if heights.len() < w || valid.len() < nb {
            return Err(CodecError::BufferTooSmall);
        }
        let (heights, valid) = (&mut heights[..w], &mut valid[..nb]);
        let result = self.decode_inner(input, heights, valid);
        let result = match result {
            Ok(seq) => {
                self.r.set_valid(valid);
                self.r.present = true;
                self.r.seq = seq;
                Ok(())
            }
            Err(e) => {
                self.r.present = false;
                Err(e)
            }
        };
        self.save();
        result
    }

    fn decode_inner(
        &mut self,
        input: &[u8],
        heights: &mut [i16],
        valid: &mut [u8],
    ) -> Result<u8, CodecError> {
        let (kind, seq) = peek(input)?;
        let body = &input[HEADER_LEN..];
        let w = self.r.width;
        let nb = w.div_ceil(8);
        let predicted = match kind {
            RowKind::Raw => {
                if body.len() != raw_len(w) {
                    return Err(if body.len() < raw_len(w) {
                        CodecError::Truncated
                    } else {
                        CodecError::Corrupt
                    });
                }
                let (mask, hs) = body.split_at(nb);
                valid.copy_from_slice(mask);
                clear_padding(valid, w);
                let mut fill = 0i16;
                for (c, ((src, h), rh)) in hs
                    .chunks_exact(2)
                    .zip(heights.iter_mut())
                    .zip(self.r.heights.iter_mut())
                    .enumerate()
                {
                    *h = if bit(valid, c) {
                        fill = i16::from_le_bytes([src[0], src[1]]);
                        fill
                    } else {
                        0
                    };
                    *rh = fill;
                }
                return Ok(seq);
            }
            RowKind::Intra => false,
            RowKind::Predicted => {
                if !self.r.present || seq != self.r.seq.wrapping_add(1) {
                    return Err(CodecError::MissingReference);
                }
                true
            }
        };
        let plain = input[0] & F_PLAIN_MASK != 0;
        let mut br = BitReader::new(body);
        let fail = |br: &BitReader<'_>, e: CodecError| {
            if br.overrun() {
                CodecError::Truncated
            } else {
                e
            }
        };

        // Validity section.
        valid.fill(0);
        if plain {
            for (i, byte) in valid.iter_mut().enumerate() {
                let len = (w - 8 * i).min(8) as u32;
                br.refill();
                let v = br.peek(len) as u8;
                br.skip(len);
                *byte = (v << (8 - len)).reverse_bits();
            }
        } else {
            let mut c = 0;
            let mut value = false;
            while c < w {
                let first = usize::from(c == 0);
                let max = (w - c + first) as u32;
                let len = br.gamma(max).map_err(|e| fail(&br, e))? as usize - first;
                if value {
                    set_bits(valid, c, c + len);
                }
                c += len;
                value = !value;
            }
            if predicted {
                for (v, r) in valid.iter_mut().zip(self.r.valid.iter()) {
                    *v ^= r;
                }
            } else {
                for v in valid.iter_mut() {
                    *v = !*v;
                }
            }
            clear_padding(valid, w);
        }

        // Pixels.
        let mut model = Model::new();
        let refh = &mut *self.r.heights;
        let valid: &[u8] = valid;
        let mut c = 0;
        while c < w {
            let v = bit(valid, c);
            let e = run_end(|i| word(valid, i), c, w, v);
            match (v, predicted) {
                (true, true) => {
                    let cells = Cell::from_mut(&mut *refh).as_slice_of_cells();
                    let mut a = i32::from(cells[c.saturating_sub(1)].get());
                    let mut u = a;
                    let mut b = i32::from(cells[c].get());
                    let tail = i32::from(cells[e.min(w - 1)].get());
                    let (hs, h_last) = heights[c..e].split_at_mut(e - c - 1);
                    for ((h, r), dn) in hs.iter_mut().zip(&cells[c..e - 1]).zip(&cells[c + 1..e]) {
                        let d = i32::from(dn.get());
                        let (p, q) = predict_p(a, b, u, d);
                        let x = decode_px(&mut br, &mut model, q, p)?;
                        r.set(x);
                        *h = x;
                        (a, u, b) = (i32::from(x), b, d);
                    }
                    let (p, q) = predict_p(a, b, u, tail);
                    let x = decode_px(&mut br, &mut model, q, p)?;
                    cells[e - 1].set(x);
                    h_last[0] = x;
                }
                (true, false) => {
                    let mut a = if c >= 1 { i32::from(refh[c - 1]) } else { 0 };
                    let mut aa = if c >= 2 { i32::from(refh[c - 2]) } else { 0 };
                    for (h, r) in heights[c..e].iter_mut().zip(&mut refh[c..e]) {
                        let (p, q) = predict_i(a, aa);
                        let x = decode_px(&mut br, &mut model, q, p)?;
                        *r = x;
                        *h = x;
                        (a, aa) = (i32::from(x), a);
                    }
                }
                (false, true) => heights[c..e].fill(0),
                (false, false) => {
                    let fill = if c >= 1 { refh[c - 1] } else { 0 };
                    refh[c..e].fill(fill);
                    heights[c..e].fill(0);
                }
            }
            c = e;
        }
        br.finish()?;
        Ok(seq)
    }
}

/// Owned reference memory for one end of a stream: `W` heights and `ceil(W/8)` validity
/// bytes, from which an [`Encoder`] or a [`Decoder`] borrows (`alloc` feature), and, for the
/// decoding end, whether a reference is held and its sequence number.
///
/// Decoding end: a [`ReferenceRow::decoder`] may be taken per row; it starts from the state
/// the previous one left (the reference is the row decoded last through this memory), so
/// predicted rows decode. Encoding end: keep one [`ReferenceRow::encoder`] for the whole
/// stream (its sequence number and intra budget live in the encoder; a new encoder starts with
/// an intra row and sequence number 0).
#[cfg(feature = "alloc")]
pub struct ReferenceRow {
    heights: alloc::boxed::Box<[i16]>,
    valid: alloc::boxed::Box<[u8]>,
    state: RefState,
}

#[cfg(feature = "alloc")]
impl ReferenceRow {
    /// Reference memory for rows of `width` pixels.
    pub fn new(width: usize) -> ReferenceRow {
        ReferenceRow {
            heights: alloc::vec![0; width].into_boxed_slice(),
            valid: alloc::vec![0; width.div_ceil(8)].into_boxed_slice(),
            state: RefState::default(),
        }
    }

    /// Row width.
    pub fn width(&self) -> usize {
        self.heights.len()
    }

    /// An encoder over this memory with intra period `intra_period`; `None` if the width is not
    /// supported (`1 ..= MAX_WIDTH`).
    pub fn encoder(&mut self, intra_period: u32) -> Option<Encoder<'_>> {
        let w = self.width();
        Encoder::new(&mut self.heights, &mut self.valid, w, intra_period)
    }

    /// A decoder over this memory that goes on from the row decoded last through it (see the
    /// type's docs); `None` if the width is not supported.
    pub fn decoder(&mut self) -> Option<Decoder<'_>> {
        let w = self.width();
        let mut d = Decoder::new(&mut self.heights, &mut self.valid, w)?;
        d.r.present = self.state.present;
        d.r.seq = self.state.seq;
        d.home = Some(&mut self.state);
        Some(d)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use proptest::prelude::*;
    use std::vec;
    use std::vec::Vec;

    /// splitmix64.
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }
        fn unit(&mut self) -> f64 {
            (self.next() >> 11) as f64 / (1u64 << 53) as f64
        }
        fn gauss(&mut self) -> f64 {
            let u1 = 1.0 - self.unit();
            let u2 = self.unit();
            (-2.0 * u1.ln()).sqrt() * (2.0 * core::f64::consts::PI * u2).cos()
        }
    }

    #[derive(Clone, Debug)]
    struct Img {
        w: usize,
        h: Vec<Vec<i16>>,
        v: Vec<Vec<u8>>,
    }

    fn all_valid(w: usize) -> Vec<u8> {
        let mut v = vec![0xFFu8; w.div_ceil(8)];
        clear_padding(&mut v, w);
        v
    }

    fn mask_from(w: usize, mut f: impl FnMut(usize) -> bool) -> Vec<u8> {
        let mut v = vec![0u8; w.div_ceil(8)];
        for c in 0..w {
            if f(c) {
                v[c / 8] |= 1 << (c % 8);
            }
        }
        v
    }

    /// Flat board, Gaussian noise of `sigma` LSB, `deposits` boxes of 240..800 LSB.
    fn board(rng: &mut Rng, w: usize, rows: usize, sigma: f64, deposits: usize) -> Img {
        let mut base = vec![vec![0f64; w]; rows];
        for _ in 0..deposits {
            let (r0, c0) = (
                rng.below(rows as u64) as usize,
                rng.below(w as u64) as usize,
            );
            let (dh, dw) = (20 + rng.below(60) as usize, 20 + rng.below(60) as usize);
            let z = 240.0 + rng.below(561) as f64;
            for row in base.iter_mut().skip(r0).take(dh) {
                for p in row.iter_mut().skip(c0).take(dw) {
                    *p = z;
                }
            }
        }
        let h = base
            .iter()
            .map(|row| {
                row.iter()
                    .map(|&z| (z + sigma * rng.gauss()).round() as i16)
                    .collect()
            })
            .collect();
        Img {
            w,
            h,
            v: vec![all_valid(w); rows],
        }
    }

    fn kinds(rng: &mut Rng, w: usize, rows: usize) -> Vec<Img> {
        let mut out = Vec::new();
        // Smooth.
        let smooth: Vec<Vec<i16>> = (0..rows)
            .map(|r| {
                (0..w)
                    .map(|c| (300.0 * ((c as f64) / 97.0 + r as f64 / 13.0).sin()) as i16)
                    .collect()
            })
            .collect();
        out.push(Img {
            w,
            h: smooth.clone(),
            v: vec![all_valid(w); rows],
        });
        // Noisy board with deposits, with invalid margins, holes and a few whole invalid rows.
        let mut b = board(rng, w, rows, 8.0, 1 + w * rows / 4000);
        out.push(b.clone());
        for (r, v) in b.v.iter_mut().enumerate() {
            let (lo, hi) = (w / 10 + r % 3, w - w / 7);
            let hole = rng.below(w as u64) as usize;
            *v = if r % 11 == 5 {
                vec![0; w.div_ceil(8)]
            } else {
                mask_from(w, |c| c >= lo && c < hi && c / 4 != hole / 4)
            };
        }
        out.push(b);
        // All invalid (with garbage heights that must be ignored).
        out.push(Img {
            w,
            h: smooth.clone(),
            v: vec![vec![0; w.div_ceil(8)]; rows],
        });
        // Alternating validity.
        out.push(Img {
            w,
            h: smooth.clone(),
            v: (0..rows)
                .map(|r| mask_from(w, |c| (c + r) % 2 == 0))
                .collect(),
        });
        // Random validity (with garbage padding bits).
        let v = (0..rows)
            .map(|_| (0..w.div_ceil(8)).map(|_| rng.next() as u8).collect())
            .collect();
        out.push(Img { w, h: smooth, v });
        // Extremes.
        let ext = (0..rows)
            .map(|_| {
                (0..w)
                    .map(|_| {
                        if rng.below(2) == 0 {
                            i16::MIN
                        } else {
                            i16::MAX
                        }
                    })
                    .collect()
            })
            .collect();
        out.push(Img {
            w,
            h: ext,
            v: vec![all_valid(w); rows],
        });
        let ramp = (0..rows)
            .map(|r| {
                (0..w)
                    .map(|c| (c as i16).wrapping_mul(4099).wrapping_add(r as i16 * 7))
                    .collect()
            })
            .collect();
        out.push(Img {
            w,
            h: ramp,
            v: vec![all_valid(w); rows],
        });
        // Random i16 noise.
        let noise = (0..rows)
            .map(|_| (0..w).map(|_| rng.next() as i16).collect())
            .collect();
        out.push(Img {
            w,
            h: noise,
            v: vec![all_valid(w); rows],
        });
        out
    }

    /// The row a decoder must return: padding bits cleared, invalid heights 0.
    fn expected(w: usize, h: &[i16], v: &[u8]) -> (Vec<i16>, Vec<u8>) {
        let mut v = v[..w.div_ceil(8)].to_vec();
        clear_padding(&mut v, w);
        let h = (0..w).map(|c| if bit(&v, c) { h[c] } else { 0 }).collect();
        (h, v)
    }

    /// Codes and decodes every row (resetting both ends before the rows in `resets`); returns
    /// the payloads.
    fn round_trip(img: &Img, intra_period: u32, resets: &[usize]) -> Vec<Vec<u8>> {
        let w = img.w;
        let nb = w.div_ceil(8);
        let (mut eh, mut ev, mut dh, mut dv) =
            (vec![0i16; w], vec![0u8; nb], vec![0i16; w], vec![0u8; nb]);
        let mut enc = Encoder::new(&mut eh, &mut ev, w, intra_period).unwrap();
        let mut dec = Decoder::new(&mut dh, &mut dv, w).unwrap();
        let mut out = vec![0u8; max_len(w)];
        let (mut oh, mut ov) = (vec![0i16; w], vec![0u8; nb]);
        let mut payloads = Vec::new();
        for (r, (h, v)) in img.h.iter().zip(&img.v).enumerate() {
            if resets.contains(&r) {
                enc.reset();
                dec.reset();
            }
            let n = enc.encode(h, v, &mut out).unwrap();
            assert!(n <= max_len(w));
            let kind = peek(&out[..n]).unwrap().0;
            if resets.contains(&r) || r == 0 || intra_period == 1 {
                assert_ne!(kind, RowKind::Predicted, "row {r}");
            }
            dec.decode(&out[..n], &mut oh, &mut ov)
                .unwrap_or_else(|e| panic!("row {r} w {w}: {e:?}"));
            let (xh, xv) = expected(w, h, v);
            assert_eq!(ov, xv, "validity row {r} w {w}");
            assert_eq!(oh, xh, "heights row {r} w {w}");
            payloads.push(out[..n].to_vec());
        }
        payloads
    }

    #[test]
    fn round_trips_all_kinds() {
        let mut rng = Rng(7);
        for w in [1usize, 2, 3, 7, 8, 9, 16, 31, 33, 100, 2048] {
            for (i, img) in kinds(&mut rng, w, 24).iter().enumerate() {
                for intra_period in [0, 1, 5, 32] {
                    let p = round_trip(img, intra_period, &[9, 10, 17]);
                    if i == 3 {
                        // All invalid: a few bytes per row.
                        assert!(
                            p.iter().all(|p| p.len() <= 6),
                            "{:?}",
                            p.iter().map(Vec::len).collect::<Vec<_>>()
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn max_width_round_trips() {
        let mut rng = Rng(8);
        for img in kinds(&mut rng, MAX_WIDTH, 3) {
            round_trip(&img, 32, &[]);
        }
    }

    #[test]
    fn incompressible_rows_go_raw_and_respect_max_len() {
        let mut rng = Rng(9);
        let w = 2048;
        // Random i16 noise costs about 16.5 bits per pixel coded, still below the raw 17.
        let img = Img {
            w,
            h: (0..4)
                .map(|_| (0..w).map(|_| rng.next() as i16).collect())
                .collect(),
            v: vec![all_valid(w); 4],
        };
        for p in round_trip(&img, 32, &[]) {
            assert!(p.len() <= max_len(w));
        }
        // Every residual -32768 (z = 65535): 17 bits per pixel plus the escapes while k adapts.
        let alt: Vec<i16> = (0..w)
            .map(|c| if c % 2 == 0 { 0 } else { i16::MIN })
            .collect();
        let img = Img {
            w,
            h: vec![alt; 3],
            v: vec![all_valid(w); 3],
        };
        for p in round_trip(&img, 1, &[]) {
            assert_eq!(p.len(), max_len(w));
            assert_eq!(peek(&p).unwrap().0, RowKind::Raw);
        }
        assert_eq!(max_len(w), raw_len(w) + 2);
    }

    #[test]
    fn intra_period_and_sequence() {
        let mut rng = Rng(10);
        let img = board(&mut rng, 64, 20, 8.0, 3);
        let p = round_trip(&img, 4, &[]);
        let k: Vec<_> = p.iter().map(|p| peek(p).unwrap()).collect();
        for (i, (kind, seq)) in k.iter().enumerate() {
            assert_eq!(*seq as usize, i);
            assert_eq!(*kind == RowKind::Intra, i % 4 == 0, "row {i}");
        }
    }

    #[test]
    fn loss_is_detected_and_recovered_at_next_intra() {
        let mut rng = Rng(11);
        let w = 300;
        let img = board(&mut rng, w, 20, 8.0, 4);
        let p = round_trip(&img, 6, &[]);
        let nb = w.div_ceil(8);
        let (mut dh, mut dv, mut oh, mut ov) =
            (vec![0i16; w], vec![0u8; nb], vec![0i16; w], vec![0u8; nb]);
        let mut dec = Decoder::new(&mut dh, &mut dv, w).unwrap();
        for (r, pl) in p.iter().enumerate() {
            if r == 8 {
                continue; // lost
            }
            let res = dec.decode(pl, &mut oh, &mut ov);
            if (9..12).contains(&r) {
                assert_eq!(res, Err(CodecError::MissingReference), "row {r}");
            } else {
                res.unwrap();
                assert_eq!(oh, expected(w, &img.h[r], &img.v[r]).0, "row {r}");
            }
        }
        // A predicted row straight after a reset.
        dec.reset();
        assert_eq!(
            dec.decode(&p[1], &mut oh, &mut ov),
            Err(CodecError::MissingReference)
        );
        assert!(!dec.has_reference());
    }

    /// A [`ReferenceRow`] keeps the whole reference, its state included: a decoder taken per
    /// row (as the host stream decoder does) decodes predicted rows, still detects a loss and
    /// recovers at the next intra row, and a reset through one decoder holds for the next.
    #[test]
    fn reference_row_decoders_taken_per_row_follow_the_stream() {
        let mut rng = Rng(12);
        let w = 300;
        let img = board(&mut rng, w, 40, 8.0, 4);
        for intra_period in [0u32, 2, 8, 32] {
            let p = round_trip(&img, intra_period, &[]);
            let predicted = p
                .iter()
                .filter(|p| peek(p).unwrap().0 == RowKind::Predicted)
                .count();
            assert!(
                predicted >= 20,
                "K {intra_period}: {predicted} predicted rows"
            );
            let mut reference = ReferenceRow::new(w);
            let (mut oh, mut ov) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
            for (r, pl) in p.iter().enumerate() {
                let mut dec = reference.decoder().unwrap();
                dec.decode(pl, &mut oh, &mut ov)
                    .unwrap_or_else(|e| panic!("K {intra_period} row {r}: {e:?}"));
                let (xh, xv) = expected(w, &img.h[r], &img.v[r]);
                assert_eq!((&oh, &ov), (&xh, &xv), "K {intra_period} row {r}");
            }
        }
        // A loss: the rows after it fail until the next intra row (K = 6: rows 12, 18, ...).
        let p = round_trip(&img, 6, &[]);
        let mut reference = ReferenceRow::new(w);
        let (mut oh, mut ov) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
        for (r, pl) in p.iter().enumerate().take(20) {
            if r == 8 {
                continue;
            }
            let res = reference.decoder().unwrap().decode(pl, &mut oh, &mut ov);
            if (9..12).contains(&r) {
                assert_eq!(res, Err(CodecError::MissingReference), "row {r}");
            } else {
                res.unwrap_or_else(|e| panic!("row {r}: {e:?}"));
                assert_eq!(oh, expected(w, &img.h[r], &img.v[r]).0, "row {r}");
            }
        }
        // A reset through one decoder holds for the next one over the same memory.
        reference.decoder().unwrap().reset();
        let dec = reference.decoder().unwrap();
        assert!(!dec.has_reference());
    }

    #[test]
    fn buffer_checks() {
        let (mut h, mut v) = (vec![0i16; 16], vec![0u8; 2]);
        assert!(Encoder::new(&mut h, &mut v, 0, 1).is_none());
        assert!(Encoder::new(&mut h, &mut v, 17, 1).is_none());
        assert!(Decoder::new(&mut h, &mut v, 17).is_none());
        let (mut h2, mut v2) = (vec![0i16; MAX_WIDTH + 1], vec![0u8; MAX_WIDTH]);
        assert!(Encoder::new(&mut h2, &mut v2, MAX_WIDTH + 1, 1).is_none());
        let mut enc =
            Encoder::new(&mut h, &mut v, 16, super::super::PREDICTED_INTRA_PERIOD).unwrap();
        let mut out = vec![0u8; max_len(16) - 1];
        assert_eq!(
            enc.encode(&[0; 16], &[0xFF; 2], &mut out),
            Err(CodecError::BufferTooSmall)
        );
        let mut out = vec![0u8; max_len(16)];
        assert_eq!(
            enc.encode(&[0; 15], &[0xFF; 2], &mut out),
            Err(CodecError::BufferTooSmall)
        );
        assert_eq!(
            enc.encode(&[0; 16], &[0xFF; 1], &mut out),
            Err(CodecError::BufferTooSmall)
        );
        let n = enc.encode(&[0; 16], &[0xFF; 2], &mut out).unwrap();
        assert!(n <= 12, "{n}");
        let (mut dh, mut dv) = (vec![0i16; 16], vec![0u8; 2]);
        let mut dec = Decoder::new(&mut dh, &mut dv, 16).unwrap();
        assert_eq!(
            dec.decode(&out[..n], &mut [0; 15], &mut [0; 2]),
            Err(CodecError::BufferTooSmall)
        );
        assert_eq!(
            dec.decode(&out[..n], &mut [0; 16], &mut [0; 1]),
            Err(CodecError::BufferTooSmall)
        );
        assert_eq!(
            dec.decode(&[], &mut [0; 16], &mut [0; 2]),
            Err(CodecError::Truncated)
        );
        assert_eq!(
            dec.decode(&[0x08, 0], &mut [0; 16], &mut [0; 2]),
            Err(CodecError::Corrupt)
        );
    }

    #[test]
    fn rice_parameter_matches_its_definition() {
        let mut m = Model::new();
        for a in (0..100_000u32).chain([(1 << (16 + SHIFT)) - 1]) {
            m.a[0] = a;
            let mut k = 0;
            while (1u64 << (k + 1 + SHIFT)) <= u64::from(a) {
                k += 1;
            }
            assert_eq!(m.k(0), k, "a {a}");
        }
        // The accumulator stays below 2^(16 + SHIFT), so k <= 15.
        for _ in 0..10_000 {
            m.update(0, 0xFFFF);
        }
        assert!(m.a[0] < 1 << (16 + SHIFT) && m.k(0) == 15, "{}", m.a[0]);
    }

    #[test]
    fn every_truncation_fails_and_bit_flips_never_panic() {
        let mut rng = Rng(12);
        for w in [5usize, 40, 130] {
            for img in kinds(&mut rng, w, 4) {
                let p = round_trip(&img, 32, &[]);
                let nb = w.div_ceil(8);
                let (mut dh, mut dv, mut oh, mut ov) =
                    (vec![0i16; w], vec![0u8; nb], vec![0i16; w], vec![0u8; nb]);
                let mut dec = Decoder::new(&mut dh, &mut dv, w).unwrap();
                for r in 0..p.len() {
                    for cut in 0..p[r].len() {
                        for q in &p[..r] {
                            dec.decode(q, &mut oh, &mut ov).unwrap();
                        }
                        assert!(
                            dec.decode(&p[r][..cut], &mut oh, &mut ov).is_err(),
                            "w {w} row {r} cut {cut}"
                        );
                    }
                    for b in 0..p[r].len() * 8 {
                        let mut q = p[r].clone();
                        q[b / 8] ^= 1 << (b % 8);
                        for q in &p[..r] {
                            dec.decode(q, &mut oh, &mut ov).unwrap();
                        }
                        let _ = dec.decode(&q, &mut oh, &mut ov);
                    }
                }
            }
        }
    }

    /// Residuals of the predictor on an all-valid image coded with intra period `intra_period`.
    fn residuals(img: &Img, intra_period: usize) -> Vec<i16> {
        let w = img.w;
        let mut res = Vec::new();
        for (r, row) in img.h.iter().enumerate() {
            for c in 0..w {
                let at =
                    |row: &[i16], c: isize| i32::from(row[c.clamp(0, w as isize - 1) as usize]);
                let x = i32::from(row[c]);
                let c = c as isize;
                let p = if r % intra_period == 0 {
                    let a = if c >= 1 { at(row, c - 1) } else { 0 };
                    let aa = if c >= 2 { at(row, c - 2) } else { 0 };
                    predict_i(a, aa).0
                } else {
                    let up = &img.h[r - 1];
                    let a = if c >= 1 { at(row, c - 1) } else { at(up, 0) };
                    predict_p(a, at(up, c), at(up, c - 1), at(up, c + 1)).0
                };
                res.push((x - p) as i16);
            }
        }
        res
    }

    fn entropy(xs: &[i16]) -> f64 {
        let mut hist = vec![0u32; 65536];
        for &x in xs {
            hist[x as u16 as usize] += 1;
        }
        let n = xs.len() as f64;
        hist.iter()
            .filter(|&&k| k > 0)
            .map(|&k| -(k as f64 / n) * (k as f64 / n).log2())
            .sum()
    }

    #[test]
    fn compresses_noisy_flat_board_near_residual_entropy() {
        let mut rng = Rng(13);
        let (w, rows) = (2048, 96);
        for (deposits, sigma) in [(0, 8.0), (16, 8.0), (60, 8.0), (16, 4.0), (16, 16.0)] {
            let img = board(&mut rng, w, rows, sigma, deposits);
            let cover =
                img.h.iter().flatten().filter(|&&x| x > 120).count() as f64 / (w * rows) as f64;
            let p = round_trip(&img, super::super::PREDICTED_INTRA_PERIOD, &[]);
            let bits = p.iter().map(|p| p.len() * 8).sum::<usize>() as f64 / (w * rows) as f64;
            let h = entropy(&residuals(
                &img,
                super::super::PREDICTED_INTRA_PERIOD as usize,
            ));
            let ratio = 17.0 / bits;
            std::println!(
                "sigma {sigma} deposit cover {:.0} %: {bits:.3} bits/px, residual entropy {h:.3} ({:+.1} %), ratio {ratio:.2}",
                cover * 100.0,
                (bits / h - 1.0) * 100.0
            );
            assert!(bits <= 1.05 * h, "{bits} vs {h}");
            if sigma == 8.0 {
                assert!(ratio >= 3.0, "{ratio}");
            }
        }
    }

    /// Host speed, for context only: `cargo test --release -p dpsa-core codec::tests::speed -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn speed() {
        let mut rng = Rng(15);
        let (w, rows) = (2048, 256);
        let img = board(&mut rng, w, rows, 8.0, 40);
        let nb = w.div_ceil(8);
        let (mut eh, mut ev, mut dh, mut dv) =
            (vec![0i16; w], vec![0u8; nb], vec![0i16; w], vec![0u8; nb]);
        let mut enc =
            Encoder::new(&mut eh, &mut ev, w, super::super::PREDICTED_INTRA_PERIOD).unwrap();
        let mut dec = Decoder::new(&mut dh, &mut dv, w).unwrap();
        let mut buf = vec![0u8; rows * max_len(w)];
        buf.fill(1);
        let mut lens = vec![0; rows];
        let mut te = f64::MAX;
        for _ in 0..5 {
            enc.reset();
            let t = std::time::Instant::now();
            for (r, (h, v)) in img.h.iter().zip(&img.v).enumerate() {
                lens[r] = enc.encode(h, v, &mut buf[r * max_len(w)..]).unwrap();
            }
            te = te.min(t.elapsed().as_secs_f64());
        }
        let (mut oh, mut ov) = (vec![0i16; w], vec![0u8; nb]);
        let mut td = f64::MAX;
        for _ in 0..5 {
            dec.reset();
            let t = std::time::Instant::now();
            for (r, &n) in lens.iter().enumerate() {
                let s = r * max_len(w);
                dec.decode(&buf[s..s + n], &mut oh, &mut ov).unwrap();
            }
            td = td.min(t.elapsed().as_secs_f64());
        }
        let px = (w * rows) as f64;
        std::println!(
            "encode {:.2} ns/px, decode {:.2} ns/px",
            te / px * 1e9,
            td / px * 1e9
        );
    }

    // ---- A slow decoder written from the module docs alone, to check the docs. ----

    #[derive(Default)]
    struct SpecRef {
        u: Vec<i32>,
        v: Vec<bool>,
        seq: Option<u8>,
    }

    struct Bits<'a> {
        d: &'a [u8],
        i: usize,
    }

    impl Bits<'_> {
        fn bit(&mut self) -> Result<u32, ()> {
            let b = *self.d.get(self.i / 8).ok_or(())? >> (7 - self.i % 8) & 1;
            self.i += 1;
            Ok(u32::from(b))
        }
        fn bits(&mut self, n: u32) -> Result<u32, ()> {
            let mut v = 0;
            for _ in 0..n {
                v = v << 1 | self.bit()?;
            }
            Ok(v)
        }
        fn gamma(&mut self) -> Result<u32, ()> {
            let mut z = 0;
            while self.bit()? == 0 {
                z += 1;
                if z > 20 {
                    return Err(());
                }
            }
            Ok(1 << z | self.bits(z)?)
        }
    }

    fn spec_decode(p: &[u8], w: usize, st: &mut SpecRef) -> Result<(Vec<i32>, Vec<bool>), ()> {
        let (flags, seq) = (p[0], p[1]);
        let body = &p[2..];
        let pred = flags & 1 != 0;
        if flags == 2 {
            let v: Vec<bool> = (0..w).map(|c| body[c / 8] >> (c % 8) & 1 != 0).collect();
            let nb = w.div_ceil(8);
            let h: Vec<i32> = (0..w)
                .map(|c| i32::from(i16::from_le_bytes([body[nb + 2 * c], body[nb + 2 * c + 1]])))
                .collect();
            let mut r = vec![0; w];
            for c in 0..w {
                r[c] = if v[c] {
                    h[c]
                } else if c > 0 {
                    r[c - 1]
                } else {
                    0
                };
            }
            *st = SpecRef {
                u: r,
                v: v.clone(),
                seq: Some(seq),
            };
            return Ok((h, v));
        }
        if pred && st.seq != Some(seq.wrapping_sub(1)) {
            return Err(());
        }
        let mut b = Bits { d: body, i: 0 };
        let v: Vec<bool> = if flags & 4 != 0 {
            (0..w)
                .map(|_| b.bit().map(|x| x == 1))
                .collect::<Result<_, _>>()?
        } else {
            let mut m = Vec::new();
            let mut val = false;
            while m.len() < w {
                let len = b.gamma()? as usize - usize::from(m.is_empty());
                for _ in 0..len {
                    m.push(val);
                }
                val = !val;
            }
            if m.len() != w {
                return Err(());
            }
            (0..w)
                .map(|c| m[c] ^ if pred { st.v[c] } else { true })
                .collect()
        };
        let mut am = [14u32 * 32; 3];
        let mut r = vec![0i32; w];
        let mut out = vec![0i32; w];
        let u = |c: isize| st.u[c.clamp(0, w as isize - 1) as usize];
        for c in 0..w {
            let ci = c as isize;
            if !v[c] {
                r[c] = if pred {
                    st.u[c]
                } else if c > 0 {
                    r[c - 1]
                } else {
                    0
                };
                continue;
            }
            let (p, q) = if pred {
                let a = if c > 0 { r[c - 1] } else { u(0) };
                let (b, uu, d) = (u(ci), u(ci - 1), u(ci + 1));
                let g = (a - uu).abs() + (uu - b).abs() + (b - d).abs();
                if g < 128 {
                    ((a + b + uu + d + 2) >> 2, usize::from(g >= 48))
                } else {
                    let (mn, mx) = (a.min(b), a.max(b));
                    (
                        if uu >= mx {
                            mn
                        } else if uu <= mn {
                            mx
                        } else {
                            a + b - uu
                        },
                        2,
                    )
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
            let k = 32 - (am[q] >> 6).leading_zeros();
            let mut zeros = 0;
            while zeros < 16 && b.bit()? == 0 {
                zeros += 1;
            }
            let z = if zeros == 16 {
                b.bits(16)?
            } else {
                zeros << k | b.bits(k)?
            };
            am[q] = am[q] - (am[q] >> 5) + z;
            let e = if z % 2 == 0 {
                (z / 2) as i32
            } else {
                -((z / 2) as i32) - 1
            };
            r[c] = i32::from((p + e) as i16);
            out[c] = r[c];
        }
        if b.i.div_ceil(8) != body.len() {
            return Err(());
        }
        *st = SpecRef {
            u: r,
            v: v.clone(),
            seq: Some(seq),
        };
        Ok((out, v))
    }

    #[test]
    fn spec_decoder_agrees() {
        let mut rng = Rng(14);
        for w in [1usize, 9, 77, 2048] {
            for img in kinds(&mut rng, w, 12) {
                let p = round_trip(&img, 5, &[7]);
                let mut st = SpecRef::default();
                for (r, pl) in p.iter().enumerate() {
                    if r == 7 {
                        st = SpecRef::default();
                    }
                    let (h, v) =
                        spec_decode(pl, w, &mut st).unwrap_or_else(|_| panic!("w {w} row {r}"));
                    let (xh, xv) = expected(w, &img.h[r], &img.v[r]);
                    assert_eq!(h, xh.iter().map(|&x| i32::from(x)).collect::<Vec<_>>());
                    assert_eq!(v, (0..w).map(|c| bit(&xv, c)).collect::<Vec<_>>());
                }
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(400))]

        #[test]
        fn random_rows_round_trip(w in 1usize..200, rows in 1usize..8, seed in any::<u64>(), intra_period in 0u32..4,
                                  style in proptest::collection::vec(0u8..4, 8)) {
            let mut rng = Rng(seed);
            let mut img = Img { w, h: Vec::new(), v: Vec::new() };
            for (r, &st) in style.iter().enumerate().take(rows) {
                let h = (0..w).map(|c| match st {
                    0 => rng.next() as i16,
                    1 => (8.0 * rng.gauss()) as i16 + if (c / 16) % 3 == 0 { 500 } else { 0 },
                    2 => [i16::MIN, i16::MAX, 0, -1][rng.below(4) as usize],
                    _ => (c as i16).wrapping_mul(r as i16 + 1),
                }).collect();
                let v = match st {
                    0 => (0..w.div_ceil(8)).map(|_| rng.next() as u8).collect(),
                    1 => all_valid(w),
                    2 => mask_from(w, |c| (c / (1 + r)) % 2 == 0),
                    _ => mask_from(w, |_| rng.below(10) != 0),
                };
                img.h.push(h);
                img.v.push(v);
            }
            round_trip(&img, intra_period, &[3]);
        }

        #[test]
        fn arbitrary_bytes_never_panic(w in 1usize..100, data in proptest::collection::vec(any::<u8>(), 0..300),
                                       flags in 0u8..8, prime in any::<bool>()) {
            let nb = w.div_ceil(8);
            let (mut dh, mut dv, mut oh, mut ov) = (vec![0i16; w], vec![0u8; nb], vec![0i16; w], vec![0u8; nb]);
            let mut dec = Decoder::new(&mut dh, &mut dv, w).unwrap();
            // Mostly well-formed flags, to reach the body decoder.
            let mut d = data.clone();
            if let Some(f) = d.first_mut() {
                *f = flags;
            }
            for input in [&data, &d] {
                if prime {
                    // A raw reference row whose sequence number makes `input` the next row.
                    let mut p = vec![0u8; max_len(w)];
                    p[0] = F_RAW;
                    p[1] = input.get(1).copied().unwrap_or(0).wrapping_sub(1);
                    dec.decode(&p, &mut oh, &mut ov).unwrap();
                }
                if dec.decode(input, &mut oh, &mut ov).is_ok() {
                    prop_assert!(oh.iter().enumerate().all(|(c, &h)| h == 0 || bit(&ov, c)));
                    prop_assert_eq!(ov[nb - 1] & !last_byte_mask(w), 0);
                }
            }
        }
    }
}
