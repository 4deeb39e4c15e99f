//! Crafted packet-stream corpus: replay, and regeneration on request.
//!
//! `fuzz/corpus/decode_stream/*.bin` are packet streams built from known rows and then damaged
//! by construction (truncation, bit flips, garbage, wrong length/version/codec fields, ...);
//! `fuzz/corpus/expect.json` says for each file what a decoder must report. The files are also
//! the seed corpus of the `decode_stream` fuzz target (see fuzz/README.md).
//!
//! - Replay: `cargo test -p dpsa-tests --test corpus`
//! - Regenerate (after a change of the packet encoder or of the cases below):
//!   `cargo test -p dpsa-tests --test corpus -- --ignored regenerate`
//!
//! The expectations come from the construction (which segments were damaged, and how), never
//! from running the decoder. The only call to the packet encoder is [`frame_rows`].
//!
//! ## Counting rule
//!
//! The decoder (docs/stream.md, "Resynchronisation") tries a packet at a position `p`:
//! - if the framing checks (sync word, version, length bound, CRC) it takes the packet and goes
//!   on at `p + packet length`; a framed packet whose payload cannot be unpacked (unknown codec,
//!   payload not a valid coding of the row) is reported once, at `p`, and skipped the same way;
//! - otherwise it reports the damage at `p` and goes on at the next sync word after `p`.
//!
//! So a *broken run* (a maximal run of damaged packets and garbage between two well-framed
//! packets or the ends of the stream) is reported once at its first byte, plus once at every
//! further `"DPSA"` inside the run: the intact sync word of a damaged packet that directly
//! follows another damaged packet, or a sync word planted in garbage. The generator checks that
//! every case has exactly the sync words it means to have inside its broken runs (no accidental
//! `"DPSA"` from a bit flip or from random bytes: garbage never contains the byte `'D'` unless a
//! case plants a sync word), and that the resulting report count is the one the case declares.
//! Consequences a reader may not expect, each covered by a case: a damaged packet whose sync
//! word is itself broken, directly after another damaged packet, is not reported separately
//! (it is part of the previous report); garbage directly after a damaged packet adds no report.
//! Well-framed but undecodable packets are always followed by a good packet or the end of the
//! stream, so the counts do not depend on whether a decoder checks the codec byte while framing
//! or while unpacking.

use dpsa_core::flags;
use dpsa_core::packets::{self, codec};
use dpsa_core::{Row, RowHeader};
use dpsa_sim::heightmap::HeightRow;
use serde_json::Value;
use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Largest corpus file.
const MAX_FILE: usize = 64 * 1024;

fn corpus_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz/corpus")
}

fn files_dir() -> PathBuf {
    corpus_dir().join("decode_stream")
}

// ---------------------------------------------------------------------------------------------
// Rows and packets.

/// A known row.
#[derive(Clone, Debug)]
struct TestRow {
    header: RowHeader,
    /// `W` heights, 0 where invalid.
    heights: Vec<i16>,
    /// `ceil(W/8)` validity bytes, padding bits 0.
    valid: Vec<u8>,
}

impl TestRow {
    fn valid_bools(&self) -> Vec<bool> {
        (0..self.heights.len())
            .map(|c| self.valid[c / 8] >> (c % 8) & 1 != 0)
            .collect()
    }
}

/// Frames the rows of one stream (all of one width), one packet each, in order.
///
/// The one place that calls the packet encoder: adapt it when `packets::encode` changes. One
/// `codec::Encoder` serves the stream, with the stream's intra period (1: every packet decodes
/// on its own, so damage to one packet leaves the others intact).
fn frame_rows(rows: &[TestRow]) -> Vec<Vec<u8>> {
    let Some(first) = rows.first() else {
        return Vec::new();
    };
    let w = first.heights.len();
    let (mut eh, mut ev) = (vec![0i16; w], vec![0u8; w.div_ceil(8)]);
    let mut enc =
        codec::Encoder::new(&mut eh, &mut ev, w, packets::STREAM_INTRA_PERIOD).expect("encoder");
    rows.iter()
        .map(|r| {
            let row = Row {
                header: r.header,
                heights: &r.heights,
                valid: &r.valid,
            };
            let mut buf = vec![0u8; packets::max_packet_len(w)];
            let n = packets::encode_v1(&row, &mut enc, &mut buf).expect("encode");
            buf.truncate(n);
            buf
        })
        .collect()
}

/// CRC-32/ISO-HDLC (reflected 0x04C11DB7, init and xorout 0xFFFFFFFF), bit by bit, from
/// docs/stream.md.
fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A codec-0 (raw) packet built by hand from docs/stream.md, independent of the encoder API,
/// so the corpus keeps raw packets whatever codec [`frame_rows`] uses.
fn raw_packet(r: &TestRow) -> Vec<u8> {
    let h = &r.header;
    let mut p = Vec::new();
    p.extend_from_slice(b"DPSA");
    p.extend_from_slice(&[1, 0, h.camera, h.n]);
    p.extend_from_slice(&h.row.to_le_bytes());
    p.extend_from_slice(&h.latch.to_le_bytes());
    p.extend_from_slice(&h.flags.to_le_bytes());
    p.extend_from_slice(&h.width.to_le_bytes());
    let plen = r.valid.len() + 2 * r.heights.len();
    p.extend_from_slice(&(plen as u32).to_le_bytes());
    p.extend_from_slice(&r.valid);
    for x in &r.heights {
        p.extend_from_slice(&x.to_le_bytes());
    }
    let crc = crc32(&p[4..]);
    p.extend_from_slice(&crc.to_le_bytes());
    p
}

/// Recomputes the CRC of a packet whose fields were edited (payload length field as written).
fn reseal(p: &mut Vec<u8>) {
    let plen = u32::from_le_bytes(p[28..32].try_into().unwrap()) as usize;
    p.truncate(32 + plen);
    let crc = crc32(&p[4..]);
    p.extend_from_slice(&crc.to_le_bytes());
}

/// xorshift64*.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
    /// Roughly Gaussian noise (sum of 4 uniforms), standard deviation about `sigma`.
    fn noise(&mut self, sigma: i32) -> i32 {
        let s: i32 = (0..4).map(|_| self.below(1 << 12) as i32 - 2048).sum();
        s * sigma / 2365
    }
    /// `n` bytes without `'D'` (so without a sync word).
    fn garbage(&mut self, n: usize) -> Vec<u8> {
        (0..n)
            .map(|_| match self.next() as u8 {
                b'D' => 0x5A,
                b => b,
            })
            .collect()
    }
}

/// Row styles, cycled by row index: realistic and adversarial content for the codec.
fn row_content(style: usize, w: usize, rng: &mut Rng) -> (Vec<i16>, Vec<bool>, u16) {
    let mut valid = vec![true; w];
    let mut flags = 0u16;
    let heights: Vec<i32> = match style % 7 {
        // Flat board with noise.
        0 => (0..w).map(|_| 40 + rng.noise(8)).collect(),
        // Solder deposits with sharp walls.
        1 => (0..w)
            .map(|c| if (c / 9) % 3 == 1 { 620 } else { 35 } + rng.noise(8))
            .collect(),
        // Runs of invalid pixels.
        2 => {
            for (c, v) in valid.iter_mut().enumerate() {
                *v = (c / 5) % 3 != 2;
            }
            (0..w).map(|c| -200 + 3 * c as i32 + rng.noise(4)).collect()
        }
        // No valid pixel (an invalidated row).
        3 => {
            valid.fill(false);
            flags = flags::INCOMPLETE;
            vec![0; w]
        }
        // Random i16 and random validity (the codec's raw fallback).
        4 => {
            for v in valid.iter_mut() {
                *v = rng.below(4) != 0;
            }
            (0..w).map(|_| i32::from(rng.next() as i16)).collect()
        }
        // Extremes.
        5 => {
            flags = flags::SATURATED;
            (0..w)
                .map(|c| [i32::from(i16::MIN), i32::from(i16::MAX), 0, -1][(c + c / 3) % 4])
                .collect()
        }
        // Ramp, sparse invalid pixels.
        _ => {
            for (c, v) in valid.iter_mut().enumerate() {
                *v = c % 11 != 7;
            }
            (0..w).map(|c| 12 * c as i32 - 700).collect()
        }
    };
    let heights = heights
        .iter()
        .zip(&valid)
        .map(|(&h, &v)| if v { h.clamp(-32768, 32767) as i16 } else { 0 })
        .collect();
    (heights, valid, flags)
}

/// `count` rows of `width` pixels, board rows `first ..`, styles from `style0` on.
fn make_rows(seed: u64, width: u16, count: usize, first: i64, style0: usize) -> Vec<TestRow> {
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    (0..count)
        .map(|i| {
            let w = width as usize;
            let (heights, vb, flags) = row_content(style0 + i, w, &mut rng);
            let mut valid = vec![0u8; w.div_ceil(8)];
            for (c, &v) in vb.iter().enumerate() {
                valid[c / 8] |= u8::from(v) << (c % 8);
            }
            let row = first + i as i64;
            let header = RowHeader {
                camera: 1,
                n: 4,
                row,
                latch: 1_000_003 + 26 * row,
                flags,
                width,
            };
            TestRow {
                header,
                heights,
                valid,
            }
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Streams built from segments.

enum Seg {
    /// Packet `i` of the stream, intact.
    Good(usize),
    /// Packet `i`, damaged so that its framing fails: the decoder must resynchronise.
    Broken(Vec<u8>),
    /// Packet `i` with a valid framing (CRC included) but a payload that cannot be unpacked.
    Undecodable(Vec<u8>),
    /// Bytes that are not a packet.
    Garbage(Vec<u8>),
}

struct Case {
    name: &'static str,
    description: &'static str,
    bytes: Vec<u8>,
    /// Rows of the good packets, in stream order.
    good: Vec<TestRow>,
    /// Offsets of the expected damage reports, in stream order.
    reports: Vec<usize>,
}

/// Offsets of the sync words in `bytes[from..to]`.
fn syncs_in(bytes: &[u8], from: usize, to: usize) -> Vec<usize> {
    (from..to.min(bytes.len()))
        .filter(|&i| bytes[i..].starts_with(b"DPSA"))
        .collect()
}

/// Builds a case; `corrupt` is the number of reports the case means to cause (checked against
/// the counting rule applied to the construction).
fn case(
    name: &'static str,
    description: &'static str,
    rows: &[TestRow],
    packets: &[Vec<u8>],
    segs: Vec<Seg>,
    corrupt: usize,
) -> Case {
    let mut bytes = Vec::new();
    let mut good = Vec::new();
    // (start, end) of the broken runs and the offsets of the undecodable packets.
    let mut runs: Vec<(usize, usize)> = Vec::new();
    let mut reports = Vec::new();
    let mut in_run = false;
    for (k, s) in segs.iter().enumerate() {
        let start = bytes.len();
        if let (Seg::Undecodable(_), Some(Seg::Broken(_) | Seg::Garbage(_))) = (s, segs.get(k + 1))
        {
            panic!("{name}: an undecodable packet must be followed by a good one or the end");
        }
        match s {
            Seg::Good(i) => {
                bytes.extend_from_slice(&packets[*i]);
                good.push(rows[*i].clone());
                in_run = false;
            }
            Seg::Undecodable(p) => {
                bytes.extend_from_slice(p);
                reports.push(start);
                in_run = false;
            }
            Seg::Broken(p) | Seg::Garbage(p) => {
                bytes.extend_from_slice(p);
                if in_run {
                    runs.last_mut().unwrap().1 = bytes.len();
                } else {
                    runs.push((start, bytes.len()));
                    in_run = true;
                }
            }
        }
    }
    for &(s, e) in &runs {
        reports.push(s);
        reports.extend(syncs_in(&bytes, s + 1, e));
    }
    reports.sort_unstable();
    assert_eq!(
        reports.len(),
        corrupt,
        "{name}: construction gives reports at {reports:?}"
    );
    assert!(bytes.len() < MAX_FILE, "{name}: {} bytes", bytes.len());
    Case {
        name,
        description,
        bytes,
        good,
        reports,
    }
}

fn flip(p: &[u8], byte: usize, bit: u8) -> Vec<u8> {
    let mut q = p.to_vec();
    q[byte] ^= 1 << bit;
    q
}

fn set_len(p: &[u8], len: u32) -> Vec<u8> {
    let mut q = p.to_vec();
    q[28..32].copy_from_slice(&len.to_le_bytes());
    q
}

fn payload_len(p: &[u8]) -> usize {
    u32::from_le_bytes(p[28..32].try_into().unwrap()) as usize
}

/// Offset in packet `p` of payload byte `k` (modulo the payload length).
fn pay(p: &[u8], k: usize) -> usize {
    32 + k % payload_len(p)
}

/// Every case of the corpus.
fn cases() -> Vec<Case> {
    use Seg::*;
    let mut out = Vec::new();
    let mut rng = Rng(0x5EED);

    // Clean streams.
    out.push(case("empty", "zero-length file", &[], &[], vec![], 0));
    {
        let rows = make_rows(1, 8, 1, 0, 0);
        let p = frame_rows(&rows);
        out.push(case(
            "one-packet-w8",
            "one packet, width 8",
            &rows,
            &p,
            vec![Good(0)],
            0,
        ));
    }
    for (name, desc, seed, w, n, first, style) in [
        ("clean-w1", "6 packets of width 1", 2, 1u16, 6, 0i64, 0),
        (
            "clean-w13",
            "8 packets of width 13, every row style",
            3,
            13,
            8,
            100,
            0,
        ),
        (
            "clean-w64",
            "7 packets of width 64, every row style",
            4,
            64,
            7,
            5000,
            0,
        ),
        (
            "clean-w512",
            "8 packets of width 512, every row style",
            5,
            512,
            8,
            42,
            1,
        ),
        (
            "clean-negative-rows",
            "board rows -3..2 (i64 little-endian, negative)",
            6,
            24,
            6,
            -3,
            2,
        ),
        (
            "clean-all-invalid",
            "5 rows without a valid pixel",
            7,
            100,
            5,
            10,
            3,
        ),
    ] {
        let mut rows = make_rows(seed, w, n, first, style);
        if name == "clean-all-invalid" {
            for r in &mut rows {
                r.heights.fill(0);
                r.valid.fill(0);
                r.header.flags = flags::INCOMPLETE;
            }
        }
        let p = frame_rows(&rows);
        let segs = (0..n).map(Good).collect();
        out.push(case(name, desc, &rows, &p, segs, 0));
    }
    {
        let rows = make_rows(8, 20, 6, 0, 0);
        let p = frame_rows(&rows);
        let raw: Vec<Vec<u8>> = rows.iter().map(raw_packet).collect();
        // Packets 1, 3, 5 raw (codec 0, built by hand), the others from the encoder.
        let pk: Vec<Vec<u8>> = (0..6)
            .map(|i| {
                if i % 2 == 1 {
                    raw[i].clone()
                } else {
                    p[i].clone()
                }
            })
            .collect();
        out.push(case(
            "clean-raw-by-hand-mixed",
            "codec-0 packets built by hand from docs/stream.md (rows 1, 3, 5) between encoder packets",
            &rows,
            &pk,
            (0..6).map(Good).collect(),
            0,
        ));
    }

    // Truncations.
    {
        let rows = make_rows(9, 16, 5, 0, 0);
        let p = frame_rows(&rows);
        let cut = |i: usize, n: usize| p[i][..n].to_vec();
        let half = p[4].len() / 2;
        out.push(case(
            "truncated-final-payload",
            "last packet cut in the middle",
            &rows,
            &p,
            vec![Good(0), Good(1), Good(2), Good(3), Broken(cut(4, half))],
            1,
        ));
        out.push(case(
            "truncated-final-header",
            "last packet cut after 10 bytes",
            &rows,
            &p,
            vec![Good(0), Good(1), Good(2), Good(3), Broken(cut(4, 10))],
            1,
        ));
        out.push(case(
            "truncated-final-crc",
            "last packet missing the last CRC byte",
            &rows,
            &p,
            vec![
                Good(0),
                Good(1),
                Good(2),
                Good(3),
                Broken(cut(4, p[4].len() - 1)),
            ],
            1,
        ));
        out.push(case(
            "truncated-final-sync",
            "stream ends with 3 bytes of a sync word",
            &rows,
            &p,
            vec![Good(0), Good(1), Good(2), Good(3), Broken(cut(4, 3))],
            1,
        ));
        out.push(case(
            "truncated-middle",
            "packet 2 cut in half, then packets 3 and 4",
            &rows,
            &p,
            vec![
                Good(0),
                Good(1),
                Broken(cut(2, p[2].len() / 2)),
                Good(3),
                Good(4),
            ],
            1,
        ));
        out.push(case(
            "only-sync",
            "a lone sync word",
            &rows,
            &p,
            vec![Broken(cut(0, 4))],
            1,
        ));
    }

    // Single bit flips in packet 2 of 5.
    {
        let rows = make_rows(10, 40, 5, 7, 0);
        let p = frame_rows(&rows);
        let pl = payload_len(&p[2]);
        for (name, desc, byte, bit) in [
            (
                "flip-sync",
                "bit flip in the sync word of packet 2",
                1usize,
                3u8,
            ),
            (
                "flip-version",
                "bit flip in the version byte of packet 2",
                4,
                0,
            ),
            ("flip-codec", "bit flip in the codec byte of packet 2", 5, 2),
            (
                "flip-camera",
                "bit flip in the camera byte of packet 2",
                6,
                7,
            ),
            ("flip-row", "bit flip in the board row of packet 2", 8, 0),
            ("flip-latch", "bit flip in the latch of packet 2", 23, 7),
            ("flip-flags", "bit flip in the row flags of packet 2", 24, 1),
            ("flip-width", "bit flip in the width of packet 2", 26, 4),
            (
                "flip-length-low",
                "bit flip in the low byte of the payload length of packet 2",
                28,
                0,
            ),
            (
                "flip-length-mid",
                "bit flip making the payload length of packet 2 too long",
                29,
                1,
            ),
            (
                "flip-length-high",
                "bit flip in the top bit of the payload length of packet 2",
                31,
                7,
            ),
            (
                "flip-payload-first",
                "bit flip in the first payload byte of packet 2",
                32,
                0,
            ),
            (
                "flip-payload-mid",
                "bit flip in the middle of the payload of packet 2",
                32 + pl / 2,
                5,
            ),
            (
                "flip-payload-last",
                "bit flip in the last payload byte of packet 2",
                31 + pl,
                6,
            ),
            (
                "flip-crc-first",
                "bit flip in the first CRC byte of packet 2",
                32 + pl,
                0,
            ),
            (
                "flip-crc-last",
                "bit flip in the last CRC byte of packet 2",
                35 + pl,
                7,
            ),
        ] {
            let segs = vec![
                Good(0),
                Good(1),
                Broken(flip(&p[2], byte, bit)),
                Good(3),
                Good(4),
            ];
            out.push(case(name, desc, &rows, &p, segs, 1));
        }
        out.push(case(
            "flip-first-packet",
            "bit flip in the payload of packet 0",
            &rows,
            &p,
            vec![
                Broken(flip(&p[0], pay(&p[0], 8), 1)),
                Good(1),
                Good(2),
                Good(3),
                Good(4),
            ],
            1,
        ));
        out.push(case(
            "flip-last-packet",
            "bit flip in the payload of the last packet",
            &rows,
            &p,
            vec![
                Good(0),
                Good(1),
                Good(2),
                Good(3),
                Broken(flip(&p[4], pay(&p[4], 1), 3)),
            ],
            1,
        ));
        out.push(case(
            "flip-every-packet",
            "a bit flip in every packet (sync words intact)",
            &rows,
            &p,
            (0..5)
                .map(|i| Broken(flip(&p[i], pay(&p[i], 3 * i), i as u8)))
                .collect(),
            5,
        ));
        out.push(case(
            "two-damaged-in-a-row",
            "packets 1 and 2 damaged (CRC flip, payload flip), sync words intact: two reports",
            &rows,
            &p,
            vec![
                Good(0),
                Broken(flip(&p[1], p[1].len() - 2, 2)),
                Broken(flip(&p[2], pay(&p[2], 3), 4)),
                Good(3),
                Good(4),
            ],
            2,
        ));
        out.push(case(
            "two-damaged-second-sync-broken",
            "packet 1 damaged, packet 2 with a broken sync word: one report (the run has one sync word)",
            &rows,
            &p,
            vec![Good(0), Broken(flip(&p[1], pay(&p[1], 8), 0)), Broken(flip(&p[2], 2, 6)), Good(3), Good(4)],
            1,
        ));
        out.push(case(
            "damaged-then-garbage",
            "packet 1 damaged, then 23 bytes of garbage: one report",
            &rows,
            &p,
            vec![
                Good(0),
                Broken(flip(&p[1], pay(&p[1], 18), 2)),
                Garbage(rng.garbage(23)),
                Good(2),
                Good(3),
                Good(4),
            ],
            1,
        ));
        out.push(case(
            "garbage-then-damaged",
            "garbage, then packet 2 damaged (sync intact): two reports",
            &rows,
            &p,
            vec![
                Good(0),
                Good(1),
                Garbage(rng.garbage(9)),
                Broken(flip(&p[2], pay(&p[2], 13), 6)),
                Good(3),
                Good(4),
            ],
            2,
        ));
    }

    // Payload length and version fields.
    {
        let rows = make_rows(11, 33, 4, 300, 1);
        let p = frame_rows(&rows);
        let pl = payload_len(&p[1]) as u32;
        for (name, desc, len) in [
            (
                "length-plus-one",
                "payload length of packet 1 one too large",
                pl + 1,
            ),
            (
                "length-minus-one",
                "payload length of packet 1 one too small",
                pl - 1,
            ),
            ("length-zero", "payload length of packet 1 zero", 0),
            (
                "length-huge",
                "payload length of packet 1 0xFFFFFFFF",
                u32::MAX,
            ),
            (
                "length-past-end",
                "payload length of packet 1 reaching past the end of the stream",
                pl + 120,
            ),
        ] {
            let segs = vec![Good(0), Broken(set_len(&p[1], len)), Good(2), Good(3)];
            out.push(case(name, desc, &rows, &p, segs, 1));
        }
        // Shortened payload, length and CRC made consistent: framed, but not a valid payload.
        let mut short = p[1][..p[1].len() - 5].to_vec();
        short[28..32].copy_from_slice(&(pl - 1).to_le_bytes());
        reseal(&mut short);
        out.push(case(
            "length-short-crc-ok",
            "packet 1 one payload byte short with length and CRC consistent: framed but undecodable",
            &rows, &p, vec![Good(0), Undecodable(short), Good(2), Good(3)], 1,
        ));
        for (name, desc, v) in [
            ("version-2", "packet 1 with version 2 and a valid CRC", 2u8),
            ("version-0", "packet 1 with version 0 and a valid CRC", 0),
            (
                "version-255",
                "packet 1 with version 255 and a valid CRC",
                255,
            ),
        ] {
            let mut q = p[1].clone();
            q[4] = v;
            reseal(&mut q);
            out.push(case(
                name,
                desc,
                &rows,
                &p,
                vec![Good(0), Broken(q), Good(2), Good(3)],
                1,
            ));
        }
        let mut q = p[2].clone();
        q[5] = 7;
        reseal(&mut q);
        out.push(case(
            "unknown-codec-crc-ok",
            "packet 2 with codec byte 7 and a valid CRC: framed but undecodable",
            &rows,
            &p,
            vec![Good(0), Good(1), Undecodable(q.clone()), Good(3)],
            1,
        ));
        out.push(case(
            "unknown-codec-last",
            "last packet with codec byte 7 and a valid CRC",
            &rows,
            &p,
            vec![Good(0), Good(1), Good(3), Undecodable(q)],
            1,
        ));
    }

    // Garbage.
    {
        let rows = make_rows(12, 12, 4, 0, 0);
        let p = frame_rows(&rows);
        out.push(case(
            "garbage-between",
            "17 bytes of garbage between packets 1 and 2",
            &rows,
            &p,
            vec![Good(0), Good(1), Garbage(rng.garbage(17)), Good(2), Good(3)],
            1,
        ));
        out.push(case(
            "garbage-lead",
            "100 bytes of garbage before the first packet",
            &rows,
            &p,
            vec![
                Garbage(rng.garbage(100)),
                Good(0),
                Good(1),
                Good(2),
                Good(3),
            ],
            1,
        ));
        out.push(case(
            "garbage-tail",
            "garbage after the last packet",
            &rows,
            &p,
            vec![Good(0), Good(1), Good(2), Good(3), Garbage(rng.garbage(31))],
            1,
        ));
        out.push(case(
            "garbage-one-byte",
            "a single zero byte between packets",
            &rows,
            &p,
            vec![Good(0), Good(1), Garbage(vec![0]), Good(2), Good(3)],
            1,
        ));
        out.push(case(
            "garbage-everywhere",
            "garbage before, between and after every packet",
            &rows,
            &p,
            vec![
                Garbage(rng.garbage(5)),
                Good(0),
                Garbage(rng.garbage(1)),
                Good(1),
                Garbage(rng.garbage(64)),
                Good(2),
                Garbage(rng.garbage(3)),
                Good(3),
                Garbage(rng.garbage(8)),
            ],
            5,
        ));
        let mut g = rng.garbage(60);
        g[20..24].copy_from_slice(b"DPSA");
        out.push(case(
            "sync-in-garbage",
            "garbage with a sync word inside between packets 1 and 2: two reports",
            &rows,
            &p,
            vec![Good(0), Good(1), Garbage(g), Good(2), Good(3)],
            2,
        ));
        let mut g = rng.garbage(40);
        g[30..34].copy_from_slice(b"DPSA");
        g[34] = 1;
        out.push(case(
            "sync-version-in-garbage",
            "garbage with a sync word and version 1 reaching into the next packet: two reports",
            &rows,
            &p,
            vec![Good(0), Garbage(g), Good(1), Good(2), Good(3)],
            2,
        ));
        let mut g = rng.garbage(30);
        g[27..30].copy_from_slice(b"DPS");
        out.push(case(
            "partial-sync-before-packet",
            "garbage ending in \"DPS\" right before a packet",
            &rows,
            &p,
            vec![Good(0), Garbage(g), Good(1), Good(2), Good(3)],
            1,
        ));
        out.push(case(
            "sync-spam",
            "ten sync words in a row, then the packets: ten reports",
            &rows,
            &p,
            vec![
                Garbage(b"DPSA".repeat(10)),
                Good(0),
                Good(1),
                Good(2),
                Good(3),
            ],
            10,
        ));
        out.push(case(
            "pure-garbage",
            "1000 bytes without a sync word",
            &rows,
            &p,
            vec![Garbage(rng.garbage(1000))],
            1,
        ));
        let mut g = rng.garbage(3000);
        for at in [0, 700, 2996] {
            g[at..at + 4].copy_from_slice(b"DPSA");
        }
        out.push(case(
            "pure-garbage-with-syncs",
            "3000 bytes of garbage with sync words at 0, 700 and 2996",
            &rows,
            &p,
            vec![Garbage(g)],
            3,
        ));
    }

    // Several kinds of damage in one longer stream.
    {
        let rows = make_rows(13, 256, 12, 1000, 0);
        let p = frame_rows(&rows);
        let mut ver = p[9].clone();
        ver[4] = 9;
        reseal(&mut ver);
        out.push(case(
            "mixed-damage-w256",
            "12 rows of width 256: flips, garbage, a wrong length, a broken sync word followed by a wrong version (two reports) and a truncated last packet",
            &rows,
            &p,
            vec![
                Good(0), Broken(flip(&p[1], pay(&p[1], 68), 0)), Good(2), Garbage(rng.garbage(50)), Good(3),
                Good(4), Broken(set_len(&p[5], 7)), Good(6), Good(7), Broken(flip(&p[8], 2, 1)),
                Broken(ver), Good(10), Broken(p[11][..p[11].len() / 2].to_vec()),
            ],
            6,
        ));
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Expectations file.

fn row_json(r: &TestRow) -> String {
    let valid: String = r
        .valid_bools()
        .iter()
        .map(|&v| if v { '1' } else { '0' })
        .collect();
    let heights: Vec<String> = r.heights.iter().map(|h| h.to_string()).collect();
    format!(
        "{{\"row\": {}, \"latch\": {}, \"flags\": {}, \"width\": {}, \"valid\": \"{}\", \"heights\": [{}]}}",
        r.header.row,
        r.header.latch,
        r.header.flags,
        r.header.width,
        valid,
        heights.join(", ")
    )
}

fn file_name(i: usize, c: &Case) -> String {
    format!("{:02}-{}.bin", i + 1, c.name)
}

/// `expect.json`, one row per line.
fn expect_json(cases: &[Case]) -> String {
    let mut s = String::new();
    s.push_str("{\n");
    s.push_str("  \"about\": \"Expected decode of each file in decode_stream/: ok = good packets, corrupt = damage reports (see tests/corpus.rs for the counting rule), corrupt_offsets = byte offsets of the reports, rows = the good packets' rows sorted by board row (valid: one char per column, heights in LSB, 0 where invalid). Generated by tests/corpus.rs (regenerate), from the construction.\",\n");
    s.push_str("  \"files\": {\n");
    for (i, c) in cases.iter().enumerate() {
        let mut rows = c.good.clone();
        rows.sort_by_key(|r| r.header.row);
        let _ = write!(
            s,
            "    \"{}\": {{\n      \"description\": {},\n      \"bytes\": {},\n      \"ok\": {},\n      \"corrupt\": {},\n      \"corrupt_offsets\": {:?},\n      \"rows\": [",
            file_name(i, c),
            Value::String(c.description.into()),
            c.bytes.len(),
            c.good.len(),
            c.reports.len(),
            c.reports,
        );
        for (j, r) in rows.iter().enumerate() {
            s.push_str(if j == 0 { "\n" } else { ",\n" });
            s.push_str("        ");
            s.push_str(&row_json(r));
        }
        s.push_str(if rows.is_empty() {
            "]\n"
        } else {
            "\n      ]\n"
        });
        s.push_str(if i + 1 == cases.len() {
            "    }\n"
        } else {
            "    },\n"
        });
    }
    s.push_str("  }\n}\n");
    s
}

#[test]
#[ignore]
fn regenerate() {
    let cases = cases();
    let dir = files_dir();
    std::fs::create_dir_all(&dir).unwrap();
    for e in std::fs::read_dir(&dir).unwrap() {
        let path = e.unwrap().path();
        if path.extension().is_some_and(|x| x == "bin") {
            std::fs::remove_file(path).unwrap();
        }
    }
    for (i, c) in cases.iter().enumerate() {
        std::fs::write(dir.join(file_name(i, c)), &c.bytes).unwrap();
    }
    let json = expect_json(&cases);
    serde_json::from_str::<Value>(&json).expect("expect.json is JSON");
    std::fs::write(corpus_dir().join("expect.json"), json).unwrap();
    println!("wrote {} files to {}", cases.len(), dir.display());
}

// ---------------------------------------------------------------------------------------------
// Replay.

fn expect() -> Value {
    let text = std::fs::read_to_string(corpus_dir().join("expect.json"))
        .expect("fuzz/corpus/expect.json (regenerate with -- --ignored regenerate)");
    serde_json::from_str(&text).expect("expect.json parses")
}

fn expected_row(v: &Value) -> HeightRow {
    let valid: Vec<bool> = v["valid"]
        .as_str()
        .unwrap()
        .chars()
        .map(|c| c == '1')
        .collect();
    let heights: Vec<i16> = v["heights"]
        .as_array()
        .unwrap()
        .iter()
        .map(|h| h.as_i64().unwrap() as i16)
        .collect();
    assert_eq!(valid.len(), v["width"].as_u64().unwrap() as usize);
    assert_eq!(heights.len(), valid.len());
    HeightRow {
        row: v["row"].as_i64().unwrap(),
        latch: v["latch"].as_i64().unwrap(),
        flags: v["flags"].as_u64().unwrap() as u16,
        heights,
        valid,
    }
}

/// Decodes a stream, turning a panic into a test failure naming the file.
fn decode(
    name: &str,
    bytes: &[u8],
) -> (
    dpsa_sim::heightmap::HeightMap,
    dpsa_sim::stream::DecodeReport,
) {
    std::panic::catch_unwind(|| dpsa_sim::stream::decode_stream(bytes, 0.25))
        .unwrap_or_else(|_| panic!("{name}: decode_stream panicked"))
}

#[test]
fn corpus_files_decode_as_expected() {
    let expect = expect();
    let files = expect["files"].as_object().expect("files");
    assert!(files.len() >= 20, "{} files", files.len());
    let mut failures = Vec::new();
    for (name, e) in files {
        let path = files_dir().join(name);
        let bytes = std::fs::read(&path).unwrap_or_else(|err| panic!("{}: {err}", path.display()));
        assert!(bytes.len() < MAX_FILE, "{name}: {} bytes", bytes.len());
        assert_eq!(
            bytes.len() as u64,
            e["bytes"].as_u64().unwrap(),
            "{name}: size"
        );
        let (map, rep) = decode(name, &bytes);
        let offsets: Vec<usize> = rep.damage.iter().map(|d| d.offset).collect();
        let want_offsets: Vec<usize> = e["corrupt_offsets"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_u64().unwrap() as usize)
            .collect();
        let want_rows: Vec<HeightRow> = e["rows"]
            .as_array()
            .unwrap()
            .iter()
            .map(expected_row)
            .collect();
        let mut problems = Vec::new();
        if rep.ok != e["ok"].as_u64().unwrap() as usize {
            problems.push(format!("ok {} != {}", rep.ok, e["ok"]));
        }
        if rep.corrupt != e["corrupt"].as_u64().unwrap() as usize {
            problems.push(format!("corrupt {} != {}", rep.corrupt, e["corrupt"]));
        }
        if rep.damage.len() != rep.corrupt {
            problems.push(format!(
                "{} damage entries for corrupt {}",
                rep.damage.len(),
                rep.corrupt
            ));
        }
        // Every damaged packet (and garbage region) reported, where it starts.
        if offsets != want_offsets {
            problems.push(format!(
                "damage at {offsets:?}, expected {want_offsets:?} ({:?})",
                rep.damage
            ));
        }
        // Every good packet recovered, with the heights and validity it was sent with.
        let got_rows: BTreeSet<i64> = map.rows.iter().map(|r| r.row).collect();
        for w in &want_rows {
            match map.rows.iter().find(|r| r.row == w.row) {
                None => problems.push(format!("row {} missing", w.row)),
                Some(r) if r != w => {
                    problems.push(format!("row {} differs: {r:?} vs {w:?}", w.row))
                }
                Some(_) => {}
            }
        }
        let want_set: BTreeSet<i64> = want_rows.iter().map(|r| r.row).collect();
        if got_rows != want_set || map.rows.len() != want_rows.len() {
            problems.push(format!(
                "rows {:?}, expected {:?}",
                map.rows.iter().map(|r| r.row).collect::<Vec<_>>(),
                want_set
            ));
        }
        if let Some(w) = want_rows.first() {
            if map.width != w.valid.len() {
                problems.push(format!("map width {} != {}", map.width, w.valid.len()));
            }
        }
        if !problems.is_empty() {
            failures.push(format!("{name}: {}", problems.join("; ")));
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} files:\n{}",
        failures.len(),
        files.len(),
        failures.join("\n")
    );
}

/// Files in the corpus folder without expectations (e.g. inputs a fuzz run added there) must
/// still decode without a panic; listed files must exist.
#[test]
fn other_corpus_files_do_not_panic() {
    let expect = expect();
    let files = expect["files"].as_object().unwrap();
    let mut listed = BTreeSet::new();
    for e in std::fs::read_dir(files_dir()).unwrap() {
        let path = e.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if files.contains_key(&name) {
            listed.insert(name);
        } else if path.is_file() && !name.starts_with('.') {
            let bytes = std::fs::read(&path).unwrap();
            let (map, rep) = decode(&name, &bytes);
            assert_eq!(map.rows.len(), rep.ok, "{name}");
            assert_eq!(rep.damage.len(), rep.corrupt, "{name}");
        }
    }
    assert_eq!(
        listed.len(),
        files.len(),
        "listed files missing from {}",
        files_dir().display()
    );
}

/// The committed corpus is what the generator builds today (else: regenerate).
#[test]
fn corpus_matches_generator() {
    let cases = cases();
    let stale: Vec<String> = cases
        .iter()
        .enumerate()
        .filter(|(i, c)| {
            std::fs::read(files_dir().join(file_name(*i, c)))
                .ok()
                .as_deref()
                != Some(&c.bytes[..])
        })
        .map(|(i, c)| file_name(i, c))
        .collect();
    let json = std::fs::read_to_string(corpus_dir().join("expect.json")).unwrap_or_default();
    assert!(
        stale.is_empty() && json == expect_json(&cases),
        "corpus out of date ({stale:?}{}): cargo test -p dpsa-tests --test corpus -- --ignored regenerate",
        if json == expect_json(&cases) { "" } else { ", expect.json" }
    );
}

/// The CRC and the raw framing written here from docs/stream.md agree with the crate: the
/// check value, the encoder's packets, and hand-built codec-0 packets accepted by the parser.
#[test]
fn stream_doc_definitions_match() {
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    let rows = make_rows(99, 21, 7, 0, 0);
    for (r, p) in rows.iter().zip(frame_rows(&rows)) {
        let l = payload_len(&p);
        assert_eq!(p.len(), 36 + l);
        assert_eq!(crc32(&p[4..32 + l]).to_le_bytes(), p[32 + l..]);
        let raw = raw_packet(r);
        let (pk, len) = packets::decode(&raw).expect("hand-built raw packet decodes");
        assert_eq!((len, pk.codec, pk.header), (raw.len(), 0, r.header));
    }
}

// ---------------------------------------------------------------------------------------------
// Version 2 cases (built on the fly through the core's PacketSink, the pipeline's framing).

struct VecLink(Vec<Vec<u8>>);
impl dpsa_core::sink::Link for VecLink {
    type Error = std::convert::Infallible;
    fn send(&mut self, p: &[u8]) -> Result<(), Self::Error> {
        self.0.push(p.to_vec());
        Ok(())
    }
    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// Header, the rows, a gap after the third row, end: one packet per entry.
fn v2_packets(rows: &[TestRow]) -> Vec<Vec<u8>> {
    use dpsa_core::row::{Gap, StreamInfo};
    use dpsa_core::Sink as _;
    let w = rows[0].heights.len();
    let mut reference = codec::ReferenceRow::new(w);
    let enc = reference.encoder(packets::STREAM_INTRA_PERIOD).unwrap();
    let mut buf = vec![0u8; packets::max_packet_len(w)];
    let mut sink = dpsa_core::sink::PacketSink::new(VecLink(Vec::new()), enc, &mut buf);
    sink.set_run_id(0xfeed);
    let info = StreamInfo {
        camera: rows[0].header.camera,
        n: rows[0].header.n,
        width: w as u16,
        rows: 40,
        max_step_rows: 10,
        config_hash: 0xabc,
        ..StreamInfo::default()
    };
    sink.start(&info).unwrap();
    for (i, r) in rows.iter().enumerate() {
        sink.row(&Row {
            header: r.header,
            heights: &r.heights,
            valid: &r.valid,
        })
        .unwrap();
        if i == 2 {
            sink.gap(&Gap {
                camera: info.camera,
                first: r.header.row + 1,
                count: 1_000_000_000_000,
                flags: flags::SKIPPED | flags::ENCODER_FAULT,
            })
            .unwrap();
        }
    }
    sink.end().unwrap();
    sink.into_link().0
}

#[test]
fn v2_streams_decode_and_report() {
    let mut rows = make_rows(7, 33, 6, 10, 0);
    // Rows after the gap continue past it.
    for r in rows.iter_mut().skip(3) {
        r.header.row += 1_000_000_000_000;
    }
    let pk = v2_packets(&rows);
    assert_eq!(pk.len(), rows.len() + 3);
    let clean = pk.concat();
    let (map, rep) = decode("v2-clean", &clean);
    assert_eq!((rep.ok, rep.corrupt), (pk.len(), 0));
    assert_eq!(map.rows.len(), rows.len());
    let s = &rep.stream;
    assert_eq!((s.version, s.run_id, s.width), (2, Some(0xfeed), Some(33)));
    assert_eq!(
        (s.gap_records, s.gap_rows, s.rows_missing),
        (1, 1_000_000_000_000, 0)
    );
    assert!(!s.truncated && s.missing == 0);
    assert_eq!(rep.verdict(&map), dpsa_sim::stream::DecodeOutcome::Clean);
    for (got, want) in map.rows.iter().zip(&rows) {
        assert_eq!(got.row, want.header.row);
        assert_eq!(got.heights, want.heights);
        assert_eq!(got.valid, want.valid_bools());
    }

    // One bit flipped in a row payload: lost, reported missing, the rest at their rows.
    let mut bad = pk.clone();
    let l = bad[2].len();
    bad[2][l - 8] ^= 0x10;
    let (map, rep) = decode("v2-flip", &bad.concat());
    assert_eq!(
        (rep.corrupt, rep.stream.missing, rep.stream.rows_missing),
        (1, 1, 1)
    );
    assert!(map.get(rows[1].header.row).is_none());
    assert_eq!(map.rows.len(), rows.len() - 1);

    // Duplicate and reorder.
    let mut dr = pk.clone();
    dr.insert(3, pk[2].clone());
    dr.swap(5, 6);
    let (map, rep) = decode("v2-dup-reorder", &dr.concat());
    assert_eq!((rep.stream.duplicated, rep.stream.reordered), (1, 1));
    assert_eq!(map.rows.len(), rows.len());
    assert_eq!(rep.verdict(&map), dpsa_sim::stream::DecodeOutcome::Damaged);

    // Truncated: no end packet.
    let (_, rep) = decode("v2-cut", &pk[..pk.len() - 1].concat());
    assert!(rep.stream.truncated);

    // A version 1 stream and a version 2 stream of another width before the good one.
    let other = v2_packets(&make_rows(8, 9, 4, 0, 0));
    let mut mixed = other[1].clone();
    mixed.extend(&clean);
    let (map, rep) = decode("v2-stray-width", &mixed);
    assert_eq!(map.width, 33);
    assert_eq!(map.rows.len(), rows.len());
    assert!(rep.ok >= pk.len());
}
